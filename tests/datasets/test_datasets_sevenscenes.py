"""The 7-Scenes reader on tiny folders: frames, invalid depth and poses, gravity alignment, sequences."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from datasets_builders import build_seven_scenes

from arcloud.core.types import Intrinsics
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
