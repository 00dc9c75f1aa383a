"""The key stores (a JSON file, Redis) and the rate limiters (memory, Redis), each against the same
expectations; the Redis ones on a real redis-server and on a real Redis Cluster."""

from __future__ import annotations

import json
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from redis_server import empty_redis_url

from arcloud.access import new_key, new_viewer_pass, secret_digest
from arcloud.errors import StoreError, StoreUnavailable
from arcloud.ports import KeyStore, RateLimiter, ViewerPasses
from arcloud.stores.file_api_keys import FileKeyStore
from arcloud.stores.keys import viewer_pass_key
from arcloud.stores.memory_rate import MemoryRateLimiter
from arcloud.stores.memory_viewer_passes import MemoryViewerPasses
from arcloud.stores.redis_api_keys import RedisKeyStore
from arcloud.stores.redis_rate import RedisRateLimiter
from arcloud.stores.redis_viewer_passes import RedisViewerPasses

REDIS = [pytest.param("redis", marks=pytest.mark.redis), pytest.param("cluster", marks=pytest.mark.redis)]


@pytest.fixture(params=["file", *REDIS])
def key_store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[KeyStore]:
    if request.param == "file":
        yield FileKeyStore(tmp_path / "keys.json")
        return
    store = RedisKeyStore(empty_redis_url(request))
    yield store
    store.close()


def test_keys_are_added_found_listed_and_revoked(key_store: KeyStore) -> None:
    first, _ = new_key("device", ("a", "b"), now_s=1.0, name="tablet")
    second, _ = new_key("admin", ("*",), now_s=2.0)
    assert key_store.find(first.id) is None and key_store.list_keys() == [] and key_store.count_keys() == 0
    key_store.add(first)
    key_store.add(second)
    assert key_store.find(first.id) == first
    assert [k.id for k in key_store.list_keys()] == [first.id, second.id] and key_store.count_keys() == 2
    assert key_store.revoke(first.id) is True
    assert key_store.revoke(first.id) is False
    assert key_store.find(first.id) is None and key_store.list_keys() == [second] and key_store.count_keys() == 1


