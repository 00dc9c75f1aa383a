"""Regressions the API fuzz run (tests/fuzz) and its raw-HTTP probes found, each named after its case: every
answer an RFC 9457 problem with ``detail`` and ``field`` (uvicorn's and Starlette's own included), documented in the OpenAPI
schema, and no 5xx but a 503 with Retry-After. Against the real app, over ASGI or real HTTP, on a real
redis-server where Redis is named.
"""

from __future__ import annotations

import io
import json
import socket
import zipfile
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from redis_server import RedisServer
from svc_helpers import PROBLEM_MEDIA_TYPE, AppClient, BlobDetector, UvicornThread, make_test_frame, wait_until

from arcloud.proto.convert import frame_to_proto
from arcloud.service import http_protocol
from arcloud.service.http_protocol import MAX_HEAD_BYTES, JsonProblemHTTP
from arcloud.service.settings import Settings
from arcloud.stores import keys
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}


def frame_body(map_id: str = "m", index: int = 0) -> bytes:
    return frame_to_proto(make_test_frame(index, map_id=map_id)).SerializeToString()  # type: ignore[no-any-return]  # protobuf's stubs


def assert_problem(status: int, body: bytes, expected_status: int, field: str | None) -> dict[str, Any]:
    assert status == expected_status, body
    problem = json.loads(body)
    assert isinstance(problem["detail"], str) and problem["detail"] and problem["field"] == field, problem
    assert problem["status"] == status and problem["type"].startswith("/problems/") and problem["title"], problem
    return problem  # type: ignore[no-any-return]  # json's Any


def raw_http(port: int, request: bytes) -> tuple[int, dict[str, str], bytes]:
    """Send ``request`` as it is on a new connection; (status, headers, body) of the answer (read to its end)."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(request)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    status_line, *lines = head.decode("latin-1").split("\r\n")
    headers = {name.lower(): value.strip() for name, _, value in (line.partition(":") for line in lines)}
    return int(status_line.split()[1]), headers, body


@pytest.fixture(scope="module")
def embedded() -> Iterator[AppClient]:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as api:
        assert api.post("/v1/maps/m/frames", content=frame_body(), headers=PROTOBUF).status_code == 202
        yield api


@pytest.fixture(scope="module")
def snapshot(embedded: AppClient) -> bytes:
    """A snapshot of map m (its frame processed: objects with voxels)."""
    wait_until(lambda: embedded.get("/v1/maps/m/stats").json()["frames"]["processed"] == 1, 30, "the frame processed")
    response = embedded.get("/v1/maps/m/snapshot")
    assert response.status_code == 200 and len(zipfile.ZipFile(io.BytesIO(response.content)).namelist()) > 1
    return response.content  # type: ignore[no-any-return]  # httpx's bytes


def rezipped(snapshot: bytes, changes: dict[str, bytes]) -> bytes:
    """The snapshot with members replaced or added (``changes``: name -> bytes)."""
    source, out = zipfile.ZipFile(io.BytesIO(snapshot)), io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as rebuilt:
        for name in dict.fromkeys([*source.namelist(), *changes]):
            rebuilt.writestr(name, changes[name] if name in changes else source.read(name))
    return out.getvalue()


def with_a_corrupt_deflate_stream(snapshot: bytes) -> bytes:
    """The snapshot with its first voxels member's compressed bytes all 0xFF (no valid deflate block)."""
    data = bytearray(snapshot)
    info = next(i for i in zipfile.ZipFile(io.BytesIO(snapshot)).infolist() if i.filename.endswith(".voxels"))
    name_length, extra_length = (
        int.from_bytes(data[info.header_offset + 26 : info.header_offset + 28], "little"),
        int.from_bytes(data[info.header_offset + 28 : info.header_offset + 30], "little"),
    )
    start = info.header_offset + 30 + name_length + extra_length
    data[start : start + info.compress_size] = b"\xff" * info.compress_size
    return bytes(data)


@pytest.fixture(scope="module")
def served() -> Iterator[UvicornThread]:
    """The embedded app on uvicorn with the protocol `arcloud serve` runs."""
    with UvicornThread(
        create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector()), http=JsonProblemHTTP
    ) as server:
        yield server


