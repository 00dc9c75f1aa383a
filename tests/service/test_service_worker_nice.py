"""``FrameWorker(detect_nice=N)`` (``ARCLOUD_DETECT_NICE``): the detector runs in a thread of its own whose nice
value is N more than the worker's, so the rest of the step (locks held) keeps its priority; the map is the one
a worker detecting in its own thread makes."""

from __future__ import annotations

import os
import sys
import threading
from typing import Any

import pytest
from svc_helpers import BlobDetector, make_test_frame

from arcloud.core.types import Frame, Params
from arcloud.service.worker import FrameWorker, lower_priority
from arcloud.stores.memory import MemoryStore
from arcloud.stores.memory_queue import MemoryFrameQueue

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="a thread's own nice value is Linux's")

PARAMS = Params(voxel_size_m=0.04)


def thread_nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


class NiceRecorder(BlobDetector):
    """Records, for each frame it detects, the thread that ran it and that thread's nice value."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[tuple[int, int]] = []

    def detect(self, frame: Frame) -> Any:
        self.seen.append((threading.get_ident(), thread_nice()))
        return super().detect(frame)


class StepNice:
    """A store that records the nice value of the thread that commits (the step's thread)."""

    def __init__(self, store: MemoryStore) -> None:
        self.store = store
        self.commit_nice: list[int] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.store, name)

    def commit(self, *args: Any, **kwargs: Any) -> bool:
        self.commit_nice.append(thread_nice())
        return bool(self.store.commit(*args, **kwargs))


def run_frames(detect_nice: int, prefetch: bool = False) -> tuple[NiceRecorder, StepNice, list[tuple[Any, ...]]]:
    queue, detector = MemoryFrameQueue(), NiceRecorder()
    store = StepNice(MemoryStore())
    frames = [make_test_frame(i, map_id="m", boxes=((30, 80, 20, 70), (30, 80, 110, 150))[: 1 + i % 2]) for i in range(6)]
    for frame in frames:
        assert queue.put(frame)
    worker = FrameWorker(
        queue, store, detector, PARAMS, consumer="w", heartbeat_s=None, prefetch=prefetch, detect_nice=detect_nice
    )  # type: ignore[arg-type]  # the store's calls pass through
    while sum(queue.stats().maps.get("m", {}).values()) < len(frames):
        worker.poll_once()
    worker.finish_started()
    assert queue.stats().maps["m"] == {"processed": len(frames)}
    objects = sorted(store.store.list_objects("m"), key=lambda o: o.id)
    return detector, store, [(o.id, o.label, o.version, o.n_frames, o.keys.tobytes()) for o in objects]


@pytest.mark.parametrize("prefetch", [False, True])
def test_detections_run_niced_in_their_own_thread_and_the_step_does_not(prefetch: bool) -> None:
    base = thread_nice()
    if base > 14:
        pytest.skip(f"this process runs at nice {base} already: 5 more would be capped at 19")
    niced, store, niced_map = run_frames(5, prefetch)
    assert {nice for _, nice in niced.seen} == {base + 5}
    assert threading.get_ident() not in {thread for thread, _ in niced.seen}
    assert store.commit_nice and set(store.commit_nice) == {base}  # the step (locks held) keeps the worker's priority
    assert thread_nice() == base
    plain, _, plain_map = run_frames(0, prefetch)
    assert {nice for _, nice in plain.seen} == {base}
    assert niced_map == plain_map and len(plain_map) == 2


def test_lower_priority_of_nothing_leaves_the_thread_alone() -> None:
    before = thread_nice()
    lower_priority(0)
    assert thread_nice() == before
