import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from handmade_frames import two_box_frame

from arcloud.core.step import integrate_frame, process_frame
from arcloud.core.types import Detection, Params
from arcloud.errors import InvalidInput
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05)


class FixedDetector:
    def __init__(self, detections):
        self.detections = detections

    def detect(self, frame):
        return self.detections


def test_frames_of_one_scene_build_two_objects_and_events_in_the_change_log():
    store = MemoryStore()
    for i in range(4):
        frame, detections = two_box_frame(f"f{i}", shift_m=0.01 * i)
        result = process_frame(frame, FixedDetector(detections), store, PARAMS)
        assert result.n_detections == 2
    objects = store.list_objects("m")
    assert sorted(o.label for o in objects) == ["chair", "table"]
    assert all(o.n_frames == 4 and o.version == 4 for o in objects)
    log = store.changes_since("m", 0, 100)
    assert log.complete and [e.version for e in log.entries] == [1, 2, 3, 4] and log.version == 4
    assert [e.frame_key for e in log.entries] == [f"dev/f{i}" for i in range(4)]
    kinds = [e.kind for entry in log.entries for e in entry.events]
    assert kinds.count("created") == 2 and kinds.count("updated") == 6
    chair = next(o for o in objects if o.label == "chair")
    # The chair patch: rows 10..30, cols 10..30 at 1.5 m, f=100, c=(40, 30) -> x in [-0.45, -0.15].
    assert chair.aabb.min[2] == pytest.approx(1.5, abs=0.051)
    assert -0.5 <= chair.aabb.min[0] <= -0.4 and -0.2 <= chair.aabb.max[0] <= -0.1


def test_a_frame_processed_twice_counts_once():
    store = MemoryStore()
    frame, detections = two_box_frame("same")
    first = process_frame(frame, FixedDetector(detections), store, PARAMS)
    again = process_frame(frame, FixedDetector(detections), store, PARAMS)
    raced = integrate_frame(frame, detections, store, PARAMS)  # past the early check: refused at commit
    assert not first.skipped and again.skipped and raced.skipped
    assert all(o.n_frames == 1 for o in store.list_objects("m"))
    assert store.count_frames("m") == 1


def test_bad_detections_are_refused_before_anything_is_written():
    store = MemoryStore()
    frame, detections = two_box_frame("f0")
    integrate_frame(frame, detections, store, PARAMS)
    before = {o.id: o.version for o in store.list_objects("m")}
    frame2, _ = two_box_frame("f1")
    with pytest.raises(InvalidInput, match="mask"):
        integrate_frame(frame2, [Detection("chair", 0.9, np.ones((3, 3), bool))], store, PARAMS)
    assert {o.id: o.version for o in store.list_objects("m")} == before
    assert not store.is_frame_done("m", frame2.key)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_concurrent_frames_no_lost_update_no_duplicate_no_deadlock(seed):
    """Many threads see the same two new objects at the same moment, then keep updating them."""
    rng = np.random.default_rng(seed)
    store = MemoryStore()
    n_frames, n_threads = 48, 8
    frames = [two_box_frame(f"f{i:03d}", device_id=f"user-{i % 6}", shift_m=float(rng.normal(0, 0.01))) for i in range(n_frames)]
    start = threading.Barrier(n_threads)

    def work(chunk):
        start.wait()
        for frame, detections in chunk:
            integrate_frame(frame, detections, store, PARAMS)

    with ThreadPoolExecutor(n_threads) as pool:
        futures = [pool.submit(work, frames[i::n_threads]) for i in range(n_threads)]
        for future in futures:
            future.result(timeout=50)
    objects = store.list_objects("m")
    assert sorted(o.label for o in objects) == ["chair", "table"], [(o.id, o.label, o.n_frames) for o in objects]
    # No lost update: every frame's two detections ended up counted in exactly one object.
    assert sum(o.n_frames for o in objects) == 2 * n_frames
    assert store.count_frames("m") == n_frames
