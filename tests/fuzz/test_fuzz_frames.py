"""Property: a valid frame mutated (bit flips and cuts in its protobuf bytes and in its PNG/JPEG payloads, odd
field values, random meta JSON values) answers 202 or a 4xx JSON problem, never a 5xx (but a 503 with
Retry-After), and the service still takes and processes a valid frame afterwards. Against the real app over
real HTTP, embedded and on a real redis-server with one worker process.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import pytest
import requests
from frame_strategies import Parts, multipart_frames, protobuf_frames, valid_message
from fuzz_helpers import PROTOBUF, SEEDED_MAP, FuzzApi, assert_answer
from hypothesis import HealthCheck, given, settings
from svc_helpers import wait_until

pytestmark = pytest.mark.fuzz

MAX_EXAMPLES = 300
FUZZ_SETTINGS = settings(
    max_examples=MAX_EXAMPLES,
    derandomize=True,  # seeded: the same examples every run
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],  # each example is an HTTP round trip
)
URL = f"/v1/maps/{SEEDED_MAP}/frames"
_fresh_ids = itertools.count()


def check_answer(response: requests.Response) -> None:
    assert_answer(response.status_code, response.headers, response.content, f"{response.request.method} {response.request.url}")
    assert response.status_code == 202 or 400 <= response.status_code < 500 or response.status_code == 503, response.text


def assert_takes_a_valid_frame(api: FuzzApi) -> None:
    """A fresh valid frame is accepted and processed (no worker died on what came before)."""
    msg = valid_message(frame_id=f"after-fuzz-{next(_fresh_ids)}")
    response = api.session.post(api.url + URL, data=msg.SerializeToString(), headers={**api.headers, **PROTOBUF}, timeout=30)
    assert response.status_code == 202 and response.json()["status"] == "queued", response.text
    status_url = f"{api.url}/v1/maps/{SEEDED_MAP}/frames/{msg.device_id}/{msg.frame_id}"

    def processed() -> bool:
        state: dict[str, Any] = api.session.get(status_url, headers=api.headers, timeout=30).json()
        assert state["status"] != "failed", state
        return state["status"] == "processed"

    wait_until(processed, 60, "the valid frame to be processed")


def run_property(api: FuzzApi, post: Callable[[], None]) -> None:
    api.seed()
    post()
    assert_takes_a_valid_frame(api)


def test_a_mutated_protobuf_frame_answers_202_or_a_4xx_problem(fuzz_api: FuzzApi) -> None:
    @FUZZ_SETTINGS
    @given(body=protobuf_frames())
    def post(body: bytes) -> None:
        check_answer(fuzz_api.session.post(fuzz_api.url + URL, data=body, headers={**fuzz_api.headers, **PROTOBUF}, timeout=30))

    run_property(fuzz_api, post)


def test_a_mutated_multipart_frame_answers_202_or_a_4xx_problem(fuzz_api: FuzzApi) -> None:
    @FUZZ_SETTINGS
    @given(parts=multipart_frames())
    def post(parts: Parts) -> None:
        check_answer(fuzz_api.session.post(fuzz_api.url + URL, files=parts, headers=fuzz_api.headers, timeout=30))

    run_property(fuzz_api, post)
