"""Regressions the API fuzz run (tests/fuzz) and its raw-HTTP probes found, each named after its case: every
answer a JSON ``{"detail", "field"}`` (uvicorn's and Starlette's own included), documented in the OpenAPI
schema, and no 5xx but a 503 with Retry-After. Against the real app, over ASGI or real HTTP, on a real
redis-server where Redis is named.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest
from svc_helpers import AppClient, BlobDetector, make_test_frame

from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}


def frame_body(map_id: str = "m", index: int = 0) -> bytes:
    return frame_to_proto(make_test_frame(index, map_id=map_id)).SerializeToString()  # type: ignore[no-any-return]  # protobuf's stubs


def assert_problem(status: int, body: bytes, expected_status: int, field: str | None) -> dict[str, Any]:
    assert status == expected_status, body
    problem = json.loads(body)
    assert isinstance(problem["detail"], str) and problem["detail"] and problem["field"] == field, problem
    return problem  # type: ignore[no-any-return]  # json's Any


@pytest.fixture(scope="module")
def embedded() -> Iterator[AppClient]:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as api:
        assert api.post("/v1/maps/m/frames", content=frame_body(), headers=PROTOBUF).status_code == 202
        yield api


def test_multipart_with_too_many_parts_answers_a_documented_400(embedded: AppClient) -> None:
    parts = {name: (None, b"x") for name in ("meta", "rgb", "depth", "extra")}
    response = embedded.post("/v1/maps/m/frames", files=parts)
    assert_problem(response.status_code, response.content, 400, None)
    assert "400" in embedded.app.openapi()["paths"]["/v1/maps/{map_id}/frames"]["post"]["responses"]
