"""A worker paused past ``claim_min_idle_s`` (SIGSTOP, a long pause) on its frame's last delivery: another worker
claims the frame and gives it up (dead-lettered, counted failed). On a real redis-server with the real queue and
store, the paused worker's commit is then refused when it resumes: the frame is in the dead letters or in the map,
never both, and the map's counts add up (processed + failed == accepted). The operators' review found it (s9).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from redis_server import RedisServer
from svc_helpers import BlobDetector, make_test_frame

from arcloud.core.types import Params
from arcloud.ports import QueuedFrame
from arcloud.service.worker import FrameWorker, Started
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue

pytestmark = [pytest.mark.redis]

MAP = "paused"
PARAMS = Params(voxel_size_m=0.04)


@pytest.fixture
def server() -> Iterator[RedisServer]:
    server = RedisServer.start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def workers(server: RedisServer) -> Iterator[tuple[FrameWorker, FrameWorker]]:
    """Two workers of one delivery each (``max_deliveries`` 1: a claimed frame is given up at once), no heartbeat."""
    queues, stores = [RedisFrameQueue(server.url) for _ in range(2)], [RedisStore(server.url) for _ in range(2)]
    made = [
        FrameWorker(queue, store, BlobDetector(), PARAMS, consumer=name, max_deliveries=1, heartbeat_s=None)
        for queue, store, name in zip(queues, stores, ("first", "second"), strict=True)
    ]
    yield made[0], made[1]
    for queue, store in zip(queues, stores, strict=True):
        queue.close()
        store.close()


def counts(worker: FrameWorker) -> tuple[int, int, int]:
    """The map's frames (accepted, processed, failed), as ``GET /v1/maps/{id}/stats`` counts them."""
    accepted, failed = worker.queue.map_counts(MAP)
    return accepted, worker.store.count_frames(MAP), failed


def taken_over(first: FrameWorker, second: FrameWorker) -> tuple[Started, QueuedFrame]:
    """A frame queued; ``first`` takes and detects it, then stops before its commit; ``second`` claims it."""
    first.queue.prepare()
    assert first.queue.put(make_test_frame(0, map_id=MAP))
    item = first.queue.take("first", block_s=1.0)
    assert item is not None
    started = first.start(item)
    assert isinstance(started, Started)
    claimed = second.queue.claim_abandoned("second", min_idle_s=0.001)
    assert claimed is not None and claimed.deliveries == 2
    return started, claimed


def test_a_frame_given_up_while_its_worker_was_paused_is_not_committed_by_it(workers: tuple[FrameWorker, FrameWorker]) -> None:
    first, second = workers
    started, claimed = taken_over(first, second)
    assert second.handle(claimed) == "dead"
    assert first.finish(started) == "dead"  # its commit refused at once: nothing written, settled, counted or retried
    assert counts(first) == (1, 0, 1) and first.store.list_objects(MAP) == [] and "first" not in first.queue.stats().workers
    [failed] = first.queue.failed_frames(MAP, 10)
    assert failed.retriable and failed.reason == "delivered 2 times (max 1)"
    # Retried, the frame is another entry: processed once, its first entry's refusal no longer in the way.
    assert first.queue.retry_failed(MAP, failed.frame_key)
    again = second.queue.take("second", block_s=1.0)
    assert again is not None and second.handle(again) == "processed"
    assert counts(first) == (1, 1, 0) and len(first.store.list_objects(MAP)) == 1


def test_a_frame_its_paused_worker_committed_before_the_claim_gave_it_up_counts_once_as_processed(
    workers: tuple[FrameWorker, FrameWorker],
) -> None:
    first, second = workers
    started, claimed = taken_over(first, second)
    assert first.finish(started) == "processed"
    assert second.handle(claimed) == "redelivered"  # not given up: it was processed
    assert counts(first) == (1, 1, 0) and first.queue.failed_frames(MAP, 10) == []
