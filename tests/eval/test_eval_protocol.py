import numpy as np
import pytest
from handmade_frames import two_box_frame

from arcloud.core.types import LabelledBox, Params
from arcloud.eval.protocol import CachedDetector, interleave, run_map, table1, user_streams
from arcloud.stores.memory import MemoryStore


def test_user_streams_cut_contiguous_segments_and_shuffle_them():
    rng = np.random.default_rng(0)
    streams = user_streams(10, 3, rng)
    assert sorted(i for s in streams for i in s) == list(range(10))
    assert all(s == list(range(s[0], s[0] + len(s))) for s in streams)
    assert sorted(len(s) for s in streams) == [3, 3, 4]
    orders = {tuple(s[0] for s in user_streams(30, 5, np.random.default_rng(seed))) for seed in range(10)}
    assert len(orders) > 1  # the segment order depends on the seed
    with pytest.raises(ValueError, match="users"):
        user_streams(3, 4, rng)


def test_interleave_keeps_each_user_in_order_and_mixes_users():
    rng = np.random.default_rng(1)
    streams = [[0, 1, 2, 3], [10, 11, 12], [20, 21]]
    arrivals = interleave(streams, rng)
    assert sorted(f for _, f in arrivals) == sorted(f for s in streams for f in s)
    for user, stream in enumerate(streams):
        assert [f for u, f in arrivals if u == user] == stream
    assert [u for u, _ in arrivals] != sorted(u for u, _ in arrivals)


class CountingDetector:
    def __init__(self, detections_by_frame):
        self.detections_by_frame = detections_by_frame
        self.calls = 0

    def detect(self, frame):
        self.calls += 1
        return self.detections_by_frame[frame.frame_id]


def test_distributed_runs_give_the_centralized_map_on_a_simple_scene():
    pairs = [two_box_frame(f"f{i:02d}", shift_m=0.004 * i) for i in range(24)]
    frames = [f for f, _ in pairs]
    detector = CachedDetector(CountingDetector({f.frame_id: d for f, d in pairs}))
    # Exact extents of the two patches over the walk (see two_box_frame), one voxel thick.
    gt = [LabelledBox("chair", [-0.45, -0.3, 1.5], [-0.1, 0.0, 1.55]), LabelledBox("table", [0.15, 0.05, 2.5], [0.9, 0.6, 2.55])]
    stores: list[MemoryStore] = []

    def new_store(*, cell_m: float) -> MemoryStore:
        stores.append(MemoryStore(cell_m=cell_m))
        return stores[-1]

    central = run_map(frames, detector, Params(), new_store=new_store)
    assert sorted(o.label for o in central) == ["chair", "table"]
    assert len(stores) == 1 and stores[0].cell_m == Params().index_cell_m
    results = table1(frames, detector, gt, Params(), new_store=new_store, users=(3, 12), runs=2, workers=3)
    assert len(stores) == 1 + 1 + 2 * 2  # a fresh store for every run
    rows = results["table1"]
    assert [(r["approach"], r["users"], r["runs"]) for r in rows] == [
        ("centralized", 1, 1),
        ("distributed", 3, 2),
        ("distributed", 12, 2),
    ]
    assert rows[0]["map25_mean"] == pytest.approx(1.0) and rows[0]["map50_mean"] == pytest.approx(1.0)
    for row in rows[1:]:
        assert row["map25_mean"] == pytest.approx(rows[0]["map25_mean"], abs=1e-9)
    assert detector.detector.calls == len(frames)  # detections computed once per frame, replayed after
