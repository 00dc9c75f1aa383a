"""The 7-Scenes reader on tiny folders: frames, invalid depth and poses, gravity alignment, sequences,
and the hand-checked ground truth (gt-boxes.json): its frame, boxes, visible ranges and malformed files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from datasets_builders import build_seven_scenes

from arcloud.core.types import Intrinsics
from arcloud.datasets.frames import ColourCamera
from arcloud.datasets.gt_boxes import load_ground_truth
from arcloud.datasets.sevenscenes import DEFAULT_INTRINSICS, load_seven_scenes
from arcloud.errors import DatasetError


def test_frames_depth_and_invalid_poses(tmp_path: Path) -> None:
    sequence = load_seven_scenes(build_seven_scenes(tmp_path / "kitchen", n_frames=4))
    assert sequence.name == "kitchen" and sequence.frame_names == ("000000", "000001", "000002")
    assert sequence.skipped_frames == ("000003",)
    assert sequence.intrinsics == Intrinsics(58.5, 58.5, 32.0, 24.0)
    frame = sequence.load_frame("000001")
    assert frame.frame_id == "000001" and frame.map_id == "kitchen" and frame.rgb.shape == (48, 64, 3)
    assert np.all(frame.depth_m[:, :8] == 0.0)  # 65535 and 0 are both invalid
    np.testing.assert_allclose(frame.depth_m[:, 8:], 1.5)
    np.testing.assert_allclose(frame.cam2world[:3, 3], [0.05, 0, 0])
    assert sequence.up == (0.0, 0.0, 1.0) and sequence.up_file is None
    assert [f.frame_id for f in sequence.frames(stride=2)] == ["000000", "000002"]


def test_gravity_alignment(tmp_path: Path) -> None:
    gravity = np.array([0.0, 0.9, 0.43])
    root = build_seven_scenes(tmp_path / "g", gravity=gravity)
    plain = load_seven_scenes(root)
    np.testing.assert_allclose(plain.up, -gravity / np.linalg.norm(gravity))
    aligned = load_seven_scenes(root, align_gravity=True)
    np.testing.assert_allclose(aligned.up, [0, 0, 1], atol=1e-12)
    rotation = aligned.world2file[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    # the same point of the file world, seen through both: aligned = inv(world2file) @ file
    np.testing.assert_allclose(aligned.cam2world, np.linalg.inv(aligned.world2file) @ plain.cam2world, atol=1e-12)
    up_in_aligned = np.linalg.inv(aligned.world2file)[:3, :3] @ plain.up_file
    np.testing.assert_allclose(up_in_aligned, [0, 0, 1], atol=1e-12)


def test_sequences_and_missing_files(tmp_path: Path) -> None:
    root = build_seven_scenes(tmp_path / "scene", n_frames=2, sequences=2)
    (root / "camera-intrinsics.txt").unlink()
    sequence = load_seven_scenes(root)
    assert sequence.frame_names == ("seq-01-000000", "seq-02-000000") and sequence.intrinsics == DEFAULT_INTRINSICS
    assert sequence.load_frame("seq-02-000000").frame_id == "seq-02-000000"
    with pytest.raises(DatasetError, match="no such folder"):
        load_seven_scenes(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="finite poses"):
        load_seven_scenes(tmp_path / "empty")


#: Pose frame -> aligned frame of the tiny ground truth: up (-y in the pose frame) to +z, moved.
FILE2ALIGNED = np.array([[1.0, 0, 0, 0.5], [0, 0, 1.0, 0], [0, -1.0, 0, 1.5], [0, 0, 0, 1.0]])


def gt_file(**changes: Any) -> dict[str, Any]:
    """A gt-boxes.json payload with a table and a chair, ``changes`` applied to the chair."""
    table = {"id": "table_1", "label": "table", "visible_frames": [0, 2], "confidence": "high", "uncertainty_m": 0.04,
             "aabb_observed_min": [-1.0, -2.0, 0.03], "aabb_observed_max": [0.8, -1.1, 0.77],
             "aabb_min": [-1.0, -2.0, 0.0], "aabb_max": [0.8, -1.1, 0.77]}  # fmt: skip
    chair = {"id": "chair_A", "label": "chair", "visible_frames": [2, 2],
             "aabb_observed_min": [-1.5, -1.9, 0.4], "aabb_observed_max": [-1.0, -1.2, 0.85],
             "aabb_min": [-1.5, -1.9, 0.0], "aabb_max": [-0.9, -1.2, 0.85], **changes}  # fmt: skip
    return {"method": "by hand", "gravity_aligned": {"world_to_aligned": FILE2ALIGNED.tolist(), "objects": [table, chair]},
            "not_annotated": [{"what": "a keyboard", "why": "not a laptop"}]}  # fmt: skip


def test_ground_truth_boxes_in_its_aligned_frame(tmp_path: Path) -> None:
    root = build_seven_scenes(tmp_path / "kitchen", n_frames=4, gravity=np.array([0.0, 1.0, 0.0]))
    (root / "gt-boxes.json").write_text(json.dumps(gt_file()))
    sequence = load_seven_scenes(root, align_gravity=True)
    truth = sequence.ground_truth
    assert truth is not None and truth.path == root / "gt-boxes.json" and truth.method == "by hand"
    np.testing.assert_array_equal(truth.file2aligned, FILE2ALIGNED)
    assert [(o.id, o.label, o.visible_frames) for o in truth.objects] == [
        ("table_1", "table", (0, 2)),
        ("chair_A", "chair", (2, 2)),
    ]
    table, chair = truth.objects
    assert table.confidence == "high" and table.uncertainty_m == 0.04 and chair.uncertainty_m is None
    np.testing.assert_array_equal(chair.observed.min, [-1.5, -1.9, 0.4])
    np.testing.assert_array_equal(chair.amodal.max, [-0.9, -1.2, 0.85])
    assert chair.box("amodal") is chair.amodal and truth.not_annotated == ("a keyboard (not a laptop)",)
    # objects by visible frames: frames 0-1 see the table only
    assert [b.label for b in truth.boxes("observed", frames=(0, 1))] == ["table"]
    assert [b.label for b in truth.boxes("amodal")] == ["table", "chair"]
    assert [o.id for o in truth.objects_within((2, 5))] == ["table_1", "chair_A"]
    # the map's world (gravity-aligned) -> the ground truth's frame, through the pose frame
    np.testing.assert_allclose(sequence.world2gt, FILE2ALIGNED @ sequence.world2file)
    np.testing.assert_allclose(sequence.world2gt[:3, :3] @ [0, 0, 1], [0, 0, 1], atol=1e-12)  # both z-up
    assert sequence.frame_number("000002") == 2
    assert load_seven_scenes(build_seven_scenes(tmp_path / "plain")).ground_truth is None
    assert load_seven_scenes(tmp_path / "plain").world2gt is None


def test_the_colour_camera_comes_with_the_ground_truth_or_is_given(tmp_path: Path) -> None:
    root = build_seven_scenes(tmp_path / "kitchen", n_frames=2)
    colour = {"fx": 527.0, "fy": 526.0, "cx": 324.0, "cy": 239.0, "depth_to_colour_translation_m": [-0.035, 0, 0]}
    (root / "gt-boxes.json").write_text(json.dumps({**gt_file(), "colour_intrinsics_estimated": colour}))
    sequence = load_seven_scenes(root)
    frame = sequence.load_frame(sequence.frame_names[0])
    assert frame.rgb_intrinsics == Intrinsics(527.0, 526.0, 324.0, 239.0) and not frame.registered
    np.testing.assert_array_equal(frame.depth2rgb[:3, 3], [-0.035, 0, 0])
    given = ColourCamera(Intrinsics(500.0, 500.0, 320.0, 240.0), np.eye(4))
    assert load_seven_scenes(root, colour=given).load_frame(sequence.frame_names[0]).rgb_intrinsics.fx == 500.0
    assert load_seven_scenes(build_seven_scenes(tmp_path / "plain", n_frames=2)).load_frame("000000").registered
    (root / "gt-boxes.json").write_text(json.dumps({**gt_file(), "colour_intrinsics_estimated": {**colour, "fx": -1}}))
    with pytest.raises(DatasetError, match="colour_intrinsics_estimated: expected positive focal lengths"):
        load_seven_scenes(root)


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        ({"objects": []}, "expected a field gravity_aligned, got none"),
        ({"gravity_aligned": {"objects": []}}, "expected a field gravity_aligned.world_to_aligned"),
        (
            {"gravity_aligned": {"world_to_aligned": np.eye(3).tolist(), "objects": []}},
            r"world_to_aligned: expected finite numbers of shape \(4, 4\)",
        ),
        ({"gravity_aligned": {"world_to_aligned": (2 * np.eye(4)).tolist(), "objects": []}}, "expected a rigid transform"),
        ({"gravity_aligned": {"world_to_aligned": np.eye(4).tolist(), "objects": []}}, "expected at least one object"),
        (gt_file(label="sofa"), r"chair_A\)\.label: expected one of .*got 'sofa'"),
        (gt_file(aabb_observed_max=[-1.0, -1.2]), r"chair_A\)\.aabb_observed_max: expected finite numbers of shape \(3,\)"),
        (gt_file(aabb_max=[-1.6, -1.2, 0.85]), r"chair_A\)\.aabb_max: expected above aabb_min"),
        (gt_file(visible_frames=[5, 2]), r"visible_frames: expected \[first, last\] frame numbers, got \[5.0, 2.0\]"),
        (gt_file(id="table_1"), "expected distinct ids"),
        (gt_file(uncertainty_m="small"), r"uncertainty_m: expected finite numbers"),
    ],
)
def test_malformed_ground_truth_is_named(tmp_path: Path, payload: dict[str, Any], message: str) -> None:
    path = tmp_path / "gt-boxes.json"
    path.write_text(json.dumps(payload))
    with pytest.raises(DatasetError, match=message):
        load_ground_truth(path)


def test_unreadable_ground_truth(tmp_path: Path) -> None:
    (tmp_path / "gt-boxes.json").write_text("{not json")
    with pytest.raises(DatasetError, match="expected JSON"):
        load_ground_truth(tmp_path / "gt-boxes.json")
    with pytest.raises(DatasetError, match="expected a readable ground-truth file"):
        load_ground_truth(tmp_path / "missing.json")
