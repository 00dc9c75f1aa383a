"""The floor under objects: where the legs that a camera rarely sees end.

Each frame finds its floor: the depth map's upward-facing surfaces (normals from neighbouring depth
samples, within ``floor_max_tilt_deg`` of up), grouped into ground cells (``floor_cell_m``); in each
cell the floor is the lowest height bin (``floor_bin_m``) holding at least ``floor_min_share`` of the
cell's upward samples (and ``floor_min_samples``), provided it lies at least
``floor_min_below_camera_m`` below the camera: a hand-held device is held well above the floor, so a
frame that sees only a table top does not take it for the floor.

Every object seen in a frame takes one vote: the frame's floor in the object's ground cell (or, when
that cell shows none, in the nearest neighbouring cell that does). An object's floor is the lowest
height its votes support: the lowest bin with at least ``floor_min_votes`` votes and
``floor_min_vote_share`` of the most-voted bin's (frames that saw only a table top vote higher, never
lower). Votes add up, so an object's floor does not depend on the order in which frames arrive.
Heights are measured along ``Params.up``.
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
    """A frame's floor: ground cell (i, j) -> floor height (metres along up), and the rotation that
    gives ground coordinates (x, y) and height (z) of a world point: ``world2gravity @ p``."""

    cells: dict[tuple[int, int], float]
    world2gravity: np.ndarray
    cell_m: float

    def height_under(self, points_xyz: np.ndarray) -> np.ndarray:
        """(N,) the floor height under each world point (N, 3); NaN where this frame saw no floor."""
        gravity = np.asarray(points_xyz, np.float64).reshape(-1, 3) @ self.world2gravity.T
        out = np.full(len(gravity), np.nan)
        if not self.cells:
            return out
        ij = np.floor(gravity[:, :2] / self.cell_m).astype(np.int64)
        for cell, height in self.cells.items():
            out[(ij[:, 0] == cell[0]) & (ij[:, 1] == cell[1])] = height
        return out

    def vote_for(self, points_xyz: np.ndarray, params: Params) -> int | None:
        """The height bin this frame votes for as the floor under points (N, 3) of one object: the
        floor of the cell under their centroid, else of the nearest neighbouring cell; None if none."""
        if not self.cells or len(points_xyz) == 0:
            return None
        centre = np.asarray(points_xyz, np.float64).reshape(-1, 3).mean(axis=0) @ self.world2gravity.T
        i, j = (int(v) for v in np.floor(centre[:2] / self.cell_m))
        candidates = [
            (math.hypot(di, dj), cell) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (cell := (i + di, j + dj)) in self.cells
        ]
        if not candidates:
            return None
        return height_bin(self.cells[min(candidates)[1]], params)


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
    """The floor this frame sees, cell by cell (see the module docstring)."""
    rotation = world2gravity(params.up)
    samples = upward_samples(frame, params)
    camera_height = float((rotation @ frame.cam2world[:3, 3])[2])
    cells: dict[tuple[int, int], float] = {}
    if len(samples):
        ij = np.floor(samples[:, :2] / params.floor_cell_m).astype(np.int64)
        bins = np.floor(samples[:, 2] / params.floor_bin_m).astype(np.int64)
        order = np.lexsort((bins, ij[:, 1], ij[:, 0]))
        ij, bins = ij[order], bins[order]
        starts = np.flatnonzero(np.r_[True, np.any(ij[1:] != ij[:-1], axis=1)])
        for start, stop in zip(starts, np.r_[starts[1:], len(bins)]):
            values, counts = np.unique(bins[start:stop], return_counts=True)
            dense = values[(counts >= params.floor_min_samples) & (counts >= params.floor_min_share * (stop - start))]
            if dense.size == 0:
                continue
            height = (float(dense[0]) + 0.5) * params.floor_bin_m
            if camera_height - height >= params.floor_min_below_camera_m:
                cells[(int(ij[start, 0]), int(ij[start, 1]))] = height
    return FrameFloor(cells, rotation, params.floor_cell_m)


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
