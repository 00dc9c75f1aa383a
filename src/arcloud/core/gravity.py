"""Gravity: the rotation that takes a world with any ``up`` to one whose +z is up, and an estimate of
``up`` from depth images when a recording does not say where it is.

``Params.gravity`` holds the rotation for the parameters' ``up``, worked out once when they are built,
so the step asks for it as often as it likes without a module-level cache.

``estimate_up`` starts from a prior (a hand-held camera's image "up", the mean of its -y axes, is
biased by tens of degrees when the camera pitches down) and refines it with the normals of the
horizontal surfaces (floor, table tops, counters) within a narrowing cone around it: walls lie 90
degrees away, so a prior within about 30 degrees of up is enough.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from arcloud.core.types import Intrinsics  # types imports this module


def up_rotation(up: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """(3, 3) rotation taking the unit vector ``up`` to +z (world2gravity), the smallest such; a new
    array on every call."""
    up_xyz = tuple(float(x) for x in np.asarray(up).ravel())
    unit = np.asarray(up_xyz, np.float64) / np.linalg.norm(up_xyz)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(unit, z)
    s, c = np.linalg.norm(axis), float(unit @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * skew + (1 - c) * skew @ skew


@dataclass(frozen=True, eq=False, slots=True)
class Gravity:
    """What a world's ``up`` implies: ``world2gravity`` (3, 3, read-only), the smallest rotation taking
    up to +z (its last row is up as a unit vector), and ``is_identity``: the world is z-up already."""

    world2gravity: np.ndarray
    is_identity: bool

    @classmethod
    def of(cls, up: np.ndarray | tuple[float, ...]) -> Gravity:
        rotation = up_rotation(up)
        rotation.setflags(write=False)
        return cls(rotation, bool(np.array_equal(rotation, np.eye(3))))

    @property
    def up(self) -> np.ndarray:
        """(3,) unit up vector in world coordinates (read-only)."""
        return self.world2gravity[2]


def depth_normals(depth_m: np.ndarray, intrinsics: Intrinsics, *, step_px: int = 8, max_depth_m: float = 4.0) -> np.ndarray:
    """(N, 3) unit surface normals in camera coordinates, facing the camera, from a depth image (H, W)
    in metres (0 = invalid): one per sample of a ``step_px`` grid whose four grid neighbours are valid,
    nearer than ``max_depth_m`` and on the same surface (depth within 5 % + 2 cm of the sample's)."""
    depth = np.asarray(depth_m, np.float64)
    v_px, u_px = np.mgrid[0 : depth.shape[0] : step_px, 0 : depth.shape[1] : step_px]
    z_m = depth[v_px, u_px]
    points = np.stack([(u_px - intrinsics.cx) / intrinsics.fx * z_m, (v_px - intrinsics.cy) / intrinsics.fy * z_m, z_m], -1)
    centre = z_m[1:-1, 1:-1]
    neighbours = (z_m[1:-1, 2:], z_m[1:-1, :-2], z_m[2:, 1:-1], z_m[:-2, 1:-1])
    valid = (centre > 0) & (centre < max_depth_m)
    for z in neighbours:
        valid &= (z > 0) & (np.abs(z - centre) < 0.05 * centre + 0.02)
    along_u = (points[1:-1, 2:] - points[1:-1, :-2])[valid]
    along_v = (points[2:, 1:-1] - points[:-2, 1:-1])[valid]
    normals = np.cross(along_u, along_v)
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 0
    normals = normals[keep] / lengths[keep, None]
    away = np.einsum("ij,ij->i", normals, points[1:-1, 1:-1][valid][keep]) > 0
    normals[away] *= -1.0
    return normals


@dataclass(frozen=True, eq=False)
class UpEstimate:
    """``up`` (3,) unit, estimated from ``n_normals`` surface normals (0: none lay near the prior, and
    ``up`` is the prior itself); ``prior`` (3,) unit; ``prior_error_deg``: the angle between them."""

    up: np.ndarray
    prior: np.ndarray
    n_normals: int

    @property
    def prior_error_deg(self) -> float:
        return float(np.degrees(np.arccos(np.clip(self.up @ self.prior, -1.0, 1.0))))


def estimate_up(
    normals_world: np.ndarray, prior_up: np.ndarray | Sequence[float], *, cones_deg: Sequence[float] = (30.0, 20.0, 10.0, 10.0)
) -> UpEstimate:
    """Up (3,) from surface normals (N, 3) in world coordinates: for each cone in turn, the principal
    axis of the normals within it around the current estimate (starting at ``prior_up``), turned
    towards the prior. Horizontal surfaces face up; ``depth_normals`` gives normals facing the camera,
    so that surfaces seen from below (under a table) point away and fall out."""
    normals = np.asarray(normals_world, np.float64).reshape(-1, 3)
    prior = np.asarray(prior_up, np.float64).reshape(3)
    prior = prior / np.linalg.norm(prior)
    up, used = prior, 0
    for cone_deg in cones_deg:
        near = normals[normals @ up > np.cos(np.radians(cone_deg))]
        if len(near) == 0:
            break
        axis = np.linalg.eigh(near.T @ near)[1][:, -1]
        up, used = axis * np.sign(axis @ up), len(near)
    return UpEstimate(up, prior, used)


__all__ = ["Gravity", "UpEstimate", "depth_normals", "estimate_up", "up_rotation"]
