"""``FrameWorker(detectors=N)`` (``ARCLOUD_WORKER_DETECTORS``): N threads detect while the worker's own thread
integrates what they detected, several frames of one map as one batch (``core.staged``: one hold of the
map's locks, one commit). On a real redis-server with the real queue and store: every frame processed once,
the map the one a worker one frame at a time makes (fewer commits), two such workers on one map, and a frame
whose detection fails delivered again while the others of its batch are written.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest
from redis_server import RedisServer
from svc_helpers import BlobDetector, make_test_frame, wait_until

from arcloud.core.types import Frame, Params
from arcloud.errors import InvalidInput
from arcloud.service.worker import FrameWorker
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue

pytestmark = [pytest.mark.redis]

PARAMS = Params(voxel_size_m=0.04)
FRAMES = 18


@pytest.fixture
def server() -> Iterator[RedisServer]:
    server = RedisServer.start()
    try:
        yield server
    finally:
        server.stop()


def walk(map_id: str, n: int) -> list[Frame]:
    """The camera moving along, a chair-sized box in every frame and a second one every other frame."""
    return [make_test_frame(i, map_id=map_id, boxes=((30, 80, 20, 70), (30, 80, 110, 150))[: 1 + i % 2]) for i in range(n)]


def worker(server: RedisServer, detector: Any, consumer: str, **options: Any) -> FrameWorker:
    return FrameWorker(
        RedisFrameQueue(server.url), RedisStore(server.url), detector, PARAMS, consumer=consumer, read_block_s=0.1, **options
    )


def run_until(workers: list[FrameWorker], done: Any, what: str) -> None:
    stop = threading.Event()
    threads = [threading.Thread(target=w.run, args=(stop,)) for w in workers]
    for thread in threads:
        thread.start()
    try:
        wait_until(done, 60, what)
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=60)
            assert not thread.is_alive()


def content(store: RedisStore, map_id: str) -> list[tuple[Any, ...]]:
    """What a map holds, without clocks and versions: per object its id, label, frames, misses and voxels."""
    objects = sorted(store.list_objects(map_id), key=lambda o: o.id)
    return [(o.id, o.label, o.n_frames, o.n_missed, o.confirmed, o.keys.tobytes(), o.weights.tobytes()) for o in objects]


def processed(one: FrameWorker, map_id: str, frames: int) -> None:
    for frame in walk(map_id, frames):
        assert one.queue.put(frame)
    run_until([one], lambda: one.queue.stats().maps.get(map_id, {}).get("processed") == frames, "every frame")
    assert one.queue.stats().maps[map_id] == {"processed": frames}
    assert all(one.store.is_frame_done(map_id, f.key) for f in walk(map_id, frames))


def test_batches_make_the_map_one_frame_at_a_time_makes_in_fewer_commits(server: RedisServer) -> None:
    batched = worker(server, BlobDetector(delay_s=0.05), "batched", detectors=3)
    processed(batched, "batched", FRAMES)
    alone = worker(server, BlobDetector(), "alone")
    processed(alone, "alone", FRAMES)
    assert content(batched.store, "batched") == content(alone.store, "alone")
    assert len(content(alone.store, "alone")) == 2
    commits = {o.id: o.version for o in batched.store.list_objects("batched")}
    one_by_one = {o.id: o.version for o in alone.store.list_objects("alone")}
    assert one_by_one[min(one_by_one)] == FRAMES  # the box every frame sees: written by each frame alone
    assert commits[min(commits)] < FRAMES  # ... and by fewer commits in batches
    assert batched.store.count_frames("batched") == FRAMES


def test_two_batching_workers_on_one_map_process_every_frame_once(server: RedisServer) -> None:
    workers = [worker(server, BlobDetector(delay_s=0.03), f"w{i}", detectors=3) for i in range(2)]
    frames = walk("shared", 2 * FRAMES)
    for frame in frames:
        assert workers[0].queue.put(frame)
    run_until(workers, lambda: workers[0].queue.stats().maps.get("shared", {}).get("processed") == len(frames), "every frame")
    stats = workers[0].queue.stats()
    assert stats.maps["shared"] == {"processed": len(frames)} and stats.redelivered == 0
    objects = sorted(workers[0].store.list_objects("shared"), key=lambda o: o.id)
    assert [o.n_frames for o in objects] == [len(frames), len(frames) // 2]  # each box once, every frame counted once
    assert workers[0].store.count_frames("shared") == len(frames)


def test_a_failed_detection_is_delivered_again_and_the_rest_of_its_batch_is_written(server: RedisServer) -> None:
    frames = walk("crash", 9)
    crashing = worker(
        server,
        BlobDetector(delay_s=0.05, crash_on=[frames[4].frame_id]),
        "crashing",
        detectors=3,
        max_deliveries=2,
        claim_min_idle_s=0.3,
        claim_interval_s=0.1,
        heartbeat_s=0.1,
    )
    for frame in frames:
        crashing.queue.put(frame)
    dead_letters = keys.ingest_dead_letter_stream(keys.shard_tag(0, 1))
    run_until(
        [crashing],
        lambda: server.client().xlen(dead_letters) == 1 and crashing.queue.stats().queue_depth == 0,
        "the crashing frame dead-lettered and the rest processed",
    )
    stats = crashing.queue.stats()
    assert stats.maps["crash"] == {"processed": 8, "failed": 1}
    assert [crashing.store.is_frame_done("crash", f.key) for f in frames] == [i != 4 for i in range(9)]
    assert max(o.n_frames for o in crashing.store.list_objects("crash")) == 8


def test_a_worker_needs_a_detector() -> None:
    with pytest.raises(InvalidInput, match="detectors"):
        FrameWorker(None, None, BlobDetector(), PARAMS, detectors=0)  # type: ignore[arg-type] - refused before they are used
