"""Pose conventions: what a device's ``cam2world`` means, and the one conversion that takes it into the map's
world with OpenCV camera axes, which is all the core ever sees. The map's up is ``Params.up``, which the map's
header keeps (``core.header.MapHeader.up``: a map is never read under another).

A frame declares how to read its pose:

- ``convention`` (``POSE_CONVENTIONS``): ``opencv`` (the default, what frames always meant): camera axes x
  right, y down, z forward. ``arkit`` and ``arcore``: camera axes x right, y up, z backwards (out of the
  screen; the camera looks along -z), in a y-up world (ARKit's ``ARFrame.camera.transform``, ARCore's
  ``Camera.getPose()``, both camera-to-world).
- ``world_up``: the up direction of its world, in its world's coordinates. Not given: the map's up for
  ``opencv`` (the frame's world is the map's, as before) and +y for ``arkit`` / ``arcore``.
- ``device_from_map``: a rigid (4, 4) that maps the map's world points to the device's world points, once
  the device's world is in the map's axes (steps 1 and 2 below): the device's session origin and heading in
  the map (a rotation about up and a translation). Not given: the identity (the device's origin is the map's).

``world2map`` and ``cam2map`` apply them in this order:

1. camera axes: ``cam2world @ camera_axes(convention)``, with ``CAMERA_FLIP`` = diag(1, -1, -1, 1) for
   ``arkit`` / ``arcore`` (y and z reversed; its own inverse) and the identity for ``opencv``;
2. gravity: a world whose up is not the map's is rotated so that it is: both worlds meet in their gravity
   frame (``core.gravity.up_rotation``: the smallest rotation taking up to +z), ``gravity(map_up).T @
   gravity(world_up)``. For a z-up map and a y-up world that is +90 degrees about x, (x, y, z) -> (x, -z, y):
   ARKit's x right, y up, z back become x right, y forward (ahead of the session's first camera), z up;
3. origin: ``inv(device_from_map)``.

``world2map`` is the whole of 2 and 3 as one rigid transform (world points to map points); its inverse takes
the map's boxes back into a device's own world. A ``device_from_map`` that tilts the map's up by more than
``MAX_ALIGNMENT_TILT_DEG`` is refused (``check_device_from_map``): the device's world, made gravity-aligned
by its ``world_up``, would stand askew in the map, and its boxes with it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal, TypeGuard

import numpy as np

from arcloud.core.checks import MAX_TRANSLATION_M, check_pose, describe
from arcloud.core.errors import InvalidInput
from arcloud.core.gravity import up_rotation

PoseConvention = Literal["opencv", "arkit", "arcore"]
#: The conventions a frame may declare (``opencv`` is the default).
POSE_CONVENTIONS: tuple[PoseConvention, ...] = ("opencv", "arkit", "arcore")
#: The world up of each convention when a frame does not give one (None: the map's).
DEFAULT_WORLD_UP: dict[PoseConvention, tuple[float, float, float] | None] = {
    "opencv": None,
    "arkit": (0.0, 1.0, 0.0),
    "arcore": (0.0, 1.0, 0.0),
}
#: The most a device's alignment may tilt the map's up, in degrees.
MAX_ALIGNMENT_TILT_DEG = 2.0


def _read_only(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


#: Camera axes x right, y up, z back (ARKit, ARCore, OpenGL) <-> OpenCV's x right, y down, z forward (both ways).
CAMERA_FLIP = _read_only(np.diag([1.0, -1.0, -1.0, 1.0]))
_IDENTITY = _read_only(np.eye(4))


def is_convention(value: object) -> TypeGuard[PoseConvention]:
    return isinstance(value, str) and value in POSE_CONVENTIONS


def check_convention(field: str, value: object) -> PoseConvention:
    """A pose convention's name (one of ``POSE_CONVENTIONS``)."""
    if not is_convention(value):
        raise InvalidInput(field, f"one of {', '.join(POSE_CONVENTIONS)}", describe(value))
    return value


def check_up(field: str, value: object) -> np.ndarray:
    """(3,) unit float64 vector from 3 finite numbers, not all 0 (a world's up)."""
    try:
        up = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInput(field, "3 numbers (an up direction)", describe(value)) from None
    if up.shape != (3,):
        raise InvalidInput(field, "3 numbers (an up direction)", f"shape {up.shape}")
    if not np.all(np.isfinite(up)):
        raise InvalidInput(field, "3 finite numbers", up.tolist())
    norm = float(np.linalg.norm(up))
    if not norm > 1e-9 or not math.isfinite(norm):
        raise InvalidInput(field, "a direction (3 numbers, not all 0)", up.tolist())
    return up / norm


def camera_axes(convention: PoseConvention) -> np.ndarray:
    """(4, 4) read-only: maps OpenCV camera coordinates to the convention's (``CAMERA_FLIP`` or identity), so
    that ``cam2world @ camera_axes(c)`` is the OpenCV camera's pose."""
    return _IDENTITY if convention == "opencv" else CAMERA_FLIP


