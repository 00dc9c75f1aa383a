"""Which intrinsics the depth and poses agree with (core.calibration): exact renders of a room of boxes from
poses turned apart agree with the intrinsics that made them, and less with a principal point a few pixels off
or a focal length a few per cent off, and near moved intrinsics the ones that made them are found; frames that
only step make no pairs. The depth's edges meet the colour's where the colour camera stands."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from handmade_frames import BOX_ROOM, cast_boxes, turning_poses

from arcloud.core.calibration import (
    MAX_PAIRS,
    PAIR_TURN_DEG,
    agreeing_intrinsics,
    colour_edge_strength,
    depth_disagreement,
    stepped_pairs,
    view_pairs,
)
from arcloud.core.checks import make_frame
from arcloud.core.types import Intrinsics

INTRINSICS = Intrinsics(400.0, 400.0, 160.0, 120.0)  # 320 x 240 pixels, 44 degrees across
SHAPE = (240, 320)


def renders(poses: np.ndarray, intrinsics=INTRINSICS) -> list[np.ndarray]:
    return [cast_boxes(pose, BOX_ROOM, intrinsics=intrinsics, shape=SHAPE)[0] for pose in poses]


@pytest.fixture(scope="module")
def room_renders() -> list[np.ndarray]:
    return renders(turning_poses())


def test_pairs_are_turned_apart_near_each_other_and_drawn_the_same_each_time() -> None:
    poses = turning_poses()
    pairs = view_pairs(poses)
    assert pairs and pairs == view_pairs(poses)
    for i, j in pairs:
        relative = poses[i, :3, :3].T @ poses[j, :3, :3]
        turn = np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1)))
        assert PAIR_TURN_DEG[0] <= turn <= PAIR_TURN_DEG[1]
    assert {(0, 1), (0, 2)} <= set(pairs) and (0, 3) not in pairs  # 12, 24 degrees apart; 36 is too many
    sideways = turning_poses(step_deg=0.0, pitching=False)  # frames that only step tell little: no pairs
    assert view_pairs(sideways) == []
    stepped = stepped_pairs(sideways)  # ... but a depth's scale: pairs stepped 0.2-1 m apart
    assert stepped and all(0.2 <= np.linalg.norm(sideways[i, :3, 3] - sideways[j, :3, 3]) <= 1.0 for i, j in stepped)
    assert stepped_pairs(turning_poses()) == []  # every neighbour far enough away has turned
    many = view_pairs(turning_poses(n=60, step_deg=3.0))
    assert len(many) == MAX_PAIRS and many == sorted(many)


@pytest.mark.parametrize(
    "moved",
    [{"cy": 132.0}, {"cy": 108.0}, {"cx": 172.0}, {"fx": 420.0, "fy": 420.0}, {"fx": 380.0, "fy": 380.0}],
)
def test_the_depth_agrees_best_with_the_intrinsics_that_made_it(moved: dict[str, float], room_renders: list[np.ndarray]) -> None:
    poses = turning_poses()
    depths, pairs = room_renders, view_pairs(poses)
    right = depth_disagreement(depths, poses, INTRINSICS, pairs)
    wrong = depth_disagreement(depths, poses, dataclasses.replace(INTRINSICS, **moved), pairs)
    assert right < 0.01  # exact renders: what is left is the pixel a sample lands on
    assert wrong > 2 * right
    # and the other way round: depth made with the moved intrinsics agrees with them, not with the first
    made = renders(poses, dataclasses.replace(INTRINSICS, **moved))
    assert depth_disagreement(made, poses, dataclasses.replace(INTRINSICS, **moved), pairs) < depth_disagreement(
        made, poses, INTRINSICS, pairs
    )


def test_nothing_to_compare_is_nan() -> None:
    poses = turning_poses(n=3)
    empty = [np.zeros_like(d) for d in renders(poses)]  # no depth measured anywhere
    assert np.isnan(depth_disagreement(empty, poses, INTRINSICS, view_pairs(poses)))
    assert np.isnan(depth_disagreement(renders(poses), poses, INTRINSICS, []))


def test_near_moved_intrinsics_the_ones_that_made_the_depth_are_found(room_renders: list[np.ndarray]) -> None:
    poses = turning_poses()
    pairs = view_pairs(poses)
    moved = dataclasses.replace(INTRINSICS, fx=380.0, fy=380.0, cx=166.0, cy=130.0)
    found, gap = agreeing_intrinsics(room_renders, poses, moved, pairs)
    assert abs(found.fx - INTRINSICS.fx) <= 4 and found.fx == found.fy  # the focal length within 1 %
    assert abs(found.cx - INTRINSICS.cx) <= 2 and abs(found.cy - INTRINSICS.cy) <= 2  # within a step
    assert (
        gap
        <= depth_disagreement(room_renders, poses, INTRINSICS, pairs) * 1.5
        < depth_disagreement(room_renders, poses, moved, pairs)
    )
    # at the intrinsics that made it, nothing near does better by more than the pixels' rounding
    assert agreeing_intrinsics(room_renders, poses, INTRINSICS, pairs)[0].fx == INTRINSICS.fx


def room_frames(colour_shift_px: tuple[float, float], *, scale: float = 1.0, baseline_m: float = 0.0) -> list:
    """Frames of ``BOX_ROOM`` along ``turning_poses`` whose colour images (each box a grey of its own, the floor
    another) were taken by a camera whose principal point lies ``colour_shift_px`` from the depth camera's, whose
    focal lengths are ``scale`` times its, and which stands ``baseline_m`` from it along its x axis (a colour point
    is a depth point plus (``baseline_m``, 0, 0), as ``Frame.depth2rgb`` moves it)."""
    colour = dataclasses.replace(
        INTRINSICS, fx=INTRINSICS.fx * scale, fy=INTRINSICS.fy * scale,
        cx=INTRINSICS.cx + colour_shift_px[0], cy=INTRINSICS.cy + colour_shift_px[1],
    )  # fmt: skip
    beside = np.eye(4)
    beside[0, 3] = -baseline_m  # the colour camera's centre in depth camera coordinates
    greys = np.array([40, 70, 100, 130, 160, 190, 220], np.uint8)  # boxes 0-5, then the floor (instance -1)
    frames = []
    for i, pose in enumerate(turning_poses()):
        depth = cast_boxes(pose, BOX_ROOM, intrinsics=INTRINSICS, shape=SHAPE)[0]
        instance = cast_boxes(pose @ beside, BOX_ROOM, intrinsics=colour, shape=SHAPE)[1]
        rgb = np.repeat(greys[instance][..., None], 3, axis=2)
        frames.append(make_frame(rgb, depth, INTRINSICS, pose, timestamp_s=i / 30, map_id="m", device_id="d", frame_id=f"{i}"))
    return frames


def test_the_depth_edges_meet_the_colour_edges_where_the_colour_camera_stands() -> None:
    shifts = [(du, dv) for dv in range(-5, 6) for du in range(-5, 6)]
    moves = [(1.0, du, dv, 0.0) for du, dv in shifts]
    moved = room_frames((3.0, -2.0))
    strength = colour_edge_strength(moved, moves)
    # within a pixel: an edge lies between its near pixel and its far one, where both colour pixels change
    assert np.abs(np.subtract(shifts[int(np.argmax(strength))], (3, -2))).max() <= 1
    assert strength.max() > 2 * strength[shifts.index((0, 0))]  # as the frames say (registered), edges miss
    # told where the colour camera stands, the edges meet where they are
    told = [dataclasses.replace(f, rgb_intrinsics=dataclasses.replace(INTRINSICS, cx=163.0, cy=118.0)) for f in moved]
    assert np.abs(shifts[int(np.argmax(colour_edge_strength(told, moves)))]).max() <= 1
    assert np.isnan(colour_edge_strength([dataclasses.replace(moved[0], depth_m=np.zeros(SHAPE, np.float32))], [(1, 0, 0, 0)])[0])


def test_another_focal_length_and_a_baseline_are_told_apart_from_a_shift() -> None:
    # a Kinect v1's colour camera: a focal length 10 % shorter than its depth camera's, 3.5 cm to the side
    frames = room_frames((0.0, 0.0), scale=0.9, baseline_m=-0.035)
    moves = [(scale, du, 0.0, tx) for scale in (0.9, 1.0) for du in range(-12, 13, 2) for tx in (-0.035, 0.0, 0.035)]
    strength = colour_edge_strength(frames, moves)
    assert moves[int(np.argmax(strength))] == (0.9, 0, 0.0, -0.035)
    assert strength.max() > 1.5 * strength[moves.index((1.0, 0, 0.0, 0.0))]


def test_a_depth_image_of_another_size_is_compared_within_its_own_bounds(room_renders: list[np.ndarray]) -> None:
    poses = turning_poses()
    pairs = view_pairs(poses)
    odd = list(room_renders)
    odd[pairs[0][1]] = np.zeros((48, 64), np.float32)  # a stray small image, as a recording may hold by mistake
    assert np.isfinite(depth_disagreement(odd, poses, INTRINSICS, pairs))
