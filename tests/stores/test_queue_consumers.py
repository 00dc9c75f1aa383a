"""Stale stream consumers are removed on a real redis-server: every worker start leaves a consumer (host-pid)
in the group, and 7 restarts left 14. A queue that prepares (each worker, each API at start) deletes the consumers
idle past ``stale_consumer_s`` with no pending entry and no fresh heartbeat, their old heartbeats and their
per-worker counters; a consumer holding an entry, or beating, stays."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
from redis_server import RedisServer

from arcloud.core.checks import make_frame
from arcloud.core.types import Frame
from arcloud.ports import FrameTimings
from arcloud.stores import keys
from arcloud.stores.redis_queue import RedisFrameQueue

pytestmark = pytest.mark.redis

STALE_S = 0.3
GROUP = "sweep"


def frame(index: int) -> Frame:
    rng = np.random.default_rng(index)
    rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (12, 16)).astype(np.float32)
    return make_frame(
        rgb, depth, (20.0, 20.0, 7.5, 5.5), np.eye(4), timestamp_s=index / 30, map_id="m", device_id="d", frame_id=f"f{index:03d}"
    )


@pytest.fixture
def url(redis_server: RedisServer) -> Iterator[str]:
    client = redis_server.client()
    client.flushdb()
    client.close()
    yield redis_server.url


def consumers(queue: RedisFrameQueue) -> dict[str, int]:
    """The group's consumers -> their pending entries."""
    found = queue.client.xinfo_consumers(keys.ingest_stream(queue.shard_tag(0)), GROUP)
    return {c["name"].decode(): int(c["pending"]) for c in found}


def worker_fields(queue: RedisFrameQueue) -> set[str]:
    return {f.decode() for f in queue.client.hkeys(keys.ingest_stats(queue.shard_tag(0))) if f.startswith(b"worker:")}


def test_seven_restarts_leave_one_consumer_not_fourteen(url: str) -> None:
    queue = RedisFrameQueue(url, group=GROUP, stale_consumer_s=STALE_S)
    try:
        for restart in range(7):  # each worker: starts (prepares), takes and settles a frame, stops (leaves)
            name = f"host-{100 + restart}"
            queue.prepare()
            queue.heartbeat(name, ())
            queue.put(frame(restart))
            item = queue.take(name, block_s=1.0)
            assert item is not None
            queue.ack(item, redelivered=False, timings=FrameTimings(step_s=0.01))
            queue.leave(name)
        assert len(consumers(queue)) == 7 and len(worker_fields(queue)) == 7
        assert queue.stats().workers["host-106"] == {"processed": 1}
        time.sleep(STALE_S + 0.2)
        queue.prepare()  # the eighth start
        assert consumers(queue) == {} and worker_fields(queue) == set()
        assert queue.stats().workers == {} and queue.stats().processed == 7  # the totals stay
    finally:
        queue.close()


def test_a_consumer_holding_an_entry_or_beating_stays(url: str) -> None:
    queue = RedisFrameQueue(url, group=GROUP, stale_consumer_s=STALE_S)
    try:
        queue.prepare()
        for index in range(3):
            queue.put(frame(index))
        for name in ("died-holding", "live-idle", "stopped"):
            item = queue.take(name, block_s=1.0)
            assert item is not None
            if name != "died-holding":
                queue.ack(item, redelivered=False, timings=FrameTimings(step_s=0.01))
        queue.client.hset(keys.INGEST_WORKERS, "stopped", repr(time.time() - 3600))  # a heartbeat it left an hour ago
        time.sleep(STALE_S + 0.2)
        queue.heartbeat("live-idle", ())  # alive, with nothing to do: idle in the group, but beating
        assert queue.remove_stale_consumers() == ["stopped"]
        assert consumers(queue) == {"died-holding": 1, "live-idle": 0}
        assert set(queue.client.hkeys(keys.INGEST_WORKERS)) == {b"live-idle"}  # the hour-old heartbeat went
        assert worker_fields(queue) == {"worker:live-idle:processed"}
        # Its entry claimed by another, the dead consumer holds nothing: the next sweep takes it.
        claimed = queue.claim_abandoned("live-idle", min_idle_s=0.01)
        assert claimed is not None and claimed.consumer == "live-idle"
        queue.ack(claimed, redelivered=False, timings=FrameTimings(step_s=0.01))
        time.sleep(STALE_S + 0.2)
        queue.heartbeat("live-idle", ())
        assert queue.remove_stale_consumers() == ["died-holding"]
        assert consumers(queue) == {"live-idle": 0} and queue.stats().workers == {"live-idle": {"processed": 2}}
    finally:
        queue.close()