def gravity_rotation(world_up: np.ndarray | Sequence[float], map_up: np.ndarray | Sequence[float]) -> np.ndarray:
    """(3, 3) rotation taking a world whose up is ``world_up`` to one whose up is ``map_up`` (both worlds meet
    in their gravity frame: ``up_rotation(map_up).T @ up_rotation(world_up)``); the identity when they agree."""
    world = check_up("world_up", world_up)
    target = check_up("map_up", map_up)
    if np.array_equal(world, target):
        return np.eye(3)
    return np.asarray(up_rotation(target).T @ up_rotation(world))


def tilt_deg(device_from_map: np.ndarray, map_up: np.ndarray | Sequence[float]) -> float:
    """The angle in degrees by which a (4, 4) ``device_from_map`` turns the map's up (0: a rotation about it)."""
    up = check_up("map_up", map_up)
    turned = np.asarray(device_from_map, np.float64)[:3, :3] @ up
    return float(np.degrees(np.arccos(np.clip(turned @ up / np.linalg.norm(turned), -1.0, 1.0))))


def check_device_from_map(
    field: str, value: object, map_up: np.ndarray | Sequence[float], *, max_tilt_deg: float = MAX_ALIGNMENT_TILT_DEG
) -> np.ndarray:
    """A device's alignment (see the module docstring): a rigid, finite (4, 4) (16 numbers row-major, or 4
    rows of 4) whose translation stays within ``MAX_TRANSLATION_M`` on each axis and whose rotation tilts the
    map's up by at most ``max_tilt_deg`` degrees. A new (4, 4) float64 array."""
    pose = np.array(check_pose(field, value), dtype=np.float64)
    if np.any(np.abs(pose[:3, 3]) > MAX_TRANSLATION_M):
        raise InvalidInput(
            field, f"a translation of at most {MAX_TRANSLATION_M:g} m on each axis", np.array2string(pose[:3, 3], precision=1)
        )
    tilt = tilt_deg(pose, map_up)
    if tilt > max_tilt_deg:
        up = [round(float(v), 4) for v in check_up("map_up", map_up)]
        raise InvalidInput(
            field,
            f"a rotation about the map's up {up} and a translation (tilting up by at most {max_tilt_deg:g} degrees: "
            "the device's world, gravity-aligned by its world_up, stands upright in the map)",
            f"a rotation that tilts up by {tilt:.2f} degrees",
        )
    return pose


def world2map(
    convention: PoseConvention = "opencv",
    world_up: np.ndarray | Sequence[float] | None = None,
    map_up: np.ndarray | Sequence[float] = (0.0, 0.0, 1.0),
    device_from_map: np.ndarray | None = None,
) -> np.ndarray:
    """(4, 4) rigid: maps points of a device's world (as its frames declare it: ``convention``, ``world_up``,
    ``device_from_map``, see the module docstring) to the map's world. A new array."""
    up = DEFAULT_WORLD_UP[check_convention("convention", convention)] if world_up is None else world_up
    transform = np.eye(4)
    if up is not None:
        transform[:3, :3] = gravity_rotation(up, map_up)
    if device_from_map is not None:
        transform = rigid_inverse(device_from_map) @ transform
    return transform


def cam2map(
    cam2world: np.ndarray,
    convention: PoseConvention = "opencv",
    world_up: np.ndarray | Sequence[float] | None = None,
    map_up: np.ndarray | Sequence[float] = (0.0, 0.0, 1.0),
    device_from_map: np.ndarray | None = None,
) -> np.ndarray:
    """(4, 4): the OpenCV camera's pose in the map's world, of a device's ``cam2world`` (4, 4) declared as
    ``convention``, ``world_up``, ``device_from_map`` (see the module docstring). A new array."""
    transform = world2map(convention, world_up, map_up, device_from_map)
    return np.asarray(transform @ np.asarray(cam2world, np.float64) @ camera_axes(convention))


def cam2device(
    cam2map_pose: np.ndarray,
    convention: PoseConvention = "opencv",
    world_up: np.ndarray | Sequence[float] | None = None,
    map_up: np.ndarray | Sequence[float] = (0.0, 0.0, 1.0),
    device_from_map: np.ndarray | None = None,
) -> np.ndarray:
    """(4, 4): the inverse of ``cam2map``: the pose a device declared as ``convention``, ``world_up``,
    ``device_from_map`` reports for an OpenCV camera at ``cam2map_pose`` in the map. A new array."""
    transform = rigid_inverse(world2map(convention, world_up, map_up, device_from_map))
    return np.asarray(transform @ np.asarray(cam2map_pose, np.float64) @ camera_axes(convention))


def rigid_inverse(transform: np.ndarray) -> np.ndarray:
    """The inverse of a rigid (4, 4) (rotation transposed): exact where ``np.linalg.inv`` rounds. A new array."""
    matrix = np.asarray(transform, np.float64)
    inverse = np.eye(4)
    inverse[:3, :3] = matrix[:3, :3].T
    inverse[:3, 3] = -matrix[:3, :3].T @ matrix[:3, 3]
    return inverse


__all__ = [
    "CAMERA_FLIP",
    "DEFAULT_WORLD_UP",
    "MAX_ALIGNMENT_TILT_DEG",
    "POSE_CONVENTIONS",
    "PoseConvention",
    "cam2device",
    "cam2map",
    "camera_axes",
    "check_convention",
    "check_device_from_map",
    "check_up",
    "gravity_rotation",
    "is_convention",
    "rigid_inverse",
    "tilt_deg",
    "world2map",
]
