"""The TUM RGB-D reader: a recording written from real 7-Scenes frames reads back as the 7-Scenes reader
reads them; colour/depth association and pose interpolation at their edges; intrinsics and up, each from
where it should come; malformed files named with what was expected."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from datasets_builders import (
    TABLE_IN_BOX_ROOM,
    TUM_RGB_DELAY_S,
    build_tum_from_seven_scenes,
    tum_time,
    write_room_tum,
)
from handmade_frames import BOX_ROOM, cast_boxes
from scipy.spatial.transform import Rotation

from arcloud.core.types import Detection, Intrinsics, Params
from arcloud.core.voxels import voxelize_detections
from arcloud.datasets.files import read_png_u16
from arcloud.datasets.sevenscenes import load_seven_scenes
from arcloud.datasets.tum import (
    GENERIC_INTRINSICS,
    PUBLISHED_DISTORTION,
    PUBLISHED_INTRINSICS,
    associate,
    interpolate_poses,
    load_tum,
    tum_camera,
)
from arcloud.errors import DatasetError

SEVEN_SCENES = "data/7scenes-redkitchen"
FRAMES = [0, 1, 2, 30, 300, 600]


@pytest.fixture
def seven_root(shared: type) -> Path:
    return shared.path(f"{SEVEN_SCENES}/gt-boxes.json").parent


# ---------------------------------------------------------------- association and interpolation


def test_association_pairs_closest_first_within_the_limit() -> None:
    assert associate([0.0, 1.0], [0.015, 1.03]) == [(0, 0)]  # 30 ms apart: no pair
    assert associate([0.0, 0.01], [0.008]) == [(1, 0)]  # the closer one takes it
    assert associate([0.0, 0.01, 0.5], [0.009, 0.003, 0.49]) == [(0, 1), (1, 0), (2, 2)]  # each used once
    assert associate([0.0], [0.02]) == []  # less than 20 ms, as associate.py: 20 ms is out
    assert associate([0.0, 0.01], [0.0, 0.01], max_difference_s=0.05) == [(0, 0), (1, 1)]
    assert associate([], [0.0]) == [] and associate([0.0], []) == []


def turn_z(degrees: float) -> np.ndarray:
    return Rotation.from_euler("z", degrees, degrees=True).as_quat()


def test_poses_are_interpolated_linearly_and_by_slerp() -> None:
    times = np.array([10.00, 10.04])
    positions = np.array([[0.0, 0.0, 0.0], [0.4, -0.8, 0.0]])
    quaternions = np.array([turn_z(0.0), -turn_z(90.0)])  # the sign of a quaternion is no turn
    poses, valid = interpolate_poses(times, positions, quaternions, np.array([10.01, 10.00, 10.04]))
    assert valid.tolist() == [True, True, True]
    np.testing.assert_allclose(poses[0, :3, 3], [0.1, -0.2, 0.0], atol=1e-9)
    np.testing.assert_allclose(poses[0, :3, :3], Rotation.from_euler("z", 22.5, degrees=True).as_matrix(), atol=1e-9)
    np.testing.assert_allclose(poses[1, :3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(poses[2, :3, 3], positions[1], atol=1e-12)
    np.testing.assert_allclose(poses[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (3, 1)))


def test_across_a_gap_or_beyond_the_ends_the_nearest_pose_within_20_ms_or_none() -> None:
    times = np.array([0.0, 1.0, 1.05])
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    quaternions = np.array([turn_z(0.0), turn_z(40.0), turn_z(40.0)])
    query = np.array([0.015, 0.03, 0.5, 0.99, -0.015, -0.03, 1.065, 1.1, 1.025])
    poses, valid = interpolate_poses(times, positions, quaternions, query)
    # a fast camera moves 2 cm and turns 2 degrees in 50 ms: beyond 20 ms no pose is taken as it is
    assert valid.tolist() == [True, False, False, True, True, False, True, False, True]
    np.testing.assert_allclose(poses[[0, 4], :3, 3], [[0.0, 0, 0], [0.0, 0, 0]])  # no extrapolation, no blending
    np.testing.assert_allclose(poses[[3, 6], :3, 3], [[1.0, 0, 0], [2.0, 0, 0]])
    np.testing.assert_allclose(poses[8, :3, 3], [1.5, 0, 0])  # two poses 50 ms apart around it: between them
    assert np.all(np.isnan(poses[~valid]))
    one, ok = interpolate_poses(times[:1], positions[:1], quaternions[:1], np.array([0.01, 0.03]))
    assert ok.tolist() == [True, False] and np.allclose(one[0], np.eye(4))


# ---------------------------------------------------------------- a recording from real frames


@pytest.mark.shared
def test_a_recording_reads_back_as_the_7scenes_frames_it_was_made_of(
    seven_root: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    root = build_tum_from_seven_scenes(seven_root, tmp_path / "kitchen (TUM copy)", FRAMES)
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.tum"):
        tum = load_tum(root, align_gravity=False, estimate_up=False)
    assert (
        "dropped 1 of 7 depth images: 0 without a colour image within 0.02 s, 1 without a pose (two around it within "
        "0.05 s, or one within 0.02 s)" in caplog.text
    )
    seven = load_seven_scenes(seven_root)
    assert tum.name == "kitchen__TUM_copy_" and tum.frame_names == tuple(tum_time(n) for n in FRAMES)
    assert tum.dropped_frames == (f"{float(tum_time(FRAMES[-1])) + 1.0:.6f}",)
    assert tum.intrinsics == seven.intrinsics and tum.up_file is None and tum.world2gt is None
    assert [p.name for p in tum.rgb_paths[:2]] == [f"{float(tum_time(n)) + TUM_RGB_DELAY_S:.6f}.png" for n in FRAMES[:2]]
    for name, number in zip(tum.frame_names, FRAMES, strict=True):
        ours, theirs = tum.load_frame(name), seven.load_frame(f"{number:06d}")
        np.testing.assert_allclose(ours.depth_m, theirs.depth_m, atol=1e-6)
        np.testing.assert_array_equal(ours.rgb, theirs.rgb)
        # 7-Scenes rotations are orthonormal to about 1e-4; a quaternion is exactly a rotation
        np.testing.assert_allclose(ours.cam2world, theirs.cam2world, atol=2e-4)
        assert ours.frame_id == name and ours.map_id == tum.name
        # colour 8 ms after depth: where the next pose is a frame (33 ms) on, the camera's motion between
        # them, a quarter of the way; else no pose near the colour's time, and the frame is registered
        if number + 1 in FRAMES:
            after = seven.load_frame(f"{number + 1:06d}").cam2world
            at_colour, _ = interpolate_poses(
                np.array([0.0, 1 / 30]), np.stack([theirs.cam2world[:3, 3], after[:3, 3]]),
                Rotation.from_matrix(np.stack([theirs.cam2world[:3, :3], after[:3, :3]])).as_quat(), np.array([TUM_RGB_DELAY_S]),
            )  # fmt: skip
            assert ours.depth2rgb is not None
            np.testing.assert_allclose(ours.depth2rgb, np.linalg.inv(at_colour[0]) @ theirs.cam2world, atol=2e-4)
        else:
            assert ours.registered
    assert tum.load_frame(tum.frame_names[3]).timestamp_s == pytest.approx(1.0)


def test_masks_of_a_colour_image_taken_after_its_depth_land_where_the_turned_camera_saw(tmp_path: Path) -> None:
    intrinsics = Intrinsics(525.0, 525.0, 319.5, 239.5)
    # 10 ms at 360 degrees a second (turning_poses): the camera turns 3.6 degrees, 33 px, between the two images
    tum = load_tum(write_room_tum(tmp_path / "room", intrinsics, n_frames=11, colour_delay_s=0.01), intrinsics=intrinsics,
                   align_gravity=False, estimate_up=False)  # fmt: skip
    turn = tum.colour_turn_deg()
    assert 3.6 <= turn["median"] <= turn["max"] < 10  # the heading's 3.6 degrees, and the camera's nod
    params = Params()
    counts = np.zeros((2, 3))  # (with the motion, laid on as it is) x (table's voxels found, voxels found, table's voxels)
    for name in tum.frame_names[7:]:  # the frames that see the table (a fifth to a third of the image)
        frame = tum.load_frame(name)
        assert not frame.registered
        # the table's voxels: a mask of it drawn where the depth camera saw it, looked up the same way
        seen = cast_boxes(frame.cam2world, BOX_ROOM, intrinsics=intrinsics, shape=frame.shape)[1] == TABLE_IN_BOX_ROOM
        (table,) = voxelize_detections(replace(frame, depth2rgb=np.eye(4)), [Detection("table", 0.9, seen)], params)
        painted = Detection("table", 0.9, frame.rgb[..., 0] == 255)  # the table where the colour camera saw it
        for row, looked_up in enumerate((frame, replace(frame, depth2rgb=None))):
            (found,) = voxelize_detections(looked_up, [painted], params)
            counts[row] += np.isin(found.keys, table.keys).sum(), found.keys.size, table.keys.size
    (precision, recall), (precision_as_is, recall_as_is) = counts[:, 0:1] / counts[:, 1:]
    assert precision > 0.95 and recall > 0.9
    assert precision_as_is < 0.9 and recall_as_is < 0.8  # what the motion costs where it is not undone


def test_no_motion_is_made_up_between_two_poses_a_tracking_gap_apart(tmp_path: Path) -> None:
    intrinsics = Intrinsics(525.0, 525.0, 319.5, 239.5)
    root = write_room_tum(tmp_path / "room", intrinsics, n_frames=7, colour_delay_s=0.018)
    poses = (root / "groundtruth.txt").read_text().splitlines()
    # the poses at frame 0's colour (18 ms) and frames 3 and 6's depth (100, 200 ms): a tracking gap of 82 ms
    (root / "groundtruth.txt").write_text("\n".join([poses[1], poses[6], poses[12]]) + "\n")
    for listing in ("rgb.txt", "depth.txt"):  # frame 1 alone
        (root / listing).write_text((root / listing).read_text().splitlines()[1] + "\n")
    tum = load_tum(root, intrinsics=intrinsics, align_gravity=False, estimate_up=False, pose_time_offset_s=0.0)
    # frame 1: its depth (33 ms) takes the pose at 18 ms as it is, its colour (51 ms) lies between that one and the one
    # at 100 ms: the gap's motion is no motion of the camera between its two images
    first = tum.load_frame(tum.frame_names[0])
    assert first.frame_id == "100.033333" and first.registered and tum.colour_turn_deg() == {"median": 0.0, "max": 0.0}


@pytest.mark.shared
def test_the_pose_time_offset_moves_each_frame_along_the_trajectory(seven_root: Path, tmp_path: Path) -> None:
    root = build_tum_from_seven_scenes(seven_root, tmp_path / "kitchen", [0, 1, 2])
    plain = load_tum(root, align_gravity=False, estimate_up=False)
    shifted = load_tum(root, align_gravity=False, estimate_up=False, pose_time_offset_s=1 / 60)  # half a frame later
    assert shifted.frame_names == plain.frame_names
    halfway = (plain.cam2world[0, :3, 3] + plain.cam2world[1, :3, 3]) / 2
    np.testing.assert_allclose(shifted.cam2world[0, :3, 3], halfway, atol=1e-9)
    np.testing.assert_allclose(shifted.cam2world[2], plain.cam2world[2], atol=1e-9)  # the last pose, 17 ms away


@pytest.mark.shared
def test_a_trajectory_whose_clock_runs_ahead_is_put_back_by_the_depth(seven_root: Path, tmp_path: Path) -> None:
    imaged, posed = list(range(0, 400, 5)), list(range(0, 406))
    ahead = load_tum(build_tum_from_seven_scenes(seven_root, tmp_path / "ahead", imaged, trajectory_frames=posed, pose_clock_s=0.03),
                     align_gravity=False, estimate_up=False)  # fmt: skip
    assert ahead.pose_time_offset_s == pytest.approx(0.03) and ahead.pose_time_offset_source.startswith("+0.030 s by the depth")
    seven = load_seven_scenes(seven_root)
    for name, number in zip(ahead.frame_names[::20], imaged[::20], strict=True):
        np.testing.assert_allclose(ahead.load_frame(name).cam2world, seven.load_frame(f"{number:06d}").cam2world, atol=2e-4)
    on_time = load_tum(build_tum_from_seven_scenes(seven_root, tmp_path / "on time", imaged, trajectory_frames=posed),
                       align_gravity=False, estimate_up=False)  # fmt: skip
    assert on_time.pose_time_offset_s == 0.0 and on_time.pose_time_offset_source.startswith("0 s by the depth")
    given = load_tum(tmp_path / "ahead", align_gravity=False, estimate_up=False, pose_time_offset_s=0.01)
    assert (given.pose_time_offset_s, given.pose_time_offset_source) == (0.01, "given")


@pytest.mark.shared
def test_depth_that_reads_long_is_scaled_back_by_the_poses(seven_root: Path, tmp_path: Path) -> None:
    imaged = list(range(0, 400, 5))
    long = load_tum(build_tum_from_seven_scenes(seven_root, tmp_path / "long", imaged, depth_scale=1.04),
                    align_gravity=False, estimate_up=False, pose_time_offset_s=0.0)  # fmt: skip
    assert long.depth_factor == pytest.approx(5000 * 1.04, rel=0.011) and "by the depth" in long.depth_factor_source
    seven = load_seven_scenes(seven_root)
    theirs, ours = seven.load_frame("000100").depth_m, long.load_frame(long.frame_names[20]).depth_m
    both = (theirs > 0) & (ours > 0)
    assert np.median(theirs[both] / ours[both]) == pytest.approx(1.0, abs=0.011)  # metres again
    right = load_tum(tmp_path / "long", align_gravity=False, estimate_up=False, pose_time_offset_s=0.0, depth_factor=5200.0)
    assert (right.depth_factor, right.depth_factor_source) == (5200.0, "given")
    as_made = load_tum(build_tum_from_seven_scenes(seven_root, tmp_path / "as made", imaged), align_gravity=False,
                       estimate_up=False, pose_time_offset_s=0.0)  # fmt: skip
    assert as_made.depth_factor == 5000.0 and as_made.depth_factor_source.startswith("5000 by the depth")


@pytest.mark.shared
def test_up_comes_from_the_first_source_there(seven_root: Path, tmp_path: Path) -> None:
    root = build_tum_from_seven_scenes(seven_root, tmp_path / "kitchen", list(range(0, 1000, 50)))
    truth = np.asarray(json.loads((seven_root / "gt-boxes.json").read_text())["up_axis_world"])
    estimated = load_tum(root)
    assert estimated.up_source.startswith("estimated from") and estimated.up == pytest.approx((0.0, 0.0, 1.0))
    assert np.degrees(np.arccos(estimated.up_file @ truth / np.linalg.norm(truth))) < 3.0
    # the gravity-aligned world: a camera's pose turned, its position's height along up kept
    np.testing.assert_allclose(
        estimated.cam2world[0, 2, 3],
        estimated.up_file @ load_tum(root, align_gravity=False, estimate_up=False).cam2world[0, :3, 3],
    )
    from_truth = load_tum(root, gt_boxes=seven_root / "gt-boxes.json")
    assert from_truth.up_source.endswith("(up_axis_world)") and from_truth.ground_truth is not None
    np.testing.assert_allclose(from_truth.up_file, truth / np.linalg.norm(truth), atol=1e-12)
    np.savetxt(root / "gravity-direction.txt", [0.0, 1.0, 0.0])
    assert load_tum(root, gt_boxes=seven_root / "gt-boxes.json").up_file.tolist() == [0.0, -1.0, 0.0]
    given = load_tum(root, up=(0.0, 0.0, 2.0))
    assert given.up_source == "given (--up)" and given.up_file.tolist() == [0.0, 0.0, 1.0]
    np.testing.assert_allclose(given.world2file, np.eye(4))


# ---------------------------------------------------------------- intrinsics and malformed files


def write_tiny_tum(root: Path, *, n_frames: int = 3) -> Path:
    """``n_frames`` 64x48 frames 1/30 s apart (colour 5 ms after depth), a camera moving 1 cm a frame."""
    import cv2

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth, poses = [], [], []
    for i in range(n_frames):
        t = 100.0 + i / 30
        cv2.imwrite(str(root / "rgb" / f"{i}.png"), np.full((48, 64, 3), 80, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{i}.png"), np.full((48, 64), 10000, np.uint16))
        rgb.append(f"{t + 0.005:.6f} rgb/{i}.png")
        depth.append(f"{t:.6f} depth/{i}.png")
        poses.append(f"{t:.6f} {i * 0.01} 0 0 0 0 0 1")
    (root / "rgb.txt").write_text("# colour\n" + "\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(depth) + "\n")
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(poses) + "\n")
    return root


def test_intrinsics_given_from_a_file_by_the_folder_name_or_generic(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    fr3 = load_tum(write_tiny_tum(tmp_path / "rgbd_dataset_freiburg3_long_office_household"), estimate_up=False)
    assert fr3.intrinsics == PUBLISHED_INTRINSICS["freiburg3"] == Intrinsics(535.4, 539.2, 320.1, 247.6)
    # freiburg1 and 2 are the sensor's own images: the 525 TUM recommends for their registered depth, unless it disagrees
    fr2 = load_tum(write_tiny_tum(tmp_path / "Freiburg2_desk"), estimate_up=False)
    assert fr2.intrinsics == GENERIC_INTRINSICS
    assert fr2.intrinsics_source.startswith(
        "TUM's 525, 525, 319.5, 239.5 for freiburg2's registered depth (freiburg2 by the folder's name)"
    )
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.tum"):
        plain = load_tum(write_tiny_tum(tmp_path / "my room"), estimate_up=False)
    assert plain.intrinsics == GENERIC_INTRINSICS and "using the generic" in caplog.text
    (tmp_path / "my room" / "intrinsics.txt").write_text("500 501 320 240\n")
    assert load_tum(tmp_path / "my room", estimate_up=False).intrinsics == Intrinsics(500.0, 501.0, 320.0, 240.0)
    given = Intrinsics(1.0, 2.0, 3.0, 4.0)
    assert load_tum(tmp_path / "my room", intrinsics=given, estimate_up=False).intrinsics == given
    frame = plain.load_frame(plain.frame_names[1])
    np.testing.assert_allclose(frame.depth_m, 2.0)  # 10000 / 5000
    np.testing.assert_allclose(frame.cam2world[:3, 3], [0.01, 0.0, 0.0])
    half = load_tum(tmp_path / "my room", depth_factor=10000.0, estimate_up=False)
    np.testing.assert_allclose(half.load_frame(half.frame_names[0]).depth_m, 1.0)


def test_by_the_folder_name_the_intrinsics_the_depth_and_poses_agree_with(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    calibrated = PUBLISHED_INTRINSICS["freiburg1"]  # 16 px from the generic in cy
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.tum"):
        moved = load_tum(write_room_tum(tmp_path / "rgbd_dataset_freiburg1_room", calibrated), estimate_up=False)
    assert (
        moved.intrinsics == calibrated
        and "using TUM freiburg1's calibrated colour camera and a depth factor of 5000" in caplog.text
    )
    assert moved.intrinsics_source.startswith(
        "TUM freiburg1's calibrated colour camera, not TUM's 525, 525, 319.5, 239.5 for freiburg1's registered depth "
        "(freiburg1 by the folder's name): the depth and poses disagree by "
    )
    kept = load_tum(write_room_tum(tmp_path / "freiburg1_desk", GENERIC_INTRINSICS), estimate_up=False)
    assert kept.intrinsics == GENERIC_INTRINSICS
    assert kept.intrinsics_source.startswith(
        "TUM's 525, 525, 319.5, 239.5 for freiburg1's registered depth (freiburg1 by the folder's name): the depth and "
        "poses disagree by "
    )
    assert kept.depth_factor == moved.depth_factor == 5000.0  # exact renders: the intrinsics, not the depth's scale
    assert kept.distortion is None and moved.distortion is None  # pinhole renders: no lens to undo
    # a file or --intrinsics is taken as it is, unchecked
    (tmp_path / "freiburg1_desk" / "intrinsics.txt").write_text("517.3 516.5 318.6 255.3\n")
    from_file = load_tum(tmp_path / "freiburg1_desk", estimate_up=False)
    # ... and its depth's scale is not bent to make up for intrinsics 16 px off (that least lies at the scales' end)
    assert from_file.intrinsics == calibrated and from_file.depth_factor == 5000.0
    # frames that do not turn give nothing to check on: the name's, said so
    tiny = load_tum(write_tiny_tum(tmp_path / "rgbd_dataset_freiburg1_xyz"), estimate_up=False)
    assert (
        tiny.intrinsics == GENERIC_INTRINSICS and "no frames seen from places turned or stepped apart" in tiny.intrinsics_source
    )
    assert tiny.depth_factor_source == "5000; no frames seen from places turned or stepped apart to check it on"


def test_the_tum_camera_by_the_folder_as_resolved_or_by_the_bag_file_rgb_txt_names(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for folder in ("rgbd_dataset_freiburg1_desk2", "Freiburg1_desk2", "tum_fr1_desk", "freiburg1"):
        assert tum_camera(write_tiny_tum(tmp_path / folder)) == ("freiburg1", "by the folder's name"), folder
    renamed = write_tiny_tum(tmp_path / "office")
    assert tum_camera(renamed) is None and tum_camera(tmp_path / "freiburg12") is None
    # TUM's list files begin with the bag they were taken from
    listing = (renamed / "rgb.txt").read_text()
    (renamed / "rgb.txt").write_text("# color images\n# file: 'rgbd_dataset_freiburg2_desk.bag'\n" + listing)
    assert tum_camera(renamed) == ("freiburg2", "by the bag file rgb.txt names")
    assert load_tum(renamed, estimate_up=False).intrinsics_source.startswith(
        "TUM's 525, 525, 319.5, 239.5 for freiburg2's registered depth (freiburg2 by the bag file rgb.txt names)"
    )
    monkeypatch.chdir(tmp_path / "Freiburg1_desk2")  # `eval recording --root .`
    assert tum_camera(Path(".")) == ("freiburg1", "by the folder's name")


def test_a_scale_or_another_camera_is_taken_only_by_the_margin_over_what_it_replaces(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import arcloud.datasets.tum as tum

    root = write_room_tum(tmp_path / "rgbd_dataset_freiburg1_room", GENERIC_INTRINSICS, 12)
    plain = load_tum(root, estimate_up=False, pose_time_offset_s=0.0)
    cameras = {GENERIC_INTRINSICS.fx: 0, PUBLISHED_INTRINSICS["freiburg1"].fx: 1}

    def disagreement(table: dict[tuple[int, float], float]):  # by (camera: 0 generic, 1 calibrated; scale), else 10 mm
        def measured(depths, cam2world, intrinsics, pairs):
            scale = round(float(np.nanmedian(depths[0]) / np.nanmedian(read_png_u16(plain.depth_paths[0]) / 5000.0)), 2)
            return table.get((cameras[intrinsics.fx], scale), 0.010)

        return measured

    def read(table: dict[tuple[int, float], float]):
        monkeypatch.setattr(tum, "depth_disagreement", disagreement(table))
        return load_tum(root, estimate_up=False, pose_time_offset_s=0.0)

    # a scale 1 % better than its own camera at 1 is no scale; 3 % is
    assert read({(0, 0.98): 0.0099}).depth_factor == 5000.0
    assert read({(0, 0.98): 0.0097}).depth_factor == pytest.approx(5000 / 0.98)
    # another camera at its own scale: by the margin over this one at its scale, not over this one at 1
    assert read({(0, 0.98): 0.0090, (1, 1.0): 0.0089}).intrinsics == GENERIC_INTRINSICS
    assert read({(0, 0.98): 0.0090, (1, 1.0): 0.0087}).intrinsics == PUBLISHED_INTRINSICS["freiburg1"]
    # a least at an end of the scales is a climb, not taken
    assert read({(0, 0.95): 0.0080}).depth_factor == 5000.0


def test_a_path_that_steps_without_turning_still_tells_the_depths_scale(tmp_path: Path) -> None:
    made = Intrinsics(525.0, 525.0, 319.5, 239.5)
    stepping = write_room_tum(tmp_path / "sideways", made, 12, turn_deg=0.0, depth_scale=1.04)  # 5 cm a frame, level
    read = load_tum(stepping, intrinsics=made, estimate_up=False, pose_time_offset_s=0.0)
    assert read.depth_factor == pytest.approx(5000 * 1.04, rel=0.011) and "by the depth" in read.depth_factor_source


def test_depth_in_millimetres_read_at_tums_factor_is_told_the_factor_it_agrees_with(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A new user's review: a recording of millimetres (factor 1000) was read at 5000 with no word of the factor, and a
    warning proposed other intrinsics instead (its mAP 0.000)."""
    made = Intrinsics(525.0, 525.0, 319.5, 239.5)
    millimetres = write_room_tum(tmp_path / "mm", made, 12, depth_scale=0.2)  # what 5000 reads of millimetres: 5x short
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.tum"):
        load_tum(millimetres, intrinsics=made, estimate_up=False, pose_time_offset_s=0.0)
    assert "the depth and poses agree far better at a depth factor of 1000 (millimetres)" in caplog.text
    assert "give --depth-factor 1000 if its depth is in millimetres" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.tum"):
        load_tum(write_room_tum(tmp_path / "tum", made, 12), intrinsics=made, estimate_up=False, pose_time_offset_s=0.0)
    assert "millimetres" not in caplog.text  # TUM's own units: no such word


