"""The FrameQueue contract, run against every adapter: the embedded ``MemoryFrameQueue`` and
``RedisFrameQueue`` on a real redis-server. Where they differ by design (a failed frame: counted failed at
once in process, delivered again on Redis) each case says so."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
from redis_server import RedisServer

from arcloud.core.checks import make_frame
from arcloud.core.types import Frame
from arcloud.ports import FrameQueue, FrameStatus, QueueFull
from arcloud.stores import keys
from arcloud.stores.memory_queue import MemoryFrameQueue
from arcloud.stores.redis_queue import RedisFrameQueue

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


@pytest.fixture(params=["memory", pytest.param("redis", marks=pytest.mark.redis)])
def queue(request: pytest.FixtureRequest) -> Iterator[FrameQueue]:
    if request.param == "memory":
        yield MemoryFrameQueue(max_queued_frames=3)
        return
    server: RedisServer = request.getfixturevalue("redis_server")
    made = RedisFrameQueue(server.url, max_queued_frames=3, group="contract")
    made.client.flushdb()
    made.prepare()
    yield made
    made.close()


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
    queue.ack(item, redelivered=False, retries=2, elapsed_s=0.02)
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
    if isinstance(queue, RedisFrameQueue):
        ((entry_id, _fields),) = queue.client.xrange(keys.INGEST_STREAM)
        queue.client.xdel(keys.INGEST_STREAM, entry_id)
    else:  # in process a frame is lost only with its records: drop both, keeping the accepted mark
        assert isinstance(queue, MemoryFrameQueue)
        lost = queue._queue.get_nowait()
        del queue._status[lost.map_id][lost.key]


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


def test_heartbeats_tell_live_consumers(queue: FrameQueue) -> None:
    queue.heartbeat("c1", None)
    expected = [] if isinstance(queue, MemoryFrameQueue) else ["c1"]  # threads of one process need none
    assert queue.live_consumers(5.0) == expected
    queue.leave("c1")
    assert queue.live_consumers(5.0) == []
    assert all(v == "ok" for v in queue.health().values())
