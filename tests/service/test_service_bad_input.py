"""Implausible and hostile input through the real app: every case answers a 4xx JSON ``{"detail", "field"}``
naming the field at fault, never a 5xx, and queues nothing (issue 10, "plausible input only" and
"bounded state"). The Redis cases run against a real redis-server.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
from redis_server import RedisServer
from svc_helpers import AppClient, BlobDetector, make_test_frame, multipart_parts

from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}


def proto_body(frame: Any, **changes: Any) -> bytes:
    msg = frame_to_proto(frame)
    for name, value in changes.items():
        setattr(msg, name, value)
    return msg.SerializeToString()


def assert_problem(response: httpx.Response, status: int, field: str | None) -> None:
    """A 4xx answered as ``{"detail": str, "field": field}``."""
    assert response.status_code == status, response.text
    body = response.json()
    assert set(body) == {"detail", "field"} and isinstance(body["detail"], str) and body["detail"], body
    assert body["field"] == field, body


@pytest.fixture(scope="module")
def client() -> Iterator[AppClient]:
    settings = Settings(detector="sim:0", workers=1, max_frame_bytes=2_000_000)
    with AppClient(create_app(settings, detector=BlobDetector())) as test_client:
        assert test_client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(0)), headers=PROTOBUF).status_code == 202
        yield test_client


def bad_requests() -> list[tuple[str, str, str, dict[str, Any], int, str | None]]:
    """(case, method, path, request kwargs, status, field)."""
    frame = make_test_frame(1)
    return [
        # map ids: letters, digits, '.', '_', '-' only
        ("map id with a backslash", "DELETE", "/v1/maps/vic%5Ctim", {}, 422, "map_id"),
        ("map id with a glob star", "GET", "/v1/maps/m%2A/stats", {}, 422, "map_id"),
        (
            "map id with a colon",
            "POST",
            "/v1/maps/a:b/frames",
            {"content": proto_body(frame), "headers": PROTOBUF},
            422,
            "map_id",
        ),
        ("map id too long", "GET", "/v1/maps/" + "a" * 129 + "/objects", {}, 422, "map_id"),
        (
            "device id with a backslash",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, device_id="a\\b")},
            422,
            "device_id",
        ),
        # the framework's own 4xx
        ("unknown route", "GET", "/v2/nothing", {}, 404, None),
        ("method not allowed", "PUT", "/v1/maps/m/frames", {}, 405, None),
        (
            "multipart without boundary",
            "POST",
            "/v1/maps/m/frames",
            {"content": b"x", "headers": {"content-type": "multipart/form-data"}},
            400,
            None,
        ),
        (
            "multipart cut short",
            "POST",
            "/v1/maps/m/frames",
            {
                "content": b'--b\r\nContent-Disposition: form-data; name="meta"\r\n\r\n{',
                "headers": {"content-type": "multipart/form-data; boundary=b"},
            },
            422,
            "meta",
        ),
        ("object id not a number", "GET", "/v1/maps/m/objects/abc", {}, 422, "object_id"),
        (
            "content-length not a number",
            "POST",
            "/v1/maps/m/frames",
            {"content": b"x", "headers": {**PROTOBUF, "content-length": "x1"}},
            400,
            "content-length",
        ),
    ]


BAD_REQUESTS = bad_requests()


@pytest.mark.parametrize(
    ("case", "method", "path", "request_kwargs", "status", "field"), BAD_REQUESTS, ids=[c[0] for c in BAD_REQUESTS]
)
def test_bad_input_answers_4xx_naming_the_field(
    client: AppClient, case: str, method: str, path: str, request_kwargs: dict[str, Any], status: int, field: str | None
) -> None:
    response = client.request(method, path, **request_kwargs)
    assert_problem(response, status, field)
    stats = client.get("/v1/maps/m/stats").json()
    assert stats["frames"]["accepted"] == 1, (case, stats)  # nothing else was queued


# --- against a real redis-server -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def redis_app() -> Iterator[tuple[AppClient, RedisServer]]:
    server = RedisServer.start()
    try:
        with AppClient(create_app(Settings(store=server.url, detector="sim:0", workers=0))) as api:
            yield api, server
    finally:
        server.stop()


@pytest.mark.redis
def test_deleting_a_map_id_with_glob_escapes_never_touches_another_map(redis_app: tuple[AppClient, RedisServer]) -> None:
    api, server = redis_app
    assert (
        api.post("/v1/maps/victim/frames", content=proto_body(make_test_frame(0, map_id="victim")), headers=PROTOBUF).status_code
        == 202
    )
    redis = server.client()
    try:
        redis.set(keys.ids_key("victim"), 7)
        before = sorted(redis.scan_iter(match=keys.map_pattern("victim")))
        assert len(before) >= 2
        for path in ("/v1/maps/vic%5Ctim", "/v1/maps/vic%5Ctim%2A", "/v1/maps/v%3Fctim", "/v1/maps/%5Bv%5Dictim"):
            assert_problem(api.delete(path), 422, "map_id")
        # Below the API (defence in depth): the store's SCAN pattern escapes the id, so nothing else matches.
        with RedisStore(server.url) as store:
            for hostile in ("vic\\tim", "vic*", "v?ctim", "[v]ictim"):
                assert store.delete_map(hostile) == 0
        assert sorted(redis.scan_iter(match=keys.map_pattern("victim"))) == before
        assert api.get("/v1/maps/victim/stats").status_code == 200
    finally:
        redis.close()


def test_glob_characters_in_map_patterns_are_escaped() -> None:
    assert keys.map_pattern("vic\\tim") == "arcloud:{vic\\\\tim}:*"
    assert keys.map_pattern("a*b?[c]") == "arcloud:{a\\*b\\?\\[c\\]}:*"
    assert np.all([keys.map_pattern(m).startswith(keys.map_prefix(m)) for m in ("office", "a.b_c-d")])