def test_multipart_with_too_many_parts_answers_a_documented_400(embedded: AppClient) -> None:
    parts = {name: (None, b"x") for name in ("meta", "rgb", "depth", "extra")}
    response = embedded.post("/v1/maps/m/frames", files=parts)
    assert_problem(response.status_code, response.content, 400, None)
    assert "400" in embedded.app.openapi()["paths"]["/v1/maps/{map_id}/frames"]["post"]["responses"]


@pytest.mark.parametrize(
    "request_bytes",
    [
        b"HELLO\r\n\r\n",
        b"GET /healthz HTTP/9.9\r\nHost: x\r\n\r\n",
        b"GET /v1/maps/\xff/stats HTTP/1.1\r\nHost: x\r\n\r\n",
        b"POST /v1/maps/m/frames HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-protobuf\r\nContent-Length: -1\r\n\r\n",
        b"POST /v1/maps/m/frames HTTP/1.1\r\nHost: x\r\nContent-Length: 1\r\nContent-Length: 2\r\n\r\nab",
        b"POST /v1/maps/m/frames HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n",
        b"POST /v1/maps/m/frames HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-protobuf\r\nTransfer-Encoding: chunked\r\n\r\nZZ\r\nab\r\n",
    ],
    ids=[
        "not HTTP",
        "HTTP 9.9",
        "raw byte 0xFF in the path",
        "content-length -1",
        "two content-lengths",
        "content-length and chunked",
        "chunk size not hex",
    ],
)
def test_a_request_uvicorn_cannot_parse_answers_a_json_400(served: UvicornThread, request_bytes: bytes) -> None:
    status, headers, body = raw_http(served.port, request_bytes)
    assert headers["content-type"] == PROBLEM_MEDIA_TYPE and headers["connection"] == "close"
    assert_problem(status, body, 400, None)


def test_an_upload_the_client_abandons_answers_400_not_500(embedded: AppClient) -> None:
    """The body ends in ``http.disconnect``: before, Starlette's ``ClientDisconnect`` escaped the app (a 500 and
    a logged traceback for every abandoned upload)."""
    messages = iter([{"type": "http.request", "body": frame_body()[:10], "more_body": True}, {"type": "http.disconnect"}])
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        return next(messages)

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": "/v1/maps/m/frames",
        "raw_path": b"/v1/maps/m/frames",
        "query_string": b"",
        "root_path": "",
        "headers": [(b"host", b"app"), (b"content-type", b"application/x-protobuf"), (b"content-length", b"5000")],
        "client": ("127.0.0.1", 50000),
        "server": ("app", 80),
    }
    embedded.portal.call(embedded.app, scope, receive, send)
    assert_problem(sent[0]["status"], sent[1]["body"], 400, "body")


@pytest.mark.redis
def test_a_store_error_answers_a_json_500_telling_nothing_of_it() -> None:
    """A map's header key of the wrong type (WRONGTYPE from Redis: ``StoreError``, not a client's fault) answers 500
    as the usual JSON problem, not Starlette's plain text, and names neither Redis nor its address."""
    server = RedisServer.start()
    try:
        app = create_app(Settings(store=server.url, auth="none", detector="sim:0", workers=0))
        with UvicornThread(app, http=JsonProblemHTTP) as api, httpx.Client(base_url=api.url, timeout=30) as http:
            assert http.post("/v1/maps/m/frames", content=frame_body(), headers=PROTOBUF).status_code == 202
            redis = server.client()
            redis.delete(keys.header_key("m"))
            redis.lpush(keys.header_key("m"), "not a hash")
            redis.close()
            response = http.get("/v1/maps/m/stats")
        problem = assert_problem(response.status_code, response.content, 500, None)
        assert response.headers["content-type"] == PROBLEM_MEDIA_TYPE
        assert "redis" not in problem["detail"].lower() and str(server.port) not in problem["detail"], problem
    finally:
        server.stop()


