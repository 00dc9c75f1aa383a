"""Issue 22's bounds under its hostile requests, each sent through a real app (uvicorn) on a real redis-server with
API keys: no answer is a 5xx other than 503 with Retry-After, and while the requests run another client's PING is
answered within ``PING_BOUND_S`` (a loaded machine can hold a process back 100 ms by itself: a test whose PING went
over is run once more). Where each finding's bound is asserted:

    restore bomb         here (through the API); the store alone, and deleting the map: test_store_bounded_writes.py
    BUSY                 test_chaos_queue.py::test_the_api_answers_503_with_retry_after_while_redis_is_busy (every
                         route 503 with Retry-After; PING cannot be answered by a Redis busy by definition)
    FLUSHALL with keys   here (a workload across the flush); the keys' loss seen: test_service_access.py
    100 streams, one key here on Redis; the per-key and per-map limits: tests/viewer/test_viewer_stream_limits.py
    the big export       here on Redis; what a page and an export read: test_service_pages.py
    invalid-token spray  here on Redis; the 429 itself: test_service_access.py::test_a_spray_of_invalid_tokens_...
    one map's flood      test_service_uploads.py (another map's POST p95 within 3x, no 5xx but 503 with Retry-After);
                         p99 within 2x: bench/bench_flood.py (``bounds`` in its JSON), too noisy on 2 shared cores
    a large map deleted  tests/service/test_service_map_deletion.py
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import httpx
import pytest
import redis
from ping_watch import PING_BOUND_S, PingWatch
from redis_server import RedisServer
from store_cases import EDGE, make_object, snapshot_of, spread_object
from svc_helpers import UvicornThread, cube, make_test_frame

from arcloud.access import new_key
from arcloud.core.change import MapChange
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_api_keys import RedisKeyStore
from arcloud.tools.wiring import create_app

pytestmark = [pytest.mark.redis, pytest.mark.slow]

PROTOBUF = {"content-type": "application/x-protobuf"}


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with RedisServer.start() as server:
        yield server


@dataclass(frozen=True)
class Served:
    url: str
    redis_url: str
    tokens: dict[str, str]  # role -> a token of that role on every map

    def auth(self, role: str) -> dict[str, str]:
        return {"authorization": f"Bearer {self.tokens[role]}"}


@pytest.fixture
def served(redis_server: RedisServer) -> Iterator[Served]:
    """The API on an emptied Redis (keys in it, no workers: frames stay queued), event streams polled every 0.1 s."""
    with redis_server.client() as client:
        client.flushall()
    key_store = RedisKeyStore(redis_server.url)
    tokens = {}
    for role in ("admin", "device", "reader", "neighbour"):
        key, tokens[role] = new_key("reader" if role == "neighbour" else role, ("*",), now_s=time.time())
        key_store.add(key)
    key_store.close()
    settings = Settings(store=redis_server.url, detector="sim:0", workers=0, event_poll_s=0.1)
    with UvicornThread(create_app(settings)) as server:
        yield Served(server.url, redis_server.url, tokens)


def over_the_bound(answers: Iterable[httpx.Response]) -> list[str]:
    """The answers the issue's bound forbids: 5xx, but 503 with Retry-After."""
    return [
        f"{a.request.method} {a.request.url.path}: {a.status_code} {a.text[:200]}"
        for a in answers
        if a.status_code >= 500 and not (a.status_code == 503 and a.headers.get("retry-after"))
    ]


def watched(redis_url: str, hostile: Callable[[int], list[httpx.Response]]) -> tuple[PingWatch, list[httpx.Response]]:
    """``hostile(attempt)`` with another client's PING timed; once more when a PING went over the bound."""
    for attempt in range(2):
        with PingWatch(redis_url) as watch:
            answers = hostile(attempt)
        print(
            f"{len(answers)} answers {sorted({a.status_code for a in answers})}; PING max {1000 * watch.max_s:.1f} ms of "
            f"{len(watch.times_s)}, longest command {1000 * watch.longest_command_s:.1f} ms"
        )
        if watch.max_s < PING_BOUND_S:
            break
    return watch, answers


