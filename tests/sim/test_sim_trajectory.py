"""Walk planning: rigid poses in OpenCV axes, inside the free floor, smooth, looking at the targets."""

from __future__ import annotations

import numpy as np
import pytest

from arcloud.core.checks import check_pose
from arcloud.errors import InvalidInput
from arcloud.sim.room import generate_room
from arcloud.sim.trajectory import look_at, plan_walk, room_walk

FX, CX, CY, W, H = 525.0, 319.5, 239.5, 640, 480
TARGETS = np.array([[1.5, 1.5, 0.4], [4.5, 1.2, 0.7], [3.0, 3.5, 0.5], [5.0, 3.8, 1.0]])
OBSTACLES = [(np.array([1.2, 1.2]), np.array([1.8, 1.8])), (np.array([4.0, 0.8]), np.array([5.0, 1.6]))]


def project(cam2world: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) and depths (N,) of world points."""
    cam = (points - cam2world[:3, 3]) @ cam2world[:3, :3]
    return FX * cam[:, :2] / cam[:, 2:3] + [CX, CY], cam[:, 2]


def in_image(cam2world: np.ndarray, points: np.ndarray) -> np.ndarray:
    uv, z = project(cam2world, points)
    return (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)


def test_look_at_uses_opencv_axes_in_a_z_up_world() -> None:
    eye, target = np.array([1.0, 2.0, 1.5]), np.array([4.0, 2.0, 0.5])
    pose = look_at(eye, target)
    check_pose("pose", pose)
    uv, z = project(pose, np.array([target, target + [0, 0, 0.5], target + [0, -0.5, 0]]))
    np.testing.assert_allclose(uv[0], [CX, CY], atol=1e-9)
    assert z[0] > 0
    assert uv[1, 1] < uv[0, 1]  # higher in the world is higher in the image (smaller v)
    assert uv[2, 0] > uv[0, 0]  # looking along +x, -y is to the right
    rolled = look_at(eye, target, roll_rad=0.3)
    np.testing.assert_allclose(rolled[:3, 2], pose[:3, 2])
    with pytest.raises(InvalidInput):
        look_at(eye, eye + [0, 0, -1.0])


@pytest.fixture(scope="module")
def walk() -> list[np.ndarray]:
    return plan_walk((0, 0), (6, 5), TARGETS, 240, seed=3, obstacles_xy=OBSTACLES)


def test_poses_are_rigid_inside_the_free_floor_at_eye_height(walk: list[np.ndarray]) -> None:
    assert len(walk) == 240
    eyes = np.array([check_pose("cam2world", p)[:3, 3] for p in walk])
    assert np.all(eyes[:, :2] >= 0.3) and np.all(eyes[:, :2] <= [5.7, 4.7])
    assert np.all((eyes[:, 2] > 1.3) & (eyes[:, 2] < 1.7))
    for lo, hi in OBSTACLES:
        inside = np.all((eyes[:, :2] > lo - 0.15) & (eyes[:, :2] < hi + 0.15), axis=1)
        assert not inside.any()


def test_walk_is_smooth(walk: list[np.ndarray]) -> None:
    eyes = np.array([p[:3, 3] for p in walk])
    steps = np.linalg.norm(np.diff(eyes[:, :2], axis=0), axis=1)
    assert steps.max() < 0.06 and np.median(steps) > 0.04
    forward = np.array([p[:3, 2] for p in walk])
    turn_deg = np.degrees(np.arccos(np.clip(np.sum(forward[1:] * forward[:-1], axis=1), -1, 1)))
    # The head turns at most 4 degrees a frame sideways and 2.5 up or down (at 30 Hz: 120 and 75 degrees
    # a second), without jerks.
    assert turn_deg.max() < 5.0 and np.abs(np.diff(turn_deg)).max() < 1.0


def test_frames_look_at_targets_and_every_target_is_seen_from_several_sides(walk: list[np.ndarray]) -> None:
    seen_sides: list[set[int]] = [set() for _ in TARGETS]
    looking = 0
    for pose in walk:
        visible = in_image(pose, TARGETS)
        looking += visible.any()
        for k in np.flatnonzero(visible):
            offset = pose[:2, 3] - TARGETS[k, :2]
            seen_sides[k].add(int((np.arctan2(offset[1], offset[0]) + np.pi) // (np.pi / 4)) % 8)
    assert looking >= 0.8 * len(walk)  # the rest: turning from one target to the next
    assert all(len(sides) >= 2 for sides in seen_sides), seen_sides


def test_same_seed_same_walk_other_seed_other_walk(walk: list[np.ndarray]) -> None:
    again = plan_walk((0, 0), (6, 5), TARGETS, 240, seed=3, obstacles_xy=OBSTACLES)
    other = plan_walk((0, 0), (6, 5), TARGETS, 240, seed=4, obstacles_xy=OBSTACLES)
    np.testing.assert_array_equal(np.array(walk), np.array(again))
    assert not np.allclose(np.array(walk), np.array(other))


def test_floor_height_and_no_targets() -> None:
    poses = plan_walk((-2, -2), (2, 2), np.empty((0, 3)), 30, seed=0, floor_z_m=0.8, eye_height_jitter_m=0.0)
    eyes = np.array([p[:3, 3] for p in poses])
    assert np.all(np.abs(eyes[:, 2] - 2.3) < 0.05)
    for pose in poses:
        check_pose("cam2world", pose)
        assert pose[2, 2] < 0  # looks a little down, ahead


def test_room_walk_sees_every_object_often_and_free_standing_ones_from_several_sides() -> None:
    room = generate_room(1)
    poses = room_walk(room, 300, seed=1)
    eyes = np.array([p[:3, 3] for p in poses])
    assert np.all(eyes[:, :2] > 0.3) and np.all(eyes[:, :2] < room.size_m[:2] - 0.3)
    for lo, hi in room.obstacles_xy():
        assert not np.any(np.all((eyes[:, :2] > lo) & (eyes[:, :2] < hi), axis=1))
    for obj in room.objects:
        sides, frames = set(), 0
        for pose in poses:
            offset = pose[:2, 3] - obj.center[:2]
            if in_image(pose, obj.center[None])[0] and np.linalg.norm(offset) < 5.0:
                frames += 1
                sides.add(int((np.arctan2(offset[1], offset[0]) + np.pi) // (np.pi / 4)) % 8)
        wall_gap = min(*obj.aabb_min[:2], *(room.size_m[:2] - obj.aabb_max[:2]))
        assert frames >= 10, (obj.label, obj.instance_id, frames)
        assert len(sides) >= (1 if wall_gap < 0.3 else 2), (obj.label, obj.instance_id, sides)


@pytest.mark.parametrize(
    ("args", "kwargs"),
    [
        (((0, 0), (6, 5), TARGETS, 0, 0), {}),
        (((0, 0), (0.5, 5), TARGETS, 10, 0), {}),
        (((0, 0), (6, 5), TARGETS, 10, 0), {"step_m": 0.0}),
        (((0, 0), (6, 5), TARGETS, 10, 0), {"obstacles_xy": [((-1, -1), (7, 6))]}),
    ],
)
def test_bad_arguments_raise_invalid_input(args: tuple, kwargs: dict) -> None:
    with pytest.raises(InvalidInput):
        plan_walk(*args, **kwargs)
