"""Up in a recording's pose frame: estimated from real 7-Scenes depth, it lands within 3 degrees of the
hand-checked up of gt-boxes.json; the sources are taken in their order; the gravity-aligned world."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from datasets_builders import build_seven_scenes

from arcloud.datasets.frames import LazyFrames
from arcloud.datasets.gravity import choose_up, estimate_up_from_frames, gravity_world2file
from arcloud.datasets.gt_boxes import load_ground_truth
from arcloud.datasets.sevenscenes import load_seven_scenes
from arcloud.errors import DatasetError


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


@pytest.mark.shared
def test_the_estimate_on_real_7scenes_frames_is_within_3_degrees_of_the_ground_truth(shared: type) -> None:
    root = shared.path("data/7scenes-redkitchen/gt-boxes.json").parent
    truth = np.asarray(json.loads((root / "gt-boxes.json").read_text())["up_axis_world"], np.float64)
    sequence = load_seven_scenes(root)  # the pose frame: tilted about 26 degrees from gravity
    found = estimate_up_from_frames(LazyFrames(sequence.frame_names, sequence.load_frame, cache=False))
    assert angle_deg(found.up, truth) < 3.0, (found.up, truth)
    assert found.prior_error_deg > 15.0 and found.n_normals > 10_000  # the cameras' image up alone is far off
    estimated = load_seven_scenes(root, up=None, estimate_up=True, gt_boxes=None)
    assert estimated.up_source.endswith("gravity-direction.txt")  # a source there wins over the estimate


def test_sources_in_order_and_the_aligned_world(tmp_path: Path) -> None:
    root = build_seven_scenes(tmp_path / "kitchen", n_frames=3, gravity=np.array([0.0, 2.0, 0.0]))
    gt = tmp_path / "gt.json"
    gt.write_text(json.dumps({"up_axis_world": [0.0, 0.0, -3.0], "gravity_aligned": {"world_to_aligned": np.eye(4).tolist(), "objects": [
        {"id": "t", "label": "table", "visible_frames": [0, 1], "aabb_observed_min": [0, 0, 0], "aabb_observed_max": [1, 1, 1],
         "aabb_min": [0, 0, 0], "aabb_max": [1, 1, 1]}]}}))  # fmt: skip
    truth = load_ground_truth(gt)
    never = lambda: pytest.fail("no estimate while another source is there")  # noqa: E731 - a callback that must not run
    assert choose_up(given=(1, 0, 0), gravity_file=root / "gravity-direction.txt", estimate=never).up_file.tolist() == [
        1.0,
        0.0,
        0.0,
    ]
    chosen = choose_up(gravity_file=root / "gravity-direction.txt", ground_truth=truth, estimate=never)
    assert chosen.up_file.tolist() == [0.0, -1.0, 0.0] and chosen.source.endswith("gravity-direction.txt")
    chosen = choose_up(gravity_file=tmp_path / "none.txt", ground_truth=truth, estimate=never)
    assert chosen.up_file.tolist() == [0.0, 0.0, -1.0] and chosen.source.endswith("(up_axis_world)")
    assert choose_up().up_file is None and choose_up().source.startswith("none")
    with pytest.raises(DatasetError, match=r"--up: expected 3 finite numbers, not all 0, got \[0, 0, 0\]"):
        choose_up(given=(0, 0, 0))
    world2file = gravity_world2file(np.array([0.0, -1.0, 0.0]))
    np.testing.assert_allclose(world2file[:3, :3] @ [0.0, 0.0, 1.0], [0.0, -1.0, 0.0], atol=1e-12)  # world +z is up
    # 7-Scenes: the ground truth's up when the folder has no gravity-direction.txt
    (root / "gravity-direction.txt").unlink()
    sequence = load_seven_scenes(root, align_gravity=True, gt_boxes=gt)
    assert sequence.up_file.tolist() == [0.0, 0.0, -1.0] and sequence.up == pytest.approx((0.0, 0.0, 1.0))
