"""Ingest shards of ``RedisFrameQueue``, on a real redis-server and on a real 3-primary Redis Cluster: maps
spread over the shards, every consumer reads every shard in turn, the overall limits are shared, the counters
sum, and the number of shards is kept in Redis so that a process configured otherwise refuses to start."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from redis_server import empty_redis_url
from test_queue_contract import frame

from arcloud.errors import InvalidInput
from arcloud.ports import FrameTimings, QueueFull, QueueLimits
from arcloud.stores import keys
from arcloud.stores.redis_queue import RedisFrameQueue, shard_limits

pytestmark = pytest.mark.redis

MakeQueue = Callable[..., RedisFrameQueue]
#: Maps and their shard of 3 (``keys.shard_of``): two maps in shard 0, one in each other.
SHARD_OF_3 = {"a": 0, "qmap": 0, "walk": 1, "b": 2}


@pytest.fixture(params=["redis", "cluster"])
def make_queue(request: pytest.FixtureRequest) -> Iterator[MakeQueue]:
    """``make_queue(shards=3, fresh=True, **QueueLimits fields)``: a queue on an emptied Redis (or cluster),
    prepared; ``fresh=False`` keeps what is there (another process of the same deployment)."""
    made: list[RedisFrameQueue] = []
    url = empty_redis_url(request)

    def make(shards: int = 3, *, fresh: bool = True, prepare: bool = True, **limits: Any) -> RedisFrameQueue:
        queue = RedisFrameQueue(
            empty_redis_url(request) if fresh else url, shards=shards, limits=QueueLimits(**limits), group="shards"
        )
        made.append(queue)
        if prepare:
            queue.prepare()
        return queue

    yield make
    for queue in made:
        queue.close()


def test_the_maps_used_here_fall_in_the_shards_said() -> None:
    assert {m: keys.shard_of(m, 3) for m in SHARD_OF_3} == SHARD_OF_3


def test_maps_go_to_their_shard_and_a_consumer_takes_from_every_shard_in_turn(make_queue: MakeQueue) -> None:
    queue = make_queue()
    for i in range(4):
        for map_id in ("a", "walk", "b"):
            assert queue.put(frame(i, map_id=map_id))
    depths = [int(queue.client.xlen(keys.ingest_stream(queue.shard_tag(shard)))) for shard in range(3)]
    assert depths == [4, 4, 4] and queue.stats().queue_depth == 12
    taken = [queue.take("c1", block_s=0.1) for _ in range(6)]
    shards = [queue.shard_of(item.map_id) for item in taken if item is not None]
    assert len(shards) == 6 and sorted(shards[:3]) == [0, 1, 2] and sorted(shards[3:]) == [0, 1, 2]  # no shard waits
    for item in taken:
        assert item is not None
        queue.ack(item, redelivered=False)
    rest = [queue.take("c2", block_s=0.1) for _ in range(7)]
    assert rest[-1] is None and sorted(item.map_id for item in rest[:-1] if item is not None) == [
        "a",
        "a",
        "b",
        "b",
        "walk",
        "walk",
    ]
    for item in rest[:-1]:
        assert item is not None
        queue.ack(item, redelivered=False, timings=FrameTimings(step_s=0.3, queue_wait_s=0.01, lock_wait_s=0.002))
    stats = queue.stats()  # every shard's counters, summed
    assert (stats.accepted, stats.processed, stats.queue_depth, stats.queued_bytes, stats.latency_count) == (12, 12, 0, 0, 12)
    assert stats.latency_sum_s == pytest.approx(6 * 0.3)
    assert (stats.queue_wait.count, stats.lock_wait.count) == (6, 12)  # the first 6 acknowledged without timings
    assert stats.queue_wait.sum_s == pytest.approx(6 * 0.01) and stats.lock_wait.sum_s == pytest.approx(6 * 0.002)


def test_a_consumer_waiting_on_an_empty_shard_gets_a_frame_of_another_soon(make_queue: MakeQueue) -> None:
    queue = make_queue()
    assert queue.take("c1", block_s=0.3) is None  # nothing anywhere: waited about block_s / shards on one
    queue.put(frame(0, map_id="b"))
    started = time.monotonic()
    item = queue.take("c1", block_s=0.3)
    assert item is not None and item.map_id == "b" and time.monotonic() - started < 0.3


def test_an_abandoned_frame_is_claimed_from_whichever_shard_holds_it(make_queue: MakeQueue) -> None:
    queue = make_queue()
    queue.put(frame(0, map_id="walk"))
    queue.put(frame(0, map_id="b"))
    first, second = queue.take("c1", block_s=0.1), queue.take("c1", block_s=0.1)
    assert first is not None and second is not None
    queue.ack(first, redelivered=False)
    time.sleep(0.02)
    claimed = queue.claim_abandoned("c2", min_idle_s=0.01)
    assert claimed is not None and claimed.frame_key == second.frame_key and claimed.map_id == second.map_id
    assert claimed.deliveries == 2 and queue.claim_abandoned("c3", min_idle_s=0.01) is None
    queue.heartbeat("c2", [claimed])  # keeps the entry in its shard fresh
    queue.dead_letter(claimed, "poison")
    assert queue.stats().claimed == 1 and queue.stats().failed == 1 and queue.stats().queue_depth == 0
    (failed,) = queue.failed_frames(claimed.map_id, 10)
    assert failed.retriable and queue.retry_failed(claimed.map_id, failed.frame_key)  # from its shard's dead letters


def test_the_overall_limits_are_shared_among_the_shards_and_a_maps_limits_are_kept(make_queue: MakeQueue) -> None:
    limits = QueueLimits(max_queued_frames=6, max_queued_frames_per_map=1, max_dead_letters=4)
    assert shard_limits(limits, 1) == limits
    share = shard_limits(limits, 3)
    assert (share.max_queued_frames, share.max_queued_frames_per_map, share.max_dead_letters) == (2, 1, 2)
    assert shard_limits(QueueLimits(max_queued_frames=6, max_queued_frames_per_map=5), 3).max_queued_frames == 5  # a map's fit
    assert shard_limits(QueueLimits(max_queued_frames=6, max_queued_frames_per_map=9), 3).max_queued_frames == 6  # never more
    queue = make_queue(max_queued_frames=9, max_queued_frames_per_map=2)  # a shard: 3
    assert queue.put(frame(0, map_id="a")) and queue.put(frame(1, map_id="a")) and queue.put(frame(0, map_id="qmap"))
    with pytest.raises(QueueFull, match=r"ingest shard 0 of 3 \(its share of max_queued_frames 9\): the queue holds 3 frames"):
        queue.put(frame(1, map_id="qmap"))  # shard 0 full, its map not
    assert queue.put(frame(0, map_id="b")) and queue.put(frame(1, map_id="b"))  # another shard has room
    with pytest.raises(QueueFull, match="map b has 2 frames queued"):
        queue.put(frame(2, map_id="b"))  # shard 2 not full, its map is


def test_another_number_of_shards_is_refused_at_start(make_queue: MakeQueue) -> None:
    make_queue(shards=3)
    assert int(make_queue(shards=3, fresh=False).client.get(keys.INGEST_SHARDS)) == 3  # the same: fine
    other = make_queue(shards=2, fresh=False, prepare=False)
    with pytest.raises(InvalidInput, match="ingest_shards: expected 3, the number of shards this Redis's queue has"):
        other.prepare()


def test_a_missing_group_is_reported_by_health(make_queue: MakeQueue, caplog: pytest.LogCaptureFixture) -> None:
    queue = make_queue(shards=1)
    assert queue.health() == {"redis": "ok", "consumer_group": "ok"} and not caplog.records
    queue.client.delete(keys.ingest_stream(queue.shard_tag(0)))  # its group with it
    assert queue.health() == {"redis": "ok", "consumer_group": "missing: no group shards on arcloud:ingest:{s0.0}"}
