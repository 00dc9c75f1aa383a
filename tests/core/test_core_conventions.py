"""Pose conventions (``core.conventions``): hand-written cases (an ARKit camera at its session's origin is a
level OpenCV camera looking along +y), round trips over seeded random poses, rigidity, and the checks' refusals."""

from __future__ import annotations

import numpy as np
import pytest

from arcloud.core.conventions import (
    CAMERA_FLIP,
    MAX_ALIGNMENT_TILT_DEG,
    POSE_CONVENTIONS,
    cam2device,
    cam2map,
    camera_axes,
    check_convention,
    check_device_from_map,
    check_up,
    gravity_rotation,
    rigid_inverse,
    tilt_deg,
    world2map,
)
from arcloud.core.gravity import up_rotation
from arcloud.errors import InvalidInput

#: A y-up world's points in a z-up one: +90 degrees about x, (x, y, z) -> (x, -z, y), written out.
Z_UP_FROM_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: An OpenCV camera 1 m up, level, looking along the map's +y: x -> x, y (down) -> -z, z (forward) -> +y.
LEVEL_CAM2MAP = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]])


def rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues), independent of the module under test."""
    k = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * skew + (1 - np.cos(angle_rad)) * skew @ skew


def random_rigid(rng: np.random.Generator, translation_m: float = 3.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = rotation_about(rng.normal(size=3), rng.uniform(-np.pi, np.pi))
    pose[:3, 3] = rng.uniform(-translation_m, translation_m, 3)
    return pose


def yaw_and_shift(up: np.ndarray, yaw_rad: float, shift_m: np.ndarray) -> np.ndarray:
    """A device alignment that keeps ``up``: a rotation about it and a translation."""
    transform = np.eye(4)
    transform[:3, :3] = rotation_about(up, yaw_rad)
    transform[:3, 3] = shift_m
    return transform


def assert_rigid(transform: np.ndarray) -> None:
    rotation = transform[:3, :3]
    assert transform.shape == (4, 4) and np.allclose(transform[3], (0, 0, 0, 1), atol=0)
    assert np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-12) and np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)


# --- smoke: hand-written cases ---------------------------------------------------------------------------------------
def test_an_arkit_camera_at_its_origin_is_a_level_opencv_camera_looking_along_the_maps_y() -> None:
    arkit_pose = np.eye(4)
    arkit_pose[1, 3] = 1.0  # 1 m up in ARKit's y-up world
    assert np.array_equal(cam2map(arkit_pose, "arkit"), LEVEL_CAM2MAP)
    assert np.array_equal(cam2map(arkit_pose, "arcore"), LEVEL_CAM2MAP)


def test_a_y_up_world_turns_into_a_z_up_one_by_90_degrees_about_x() -> None:
    assert np.array_equal(gravity_rotation((0, 1, 0), (0, 0, 1)), Z_UP_FROM_Y_UP)
    assert np.array_equal(world2map("arkit")[:3, :3], Z_UP_FROM_Y_UP)
    # ARKit's forward (-z) is the map's +y, its right (+x) the map's +x, its up (+y) the map's up
    assert np.array_equal(Z_UP_FROM_Y_UP @ (0, 0, -1), (0, 1, 0)) and np.array_equal(Z_UP_FROM_Y_UP @ (0, 1, 0), (0, 0, 1))


def test_opencv_frames_without_a_declaration_are_in_the_maps_world_as_they_come() -> None:
    pose = random_rigid(np.random.default_rng(0))
    assert np.array_equal(cam2map(pose), pose)
    assert np.array_equal(world2map("opencv", None, (0.3, 0.2, 0.9)), np.eye(4))  # the map's up: nothing to rotate


def test_the_camera_flip_reverses_y_and_z_and_is_its_own_inverse() -> None:
    assert np.array_equal(CAMERA_FLIP, np.diag([1.0, -1.0, -1.0, 1.0])) and np.array_equal(CAMERA_FLIP @ CAMERA_FLIP, np.eye(4))
    assert np.array_equal(camera_axes("opencv"), np.eye(4)) and camera_axes("arkit") is CAMERA_FLIP


def test_a_point_seen_by_an_arkit_camera_lands_where_the_opencv_camera_sees_it() -> None:
    rng = np.random.default_rng(1)
    arkit_pose, point_cv = random_rigid(rng), np.array([0.2, -0.1, 1.7, 1.0])  # 1.7 m in front of the camera
    point_gl = CAMERA_FLIP @ point_cv  # the same point in ARKit's camera axes: in front is -z
    assert point_gl[2] < 0
    in_map_from_arkit = world2map("arkit") @ arkit_pose @ point_gl
    assert np.allclose(cam2map(arkit_pose, "arkit") @ point_cv, in_map_from_arkit, atol=1e-12)


def test_a_tilted_world_declaring_its_up_meets_the_map_in_the_gravity_frame() -> None:
    up = np.array([0.0089, -0.9044, -0.4265])  # 7-Scenes redkitchen: gravity-direction.txt, negated
    up /= np.linalg.norm(up)
    rotation = gravity_rotation(up, (0, 0, 1))
    assert np.allclose(rotation @ up, (0, 0, 1), atol=1e-12)
    assert np.array_equal(rotation, up_rotation(up))  # datasets' align_gravity: the same world
    other = np.array([0.1, 0.2, 1.0])
    assert np.allclose(gravity_rotation(up, other) @ up, other / np.linalg.norm(other), atol=1e-12)
    assert np.array_equal(gravity_rotation(other, other), np.eye(3))


# --- feature: round trips and rigidity over random poses -------------------------------------------------------------
@pytest.mark.parametrize("seed", range(20))
def test_cam2device_undoes_cam2map_and_both_are_rigid(seed: int) -> None:
    rng = np.random.default_rng(seed)
    convention = POSE_CONVENTIONS[seed % 3]
    map_up = rng.normal(size=3)
    world_up = None if seed % 4 == 0 else rng.normal(size=3)
    alignment = None if seed % 5 == 0 else yaw_and_shift(check_up("up", map_up), rng.uniform(-np.pi, np.pi), rng.normal(size=3))
    pose = random_rigid(rng)
    in_map = cam2map(pose, convention, world_up, map_up, alignment)
    assert_rigid(in_map)
    assert_rigid(world2map(convention, world_up, map_up, alignment))
    assert np.allclose(cam2device(in_map, convention, world_up, map_up, alignment), pose, atol=1e-12)
    assert np.allclose(cam2map(cam2device(pose, convention, world_up, map_up, alignment), convention, world_up, map_up, alignment), pose, atol=1e-12)  # fmt: skip


def test_a_device_alignment_moves_the_device_world_into_the_map() -> None:
    rng = np.random.default_rng(2)
    cam2map_pose = random_rigid(rng)
    device_from_map = yaw_and_shift(np.array([0.0, 0.0, 1.0]), 0.7, np.array([1.5, -2.0, 0.3]))
    cam2device_world = device_from_map @ cam2map_pose  # where the device, with its own origin, says the camera is
    assert np.allclose(cam2map(cam2device_world, device_from_map=device_from_map), cam2map_pose, atol=1e-12)
    arkit_pose = np.eye(4)
    arkit_pose[:3, :3] = Z_UP_FROM_Y_UP.T
    arkit_pose = arkit_pose @ cam2device_world @ CAMERA_FLIP  # the same camera as ARKit reports it in that session
    assert np.allclose(cam2map(arkit_pose, "arkit", device_from_map=device_from_map), cam2map_pose, atol=1e-12)


def test_rigid_inverse_is_the_inverse_and_every_result_is_a_new_writable_array() -> None:
    pose = random_rigid(np.random.default_rng(3))
    assert np.allclose(rigid_inverse(pose) @ pose, np.eye(4), atol=1e-12)
    for result in (cam2map(pose), cam2map(pose, "arkit"), world2map(), world2map("arkit"), cam2device(pose), rigid_inverse(pose)):
        assert result.flags.writeable and not np.shares_memory(result, pose) and not np.shares_memory(result, CAMERA_FLIP)
    assert not CAMERA_FLIP.flags.writeable


# --- exceptions: the checks say what was expected and what came -----------------------------------------------------
def test_conventions_are_named() -> None:
    assert POSE_CONVENTIONS == ("opencv", "arkit", "arcore")
    assert check_convention("pose_convention", "arkit") == "arkit"
    with pytest.raises(InvalidInput, match=r"pose_convention: expected one of opencv, arkit, arcore, got 'opengl'"):
        check_convention("pose_convention", "opengl")


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ((0, 0, 0), r"world_up: expected a direction \(3 numbers, not all 0\)"),
        ((0, float("nan"), 1), "world_up: expected 3 finite numbers"),
        ((0, 1), r"world_up: expected 3 numbers \(an up direction\), got shape \(2,\)"),
        ("up", r"world_up: expected 3 numbers \(an up direction\)"),
    ],
)
def test_a_bad_up_is_refused(value: object, message: str) -> None:
    with pytest.raises(InvalidInput, match=message):
        check_up("world_up", value)


def test_a_device_alignment_must_be_rigid_finite_near_and_keep_the_maps_up() -> None:
    up = np.array([0.0, 0.0, 1.0])
    good = yaw_and_shift(up, 1.2, np.array([3.0, -1.0, 0.2]))
    assert np.array_equal(check_device_from_map("device_from_map", good.reshape(16).tolist(), up), good)
    slightly = good.copy()
    slightly[:3, :3] = rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(MAX_ALIGNMENT_TILT_DEG - 0.5)) @ good[:3, :3]
    assert tilt_deg(check_device_from_map("device_from_map", slightly, up), up) == pytest.approx(MAX_ALIGNMENT_TILT_DEG - 0.5)
    scaled, reflected, nan, far, tilted = (good.copy() for _ in range(5))
    scaled[:3, :3] *= 1.1
    reflected[:3, 0] *= -1
    nan[0, 3] = float("nan")
    far[0, 3] = 20_000.0
    tilted[:3, :3] = rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(10.0)) @ good[:3, :3]
    cases = [
        (scaled, r"expected an orthonormal rotation"),
        (reflected, r"expected a proper rotation \(det \+1\)"),
        (nan, r"expected finite values"),
        (far, r"expected a translation of at most 10000 m on each axis"),
        (
            tilted,
            r"expected a rotation about the map's up \[0.0, 0.0, 1.0\] and a translation .*got a rotation that tilts up by 10.00 degrees",
        ),
        (np.eye(3), r"expected shape \(4, 4\), got shape \(3, 3\)"),
        ([[1, 2], [3]], r"expected a 4x4 matrix of numbers"),
    ]
    for value, message in cases:
        with pytest.raises(InvalidInput, match="device_from_map: " + message):
            check_device_from_map("device_from_map", value, up)


def test_the_tilt_is_measured_against_the_maps_own_up() -> None:
    up = check_up("up", (0.2, 0.9, 0.4))
    about_up = yaw_and_shift(up, 2.0, np.zeros(3))
    assert tilt_deg(about_up, up) == pytest.approx(0.0, abs=1e-6)
    assert tilt_deg(about_up, (0.0, 0.0, 1.0)) > MAX_ALIGNMENT_TILT_DEG  # about another up: a tilt here
    check_device_from_map("device_from_map", about_up, up)
