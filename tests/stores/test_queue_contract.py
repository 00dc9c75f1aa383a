"""The FrameQueue contract, run against every adapter: the embedded ``MemoryFrameQueue``, ``RedisFrameQueue``
on a real redis-server (one ingest shard) and on a real 3-primary Redis Cluster (three shards). Where they
differ by design (a failed frame: counted failed at once in process, delivered again on Redis; the overall
limits shared among shards) each case says so."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from redis_server import ADAPTERS, empty_redis_url
from store_cases import Clock

from arcloud.core.checks import make_frame
from arcloud.core.types import Frame
from arcloud.errors import InvalidInput
from arcloud.ports import WAIT_BUCKETS_S, FrameQueue, FrameStatus, FrameTimings, QueueFull, QueueLimits
from arcloud.stores import keys
from arcloud.stores.memory_queue import MemoryFrameQueue, queued_bytes
from arcloud.stores.redis_queue import RedisFrameQueue
from arcloud.stores.stream_frames import encode_frame

MAP = "qmap"


def frame(index: int, *, map_id: str = MAP) -> Frame:
    rng = np.random.default_rng(index)
    rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (12, 16)).astype(np.float32)
    return make_frame(
        rgb,
        depth,
        (20.0, 20.0, 7.5, 5.5),
        np.eye(4),
        timestamp_s=index / 30,
        map_id=map_id,
        device_id="d",
        frame_id=f"f{index:03d}",
    )


MakeQueue = Callable[..., FrameQueue]


#: Ingest shards of the Redis adapters under test: one on a single Redis (the default), three on the cluster.
SHARDS = {"redis": 1, "cluster": 3}


@pytest.fixture(params=ADAPTERS)
def make_queue(request: pytest.FixtureRequest) -> Iterator[MakeQueue]:
    """Builds the adapter under test: ``make_queue(clock=..., shards=..., **QueueLimits fields)`` (an empty
    Redis; ``shards`` overrides ``SHARDS``, and the embedded queue has none)."""
    made: list[RedisFrameQueue] = []

    def make(clock: Callable[[], float] = time.time, shards: int | None = None, **limits: Any) -> FrameQueue:
        if request.param == "memory":
            return MemoryFrameQueue(limits=QueueLimits(**limits), clock=clock)
        queue = RedisFrameQueue(
            empty_redis_url(request),
            limits=QueueLimits(**limits),
            group="contract",
            shards=shards or SHARDS[request.param],
            clock=clock,
        )
        queue.prepare()
        made.append(queue)
        return queue

    yield make
    for queue in made:
        queue.close()


@pytest.fixture
def queue(make_queue: MakeQueue) -> FrameQueue:
    return make_queue(max_queued_frames=3)


def test_a_take_without_waiting_answers_at_once(queue: FrameQueue) -> None:
    """``block_s=0`` (a prefetching worker with a frame in hand) never waits: on Redis a BLOCK 1 read timed
    out on the server's clock, 0-100 ms later (50 ms of every frame's latency measured)."""
    started = time.perf_counter()
    assert all(queue.take("c1", block_s=0) is None for _ in range(10))
    assert time.perf_counter() - started < 0.25
    queue.put(frame(1))
    item = queue.take("c1", block_s=0)
    assert item is not None and item.frame_key == frame(1).key


def test_a_frame_goes_through_once_and_is_counted(queue: FrameQueue) -> None:
    sent = frame(1)
    assert not queue.known_map(MAP)
    assert queue.put(sent) is True
    assert queue.put(sent) is False  # a duplicate: not queued again
    assert queue.known_map(MAP) and queue.map_counts(MAP) == (1, 0)
    assert queue.stats().queue_depth == 1
    item = queue.take("c1", block_s=0.5)
    assert item is not None and (item.map_id, item.frame_key, item.consumer, item.deliveries) == (MAP, sent.key, "c1", 1)
    assert item.frame is not None and item.frame.key == sent.key
    np.testing.assert_array_equal(item.frame.depth_m, sent.depth_m)  # carried losslessly
    np.testing.assert_array_equal(item.frame.rgb, sent.rgb)
    assert queue.take("c1", block_s=0.05) is None
    queue.ack(item, redelivered=False, retries=2, timings=FrameTimings(step_s=0.02))
    stats = queue.stats()
    assert (
        stats.accepted,
        stats.duplicates,
        stats.processed,
        stats.redelivered,
        stats.retried,
        stats.failed,
        stats.queue_depth,
    ) == (1, 1, 1, 0, 2, 0, 0)
    assert stats.latency_count == 1 and stats.latency_sum_s == pytest.approx(0.02)


def test_a_processed_frame_s_waits_are_counted_in_the_histograms(queue: FrameQueue) -> None:
    before = time.time()
    queue.put(frame(3))
    item = queue.take("c1", block_s=0.5)
    assert item is not None and item.accepted_at_s is not None and before <= item.accepted_at_s <= time.time()
    queue.ack(item, redelivered=False, timings=FrameTimings(step_s=0.2, queue_wait_s=0.004, lock_wait_s=0.0007))
    queue.put(frame(4))
    other = queue.take("c1", block_s=0.5)
    assert other is not None
    queue.ack(other, redelivered=False, timings=FrameTimings(step_s=0.2, queue_wait_s=None, lock_wait_s=70.0))
    stats = queue.stats()
    assert stats.queue_wait.bounds_s == stats.lock_wait.bounds_s == WAIT_BUCKETS_S
    assert stats.queue_wait.count == 1 and stats.queue_wait.sum_s == pytest.approx(0.004)  # None: not counted
    assert stats.queue_wait.counts[WAIT_BUCKETS_S.index(0.005)] == 1
    assert stats.lock_wait.count == 2 and stats.lock_wait.sum_s == pytest.approx(70.0007)
    assert stats.lock_wait.counts[WAIT_BUCKETS_S.index(0.001)] == 1 and stats.lock_wait.counts[-1] == 1  # +Inf
    assert stats.latency_count == 2 and stats.latency_sum_s == pytest.approx(0.4)


def test_a_redelivered_frame_is_not_counted_processed(queue: FrameQueue) -> None:
    queue.put(frame(2))
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    queue.ack(item, redelivered=True)
    stats = queue.stats()
    assert (stats.processed, stats.redelivered, stats.latency_count, stats.queue_depth) == (0, 1, 0, 0)


def test_a_full_queue_refuses(queue: FrameQueue) -> None:
    for i in range(3):
        assert queue.put(frame(i))
    with pytest.raises(QueueFull, match="try again later"):
        queue.put(frame(9))
    assert queue.map_counts(MAP) == (3, 0)  # the refused frame was not accepted: a retry goes through


def test_dead_letters_are_counted_failed_and_may_be_posted_again(queue: FrameQueue) -> None:
    queue.put(frame(3))
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    queue.dead_letter(item, "poison")
    assert queue.map_counts(MAP) == (1, 1) and queue.stats().failed == 1 and queue.stats().queue_depth == 0
    assert queue.put(frame(3)) is True  # failed before: queued again
    assert queue.map_counts(MAP) == (1, 0)
    queue.forget_map(MAP)
    assert not queue.known_map(MAP) and queue.map_counts(MAP) == (0, 0)


def test_a_frame_dead_lettered_twice_counts_one_failed_frame(queue: FrameQueue) -> None:
    # Two workers that gave one entry up (one paused between giving it up in the store and dead-lettering it while
    # the other claimed it and did both): one failed frame, in the map's counts and in the queue's stats.
    queue.put(frame(5))
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    queue.dead_letter(item, "delivered too often")
    queue.dead_letter(item, "delivered too often")
    assert queue.map_counts(MAP) == (1, 1) and queue.stats().failed == 1 and queue.stats().queue_depth == 0


def test_a_failed_frame_is_counted_failed_in_process_and_delivered_again_on_redis(queue: FrameQueue) -> None:
    queue.put(frame(4))
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    queue.fail(item, "RuntimeError: boom")
    if isinstance(queue, MemoryFrameQueue):
        assert queue.map_counts(MAP) == (1, 1) and queue.claim_abandoned("c2", min_idle_s=0.0) is None
        return
    assert queue.map_counts(MAP) == (1, 0)  # pending, not failed
    assert queue.take("c2", block_s=0.05) is None  # not a new entry
    time.sleep(0.05)
    again = queue.claim_abandoned("c2", min_idle_s=0.01)
    assert again is not None and again.deliveries == 2 and again.consumer == "c2" and again.frame_key == item.frame_key
    assert queue.stats().claimed == 1


def lose_entry(queue: FrameQueue) -> None:
    """Drop the queued entry as a crash would leave it: recorded as accepted, no longer in the queue."""
    if isinstance(queue, RedisFrameQueue):  # the entry, and its part of the backlog, gone
        tag = queue.shard_tag(queue.shard_of(MAP))
        ((entry_id, fields),) = queue.client.xrange(keys.ingest_stream(tag))
        queue.client.xdel(keys.ingest_stream(tag), entry_id)
        n_bytes, map_id = int(fields[b"bytes"]), fields[b"map_id"].decode()
        for field, delta in (("frames", 1), ("bytes", n_bytes), (f"frames:{map_id}", 1), (f"bytes:{map_id}", n_bytes)):
            queue.client.hincrby(keys.ingest_backlog(tag), field, -delta)
    else:  # in process a frame is lost only with the process: as if it were, keeping its record
        assert isinstance(queue, MemoryFrameQueue)
        lost, n_bytes, _accepted_at_s = queue._ready.popleft()
        queue._count(lost.map_id, -1, -n_bytes)
        queue._maps[lost.map_id].status[lost.key] = FrameStatus("unknown")


def test_a_frame_in_the_queue_in_hand_or_processed_is_a_duplicate(queue: FrameQueue) -> None:
    sent = frame(5)
    assert queue.put(sent) is True
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    assert queue.put(sent) is False  # in hand (pending)
    queue.ack(item, redelivered=False)
    assert queue.put(sent) is False  # processed
    assert queue.stats().duplicates == 2 and queue.stats().queue_depth == 0


def test_a_frame_accepted_but_lost_is_queued_again_on_retry_and_processed_once(queue: FrameQueue) -> None:
    sent = frame(6)
    assert queue.put(sent) is True
    lose_entry(queue)
    assert queue.take("c1", block_s=0.05) is None
    assert queue.put(sent) is True  # neither queued nor processed nor failed: queued again, not a duplicate
    assert queue.map_counts(MAP) == (1, 0)
    item = queue.take("c1", block_s=0.5)
    assert item is not None and item.frame_key == sent.key
    queue.ack(item, redelivered=False)
    assert queue.put(sent) is False and queue.take("c1", block_s=0.05) is None
    stats = queue.stats()
    assert (stats.accepted, stats.processed, stats.duplicates, stats.queue_depth) == (2, 1, 1, 0)


def test_a_frame_status_follows_it_from_accepted_to_processed_or_failed(queue: FrameQueue) -> None:
    ok, bad = frame(7), frame(8)
    assert queue.frame_status(MAP, ok.key) is None  # never accepted
    queue.put(ok)
    assert queue.frame_status(MAP, ok.key) == FrameStatus("queued")
    item = queue.take("c1", block_s=0.5)
    assert item is not None and queue.frame_status(MAP, ok.key) == FrameStatus("processing")
    queue.ack(item, redelivered=False)
    assert queue.frame_status(MAP, ok.key) == FrameStatus("processed")
    queue.put(bad)
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    queue.dead_letter(item, "InvalidInput: detections[0].label: expected a class")
    assert queue.frame_status(MAP, bad.key) == FrameStatus("failed", "InvalidInput: detections[0].label: expected a class")
    queue.put(bad)  # failed before: queued again
    lose_entry(queue)
    assert queue.frame_status(MAP, bad.key) == FrameStatus("unknown")  # accepted, then lost: a retry queues it again
    queue.forget_map(MAP)
    assert queue.frame_status(MAP, ok.key) is None


def test_a_frame_settled_while_its_status_is_read_is_processed_not_lost(
    make_queue: MakeQueue, monkeypatch: pytest.MonkeyPatch
) -> None:
    queue = make_queue()
    if not isinstance(queue, RedisFrameQueue):
        pytest.skip("the embedded queue reads a frame's status under the lock its worker settles it under")
    sent = frame(9)
    queue.put(sent)
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    read_entry = queue.client.xrange

    def settled_first(*args: Any, **kwargs: Any) -> Any:  # the worker acknowledges between the status's two reads
        monkeypatch.setattr(queue.client, "xrange", read_entry)
        queue.ack(item, redelivered=False)
        return read_entry(*args, **kwargs)

    monkeypatch.setattr(queue.client, "xrange", settled_first)
    assert queue.frame_status(MAP, sent.key) == FrameStatus("processed")  # was "unknown": the client counted it lost
    assert queue.client.xrange is read_entry  # the entry was read, after the ack


def test_settled_frames_are_counted_per_map_and_per_worker_and_a_forgotten_map_s_go(make_queue: MakeQueue) -> None:
    queue = make_queue()
    for index, map_id in ((1, "ma"), (2, "ma"), (3, "mb"), (4, "mb")):
        queue.put(frame(index, map_id=map_id))
    assert queue.stats().map_depth == {"ma": 2, "mb": 2}
    by_frame = {}
    for consumer in ("w1", "w2", "w1", "w2"):
        item = queue.take(consumer, block_s=0.5)
        assert item is not None
        by_frame[item.frame_key] = item
    queue.ack(by_frame["d/f001"], redelivered=False, timings=FrameTimings(step_s=0.01))
    queue.ack(by_frame["d/f002"], redelivered=True)
    queue.ack(by_frame["d/f003"], redelivered=False, timings=FrameTimings(step_s=0.01))
    queue.dead_letter(by_frame["d/f004"], "InvalidInput: no")
    stats = queue.stats()
    assert stats.maps == {"ma": {"processed": 1, "redelivered": 1}, "mb": {"processed": 1, "failed": 1}}
    workers: dict[str, dict[str, int]] = {}
    for key, outcome in (("d/f001", "processed"), ("d/f002", "redelivered"), ("d/f003", "processed"), ("d/f004", "failed")):
        counts = workers.setdefault(by_frame[key].consumer, {})
        counts[outcome] = counts.get(outcome, 0) + 1
    assert stats.workers == workers and stats.map_depth == {}
    queue.forget_map("ma")
    assert queue.stats().maps == {"mb": {"processed": 1, "failed": 1}}


def test_heartbeats_tell_live_consumers(queue: FrameQueue) -> None:
    queue.heartbeat("c1", ())
    expected = [] if isinstance(queue, MemoryFrameQueue) else ["c1"]  # threads of one process need none
    assert queue.live_consumers(5.0) == expected
    queue.leave("c1")
    assert queue.live_consumers(5.0) == []
    assert all(v == "ok" for v in queue.health().values())


# --- limits: frames and bytes, overall and per map ---------------------------------------------------
def sized_frame(index: int, *, map_id: str = MAP, height: int = 12, width: int = 16) -> Frame:
    """``frame(index)`` at another size (the intrinsics scaled along)."""
    rng = np.random.default_rng(index)
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (height, width)).astype(np.float32)
    intrinsics = (20.0 * width / 16, 20.0 * width / 16, (width - 1) / 2, (height - 1) / 2)
    return make_frame(
        rgb, depth, intrinsics, np.eye(4), timestamp_s=index / 30, map_id=map_id, device_id="d", frame_id=f"f{index:03d}"
    )


def held_bytes(queue: FrameQueue, sent: Frame) -> int:
    """What ``queue`` counts of ``sent``: the stream entry's frame bytes on Redis, the arrays in process."""
    return len(encode_frame(sent)) if isinstance(queue, RedisFrameQueue) else queued_bytes(sent)


