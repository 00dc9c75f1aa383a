"""Walk planning: rigid poses in OpenCV axes, inside the free floor, smooth, looking at the targets."""

from __future__ import annotations

import numpy as np
import pytest

from arcloud.core.checks import check_pose
from arcloud.errors import InvalidInput
from arcloud.sim.room import generate_room, room_walk
from arcloud.virtual_camera.gaze import look_at
from arcloud.virtual_camera.walk import (
    EYE_HEIGHT_RANGE_M,
    FIXATION_RANGE_FRAMES,
    LAPS_RANGE,
    STEP_RANGE_M,
    WalkStyle,
    plan_walk,
    scan_walk,
)

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


# Walk styles


def pitch_and_yaw_deg(poses: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(N,) pitch of the optical axis above the horizon and (N,) unwrapped yaw, in degrees."""
    forward = np.array([p[:3, 2] for p in poses])
    pitch = np.degrees(np.arcsin(np.clip(forward[:, 2], -1, 1)))
    yaw = np.degrees(np.unwrap(np.arctan2(forward[:, 1], forward[:, 0])))
    return pitch, yaw


def styled(style: WalkStyle, n_frames: int = 240, seed: int = 3) -> list[np.ndarray]:
    return plan_walk((0, 0), (6, 5), TARGETS, n_frames, seed, obstacles_xy=OBSTACLES, style=style)


def test_style_sets_eye_height_and_speed_and_keeps_the_path_of_the_default_walk(walk: list[np.ndarray]) -> None:
    for height, step in ((1.1, 0.03), (1.9, 0.07)):
        poses = styled(WalkStyle(eye_height_m=height, step_m=step))
        eyes = np.array([check_pose("cam2world", p)[:3, 3] for p in poses])
        assert abs(np.median(eyes[:, 2]) - height) < 0.03 and np.ptp(eyes[:, 2]) < 0.1
        assert abs(np.median(np.linalg.norm(np.diff(eyes[:, :2], axis=0), axis=1)) - step) < 0.005
    # The default figures walk the default path (only the per-walk eye height offset is gone).
    same = styled(WalkStyle())
    np.testing.assert_array_equal(np.array(same)[:, :2, 3], np.array(walk)[:, :2, 3])


def test_a_scan_walks_the_default_path_looking_along_the_walls_not_at_the_targets(walk: list[np.ndarray]) -> None:
    scan = scan_walk((0, 0), (6, 5), TARGETS, 240, seed=3, obstacles_xy=OBSTACLES)
    assert len(scan) == 240 and all(check_pose("cam2world", p) is not None for p in scan)
    np.testing.assert_array_equal(np.array(scan)[:, :3, 3], np.array(walk)[:, :3, 3])  # the same path and eye heights
    down = np.degrees(np.arcsin(-np.array([p[2, 2] for p in scan])))  # the optical axis below the horizon
    assert down.min() >= 10 - 1e-6 and down.max() <= 55 + 1e-6 and np.ptp(down) > 40
    # Mostly facing away from the room's centre: towards the walls and what stands before them.
    outward = np.array([p[:2, 3] - [3.0, 2.5] for p in scan])
    facing = np.einsum("ij,ij->i", outward, np.array([p[:2, 2] for p in scan])) > 0
    assert 0.5 < facing.mean() < 0.9  # every third stretch of 90 frames faces the room

    # The default walk keeps its targets near the image centre; the scan does not look at them.
    def near_centre(poses: list[np.ndarray]) -> float:
        uv, z = zip(*(project(p, TARGETS) for p in poses))
        offset = np.abs(np.array(uv) - [CX, CY]).max(axis=2)
        return float(((np.array(z) > 0) & (offset < 120)).any(axis=1).mean())

    assert near_centre(walk) > 0.6 and near_centre(scan) < 0.3  # measured 0.73 and 0.11


def angles_around_room(poses: list[np.ndarray], centre: np.ndarray) -> set[int]:
    """The 10-degree sectors around ``centre`` that the walk passes through."""
    offset = np.array([p[:2, 3] for p in poses]) - centre
    return set((np.degrees(np.arctan2(offset[:, 1], offset[:, 0])) // 10).astype(int).tolist())


@pytest.mark.parametrize("seed", [3, 4])
def test_laps_below_one_walk_only_part_of_the_room(seed: int) -> None:
    centre = np.array([3.0, 2.5])
    partial = styled(WalkStyle(laps=0.4), n_frames=150, seed=seed)
    full = styled(WalkStyle(laps=1.0), n_frames=150, seed=seed)
    assert len(angles_around_room(partial, centre)) <= 0.6 * 36
    assert len(angles_around_room(full, centre)) >= 0.9 * 36


def test_glances_pitch_to_the_floor_and_the_ceiling_and_come_back() -> None:
    calm = styled(WalkStyle(), n_frames=300)
    glancing = styled(WalkStyle(glances_per_100_frames=1.5), n_frames=300)
    calm_pitch, _ = pitch_and_yaw_deg(calm)
    pitch, _ = pitch_and_yaw_deg(glancing)
    assert calm_pitch.max() < 25.0
    assert np.count_nonzero(pitch > 30.0) >= 3 and np.count_nonzero(pitch < -55.0) >= 3
    assert np.abs(pitch).max() < 85.0  # never straight up or down
    assert np.count_nonzero(np.abs(pitch - calm_pitch) > 5.0) < 0.6 * len(pitch)  # and back to the targets


def test_fast_turns_are_bursts_of_high_yaw_rate() -> None:
    calm = styled(WalkStyle(), n_frames=300)
    turning = styled(WalkStyle(fast_turns_per_100_frames=1.5), n_frames=300)
    calm_rate = np.abs(np.diff(pitch_and_yaw_deg(calm)[1]))
    rate = np.abs(np.diff(pitch_and_yaw_deg(turning)[1]))
    assert calm_rate.max() < 5.0
    assert rate.max() > 10.0
    assert 2 <= np.count_nonzero(rate > 6.0) < 0.4 * len(rate)  # bursts, not a spin


def test_jitter_moves_the_camera_by_its_standard_deviations() -> None:
    from scipy.spatial.transform import Rotation

    steady = np.array(styled(WalkStyle(), n_frames=300))
    shaky = np.array(styled(WalkStyle(jitter_deg=0.5, jitter_m=0.004), n_frames=300))
    motion = np.linalg.inv(steady) @ shaky  # in each camera's frame
    angles_deg = np.degrees(Rotation.from_matrix(motion[:, :3, :3]).as_rotvec())
    assert 0.35 < np.std(angles_deg) < 0.65
    assert 0.0028 < np.std(motion[:, :3, 3]) < 0.0052
    for pose in shaky:
        check_pose("cam2world", pose)


def test_sampled_styles_are_varied_within_their_ranges_and_seeded() -> None:
    rng = np.random.default_rng(11)
    styles = [WalkStyle.sample(rng) for _ in range(40)]
    assert styles[:5] == [WalkStyle.sample(r) for r in [np.random.default_rng(11)] for _ in range(5)]
    heights = np.array([s.eye_height_m for s in styles])
    assert EYE_HEIGHT_RANGE_M[0] <= heights.min() < 1.3 and 1.7 < heights.max() <= EYE_HEIGHT_RANGE_M[1]
    assert all(STEP_RANGE_M[0] <= s.step_m <= STEP_RANGE_M[1] for s in styles)
    assert all(LAPS_RANGE[0] <= s.laps <= LAPS_RANGE[1] for s in styles)
    assert any(s.laps < 1 for s in styles) and any(s.laps > 1 for s in styles)
    assert all(FIXATION_RANGE_FRAMES[0] <= s.fixation_frames <= FIXATION_RANGE_FRAMES[1] for s in styles)
    assert len({s.fixation_frames for s in styles}) > 10


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sampled_walks_stay_rigid_inside_the_free_floor(seed: int) -> None:
    room = generate_room(seed)
    style = WalkStyle.sample(np.random.default_rng(seed))
    poses = room_walk(room, 200, seed=seed, style=style)
    assert len(poses) == 200
    eyes = np.array([check_pose("cam2world", p)[:3, 3] for p in poses])
    assert np.all(eyes[:, :2] > 0.25) and np.all(eyes[:, :2] < room.size_m[:2] - 0.25)
    assert np.all(np.abs(eyes[:, 2] - style.eye_height_m) < 0.06)
    np.testing.assert_array_equal(np.array(poses), np.array(room_walk(room, 200, seed=seed, style=style)))


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"eye_height_m": 3.0}, "WalkStyle.eye_height_m"),
        ({"step_m": 0.0}, "WalkStyle.step_m"),
        ({"laps": -1.0}, "WalkStyle.laps"),
        ({"fixation_frames": 0}, "WalkStyle.fixation_frames"),
        ({"glances_per_100_frames": float("nan")}, "WalkStyle.glances_per_100_frames"),
        ({"jitter_deg": True}, "WalkStyle.jitter_deg"),
    ],
)
def test_bad_styles_name_their_field(changes: dict, field: str) -> None:
    with pytest.raises(InvalidInput) as info:
        WalkStyle(**changes)
    assert info.value.field == field


def test_a_style_does_not_come_with_the_figures_it_sets() -> None:
    with pytest.raises(InvalidInput, match="eye_height_m"):
        plan_walk((0, 0), (6, 5), TARGETS, 10, 0, style=WalkStyle(), eye_height_m=1.6)
    with pytest.raises(InvalidInput, match="WalkStyle or None"):
        plan_walk((0, 0), (6, 5), TARGETS, 10, 0, style="random")  # type: ignore[arg-type]  # on purpose: a refused style