def in_threads(n_threads: int, work: Callable[[httpx.Client], list[httpx.Response]], url: str) -> list[httpx.Response]:
    """``work`` in ``n_threads`` threads, each with a client of its own: every answer."""
    answers: list[httpx.Response] = []
    lock = threading.Lock()

    def run() -> None:
        with httpx.Client(base_url=url, timeout=60) as http:
            got = work(http)
        with lock:
            answers.extend(got)

    threads = [threading.Thread(target=run) for _ in range(n_threads)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(120)
    return answers


def frame_body(map_id: str, index: int) -> bytes:
    return frame_to_proto(make_test_frame(index, map_id=map_id)).SerializeToString()


def test_a_restore_bomb_through_the_api(served: Served) -> None:
    """An admin key of one map sends a crafted snapshot (an object over the cell limit: 422 naming it, nothing
    written), then 60 objects of 4096 index cells each (one script of them held Redis about a second before)."""
    crafted = snapshot_of([make_object(1, (0.0, 0, 0)), spread_object(2, (20.0, 0, 0), EDGE + 1)])
    at_limit = snapshot_of([spread_object(i, (20.0 * i, 0, 0), EDGE) for i in range(1, 61)])
    zipped = {"content-type": "application/zip", **served.auth("admin")}

    def restore(attempt: int) -> list[httpx.Response]:
        with httpx.Client(base_url=served.url, timeout=120) as http:
            return [
                http.put(f"/v1/maps/bomb{attempt}/snapshot", content=crafted, headers=zipped),
                http.put(f"/v1/maps/bomb{attempt}/snapshot", content=at_limit, headers=zipped),
            ]

    watch, (refused, restored) = watched(served.redis_url, restore)
    assert refused.status_code == 422 and refused.json()["field"] == "objects/2.bounds", refused.text
    assert restored.status_code == 200 and restored.json()["restored_objects"] == 60, restored.text
    assert watch.max_s < PING_BOUND_S, f"a PING waited {watch.max_s:.3f} s during the restore"


def test_the_big_export_and_pages_of_many_readers(served: Served) -> None:
    """2,000 objects; 6 readers export them (JSON with voxels, PLY, glTF) and page through them at once."""
    store = RedisStore(served.redis_url)
    try:
        with httpx.Client(base_url=served.url, timeout=30) as http:
            posted = http.post("/v1/maps/big/frames", content=frame_body("big", 0), headers={**PROTOBUF, **served.auth("device")})
            assert posted.status_code == 202, posted.text
        for start in range(1, 2001, 100):
            store.commit("big", [], MapChange.writing("big", [cube(i) for i in range(start, start + 100)]))
    finally:
        store.close()
    reads = [
        ("/v1/maps/big/export", {"format": "json", "voxels": "true", "include": "tentative"}),
        ("/v1/maps/big/export", {"format": "ply", "include": "tentative"}),
        ("/v1/maps/big/export", {"format": "glb"}),
        ("/v1/maps/big/objects", {"limit": "1000", "include": "tentative"}),
        ("/v1/maps/big/objects", {"limit": "10", "cursor": "1500"}),
        ("/v1/maps/big/stats", {}),
    ]

    def read_all(http: httpx.Client) -> list[httpx.Response]:
        return [http.get(path, params=query, headers=served.auth("reader")) for path, query in reads * 2]

    watch, answers = watched(served.redis_url, lambda _attempt: in_threads(6, read_all, served.url))
    assert over_the_bound(answers) == []
    assert {a.status_code for a in answers} <= {200, 429}, sorted({a.status_code for a in answers})
    exported = [a for a in answers if a.status_code == 200 and a.request.url.params.get("voxels") == "true"]
    assert exported and len(exported[0].json()["objects"]) == 2000
    assert watch.max_s < PING_BOUND_S, f"a PING waited {watch.max_s:.3f} s during the exports"


def test_an_invalid_token_spray(served: Served) -> None:
    """400 random tokens from 8 threads of one address: 401, then 429 once the address failed too often."""
    rng = random.Random(22)
    alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-"
    tokens = [f"arc_{rng.getrandbits(48):012x}_{''.join(rng.choice(alphabet) for _ in range(43))}" for _ in range(400)]

    lock = threading.Lock()

    def spray(http: httpx.Client) -> list[httpx.Response]:
        with lock:
            mine = [tokens.pop() for _ in range(50)] if tokens else []
        return [http.get("/v1/maps/a/stats", headers={"authorization": f"Bearer {t}"}) for t in mine]

    watch, answers = watched(served.redis_url, lambda _attempt: in_threads(8, spray, served.url))
    assert over_the_bound(answers) == []
    statuses = [a.status_code for a in answers]
    assert set(statuses) <= {401, 429} and statuses.count(429) > 0, sorted(set(statuses))
    assert watch.max_s < PING_BOUND_S, f"a PING waited {watch.max_s:.3f} s during the spray"


def test_one_key_asking_for_100_streams(served: Served) -> None:
    """A reader key asks for 100 event streams of two maps (each open one polls Redis every 0.1 s); another key's
    viewer of one of them is served all the while."""
    with httpx.Client(base_url=served.url, timeout=30) as http:
        for map_id in ("a", "b"):
            answer = http.post(
                f"/v1/maps/{map_id}/frames", content=frame_body(map_id, 0), headers={**PROTOBUF, **served.auth("device")}
            )
            assert answer.status_code == 202, answer.text
    limits = httpx.Limits(max_connections=200, max_keepalive_connections=0)

    def hoard(_attempt: int) -> list[httpx.Response]:
        with httpx.Client(base_url=served.url, timeout=30, limits=limits) as http:
            opened: list[httpx.Response] = []
            try:
                for i in range(100):
                    request = http.build_request("GET", f"/v1/maps/{'ab'[i % 2]}/events", headers=served.auth("reader"))
                    opened.append(http.send(request, stream=True))
                    if opened[-1].status_code != 200:
                        opened[-1].read()
                neighbour = http.build_request("GET", "/v1/maps/a/events", headers=served.auth("neighbour"))
                opened.append(http.send(neighbour, stream=True))
                time.sleep(1.0)  # the open streams poll their maps
                return opened
            finally:
                for response in opened:
                    response.close()

    watch, answers = watched(served.redis_url, hoard)
    assert over_the_bound(answers) == []
    *hoarded, neighbour = answers
    statuses = [a.status_code for a in hoarded]
    assert statuses.count(200) == Settings().max_event_streams_per_key and set(statuses) == {200, 429}, statuses
    assert all(a.headers.get("retry-after") for a in hoarded if a.status_code == 429)
    assert neighbour.status_code == 200, "another key's viewer was refused a stream"
    assert watch.max_s < PING_BOUND_S, f"a PING waited {watch.max_s:.3f} s while the streams were open"


def test_a_flushall_under_a_workload_with_the_keys_in_the_data(served: Served) -> None:
    """Devices upload and readers read while the data Redis, keys and all, is flushed: the keys' loss answers 401
    (and /readyz 503 with Retry-After), never a 500."""
    stop = threading.Event()

    def workload(http: httpx.Client) -> list[httpx.Response]:
        answers = []
        index = 0
        while not stop.is_set():
            index += 1
            answers.append(
                http.post("/v1/maps/w/frames", content=frame_body("w", index), headers={**PROTOBUF, **served.auth("device")})
            )
            answers.append(http.get("/v1/maps/w/objects", headers=served.auth("reader")))
            answers.append(http.get("/v1/maps", headers=served.auth("reader")))
            answers.append(http.get("/readyz"))
        return answers

    collected: list[httpx.Response] = []
    runner = threading.Thread(target=lambda: collected.extend(in_threads(4, workload, served.url)))
    runner.start()
    time.sleep(1.0)
    with redis.Redis.from_url(served.redis_url) as client:
        client.flushall()
    time.sleep(7.0)  # past the key cache (5 s): lookups meet the flushed key store
    stop.set()
    runner.join(60)
    assert over_the_bound(collected) == []
    statuses = {a.status_code for a in collected}
    assert 401 in statuses and 202 in statuses, sorted(statuses)
    assert any(a.status_code == 503 and a.request.url.path == "/readyz" for a in collected), "readyz never said keys lost"
