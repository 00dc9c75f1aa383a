"""Up estimated from depth: the normals of a depth image of a plane are the plane's, facing the camera,
and the estimate finds a floor's normal from a prior tens of degrees off, ignoring walls and noise."""

from __future__ import annotations

import numpy as np
import pytest

from arcloud.core.gravity import depth_normals, estimate_up, up_rotation
from arcloud.core.types import Intrinsics

K = Intrinsics(300.0, 300.0, 31.5, 23.5)  # about 0.8 degrees between samples 4 px apart, as 8 px at 585


def plane_depth(normal_cam: np.ndarray, distance_m: float, shape: tuple[int, int] = (48, 64)) -> np.ndarray:
    """Depth (H, W) of the plane n . p = -distance_m (n facing the camera) seen by a camera at the origin."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(shape)], -1)
    along = rays @ normal_cam
    return np.where(along < -1e-6, -distance_m / np.where(along < -1e-6, along, -1.0), 0.0)


def test_normals_of_a_plane_face_the_camera() -> None:
    normal = np.array([0.0, -0.8, -0.6])  # a floor below a camera pitched down, facing back up at it
    normals = depth_normals(plane_depth(normal, 1.5), K, step_px=4)
    assert len(normals) > 50
    np.testing.assert_allclose(normals, np.tile(normal, (len(normals), 1)), atol=1e-6)
    assert len(depth_normals(np.zeros((48, 64)), K)) == 0  # no depth, no normals


def test_a_step_in_depth_gives_no_normal_across_it() -> None:
    depth = np.full((48, 64), 2.0)
    depth[:, 32:] = 3.0  # two walls facing the camera, one behind the other
    normals = depth_normals(depth, K, step_px=4)
    np.testing.assert_allclose(normals, np.tile([0.0, 0.0, -1.0], (len(normals), 1)), atol=1e-9)


def test_the_estimate_finds_the_floor_from_a_prior_far_off() -> None:
    rng = np.random.default_rng(3)
    up = np.array([0.1, -0.9, -0.42])
    up /= np.linalg.norm(up)
    to_world = up_rotation(up).T  # +z -> up
    floor = np.tile(up, (3000, 1)) + rng.normal(0.0, 0.05, (3000, 3))
    angles = rng.uniform(0.0, 2 * np.pi, 3000)
    walls = np.stack([np.cos(angles), np.sin(angles), np.zeros(3000)], -1) @ to_world.T  # horizontal normals
    clutter = rng.normal(size=(1500, 3))
    normals = np.concatenate([floor, walls, clutter])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    prior = to_world @ np.array([np.sin(np.radians(25.0)), 0.0, np.cos(np.radians(25.0))])  # 25 degrees off
    found = estimate_up(normals, prior)
    assert np.degrees(np.arccos(found.up @ up)) < 0.5
    assert found.prior_error_deg == pytest.approx(25.0, abs=0.5) and found.n_normals > 2500


def test_without_a_surface_near_the_prior_the_prior_is_kept() -> None:
    found = estimate_up(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), [0.0, 0.0, 2.0])
    np.testing.assert_array_equal(found.up, [0.0, 0.0, 1.0])
    assert found.n_normals == 0 and found.prior_error_deg == 0.0
