"""Gravity: the rotation that takes a world with any ``up`` to one whose +z is up.

``Params.gravity`` holds it for the parameters' ``up``, worked out once when they are built, so the
step asks for it as often as it likes without a module-level cache.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


__all__ = ["Gravity", "up_rotation"]
