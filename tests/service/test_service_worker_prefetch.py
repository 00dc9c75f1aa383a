"""``FrameWorker(prefetch=True)`` (``ARCLOUD_WORKER_PREFETCH``): the worker detects its next frame while it
integrates the one before. On a real redis-server with the real queue and store, a worker in a thread as
the service runs it: every frame processed once, the same map as one frame at a time, both frames in hand
kept fresh by the heartbeat, a stop finishing them, and a detector failure on the prefetched frame
delivered again and dead-lettered as before.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

import pytest
import redis
from redis_server import RedisServer
from svc_helpers import BlobDetector, make_test_frame, wait_until

from arcloud.core.types import Frame, ObjectEvent, Params
from arcloud.service.change_feed import ChangeFeed
from arcloud.service.worker import FrameWorker
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue

pytestmark = [pytest.mark.redis]

STREAM = keys.ingest_stream(keys.shard_tag(0, 1))
GROUP = "arcloud-workers"
PARAMS = Params(voxel_size_m=0.04)


@pytest.fixture
def server() -> Iterator[RedisServer]:
    server = RedisServer.start()
    try:
        yield server
    finally:
        server.stop()


class Running:
    """``worker.run`` in a thread until ``stop``."""

    def __init__(self, worker: FrameWorker) -> None:
        self.worker = worker
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=worker.run, args=(self.stop_event,), name=f"test-{worker.consumer}")
        self.thread.start()

    def stop(self) -> None:
        self.stop_event.set()
        self.thread.join(timeout=60)
        assert not self.thread.is_alive()


def walk(map_id: str, n: int) -> list[Frame]:
    """A sequential stream: the camera moving along, a chair-sized box and a second one half the time."""
    return [make_test_frame(i, map_id=map_id, boxes=((30, 80, 20, 70), (30, 80, 110, 150))[: 1 + i % 2]) for i in range(n)]


def worker(server: RedisServer, detector: Any, *, prefetch: bool, consumer: str, **options: Any) -> FrameWorker:
    return FrameWorker(
        RedisFrameQueue(server.url),
        RedisStore(server.url),
        detector,
        PARAMS,
        consumer=consumer,
        read_block_s=0.1,
        prefetch=prefetch,
        **options,
    )


def map_state(store: RedisStore, map_id: str) -> list[tuple[Any, ...]]:
    """What a map holds, without clocks: per object its id, label, version, frames and voxels."""
    objects = sorted(store.list_objects(map_id), key=lambda o: o.id)
    return [(o.id, o.label, o.version, o.n_frames, o.n_missed, o.confirmed, o.keys.tobytes()) for o in objects]


def pending_of(server: RedisServer, consumer: str) -> list[dict[str, Any]]:
    """The consumer's pending entries; none while its worker's thread has not made the group yet (under load
    a test's first look can come first: NOGROUP)."""
    try:
        return list(server.client().xpending_range(STREAM, GROUP, min="-", max="+", count=100, consumername=consumer))
    except redis.ResponseError as exc:
        if not str(exc).startswith("NOGROUP"):
            raise
        return []


def processed_map(server: RedisServer, map_id: str, frames: int, *, prefetch: bool) -> list[tuple[Any, ...]]:
    """Queue the walk of ``frames`` into ``map_id``, run one worker until every frame is processed, check
    each was once; returns the map's state."""
    one = worker(server, BlobDetector(), prefetch=prefetch, consumer=f"w-{map_id}")
    for frame in walk(map_id, frames):
        assert one.queue.put(frame)
    running = Running(one)
    try:
        wait_until(lambda: one.queue.stats().maps.get(map_id, {}).get("processed") == frames, 60, "every frame")
    finally:
        running.stop()
    assert one.queue.stats().maps[map_id] == {"processed": frames}
    assert all(one.store.is_frame_done(map_id, f.key) for f in walk(map_id, frames))
    return map_state(one.store, map_id)


def test_with_prefetch_every_frame_is_processed_once_and_the_map_is_the_one_without(server: RedisServer) -> None:
    with_prefetch = processed_map(server, "prefetch", 16, prefetch=True)
    assert with_prefetch == processed_map(server, "one-at-a-time", 16, prefetch=False) and len(with_prefetch) == 2


class SlowPublisher:
    """Takes ``delay_s`` to publish: the frame integrating stays in hand that long after its commit."""

    def __init__(self, delay_s: float) -> None:
        self.delay_s = delay_s

    def publish(self, events: Sequence[ObjectEvent]) -> None:
        time.sleep(self.delay_s)


def test_the_heartbeat_keeps_both_frames_in_hand_fresh(server: RedisServer) -> None:
    """Integrating a frame takes 1.5 s (publishing its change log), detecting one 0.3 s: the prefetched frame waits
    1.2 s in hand beside it, yet no entry of the worker idles past a few heartbeats (0.1 s), and another
    consumer claims none of them."""
    slow = worker(
        server,
        BlobDetector(delay_s=0.3),
        prefetch=True,
        consumer="slow",
        heartbeat_s=0.1,
        feed=ChangeFeed(RedisStore(server.url), SlowPublisher(1.5)),
    )
    for frame in walk("beat", 4):
        slow.queue.put(frame)
    rival = RedisFrameQueue(server.url)
    running = Running(slow)
    most_in_hand, most_idle_ms = 0, 0
    try:
        deadline = time.monotonic() + 4.0
        while time.monotonic() < deadline:
            entries = pending_of(server, "slow")
            most_in_hand = max(most_in_hand, len(entries))
            most_idle_ms = max([most_idle_ms, *(e["time_since_delivered"] for e in entries)])
            assert rival.claim_abandoned("rival", min_idle_s=0.6) is None
            time.sleep(0.05)
    finally:
        running.stop()
        rival.close()
    assert most_in_hand == 2
    assert most_idle_ms < 600, most_idle_ms


def test_a_stop_finishes_both_frames_in_hand_and_leaves_the_rest_queued(server: RedisServer) -> None:
    slow = worker(server, BlobDetector(delay_s=0.5), prefetch=True, consumer="stopping")
    for frame in walk("stop", 8):
        slow.queue.put(frame)
    # two frames are in hand only while the first's step runs (the next is taken once the detector is free of the
    # first): that step is held here until the stop is asked for, so the test cannot miss the moment under load
    stepping, go_on, finish = threading.Event(), threading.Event(), slow.finish

    def held_finish(started: Any) -> Any:
        stepping.set()
        go_on.wait(30)
        return finish(started)

    slow.finish = held_finish  # type: ignore[method-assign]  # the worker's own finish, held until the stop is asked
    running = Running(slow)
    wait_until(lambda: stepping.is_set() and len(pending_of(server, "stopping")) == 2, 30, "two frames in hand")
    running.stop_event.set()
    go_on.set()
    running.stop()
    assert pending_of(server, "stopping") == []
    stats = slow.queue.stats()
    processed = stats.maps["stop"]["processed"]
    assert processed >= 2 and stats.queue_depth == 8 - processed and stats.failed == 0
    done = [slow.store.is_frame_done("stop", f.key) for f in walk("stop", 8)]
    assert done == [True] * processed + [False] * (8 - processed)  # the rest left in the stream, in order


def test_a_detector_failure_on_the_prefetched_frame_is_delivered_again_then_dead_lettered(server: RedisServer) -> None:
    frames = walk("crash", 6)
    crashing = worker(
        server,
        BlobDetector(crash_on=[frames[3].frame_id]),
        prefetch=True,
        consumer="crashing",
        max_deliveries=2,
        claim_min_idle_s=0.3,
        claim_interval_s=0.1,
        heartbeat_s=0.1,
    )
    for frame in frames:
        crashing.queue.put(frame)
    running = Running(crashing)
    try:
        wait_until(lambda: server.client().xlen(keys.ingest_dead_letter_stream(keys.shard_tag(0, 1))) == 1, 60, "dead letter")
        wait_until(lambda: crashing.queue.stats().queue_depth == 0, 30, "the queue empty")
    finally:
        running.stop()
    [(_, dead)] = server.client().xrange(keys.ingest_dead_letter_stream(keys.shard_tag(0, 1)))
    assert dead[b"frame_key"].decode() == frames[3].key and dead[b"reason"] == b"delivered 3 times (max 2)", dead
    stats = crashing.queue.stats()
    assert stats.maps["crash"] == {"processed": 5, "failed": 1} and stats.redelivered == 0 and stats.claimed == 2
    assert [crashing.store.is_frame_done("crash", f.key) for f in frames] == [True, True, True, False, True, True]
    assert max(o.n_frames for o in crashing.store.list_objects("crash")) == 5