def test_the_keys_file_holds_digests_only_is_private_and_survives_concurrent_writers(tmp_path: Path) -> None:
    path = tmp_path / "keys.json"
    created: list[tuple[str, str]] = []

    def create(index: int) -> None:
        key, token = new_key("reader", (f"m{index}",), now_s=float(index))
        FileKeyStore(path).add(key)  # each writer its own instance, as separate `keys create` runs are
        created.append((key.id, token))

    threads = [threading.Thread(target=create, args=(i,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    reader = FileKeyStore(path)
    assert sorted(k.id for k in reader.list_keys()) == sorted(key_id for key_id, _ in created)  # no write lost
    text = path.read_text()
    assert all(token.split("_", 2)[2] not in text for _, token in created)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    # A key revoked by another writer (the CLI) is gone at the reader's next lookup.
    FileKeyStore(path).revoke(created[0][0])
    assert reader.find(created[0][0]) is None


def test_a_corrupt_keys_file_is_an_error_not_an_open_door(tmp_path: Path) -> None:
    path = tmp_path / "keys.json"
    path.write_text(json.dumps({"keys": [{"id": "x"}]}))
    with pytest.raises(StoreError, match="keys file"):
        FileKeyStore(path).find("x")


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_memory_limiter_allows_a_burst_then_the_rate() -> None:
    clock = Clock()
    limiter = MemoryRateLimiter(clock)
    assert [limiter.take("k", rate_per_s=2.0, burst=3) for _ in range(3)] == [0.0, 0.0, 0.0]
    assert limiter.take("k", rate_per_s=2.0, burst=3) == pytest.approx(0.5)
    assert limiter.take("other", rate_per_s=2.0, burst=3) == 0.0  # buckets are independent
    clock.now += 0.5
    assert limiter.take("k", rate_per_s=2.0, burst=3) == 0.0
    assert limiter.take("k", rate_per_s=2.0, burst=3) == pytest.approx(0.5)
    clock.now += 10  # a long pause refills the burst, no more
    assert [limiter.take("k", rate_per_s=2.0, burst=3) for _ in range(4)][-1] == pytest.approx(0.5)


@pytest.fixture(params=REDIS)
def emptied_redis_url(request: pytest.FixtureRequest) -> str:
    """An emptied Redis, or Redis Cluster."""
    return empty_redis_url(request)


def test_redis_limiter_is_shared_by_every_client(emptied_redis_url: str) -> None:
    first, second = RedisRateLimiter(emptied_redis_url), RedisRateLimiter(emptied_redis_url)
    try:
        limiters: list[RateLimiter] = [first, second]
        answers = [limiters[i % 2].take("key:shared", rate_per_s=1.0, burst=4) for i in range(6)]
        assert answers[:4] == [0.0] * 4  # the burst, spent by both processes together
        assert 0.0 < answers[4] <= 1.0 and 0.0 < answers[5] <= 1.0  # refused: nothing spent
        assert first.take("key:other", rate_per_s=1.0, burst=4) == 0.0
        ttl_ms = first.client.pttl("arcloud:rate:key:shared")
        assert 0 < ttl_ms <= 4001  # the key goes once the bucket is full again
    finally:
        first.close()
        second.close()


# --- viewer passes (memory, Redis) ---------------------------------------------------------------------
@pytest.fixture(params=["memory", *REDIS])
def viewer_passes(request: pytest.FixtureRequest) -> Iterator[ViewerPasses]:
    if request.param == "memory":
        yield MemoryViewerPasses()
        return
    passes = RedisViewerPasses(empty_redis_url(request))
    yield passes
    passes.close()


def test_a_viewer_pass_is_found_until_taken_and_taken_once(viewer_passes: ViewerPasses) -> None:
    grant, secret = new_viewer_pass("ticket", "room", "0123456789ab", now_s=time.time(), ttl_s=60)
    digest = secret_digest(secret)
    assert viewer_passes.find(digest) is None
    viewer_passes.put(digest, grant)
    assert viewer_passes.find(digest) == grant
    taken = []
    threads = [threading.Thread(target=lambda: taken.append(viewer_passes.take(digest))) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(taken, key=lambda g: g is not None) == [None, None, None, grant]  # one of four takers got it
    assert viewer_passes.find(digest) is None


@pytest.mark.redis
def test_redis_drops_a_viewer_pass_when_it_expires(redis_url: str) -> None:
    passes = RedisViewerPasses(redis_url)
    grant, secret = new_viewer_pass("session", "room", "0123456789ab", now_s=time.time(), ttl_s=60)
    passes.put(secret_digest(secret), grant)
    ttl_ms = passes.client.pttl(viewer_pass_key(secret_digest(secret)))
    assert 55_000 < ttl_ms <= 60_000  # the secret itself is nowhere: the key is its digest
    passes.close()


def test_a_key_drawing_passes_past_its_bound_ends_its_own_oldest_never_another_keys(
    viewer_passes: ViewerPasses, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A review: in memory, a key holding no pass of its own ended the oldest pass of anyone once the store was full
    (another key's viewer logged out); on Redis nothing bounded a key (2.2 million sessions in a session's 12 h)."""
    import arcloud.stores.memory_viewer_passes as memory_passes
    import arcloud.stores.redis_viewer_passes as redis_passes

    monkeypatch.setattr(memory_passes, "MAX_VIEWER_PASSES_PER_KEY", 4)
    monkeypatch.setattr(redis_passes, "MAX_VIEWER_PASSES_PER_KEY", 4)
    now = time.time()
    victim, victim_secret = new_viewer_pass("session", "beta", "aaaaaaaaaaaa", now_s=now, ttl_s=3600)
    viewer_passes.put(secret_digest(victim_secret), victim)  # the oldest pass of all
    drawn = []
    for i in range(10):  # a reader key drawing sessions as fast as its rate lets it
        grant, secret = new_viewer_pass("session", "alpha", "bbbbbbbbbbbb", now_s=now + i, ttl_s=3600)
        viewer_passes.put(secret_digest(secret), grant)
        drawn.append(secret_digest(secret))
    assert viewer_passes.find(secret_digest(victim_secret)) == victim  # still logged in
    assert [viewer_passes.find(d) is not None for d in drawn] == [False] * 6 + [True] * 4  # its own oldest went
    assert viewer_passes.take(drawn[-1]) is not None  # a pass taken leaves room for one more of its key
    grant, secret = new_viewer_pass("ticket", "alpha", "bbbbbbbbbbbb", now_s=now, ttl_s=60)
    viewer_passes.put(secret_digest(secret), grant)
    assert [viewer_passes.find(d) is not None for d in drawn[-4:-1]] == [True] * 3


def test_a_full_memory_store_refuses_a_pass_rather_than_end_another_keys(monkeypatch: pytest.MonkeyPatch) -> None:
    import arcloud.stores.memory_viewer_passes as memory_passes

    monkeypatch.setattr(memory_passes, "MAX_PASSES", 3)
    passes, now = MemoryViewerPasses(), time.time()
    held = []
    for key_id in ("aaaaaaaaaaaa", "bbbbbbbbbbbb", "cccccccccccc"):
        grant, secret = new_viewer_pass("session", "m", key_id, now_s=now, ttl_s=3600)
        passes.put(secret_digest(secret), grant)
        held.append(secret_digest(secret))
    grant, secret = new_viewer_pass("ticket", "m", "dddddddddddd", now_s=now, ttl_s=60)
    with pytest.raises(StoreUnavailable, match="viewer passes: 3 live ones are kept"):
        passes.put(secret_digest(secret), grant)
    assert all(passes.find(d) is not None for d in held)
