"""Property: a valid map snapshot mutated (its bytes, or one member's bytes, name or JSON values) and PUT back
answers 200 or a 4xx JSON problem, never a 5xx (but a 503 with Retry-After), and the valid snapshot still
restores afterwards, every object back. Against the real app over real HTTP, embedded and on a real
redis-server.
"""

from __future__ import annotations

import pytest
from fuzz_helpers import SEEDED_MAP, FuzzApi, assert_answer
from hypothesis import HealthCheck, given, settings
from snapshot_strategies import mutated_snapshots

pytestmark = pytest.mark.fuzz

MAX_EXAMPLES = 200
RESTORED_MAP = "restored"


def test_a_mutated_snapshot_answers_200_or_a_4xx_problem(fuzz_api: FuzzApi) -> None:
    api = fuzz_api
    api.seed()
    taken = api.session.get(f"{api.url}/v1/maps/{SEEDED_MAP}/snapshot", headers=api.headers, timeout=30)
    assert taken.status_code == 200, taken.text
    valid = taken.content
    zip_headers = {**api.headers, "content-type": "application/zip"}
    url = f"{api.url}/v1/maps/{RESTORED_MAP}/snapshot?replace=true"

    @settings(
        max_examples=MAX_EXAMPLES, derandomize=True, database=None, deadline=None, suppress_health_check=[HealthCheck.too_slow]
    )
    @given(body=mutated_snapshots(valid))
    def put(body: bytes) -> None:
        response = api.session.put(url, data=body, headers=zip_headers, timeout=30)
        assert_answer(response.status_code, response.headers, response.content, f"PUT {url}")
        assert response.status_code in (200, 503) or 400 <= response.status_code < 500, response.text

    put()
    restored = api.session.put(url, data=valid, headers=zip_headers, timeout=30)
    assert restored.status_code == 200, restored.text
    ours = api.session.get(f"{api.url}/v1/maps/{SEEDED_MAP}/objects", params={"include": "tentative"}, headers=api.headers)
    theirs = api.session.get(f"{api.url}/v1/maps/{RESTORED_MAP}/objects", params={"include": "tentative"}, headers=api.headers)
    assert theirs.status_code == 200 and [o["id"] for o in theirs.json()["objects"]] == [o["id"] for o in ours.json()["objects"]]
    assert restored.json()["restored_objects"] == len(ours.json()["objects"]) > 0
