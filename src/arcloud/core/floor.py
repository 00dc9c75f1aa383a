"""The floor under objects: where the legs that a camera rarely sees end.

Each frame finds its floor: the depth map's upward-facing surfaces (normals from neighbouring depth
samples, within ``floor_max_tilt_deg`` of up); the floor is the lowest height bin (``floor_bin_m``)
holding at least ``floor_min_share`` of them (and ``floor_min_samples``), among those at least
``floor_min_below_camera_m`` below the camera: a hand-held device is held well above the floor, and a
frame that sees only a table top or a seat offers no floor rather than a wrong one. The lowest surface
of the whole view, not of the spot under an object: a coffee table often hides the floor right under
it, seldom the floor of the whole view.

Every object seen in a frame takes one vote for the frame's floor, when it lies below the object. An
object's floor is the lowest height its votes support: the lowest bin with at least
``floor_min_votes`` votes and ``floor_min_vote_share`` of the most-voted bin's (frames that saw only a
table top vote higher, never lower). Votes add up, so an object's floor does not depend on the order in
which frames arrive. Heights are measured along ``Params.up``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from arcloud.core.gravity import world2gravity
from arcloud.core.types import Frame, Params

FLOOR_GRID_COLUMNS = 80  # depth samples for normals: about 80 across (a VGA frame: every 8th pixel)


@dataclass(frozen=True, eq=False, slots=True)
class FrameFloor:
    """A frame's floor: its height (metres along up; None: this frame offers none), and the rotation
    that gives ground coordinates (x, y) and height (z) of a world point: ``world2gravity @ p``."""

    height_m: float | None
    world2gravity: np.ndarray

    def vote_for(self, points_xyz: np.ndarray, params: Params) -> int | None:
        """The height bin this frame votes for as the floor under an object of points (N, 3) in world
        coordinates; None when the frame saw no floor, or none below the object."""
        if self.height_m is None or len(points_xyz) == 0:
            return None
        lowest = float((np.asarray(points_xyz, np.float64).reshape(-1, 3) @ self.world2gravity[2]).min())
        if self.height_m > lowest + params.floor_bin_m:
            return None
        return height_bin(self.height_m, params)


def height_bin(height_m: float, params: Params) -> int:
    return int(math.floor(height_m / params.floor_bin_m))


def upward_samples(frame: Frame, params: Params) -> np.ndarray:
    """(N, 3) gravity coordinates (ground x, y and height) of the frame's depth samples on surfaces
    that face up (a floor, a seat, a table top)."""
    stride = max(1, frame.depth_m.shape[1] // FLOOR_GRID_COLUMNS)
    depth = frame.depth_m[::stride, ::stride].astype(np.float64)
    rows, cols = depth.shape
    v, u = np.mgrid[0:rows, 0:cols] * stride
    intr = frame.intrinsics
    points = np.stack(((u - intr.cx) * depth / intr.fx, (v - intr.cy) * depth / intr.fy, depth), axis=-1)
    gravity = points @ (world2gravity(params.up) @ frame.cam2world[:3, :3]).T
    gravity += world2gravity(params.up) @ frame.cam2world[:3, 3]
    valid = (depth >= params.depth_min_m) & (depth <= params.depth_max_m)
    inner = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    ax, ay, az = (gravity[1:-1, 2:, k] - gravity[1:-1, :-2, k] for k in range(3))  # along the row
    dx, dy, dz = (gravity[2:, 1:-1, k] - gravity[:-2, 1:-1, k] for k in range(3))  # down the column
    nx, ny, nz = ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx  # the surface normal
    squared = nx * nx + ny * ny + nz * nz
    cos_tilt = math.cos(math.radians(params.floor_max_tilt_deg))
    facing_up = inner & (squared > 0) & (nz * nz >= cos_tilt * cos_tilt * squared)
    return gravity[1:-1, 1:-1][facing_up]


def frame_floor(frame: Frame, params: Params) -> FrameFloor:
    """The floor this frame sees (see the module docstring)."""
    rotation = world2gravity(params.up)
    heights = upward_samples(frame, params)[:, 2]
    camera_height = float((rotation @ frame.cam2world[:3, 3])[2])
    floor = None
    if heights.size:
        values, counts = np.unique(np.floor(heights / params.floor_bin_m).astype(np.int64), return_counts=True)
        centres = (values + 0.5) * params.floor_bin_m
        dense = (counts >= params.floor_min_samples) & (counts >= params.floor_min_share * heights.size)
        dense &= camera_height - centres >= params.floor_min_below_camera_m
        if dense.any():
            floor = float(centres[np.flatnonzero(dense)[0]])
    return FrameFloor(floor, rotation)


def floor_height(votes: Mapping[int, int], params: Params) -> float | None:
    """The floor height (metres along up) an object's votes support (see the module docstring)."""
    if not votes:
        return None
    most = max(votes.values())
    for height in sorted(votes):
        count = votes[height]
        if count >= params.floor_min_votes and count >= params.floor_min_vote_share * most:
            return (height + 0.5) * params.floor_bin_m
    return None


def add_votes(a: Mapping[int, int], b: Mapping[int, int]) -> dict[int, int]:
    """The sum of two vote tallies (a new dict)."""
    out = dict(a)
    for height, count in b.items():
        out[height] = out.get(height, 0) + count
    return out
