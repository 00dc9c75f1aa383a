"""Viewer tickets and sessions over real HTTP (issue 22: no API key in a URL): a real uvicorn server running the
embedded service with a keys file. A key draws a ticket; the ticket, traded once, sets the viewer session's cookie;
the cookie reads its map (the event stream included) and nothing else, while the key may."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from svc_helpers import UvicornThread, make_test_frame
from viewer_helpers import BlobDetector, EventStream, bearer, make_keys

from arcloud.proto.convert import frame_to_proto
from arcloud.service.access import VIEWER_COOKIE
from arcloud.service.settings import Settings
from arcloud.stores.file_api_keys import FileKeyStore
from arcloud.tools.wiring import create_app

TICKET_S = 1.0


class Service:
    def __init__(self, url: str, tokens: dict[str, str], keys_file: Path) -> None:
        self.url = url
        self.tokens = tokens
        self.keys_file = keys_file

    def client(self) -> httpx.Client:
        """A new client: its own cookie jar, as a new browser."""
        return httpx.Client(base_url=self.url, timeout=10.0)

    def ticket(self, map_id: str, token: str) -> dict[str, str]:
        with self.client() as http:
            answer = http.post(f"/v1/maps/{map_id}/viewer-tickets", headers=bearer(token))
        assert answer.status_code == 201, answer.text
        return answer.json()  # type: ignore[no-any-return]  # httpx's JSON is Any


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    keys_file = tmp_path_factory.mktemp("keys") / "keys.json"
    tokens = make_keys(keys_file, device=("device", "*"), reader=("reader", "room,other"), stranger=("reader", "elsewhere"))
    settings = Settings(
        detector="sim:0",
        workers=1,
        keys_file=str(keys_file),
        key_cache_s=0.0,
        key_rate_per_s=0,
        auth_failure_rate_per_s=0,
        event_poll_s=0.1,
        viewer_ticket_s=TICKET_S,
    )
    with UvicornThread(create_app(settings, detector=BlobDetector())) as server, httpx.Client(base_url=server.url) as http:
        for map_id in ("room", "other"):
            body = frame_to_proto(make_test_frame(0, map_id=map_id)).SerializeToString()
            headers = {"content-type": "application/x-protobuf", **bearer(tokens["device"])}
            assert http.post(f"/v1/maps/{map_id}/frames", content=body, headers=headers).status_code == 202
        yield Service(server.url, tokens, keys_file)


def assert_problem(answer: httpx.Response, status: int, contains: str) -> None:
    assert answer.status_code == status, answer.text
    assert answer.headers["content-type"] == "application/problem+json"
    assert contains in answer.json()["detail"], answer.json()


def test_a_ticket_opens_one_session_that_reads_its_map_and_nothing_else(service: Service) -> None:
    drawn = service.ticket("room", service.tokens["reader"])
    ticket = drawn["ticket"]
    assert drawn["viewer_url"] == f"/viewer?map=room#ticket={ticket}" and drawn["expires_in_s"] == TICKET_S
    assert service.tokens["reader"] not in drawn["viewer_url"]
    with service.client() as browser:
        traded = browser.post("/v1/maps/room/viewer-session", json={"ticket": ticket})
        assert traded.status_code == 204, traded.text
        cookie = traded.headers["set-cookie"]
        assert re.match(rf"{VIEWER_COOKIE}=[A-Za-z0-9_-]{{43}};", cookie), cookie
        assert ticket not in cookie and service.tokens["reader"] not in cookie  # a new secret
        for attribute in ("HttpOnly", "Max-Age=43200", "Path=/v1/maps/room", "SameSite=strict"):
            assert attribute in cookie, cookie
        session = browser.cookies[VIEWER_COOKIE]

        assert browser.get("/v1/maps/room/stats").status_code == 200  # the cookie alone
        assert_problem(browser.post("/v1/maps/room/viewer-session", json={"ticket": ticket}), 401, "unknown, used or expired")
    with EventStream(service.url, "room", cookies={VIEWER_COOKIE: session}) as stream:
        assert stream.next_event("snapshot")[0] == "snapshot"

    with httpx.Client(base_url=service.url, timeout=10.0, cookies={VIEWER_COOKIE: session}) as forged:
        # the cookie sent where a browser would not send it: its map's reads only
        assert_problem(forged.get("/v1/maps/other/stats"), 403, "not for map 'other'")
        assert_problem(forged.post("/v1/maps/room/frames", content=b"x"), 403, "a reader key may not write")
        assert_problem(forged.post("/v1/maps/room/viewer-tickets"), 403, "a viewer session draws none")
        assert_problem(forged.delete("/v1/maps/room"), 403, "may not admin")


def test_a_ticket_of_another_map_a_wrong_or_an_expired_one_is_refused(service: Service) -> None:
    with service.client() as browser:
        ticket = service.ticket("room", service.tokens["reader"])["ticket"]
        assert_problem(browser.post("/v1/maps/other/viewer-session", json={"ticket": ticket}), 403, "for map 'room'")
        wrong = "A" * 43
        assert_problem(browser.post("/v1/maps/room/viewer-session", json={"ticket": wrong}), 401, "viewer-tickets")
        assert_problem(browser.post("/v1/maps/room/viewer-session", json={"ticket": "short"}), 401, "unknown")
        not_json = browser.post(
            "/v1/maps/room/viewer-session", content=b"ticket=abc", headers={"content-type": "application/json"}
        )
        assert_problem(not_json, 400, "body: expected a JSON document")
        assert not_json.json()["field"] == "body"
        expired = service.ticket("room", service.tokens["reader"])["ticket"]
        time.sleep(TICKET_S + 0.1)
        assert_problem(browser.post("/v1/maps/room/viewer-session", json={"ticket": expired}), 401, "expired")
        assert_problem(browser.get("/v1/maps/room/stats"), 401, "Bearer")  # no session was opened
        assert_problem(
            browser.get("/v1/maps/room/stats", headers={"cookie": f"{VIEWER_COOKIE}={wrong}"}),
            401,
            "viewer session is unknown or expired",
        )
    with service.client() as http:  # only a key that may read the map draws a ticket
        assert_problem(http.post("/v1/maps/room/viewer-tickets", headers=bearer(service.tokens["stranger"])), 403, "not for")
        assert_problem(http.post("/v1/maps/room/viewer-tickets"), 401, "Bearer")


def test_a_session_ends_with_its_key(service: Service) -> None:
    token = make_keys(service.keys_file, revocable=("reader", "room"))["revocable"]
    ticket = service.ticket("room", token)["ticket"]
    with service.client() as browser:
        assert browser.post("/v1/maps/room/viewer-session", json={"ticket": ticket}).status_code == 204
        with EventStream(service.url, "room", cookies={VIEWER_COOKIE: browser.cookies[VIEWER_COOKIE]}) as stream:
            stream.next_event("snapshot")
            keys = FileKeyStore(service.keys_file)
            assert keys.revoke(token.split("_")[1])
            keys.close()
            _, data = stream.next_event("refused", timeout_s=5)
            assert "was revoked" in data["detail"]
        assert_problem(browser.get("/v1/maps/room/stats"), 401, "was revoked")


def test_a_key_in_the_viewers_url_is_refused_and_the_viewer_puts_none_there(service: Service) -> None:
    with service.client() as http:
        assert_problem(http.get(f"/viewer?map=room&token={service.tokens['reader']}"), 400, "viewer-tickets")
        assert http.get("/viewer?map=room").status_code == 200
        page = http.get("/viewer").text
        script = http.get("/viewer/viewer.js").text
    assert "token" not in page and 'name="key"' not in page  # the form submits no key, even without its script
    for where in ("sessionStorage", "localStorage", 'get("token")', "?token", "&token"):
        assert where not in script, where
    assert script.count("Authorization") == 1 and 'viewer-tickets`, { method: "POST", headers: { Authorization' in script


def test_with_auth_none_there_is_no_ticket_to_draw() -> None:
    with UvicornThread(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as server:
        answer = httpx.post(f"{server.url}/v1/maps/room/viewer-tickets", timeout=10.0)
    assert_problem(answer, 404, "(the viewer needs none): open /viewer?map=room")
