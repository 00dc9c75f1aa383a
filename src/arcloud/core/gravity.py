"""Gravity: the rotation that takes a world with any ``up`` to one whose +z is up."""

from __future__ import annotations

import functools

import numpy as np


def up_rotation(up: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """(3, 3) rotation taking the unit vector ``up`` to +z (world2gravity), the smallest such."""
    return _up_rotation(tuple(float(x) for x in np.asarray(up).ravel())).copy()


def world2gravity(up: np.ndarray | tuple[float, ...]) -> np.ndarray:
    """``up_rotation(up)``, shared and read-only (cached: every frame asks for the same few)."""
    return _up_rotation(_key(up))


def is_vertical(up: np.ndarray | tuple[float, ...]) -> bool:
    """Whether ``up`` needs no rotation (its world2gravity is the identity)."""
    return _is_vertical(_key(up))


def _key(up: np.ndarray | tuple[float, ...]) -> tuple[float, ...]:
    """``up`` as the cache's key: ``Params.up`` is a tuple of floats already (asked for every object)."""
    if isinstance(up, tuple) and all(type(x) is float for x in up):
        return up
    return tuple(float(x) for x in np.asarray(up).ravel())


@functools.lru_cache(maxsize=16)
def _is_vertical(up_xyz: tuple[float, ...]) -> bool:
    return bool(np.array_equal(_up_rotation(up_xyz), np.eye(3)))


@functools.lru_cache(maxsize=16)
def _up_rotation(up_xyz: tuple[float, ...]) -> np.ndarray:
    up = np.asarray(up_xyz, np.float64) / np.linalg.norm(up_xyz)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    s, c = np.linalg.norm(axis), float(up @ z)
    if s < 1e-12:
        rotation = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        k = axis / s
        skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rotation = np.eye(3) + s * skew + (1 - c) * skew @ skew
    rotation.setflags(write=False)
    return rotation