def backlog_is_empty(queue: FrameQueue) -> bool:
    stats = queue.stats()
    if isinstance(queue, RedisFrameQueue):
        backlogs = [queue.client.hgetall(keys.ingest_backlog(queue.shard_tag(shard))) for shard in range(queue.shards)]
        per_map_empty = all(int(v) == 0 for backlog in backlogs for v in backlog.values())
    else:
        assert isinstance(queue, MemoryFrameQueue)
        per_map_empty = not queue._map_frames and not queue._map_bytes
    return stats.queue_depth == 0 and stats.queued_bytes == 0 and per_map_empty


def test_a_map_at_its_frame_limit_is_refused_while_another_map_is_accepted(make_queue: MakeQueue) -> None:
    queue = make_queue(max_queued_frames=5, max_queued_frames_per_map=2, shards=1)  # one shard: the overall limit whole
    assert queue.put(frame(0, map_id="a")) and queue.put(frame(1, map_id="a"))
    with pytest.raises(
        QueueFull, match="map a has 2 frames queued \\(max_queued_frames_per_map 2\\); try again later"
    ) as refused:
        queue.put(frame(2, map_id="a"))
    assert refused.value.limit == "max_queued_frames_per_map"
    assert queue.put(frame(0, map_id="b")) and queue.put(frame(1, map_id="b"))  # another map still gets in
    assert queue.map_counts("a") == (2, 0)  # the refused frame was not accepted
    item = queue.take("c1", block_s=0.5)  # a's first frame: settled, it makes room for one more of a
    assert item is not None and item.map_id == "a"
    queue.ack(item, redelivered=False)
    assert queue.put(frame(2, map_id="a"))
    assert queue.put(frame(0, map_id="c"))
    with pytest.raises(QueueFull, match="the queue holds 5 frames \\(max_queued_frames 5\\)") as refused:
        queue.put(frame(0, map_id="d"))  # the overall limit refuses every map
    assert refused.value.limit == "max_queued_frames"