def test_a_lens_that_bends_both_images_is_undone_when_the_depth_agrees(tmp_path: Path) -> None:
    calibrated, lens = PUBLISHED_INTRINSICS["freiburg1"], PUBLISHED_DISTORTION["freiburg1"]
    bent = load_tum(write_room_tum(tmp_path / "rgbd_dataset_freiburg1_room", calibrated, 12, distortion=lens), estimate_up=False)
    assert bent.distortion == lens and bent.intrinsics == calibrated
    assert "with its lens distortion" in bent.intrinsics_source and bent.depth_factor == 5000.0
    # its frames are the pinhole images: depth as a straight camera sees it, but at the image's outer pixels
    frame = bent.load_frame(bent.frame_names[8])
    straight = cast_boxes(frame.cam2world, BOX_ROOM, intrinsics=calibrated, shape=(480, 640))[0]
    both = (frame.depth_m > 0) & (straight > 0)
    assert both.mean() > 0.8 and np.mean(np.abs(frame.depth_m[both] - straight[both]) < 0.005) > 0.98
    as_read = read_png_u16(bent.depth_paths[8]) / 5000.0
    assert np.mean(np.abs(as_read[both] - straight[both]) < 0.005) < 0.5  # what the lens did


@pytest.mark.parametrize(
    ("file", "text", "message"),
    [
        ("rgb.txt", "1.0 rgb/0.png extra\n", r"rgb.txt:1: expected 'timestamp path' \(2 fields\), got '1.0 rgb/0.png extra'"),
        ("depth.txt", "# only comments\n", r"depth.txt: expected lines 'timestamp path', got none"),
        ("depth.txt", "noon depth/0.png\n", r"depth.txt:1: expected a timestamp in seconds first, got 'noon'"),
        ("groundtruth.txt", "100.0 0 0 0 0 0 0\n", r"groundtruth.txt:1: expected 'timestamp tx ty tz qx qy qz qw' \(8 fields\)"),
        (
            "groundtruth.txt",
            "# poses\n100.0 0 0 0 0 0 0 2\n",
            r"groundtruth.txt:2: expected unit quaternions qx qy qz qw, got norm 2.0000 at time 100.0",
        ),
        ("groundtruth.txt", "100.0 0 0 nan 0 0 0 1\n", r"groundtruth.txt:1: expected finite poses"),
        (
            "groundtruth.txt",
            "100.0 0 0 0 0 0 0 1\n101.0 0 x 0 0 0 0 1\n",
            r"groundtruth.txt:2: expected numbers 'timestamp tx ty tz qx qy qz qw', got '101.0 0 x 0 0 0 0 1'",
        ),
        ("groundtruth.txt", "100.0 0 0 0 0 0 0 1\n100.0 1 0 0 0 0 0 1\n", "expected one pose per timestamp, got two at 100.0"),
        ("groundtruth.txt", "500.0 0 0 0 0 0 0 1\n", "expected depth images with a colour image and a pose, got none of 3"),
        (
            "intrinsics.txt",
            "1 2 3 4 5\n",
            r"intrinsics.txt: expected 4, 9 or 16 numbers \(fx fy cx cy, or a camera matrix\), got 5",
        ),
        ("intrinsics.txt", "-1 2 3 4\n", "expected finite intrinsics with positive focal lengths"),
        (
            "gravity-direction.txt",
            "0 0 0\n",
            r"gravity-direction.txt: expected 3 finite numbers, not all 0, got \[0.0, 0.0, 0.0\]",
        ),
    ],
)
def test_malformed_files_are_named(tmp_path: Path, file: str, text: str, message: str) -> None:
    root = write_tiny_tum(tmp_path / "room")
    (root / file).write_text(text)
    with pytest.raises(DatasetError, match=message):
        load_tum(root, estimate_up=False)


def test_missing_files_and_options_are_named(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="expected a TUM RGB-D folder, got no such folder"):
        load_tum(tmp_path / "nowhere")
    root = write_tiny_tum(tmp_path / "room")
    with pytest.raises(DatasetError, match="depth factor: expected a positive number of depth units a metre, got 0.0"):
        load_tum(root, depth_factor=0.0)
    (root / "groundtruth.txt").unlink()
    with pytest.raises(DatasetError, match=r"expected groundtruth.txt \(TUM RGB-D layout\), got no such file"):
        load_tum(root)
    with pytest.raises(DatasetError, match="gt.json: expected a readable ground-truth file"):
        load_tum(write_tiny_tum(tmp_path / "other"), gt_boxes=tmp_path / "gt.json", estimate_up=False)
