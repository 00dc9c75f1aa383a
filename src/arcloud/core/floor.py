"""The floor under objects: where the legs that a camera rarely sees end.

Each frame finds its floor: the depth map's upward-facing surfaces (normals from neighbouring depth
samples, within ``floor_max_tilt_deg`` of up); the floor is the lowest height bin (``floor_bin_m``)
holding at least ``floor_min_share`` of them (and ``floor_min_samples``), among those at least
``floor_min_below_camera_m`` below the camera: a hand-held device is held well above the floor, and a
frame that sees only a table top or a seat offers no floor rather than a wrong one. The lowest surface
of the whole view, not of the spot under an object: a coffee table often hides the floor right under
it, seldom the floor of the whole view.

Every object seen in a frame takes one vote for the frame's floor, when it lies below the object and the
frame does not see the floor beside it hidden (``floor_beside_seen``: of the points around its footprint at
floor height, ``floor_ring_margin_m`` outside it, fewer than ``floor_ring_min_seen`` show the floor and the
others something in front of it): a chair pushed under a table, whose legs no frame sees, gets no vote,
and its box stays what was seen of it (the observed box, which ScanNet's ground truth and ours score). An
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

from arcloud.core.types import Frame, Params

FLOOR_GRID_COLUMNS = 80  # depth samples for normals: about 80 across (a VGA frame: every 8th pixel)


@dataclass(frozen=True, eq=False, slots=True)
class FrameFloor:
    """A frame's floor: its height (metres along up; None: this frame offers none), the rotation that
    gives ground coordinates (x, y) and height (z) of a world point (``world2gravity @ p``), and the
    frame whose depth tells whether the floor beside an object is in view (None: not checked)."""

    height_m: float | None
    world2gravity: np.ndarray
    frame: Frame | None = None

    def vote_for(self, points_xyz: np.ndarray, params: Params) -> int | None:
        """The height bin this frame votes for as the floor under an object of points (N, 3) in world
        coordinates; None when the frame saw no floor, or none below the object."""
        if self.height_m is None or len(points_xyz) == 0:
            return None
        lowest = float((np.asarray(points_xyz, np.float64).reshape(-1, 3) @ self.world2gravity[2]).min())
        if self.height_m > lowest + params.floor_bin_m:
            return None
        if self.frame is not None and not floor_beside_seen(self.frame, points_xyz, self.height_m, self.world2gravity, params):
            return None
        return height_bin(self.height_m, params)


#: Where around a footprint the floor is looked at: its rectangle's corners and side midpoints, as unit offsets.
_RING = np.array([[-1, -1], [0, -1], [1, -1], [1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0]], np.float64)


def floor_beside_seen(frame: Frame, points_xyz: np.ndarray, floor_m: float, world2gravity: np.ndarray, params: Params) -> bool:
    """Whether the frame may see the floor beside an object of points (N, 3): of 8 points at height
    ``floor_m`` around the ground rectangle of the points (corners and side midpoints, each
    ``floor_ring_margin_m`` outside it), at least ``floor_ring_min_seen`` land in the image where nothing
    stands in front of them (the depth measured is not ``visibility_tolerance_m`` nearer), or too few land
    where depth was measured to tell (a large table whose surroundings are out of view)."""
    ground = np.asarray(points_xyz, np.float64).reshape(-1, 3) @ world2gravity[:2].T
    lo, hi = ground.min(axis=0), ground.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 + params.floor_ring_margin_m
    ring = np.column_stack([centre + _RING * half, np.full(len(_RING), floor_m)]) @ world2gravity  # gravity -> world
    rotation, origin = frame.cam2world[:3, :3], frame.cam2world[:3, 3]
    cam = (ring - origin) @ rotation
    z = cam[:, 2]
    intr = frame.intrinsics
    height, width = frame.depth_m.shape
    ahead = z > params.depth_min_m
    u = np.floor(cam[ahead, 0] * intr.fx / z[ahead] + intr.cx + 0.5)
    v = np.floor(cam[ahead, 1] * intr.fy / z[ahead] + intr.cy + 0.5)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    measured = frame.depth_m[v[inside].astype(np.intp), u[inside].astype(np.intp)]
    hidden = (measured > 0) & (measured < z[ahead][inside] - params.visibility_tolerance_m)
    n_seen = int(np.count_nonzero((measured > 0) & ~hidden))
    return n_seen >= params.floor_ring_min_seen or n_seen + int(np.count_nonzero(hidden)) < params.floor_ring_min_seen


def height_bin(height_m: float, params: Params) -> int:
    return int(math.floor(height_m / params.floor_bin_m))


def upward_heights(frame: Frame, params: Params) -> np.ndarray:
    """(N,) heights (metres along up) of the frame's depth samples on surfaces that face up (a floor, a
    seat, a table top): normals from neighbouring samples, within ``floor_max_tilt_deg`` of up. Worked
    out in the camera frame, where up is ``cam2world``'s rotation applied backwards."""
    stride = max(1, frame.depth_m.shape[1] // FLOOR_GRID_COLUMNS)
    z = frame.depth_m[::stride, ::stride].astype(np.float64)
    rows, cols = z.shape
    intr = frame.intrinsics
    x = (np.arange(cols) * stride - intr.cx)[None, :] / intr.fx * z
    y = (np.arange(rows) * stride - intr.cy)[:, None] / intr.fy * z
    up_world = params.gravity.up
    up_cam = frame.cam2world[:3, :3].T @ up_world
    valid = (z >= params.depth_min_m) & (z <= params.depth_max_m)
    inner = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    ax, ay, az = (c[1:-1, 2:] - c[1:-1, :-2] for c in (x, y, z))  # along the row
    dx, dy, dz = (c[2:, 1:-1] - c[:-2, 1:-1] for c in (x, y, z))  # down the column
    nx, ny, nz = ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx  # the surface normal
    along_up = nx * up_cam[0] + ny * up_cam[1] + nz * up_cam[2]
    cos_tilt = math.cos(math.radians(params.floor_max_tilt_deg))
    facing_up = inner & (along_up * along_up >= cos_tilt * cos_tilt * (nx * nx + ny * ny + nz * nz)) & (along_up != 0)
    heights = x[1:-1, 1:-1] * up_cam[0] + y[1:-1, 1:-1] * up_cam[1] + z[1:-1, 1:-1] * up_cam[2]
    return heights[facing_up] + float(frame.cam2world[:3, 3] @ up_world)


def frame_floor(frame: Frame, params: Params) -> FrameFloor:
    """The floor this frame sees (see the module docstring)."""
    rotation = params.gravity.world2gravity
    heights = upward_heights(frame, params)
    camera_height = float(frame.cam2world[:3, 3] @ rotation[2])
    floor = None
    if heights.size:
        bins = np.floor(heights / params.floor_bin_m).astype(np.int64)
        lowest = int(bins.min())
        counts = np.bincount(bins - lowest)
        centres = (np.arange(counts.size) + lowest + 0.5) * params.floor_bin_m
        dense = (counts >= params.floor_min_samples) & (counts >= params.floor_min_share * heights.size)
        dense &= camera_height - centres >= params.floor_min_below_camera_m
        if dense.any():
            floor = float(centres[np.flatnonzero(dense)[0]])
    return FrameFloor(floor, rotation, frame if params.floor_ring_min_seen else None)


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