def test_a_map_at_its_byte_limit_is_refused_while_another_map_is_accepted(make_queue: MakeQueue) -> None:
    probe = make_queue()
    size = held_bytes(probe, frame(0))
    queue = make_queue(max_queued_bytes_per_map=2 * size + size // 2)
    assert queue.put(frame(0, map_id="a")) and queue.put(frame(1, map_id="a"))
    with pytest.raises(QueueFull, match=f"map a has {2 * size / 1e6:.1f} MB queued; this frame's") as refused:
        queue.put(frame(2, map_id="a"))
    assert refused.value.limit == "max_queued_bytes_per_map"
    assert queue.put(frame(0, map_id="b"))
    assert queue.stats().queued_bytes == 3 * size


def test_the_byte_limit_refuses_a_large_frame_that_small_ones_pass(make_queue: MakeQueue) -> None:
    small, large = frame(0), sized_frame(1, height=48, width=64)
    probe = make_queue()
    small_bytes, large_bytes = held_bytes(probe, small), held_bytes(probe, large)
    assert large_bytes > 10 * small_bytes
    queue = make_queue(max_queued_bytes=large_bytes + small_bytes - 1)
    assert queue.put(small)
    with pytest.raises(QueueFull, match="the queue holds .* MB queued; this frame's .* would pass max_queued_bytes") as refused:
        queue.put(large)
    assert refused.value.limit == "max_queued_bytes"
    assert queue.put(frame(2)) and queue.put(frame(3))  # small frames still fit beside
    for _ in range(3):
        item = queue.take("c1", block_s=0.5)
        assert item is not None
        queue.ack(item, redelivered=False)
    assert queue.put(large)  # alone it fits
    assert queue.stats().queued_bytes == large_bytes


def test_the_backlog_returns_to_zero_once_every_frame_is_acknowledged_or_dead_lettered(make_queue: MakeQueue) -> None:
    queue = make_queue()
    sent = [frame(i, map_id="ab"[i % 2]) for i in range(6)]
    for each in sent:
        queue.put(each)
    assert queue.stats().queue_depth == 6 and queue.stats().queued_bytes == sum(held_bytes(queue, f) for f in sent)
    taken = [queue.take("c1", block_s=0.5) for _ in range(6)]
    assert all(item is not None for item in taken)
    first, second, third, fourth, fifth, sixth = taken
    assert first is not None and second is not None and third is not None
    assert fourth is not None and fifth is not None and sixth is not None
    queue.ack(first, redelivered=False)
    queue.ack(first, redelivered=True)  # settled twice (a claimed frame's slow worker): counted off once
    queue.fail(second, "RuntimeError: boom")  # Redis: still pending, still counted
    if isinstance(queue, RedisFrameQueue):
        assert queue.stats().queue_depth == 5 and not backlog_is_empty(queue)
    queue.dead_letter(third, "poison")
    queue.dead_letter(third, "poison")
    queue.forget_map("b")  # the map deleted while its frames are in hand: they still leave the backlog
    for item in (fourth, fifth, sixth):
        queue.ack(item, redelivered=False)
    if isinstance(queue, RedisFrameQueue):  # the failed frame, the one left pending, claimed and given up
        assert not backlog_is_empty(queue)
        time.sleep(0.02)
        second = queue.claim_abandoned("c2", min_idle_s=0.01)
        assert second is not None and second.deliveries == 2
        queue.dead_letter(second, "poison")
    assert backlog_is_empty(queue)
    assert not queue.known_map("b") and queue.map_counts("a") == (3, 1)  # nothing of b written back


# --- records: retention, counts, dead letters --------------------------------------------------------
def kept_records(queue: FrameQueue, map_id: str) -> int:
    """How many frame records of the map the queue holds."""
    if isinstance(queue, RedisFrameQueue):
        return int(queue.client.hlen(keys.ingest_status_key(queue.shard_tag(queue.shard_of(map_id)), map_id)))
    assert isinstance(queue, MemoryFrameQueue)
    records = queue._maps.get(map_id)
    return 0 if records is None else len(records.status)


def test_settled_records_are_dropped_after_the_retention_and_the_counts_stay(make_queue: MakeQueue) -> None:
    clock = Clock()
    queue = make_queue(clock=clock, frame_record_retention_s=10.0)
    n_frames = 300
    for i in range(n_frames):
        sent = frame(i)
        assert queue.put(sent)
        item = queue.take("c1", block_s=0.5)
        assert item is not None
        if i % 10 == 9:
            queue.dead_letter(item, f"poison {i}")
        else:
            queue.ack(item, redelivered=False)
        clock.now_s += 1.0
    assert kept_records(queue, MAP) <= 11  # the frames of the last 10 s, not 300
    assert queue.map_counts(MAP) == (n_frames, n_frames // 10)  # counters: records expiring do not lower them
    assert queue.frame_status(MAP, frame(0).key) is None  # gone: as never accepted (404)
    assert queue.frame_status(MAP, frame(n_frames - 2).key) == FrameStatus("processed")
    assert queue.put(frame(n_frames - 2)) is False  # within the retention: a duplicate
    assert queue.put(frame(0)) is True  # past it: a new frame
    assert queue.map_counts(MAP) == (n_frames + 1, n_frames // 10)
    assert [f.frame_key for f in queue.failed_frames(MAP, 10)] == [frame(n_frames - 1).key]
    clock.now_s += 10.5  # past the retention of every settled frame, nothing trimmed yet: gone all the same
    assert queue.frame_status(MAP, frame(n_frames - 2).key) is None and queue.failed_frames(MAP, 10) == []
    assert queue.put(frame(n_frames - 2)) is True


def test_a_failed_frame_is_listed_with_its_reason_and_queued_again_from_its_dead_letter(make_queue: MakeQueue) -> None:
    clock = Clock()
    queue = make_queue(clock=clock, max_queued_frames_per_map=1)
    sent = frame(1)
    queue.put(sent)
    item = queue.take("c1", block_s=0.5)
    assert item is not None
    queue.dead_letter(item, "InvalidInput: detections[0].label: expected a class")
    (failed,) = queue.failed_frames(MAP, 10)
    assert (failed.frame_key, failed.reason, failed.deliveries, failed.failed_at_s, failed.retriable) == (
        sent.key,
        "InvalidInput: detections[0].label: expected a class",
        1,
        clock.now_s,
        True,
    )
    with pytest.raises(InvalidInput, match="a failed frame of map qmap, got d/f009: no record"):
        queue.retry_failed(MAP, frame(9).key)
    queue.put(frame(2))  # the map's one place taken: the retry is refused by the limit
    with pytest.raises(QueueFull, match="max_queued_frames_per_map"):
        queue.retry_failed(MAP, sent.key)
    other = queue.take("c1", block_s=0.5)
    assert other is not None
    queue.ack(other, redelivered=False)
    assert queue.retry_failed(MAP, sent.key) is True
    assert queue.frame_status(MAP, sent.key) == FrameStatus("queued") and queue.map_counts(MAP) == (2, 0)
    assert queue.failed_frames(MAP, 10) == []
    again = queue.take("c1", block_s=0.5)
    assert again is not None and again.frame is not None and again.frame_key == sent.key
    np.testing.assert_array_equal(again.frame.depth_m, sent.depth_m)  # the dead letter carried it whole
    queue.ack(again, redelivered=False)
    assert queue.frame_status(MAP, sent.key) == FrameStatus("processed")
    with pytest.raises(InvalidInput, match="got d/f001: processed"):
        queue.retry_failed(MAP, sent.key)


def test_dead_letters_are_capped_and_the_oldest_go_first(make_queue: MakeQueue) -> None:
    clock = Clock()
    queue = make_queue(clock=clock, max_dead_letters=2, shards=1)  # one shard: the cap whole
    for i in range(3):
        queue.put(frame(i))
        item = queue.take("c1", block_s=0.5)
        assert item is not None
        queue.dead_letter(item, f"poison {i}")
        clock.now_s += 1.0
    listed = queue.failed_frames(MAP, 10)
    assert [(f.frame_key, f.reason, f.retriable) for f in listed] == [
        ("d/f002", "poison 2", True),
        ("d/f001", "poison 1", True),
        ("d/f000", "poison 0", False),  # its reason kept, its payload dropped
    ]
    assert [f.frame_key for f in queue.failed_frames(MAP, 1)] == ["d/f002"]
    with pytest.raises(InvalidInput, match="dead letter is kept, got d/f000: dropped"):
        queue.retry_failed(MAP, "d/f000")
    assert queue.put(frame(0)) is True  # a device may still post it again
    if isinstance(queue, RedisFrameQueue):
        tag = queue.shard_tag(queue.shard_of(MAP))
        assert queue.client.xlen(keys.ingest_dead_letter_stream(tag)) == 2
        kept = sum(len(fields[b"frame"]) for _, fields in queue.client.xrange(keys.ingest_dead_letter_stream(tag)))
        assert int(queue.client.get(keys.ingest_dead_letter_bytes(tag))) == kept
