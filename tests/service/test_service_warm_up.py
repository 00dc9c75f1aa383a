"""A service's worker warms up before it takes frames: the detector runs once on a blank frame, so the first
frames after a start or a scale-up do not wait for what a first call loads (measured with
``bench/bench_load.py``: the first frame of each worker took 0.8-0.9 s, every later one 20-30 ms)."""

from __future__ import annotations

import logging
import threading
import time

import pytest
from svc_helpers import BlobDetector, make_test_frame

from arcloud.core.types import Detection, Frame, Params
from arcloud.service.worker import WARM_UP_SHAPE, FrameWorker
from arcloud.stores.memory import MemoryStore
from arcloud.stores.memory_queue import MemoryFrameQueue


class Recording(BlobDetector):
    """A ``BlobDetector`` that records the frames it is given, and refuses blank ones when asked."""

    def __init__(self, *, refuse_blank: bool = False) -> None:
        super().__init__()
        self.seen: list[tuple[str, str, tuple[int, int]]] = []
        self.refuse_blank = refuse_blank

    def detect(self, frame: Frame) -> list[Detection]:
        self.seen.append((frame.map_id, frame.frame_id, frame.shape))
        if self.refuse_blank and frame.map_id == "warm-up":
            raise ValueError("only frames of known maps")
        return super().detect(frame)


def run_until_processed(worker: FrameWorker, queue: MemoryFrameQueue, n_frames: int) -> None:
    stop = threading.Event()
    thread = threading.Thread(target=worker.run, args=(stop,))
    thread.start()
    deadline = time.monotonic() + 30
    while queue.stats().processed < n_frames and time.monotonic() < deadline:
        time.sleep(0.02)
    stop.set()
    thread.join(10)
    assert queue.stats().processed == n_frames


@pytest.mark.parametrize("refuse_blank", [False, True])
def test_a_warming_worker_runs_its_detector_on_a_blank_frame_before_any_frame(
    refuse_blank: bool, caplog: pytest.LogCaptureFixture
) -> None:
    queue, store, detector = MemoryFrameQueue(), MemoryStore(), Recording(refuse_blank=refuse_blank)
    for i in range(2):
        queue.put(make_test_frame(i))
    worker = FrameWorker(queue, store, detector, Params(), heartbeat_s=None, read_block_s=0.05, warm_up=True)
    with caplog.at_level(logging.INFO, logger="arcloud.service.worker"):
        run_until_processed(worker, queue, 2)
    assert detector.seen[0] == ("warm-up", "0", WARM_UP_SHAPE)  # first, and on nothing of any map
    assert [s[:2] for s in detector.seen[1:]] == [("m", "f000000"), ("m", "f000001")]
    assert store.list_objects("warm-up") == [] and len(store.list_objects("m")) == 1
    assert any("warmed up in" in r.message for r in caplog.records)
    assert any("did not warm up" in r.message for r in caplog.records) == refuse_blank


def test_a_worker_without_warm_up_starts_on_its_first_frame() -> None:
    queue, detector = MemoryFrameQueue(), Recording()
    queue.put(make_test_frame(0))
    run_until_processed(FrameWorker(queue, MemoryStore(), detector, Params(), heartbeat_s=None, read_block_s=0.05), queue, 1)
    assert [s[:2] for s in detector.seen] == [("m", "f000000")]