@pytest.mark.redis
def test_no_worker_anywhere_leaves_the_api_ready_and_the_workers_report_503() -> None:
    """Redis with no worker anywhere: /readyz answers 200 (this process takes and answers requests: a frame is
    queued, the map read), /healthz/workers 503 with Retry-After, its checks and the problem's fields."""
    server = RedisServer.start()
    try:
        with AppClient(create_app(Settings(store=server.url, auth="none", detector="sim:0", workers=0))) as api:
            ready = api.get("/readyz")
            queued = api.post("/v1/maps/m/frames", content=frame_body(), headers=PROTOBUF)
            stats = api.get("/v1/maps/m/stats")
            workers = api.get("/healthz/workers")
            metrics = api.get("/metrics").text
    finally:
        server.stop()
    assert ready.status_code == 200 and ready.json() == {"status": "ready", "checks": {"store": "ok"}}, ready.text
    assert queued.json()["status"] == "queued" and stats.json()["frames"]["pending"] == 1
    problem = assert_problem(workers.status_code, workers.content, 503, None)
    assert workers.headers["content-type"] == PROBLEM_MEDIA_TYPE and workers.headers["retry-after"].isdigit()
    assert problem["type"] == "/problems/workers-unavailable" and problem["checks"]["workers"].startswith("no worker heartbeat")
    assert problem["detail"].startswith("workers unavailable (workers: no worker heartbeat"), problem
    assert problem["checks"]["consumer_group"] == "ok" and problem["live"] == [] and problem["expected"] is None, problem
    assert "\narcloud_workers_up 0.0\n" in metrics and "\narcloud_live_workers 0.0\n" in metrics


@pytest.mark.parametrize(
    ("case", "change"),
    [
        ("snapshot with a member outside objects/", lambda valid: rezipped(valid, {"a.meta": b"{}"})),
        ("snapshot with a corrupt deflate stream", with_a_corrupt_deflate_stream),
        ("snapshot with a voxels blob shorter than its header", lambda valid: rezipped(valid, {"objects/1.voxels": b"junk"})),
    ],
    ids=lambda value: value if isinstance(value, str) else "",
)
def test_a_malformed_snapshot_answers_422_naming_it(embedded: AppClient, snapshot: bytes, case: str, change: Any) -> None:
    """Each raised past read_snapshot's except (IndexError, zlib.error, the codec's StoreError): a 500. The valid
    snapshot still restores."""
    body = change(snapshot)
    response = embedded.request("PUT", "/v1/maps/r/snapshot", content=body, headers={"content-type": "application/zip"})
    assert_problem(response.status_code, response.content, 422, "snapshot")
    restored = embedded.request(
        "PUT", "/v1/maps/r/snapshot?replace=true", content=snapshot, headers={"content-type": "application/zip"}
    )
    assert restored.status_code == 200, restored.text


def test_a_405_allows_every_method_of_the_path(embedded: AppClient) -> None:
    """Starlette's Allow named the first route of the path only: GET for GET and PUT .../snapshot."""
    response = embedded.post("/v1/maps/m/snapshot")
    assert_problem(response.status_code, response.content, 405, None)
    assert response.headers["allow"] == "GET, PUT"
    assert embedded.request("PATCH", "/v1/maps/m").headers["allow"] == "DELETE"


@pytest.mark.parametrize("how", ["one endless header", "many headers", "path of 200 kB"])
def test_a_request_head_over_its_cap_answers_431_and_closes(served: UvicornThread, how: str) -> None:
    # httptools caps neither a header's size nor their number: one endless header grew the server's memory and
    # stalled every other request (a hostile client's review, no key needed).
    if how == "one endless header":  # never finished: the head is refused while it comes
        headers = b"X-Big: " + b"a" * (4 * MAX_HEAD_BYTES)
    elif how == "many headers":
        headers = b"".join(b"X-%d: 1\r\n" % i for i in range(MAX_HEAD_BYTES // 8))
    path = b"/v1/maps/" + b"a" * 200_000 + b"/stats" if how == "path of 200 kB" else b"/healthz"
    if how == "path of 200 kB":
        headers = b""
    end = b"" if how == "one endless header" else b"\r\n"
    status, response_headers, body = raw_http(served.port, b"GET " + path + b" HTTP/1.1\r\nHost: x\r\n" + headers + end)
    assert response_headers["connection"] == "close"
    assert_problem(status, body, 431, None)
    with httpx.Client(base_url=f"http://127.0.0.1:{served.port}") as client:  # and the service still answers
        assert client.get("/healthz").status_code == 200


def test_a_request_head_that_trickles_answers_408_and_closes(served: UvicornThread, monkeypatch: pytest.MonkeyPatch) -> None:
    # A head sent a byte at a time held its connection open for good (slowloris); a body has its own timeout.
    monkeypatch.setattr(http_protocol, "HEAD_TIMEOUT_S", 0.5)
    with socket.create_connection(("127.0.0.1", served.port), timeout=10) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 408 ")
    assert assert_problem(408, body, 408, None)["type"] == "/problems/too-slow"
