"""Every error answer is an RFC 9457 problem (``application/problem+json``: type, title, status, detail, field), through
the real app: a 4xx provoked on every operation of its own OpenAPI schema (invalid input, a wrong method, no token,
a key of another map), the framework's own refusals (unknown route, 405, 413, 415, 429), 500 and 503; each problem's
``type`` answers its description; the schema documents every error as sent; the SDK reads the problem."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from svc_helpers import PROBLEM_MEDIA_TYPE, AppClient, BlobDetector, UvicornThread, assert_problem, make_test_frame

from arcloud.access import new_key
from arcloud.client.http import ServiceError, service_error
from arcloud.errors import StoreUnavailable
from arcloud.proto.convert import frame_to_proto
from arcloud.service.problems import PROBLEM_TYPES, problem_body
from arcloud.service.settings import Settings
from arcloud.stores.file_api_keys import FileKeyStore
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import create_app

DOCS = Path(__file__).resolve().parents[2] / "docs" / "service.md"
PROTOBUF = {"content-type": "application/x-protobuf"}
OPEN = {"/", "/healthz", "/readyz", "/healthz/workers", "/metrics", "/problems/{name}"}  # no token asked
TICKETED = {"/v1/maps/{map_id}/viewer-session"}  # a viewer ticket in the body, not a token
#: A value refused for each path parameter, and the status it gets (map ids are checked before anything else).
BAD_PATH_VALUES = {"map_id": ("bad id", 422), "name": ("no-such-type", 404)}


@pytest.fixture(scope="module")
def keyed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[AppClient, dict[str, str]]]:
    """The embedded service with a keys file: an admin key of every map, a reader key of map ``other``."""
    keys_file = tmp_path_factory.mktemp("keys") / "keys.json"
    store = FileKeyStore(str(keys_file))
    tokens = {}
    for name, role, maps in (("admin", "admin", ("*",)), ("reader", "reader", ("other",))):
        key, token = new_key(role, maps, now_s=0.0, name=name)
        store.add(key)
        tokens[name] = token
    settings = Settings(detector="sim:0", workers=1, keys_file=str(keys_file), max_frame_bytes=1 << 20)
    with AppClient(create_app(settings, detector=BlobDetector())) as api:
        yield api, tokens


def bearer(token: str) -> dict[str, str]:
    return {"authorization": f"Bearer {token}"}


def operations(spec: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    return [(method.upper(), path, op) for path, ops in spec["paths"].items() for method, op in ops.items()]


def provoked(method: str, path: str, op: dict[str, Any]) -> tuple[str, dict[str, str], int, str | None]:
    """A request refused by the operation ``op`` for its input: (url, query, expected status, field)."""
    names = re.findall(r"\{(\w+)\}", path)
    if names:
        url, status, field = path, 0, None
        for name in names:
            value, status_of = BAD_PATH_VALUES.get(name, ("x", 404))
            url = url.replace("{" + name + "}", value.replace(" ", "%20"))
            if not status:
                status, field = status_of, (name if status_of == 422 else None)
        return url, {}, status, field
    query = {p["name"]: p for p in op.get("parameters", []) if p["in"] == "query"}
    if "limit" in query:
        return path, {"limit": "0"}, 422, "limit"
    return path, {}, 405, None  # no input to get wrong: the wrong method (sent by the caller)


def test_every_operation_of_the_schema_answers_its_4xx_as_a_problem(keyed: tuple[AppClient, dict[str, str]]) -> None:
    api, tokens = keyed
    spec = api.get("/openapi.json").json()
    walked = set()
    for method, path, op in operations(spec):
        url, query, status, field = provoked(method, path, op)
        sent = method
        if status == 405:
            allowed = {m.upper() for m in spec["paths"][path]}
            sent = next(m for m in ("PATCH", "DELETE", "PUT", "POST") if m not in allowed)
        answer = api.request(sent, url, params=query, headers=bearer(tokens["admin"]))
        problem = assert_problem(answer, status, field)
        if status == 405:
            assert answer.headers["allow"] == ", ".join(sorted({m.upper() for m in spec["paths"][path]})), path
        walked.add((method, path))
        if path in OPEN:
            continue
        # Map routes: no token, 401 (with WWW-Authenticate); a reader key of another map, 403.
        concrete = re.sub(r"\{\w+\}", "room", path).replace("/objects/room", "/objects/1")
        unauthenticated = api.request(method, concrete, json={"ticket": "A" * 43} if path in TICKETED else None)
        assert_problem(unauthenticated, 401, "authorization")
        assert unauthenticated.headers["www-authenticate"].startswith("Bearer"), path
        if "{map_id}" in path and path not in TICKETED:
            assert_problem(api.request(method, concrete, headers=bearer(tokens["reader"])), 403, "authorization")
        assert problem["type"].startswith("/problems/"), problem
    assert walked == {(m, p) for m, p, _ in operations(spec)}


def test_the_frameworks_refusals_are_problems(keyed: tuple[AppClient, dict[str, str]]) -> None:
    api, tokens = keyed
    admin = bearer(tokens["admin"])
    problem = assert_problem(api.get("/no/such/route"), 404, None)
    assert (
        problem["detail"] == "GET /no/such/route: no such route (the routes: /openapi.json)" and problem["title"] == "Not found"
    )
    assert_problem(api.request("PATCH", "/v1/maps/m/snapshot", headers=admin), 405, None)
    too_big = {**PROTOBUF, **admin, "content-length": str(2 << 20)}
    assert_problem(api.post("/v1/maps/m/frames", content=b"", headers=too_big), 413, "body")
    bad_length = {**PROTOBUF, **admin, "content-length": "lots"}
    assert_problem(api.post("/v1/maps/m/frames", content=b"", headers=bad_length), 400, "content-length")
    wrong_type = api.post("/v1/maps/m/frames", content=b"{}", headers={**admin, "content-type": "application/json"})
    assert_problem(wrong_type, 415, None)
    frame = frame_to_proto(make_test_frame(0, map_id="m")).SerializeToString()
    assert api.post("/v1/maps/m/frames", content=frame, headers={**PROTOBUF, **admin}).status_code == 202
    assert_problem(api.get("/v1/maps/m/objects/99999", headers=admin), 404, None)
    assert_problem(api.get("/v1/maps/m/objects", params={"bbox": "1,2"}, headers=admin), 422, "bbox")


def test_429_500_and_503_are_problems_too() -> None:
    class Broken(MemoryStore):
        def list_maps(self) -> dict[str, float]:
            raise RuntimeError("a bug")

        def ping(self) -> None:
            raise StoreUnavailable("the store went away")

    settings = Settings(detector="sim:0", workers=1, auth="none", key_rate_per_s=0.01, key_burst=3)
    # Over real HTTP: Starlette raises the 500's exception again after answering (uvicorn logs it, and closes the
    # connection: the 500 has one of its own).
    with UvicornThread(create_app(settings, store=Broken(), detector=BlobDetector())) as server:
        assert_problem(httpx.get(f"{server.url}/v1/maps"), 500, None)
        with httpx.Client(base_url=server.url) as http:
            not_ready = http.get("/readyz")  # open: not rate limited
            problem = assert_problem(not_ready, 503, None)
            assert problem["type"] == "/problems/not-ready" and problem["checks"]["store"].startswith("unreachable"), problem
            assert not_ready.headers["retry-after"] == "5"
            answers = [http.get("/v1/maps/m/stats") for _ in range(3)]
    limited = assert_problem(answers[-1], 429, None)
    assert limited["type"] == "/problems/rate-limited" and int(answers[-1].headers["retry-after"]) >= 1


def test_each_problem_type_answers_its_description_and_the_docs_list_them(keyed: tuple[AppClient, dict[str, str]]) -> None:
    api, _ = keyed
    documented = DOCS.read_text()
    for name, kind in PROBLEM_TYPES.items():
        described = api.get(kind.uri)
        assert described.status_code == 200 and described.json()["title"] == kind.title, described.text
        assert f"| `{kind.uri}` | {kind.title} |" in documented, f"docs/service.md does not list {kind.uri}"
        body = problem_body(kind.statuses[0], "what happened", kind=name)
        assert (body["type"], body["title"], body["status"]) == (kind.uri, kind.title, kind.statuses[0])
    listed = set(re.findall(r"\| `(/problems/[a-z-]+)` \|", documented))
    assert listed == {kind.uri for kind in PROBLEM_TYPES.values()}
    assert problem_body(418, "a teapot") == {
        "type": "about:blank",
        "title": "I'm a Teapot",
        "status": 418,
        "detail": "a teapot",
        "field": None,
    }
    with pytest.raises(ValueError, match="standard member"):
        problem_body(422, "x", extra={"status": 1})


def test_the_schema_documents_every_error_as_a_problem(keyed: tuple[AppClient, dict[str, str]]) -> None:
    api, _ = keyed
    spec = api.get("/openapi.json").json()
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    problem = spec["components"]["schemas"]["Problem"]
    assert {"type", "title", "status", "detail"} <= set(problem["required"]) and "field" in problem["properties"]
    for method, path, op in operations(spec):
        for code, response in op["responses"].items():
            if int(code) >= 400:
                assert set(response["content"]) == {PROBLEM_MEDIA_TYPE}, (method, path, code)


def test_the_sdk_reads_the_problem_and_the_body_of_before() -> None:
    def answer(status: int, **kwargs: Any) -> httpx.Response:
        return httpx.Response(status, request=httpx.Request("GET", "http://x/v1/maps/m/stats"), **kwargs)

    body = problem_body(503, "queue full: map m has 250 frames queued", kind="queue-full")
    error = service_error(answer(503, json=body, headers={"content-type": PROBLEM_MEDIA_TYPE}))
    assert isinstance(error, ServiceError) and (error.status, error.type, error.title) == (
        503,
        "/problems/queue-full",
        "Queue full",
    )
    assert error.detail == body["detail"] and error.field is None and error.problem == body
    old = service_error(answer(422, json={"detail": "bbox: expected six numbers", "field": "bbox"}))
    assert (old.detail, old.field, old.type, old.title) == ("bbox: expected six numbers", "bbox", "about:blank", "")
    proxy = service_error(answer(502, text="<html>Bad Gateway</html>"))
    assert proxy.detail == "<html>Bad Gateway</html>" and proxy.problem == {}
