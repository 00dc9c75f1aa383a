"""A caller waiting for a Redis lock or claim is woken by its release (BLPOP on the key's wake list), not by a
poll: it takes the lock within a round trip of the release, however long it may block, and the keys the wait
leaves behind expire with the lock. A step's commit releases its locks and claims itself: no release script
follows it (the waiter woken by the commit: ``test_store_contract``)."""

from __future__ import annotations

import threading
import time

import pytest
from redis.crc import key_slot
from redis_server import RedisServer
from store_cases import step_frame
from test_redis_cluster import Monitor

from arcloud.core.step import integrate_frame
from arcloud.core.types import Params
from arcloud.stores import keys, redis
from arcloud.stores.redis import RedisStore

MAP = "wake"

pytestmark = pytest.mark.redis


@pytest.mark.parametrize("kind", ["lock", "claim"])
def test_a_waiter_takes_the_lock_as_soon_as_it_is_released(
    redis_store: RedisStore, monkeypatch: pytest.MonkeyPatch, kind: str
) -> None:
    monkeypatch.setattr(redis, "WAKE_MAX_S", 5.0)  # a waiter that polled would wait this long
    take = redis_store.lock if kind == "lock" else redis_store.claim
    what = [7, 8] if kind == "lock" else [(0, 0, 0), (0, 0, 1)]
    held = take(MAP, what[:1], ttl_s=10, timeout_s=0)  # type: ignore[arg-type]  # ids or cells, by kind
    taken_at: list[float] = []

    def wait() -> None:
        with take(MAP, what, ttl_s=10, timeout_s=8):  # type: ignore[arg-type]  # ids or cells, by kind
            taken_at.append(time.monotonic())

    waiter = threading.Thread(target=wait)
    waiter.start()
    lease_key = keys.lock_key(MAP, 7) if kind == "lock" else keys.claim_key(MAP, (0, 0, 0))
    wanted = f"{lease_key}:wanted"
    deadline = time.monotonic() + 5
    while not redis_store.client.exists(wanted):  # the waiter found the key busy and waits
        assert time.monotonic() < deadline, "the waiter never marked the key wanted"
        time.sleep(0.01)
    assert 0 < redis_store.client.pttl(wanted) <= 10_000  # it expires with the holder's lock
    assert key_slot(wanted.encode()) == key_slot(keys.lease_wake_key(lease_key).encode()) == key_slot(lease_key.encode())
    time.sleep(0.2)
    released_at = time.monotonic()
    held.release()
    waiter.join(10)
    assert taken_at and taken_at[0] - released_at < 1.0, "woken by the release, not at the end of its 5 s wait"
    assert redis_store.client.pttl(keys.lease_wake_key(lease_key)) <= 1000  # a token left over expires soon


def test_an_uncontended_lock_leaves_no_wait_keys(redis_store: RedisStore) -> None:
    with redis_store.lock(MAP, [1, 2], ttl_s=10, timeout_s=0):
        pass
    assert not [k for k in redis_store.client.scan_iter(match=f"{keys.map_prefix(MAP)}:*")]


def test_a_waiter_still_times_out_when_the_holder_keeps_the_lock(redis_store: RedisStore) -> None:
    from arcloud.errors import LockTimeout

    held = redis_store.lock(MAP, [3], ttl_s=10, timeout_s=0)
    started = time.monotonic()
    with pytest.raises(LockTimeout, match="busy after 0.3 s"):
        redis_store.lock(MAP, [3], ttl_s=10, timeout_s=0.3)
    assert 0.3 <= time.monotonic() - started < 2.0
    held.release()


def test_a_step_that_commits_sends_no_release(redis_server: RedisServer, redis_store: RedisStore) -> None:
    params = Params(index_cell_m=0.5)
    monitor = Monitor(redis_server)
    created = integrate_frame(*step_frame(0, 0), redis_store, params)  # new objects: under space claims
    fused = integrate_frame(*step_frame(0, 1), redis_store, params)  # the same objects: under their locks
    commands = monitor.stop()
    assert created.created and fused.updated and not fused.created
    scripts = [args[1].decode() for source, args in commands if source != "lua" and args[:1] == [b"EVALSHA"]]
    assert redis_store._scripts["acquire"].sha in scripts and redis_store._scripts["commit"].sha in scripts
    assert redis_store._scripts["release"].sha not in scripts  # each commit released them
    assert not [k for k in redis_store.client.scan_iter(match=f"{keys.map_prefix('map-a')}:lock:*")]
    assert not [k for k in redis_store.client.scan_iter(match=f"{keys.map_prefix('map-a')}:claim:*")]
