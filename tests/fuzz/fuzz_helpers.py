"""Helpers of the fuzz suite: the real app served over real HTTP (embedded, or on a real redis-server),
the answer rules every response is held to, and odd strings for path and query parameters.

Imported as ``from fuzz_helpers import ...`` (tests/fuzz/conftest.py puts this folder on sys.path).
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from typing import Any

import requests
from redis_server import RedisServer
from svc_helpers import UvicornThread, make_test_frame, wait_until

from arcloud.access import new_key, parse_maps
from arcloud.proto.convert import frame_to_proto
from arcloud.service.http_protocol import JsonProblemHTTP
from arcloud.service.settings import Settings
from arcloud.stores.redis_api_keys import RedisKeyStore
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
SEEDED_MAP = "office"  # the map id the OpenAPI examples name: examples hit a map that exists
SEED_FRAMES = 8  # frames of it processed at start: the simulator's detector finds objects in them (ids 1, 2, ...)
# Strings mixed into every generated string (path ids, queries, meta): escapes, glob and path characters,
# non-ASCII, controls, numbers' spellings, and lengths past every limit.
ODD_STRINGS = [
    "a\\b",
    "\\",
    "..",
    "./.",
    "a/b",
    "%2e%2e",
    "%00",
    "\x00",
    "*",
    "[a]",
    "a?b",
    "{office}",
    "é",
    "日本語",
    "\u202eoffice",
    "\ufeff",
    "\U0001f600",
    " ",
    "\t\n",
    "NaN",
    "-Infinity",
    "1e309",
    "-0",
    "9" * 40,
    "a" * 129,
    "a" * 10_000,
    "é" * 5_000,
]


# Rate limits on (their code runs on every request) but far above the fuzz's pace: else most answers would be 429.
UNLIMITED = {
    "key_rate_per_s": 1e6,
    "key_burst": 10**6,
    "map_frame_rate_per_s": 1e6,
    "map_frame_burst": 10**6,
    "auth_failure_rate_per_s": 1e6,
    "auth_failure_burst": 10**6,
}


def settings_for(kind: str, redis_url: str | None = None) -> Settings:
    """The settings of the app under fuzz, each with its default access: embedded (memory store, simulator
    detector, one worker thread; auth none), or on Redis with one worker process (readiness and frame states see
    a real worker; auth keys)."""
    if kind == "embedded":
        return Settings(detector="sim:0", workers=1, **UNLIMITED)
    if kind == "redis":
        return Settings(store=redis_url, detector="sim:0", workers=1, **UNLIMITED)
    raise ValueError(f"kind: expected 'embedded' or 'redis', got {kind!r}")


def admin_token(redis_url: str) -> str:
    """A new admin key for every map in the Redis the service reads its keys from; its token."""
    key, token = new_key("admin", parse_maps("*"), now_s=time.time(), name="fuzz")
    keys = RedisKeyStore(redis_url)
    try:
        keys.add(key)
    finally:
        keys.close()
    return token


@dataclass
class FuzzApi:
    """A served app: its base URL, the headers every request carries, a requests session (schemathesis's transport)."""

    kind: str
    url: str
    headers: dict[str, str]
    session: requests.Session
    auth: bool  # whether the app asks for a token (auth keys)

    def post_frame(self, index: int, map_id: str = SEEDED_MAP) -> requests.Response:
        msg = frame_to_proto(make_test_frame(index, map_id=map_id, level=True))
        return self.session.post(
            f"{self.url}/v1/maps/{map_id}/frames",
            data=msg.SerializeToString(),
            headers={**self.headers, **PROTOBUF},
            timeout=30,
        )

    def seed(self, frames: int = 1) -> None:
        """Map ``SEEDED_MAP`` exists (a deleted one is made again), its first ``frames`` frames processed: routes
        on a known map and its objects answer too."""
        for index in range(frames):
            response = self.post_frame(index)
            assert response.status_code == 202, response.text

        def processed() -> bool:
            stats = self.session.get(f"{self.url}/v1/maps/{SEEDED_MAP}/stats", headers=self.headers, timeout=30).json()
            return bool(stats["frames"]["pending"] == 0)

        wait_until(processed, 60, f"map {SEEDED_MAP}'s frames to be processed")


@contextmanager
def serve(kind: str, headers: Mapping[str, str]) -> Iterator[FuzzApi]:
    """The app of ``settings_for(kind)`` on uvicorn with ``serve``'s protocol (a real redis-server for ``redis``),
    ready and seeded. Every request carries ``headers``, and with auth keys a bearer token of an admin key for
    every map."""
    headers = dict(headers)
    with ExitStack() as stack:
        redis_url = None
        if kind == "redis":
            server = RedisServer.start()
            stack.callback(server.stop)
            redis_url = server.url
        settings = settings_for(kind, redis_url)
        if settings.auth_mode == "keys" and redis_url is not None and "authorization" not in {k.lower() for k in headers}:
            headers["authorization"] = f"Bearer {admin_token(redis_url)}"
        uvicorn = stack.enter_context(UvicornThread(create_app(settings), http=JsonProblemHTTP))  # as `arcloud serve` runs it
        session = stack.enter_context(requests.Session())
        api = FuzzApi(kind, uvicorn.url, headers, session, auth=settings.auth_mode == "keys")
        wait_until(lambda: api.session.get(f"{api.url}/readyz", headers=api.headers, timeout=30).status_code == 200, 60, "ready")
        api.seed(frames=SEED_FRAMES)
        yield api


def answer_faults(status: int, headers: Mapping[str, str], body: bytes) -> list[str]:
    """What is wrong with an answer: a 5xx other than a 503 carrying Retry-After, or a 4xx/5xx whose body is not
    a JSON object with "detail" (a non-empty string) and "field" (a string or null). ``headers``: lower-case names."""
    faults = []
    if status >= 500 and not (status == 503 and headers.get("retry-after", "").isdigit()):
        faults.append(f"{status}: a server error (only a 503 with Retry-After is allowed)")
    if status >= 400:
        try:
            problem = json.loads(body)
        except ValueError:
            return [*faults, f"{status} with a body that is not JSON: {body[:200]!r}"]
        if not (
            isinstance(problem, dict)
            and isinstance(problem.get("detail"), str)
            and problem["detail"]
            and "field" in problem
            and (problem["field"] is None or isinstance(problem["field"], str))
        ):
            faults.append(f'{status} with a body that is not {{"detail": str, "field": str | null}}: {body[:200]!r}')
    return faults


def assert_answer(status: int, headers: Mapping[str, Any], body: bytes, what: str) -> None:
    lower = {k.lower(): v if isinstance(v, str) else ", ".join(v) for k, v in headers.items()}
    faults = answer_faults(status, lower, body)
    assert not faults, f"{what}: " + "; ".join(faults)
