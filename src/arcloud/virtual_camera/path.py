"""Where a walking user's feet go: a grid of free floor (far enough from walls and obstacles) and a
smoothed path of laps around the room on it. See ``arcloud.virtual_camera.walk``."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from arcloud.errors import InvalidInput

log = logging.getLogger(__name__)


class FreeGrid:
    """Free floor cells: far enough from walls and obstacles, one connected region."""

    def __init__(
        self,
        floor_min_xy: np.ndarray,
        floor_max_xy: np.ndarray,
        obstacles: Sequence[tuple[np.ndarray, np.ndarray]],
        *,
        cell_m: float,
        clearance_m: float,
        wall_margin_m: float,
    ) -> None:
        from scipy import ndimage

        self.origin = floor_min_xy
        self.cell = cell_m
        shape = np.maximum(np.ceil((floor_max_xy - floor_min_xy) / cell_m).astype(int), 1)
        self.nx, self.ny = int(shape[0]), int(shape[1])
        xs = floor_min_xy[0] + (np.arange(self.nx) + 0.5) * cell_m
        ys = floor_min_xy[1] + (np.arange(self.ny) + 0.5) * cell_m
        self.xy = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1)  # (ny, nx, 2)
        blocked = np.zeros((self.ny, self.nx), bool)
        for lo, hi in obstacles:
            blocked |= np.all((self.xy >= lo) & (self.xy <= hi), axis=-1)
        self.blocked = blocked
        # Distance from each free cell centre to the nearest obstacle, then the walls.
        obstacle_m = (
            ndimage.distance_transform_edt(~blocked) * cell_m - cell_m / 2 if blocked.any() else np.full(blocked.shape, np.inf)
        )
        wall_m = np.minimum(self.xy - floor_min_xy, floor_max_xy - self.xy).min(axis=-1)
        self.clearance = np.minimum(obstacle_m, wall_m + clearance_m - wall_margin_m)
        free = (obstacle_m >= clearance_m) & (wall_m >= wall_margin_m)
        labels, n = ndimage.label(free, structure=np.ones((3, 3)))
        if n == 0:
            raise InvalidInput("obstacles_xy", "free floor to walk on", "no free cell")
        sizes = np.bincount(labels.ravel())[1:]
        self.free = labels == 1 + int(np.argmax(sizes))
        self.free_index = np.flatnonzero(self.free.ravel())
        self.free_xy = self.xy.reshape(-1, 2)[self.free_index]
        self._graph = None

    def cell_of(self, xy: np.ndarray) -> int:
        """Flat index of the free cell nearest to ``xy``."""
        return int(self.free_index[np.argmin(np.sum((self.free_xy - xy) ** 2, axis=1))])

    def graph(self):  # scipy.sparse.csr_matrix
        """8-connected graph of free cells; edges cost their length, more near obstacles."""
        if self._graph is None:
            from scipy.sparse import coo_matrix

            idx = np.arange(self.nx * self.ny).reshape(self.ny, self.nx)
            penalty = 1.0 + 2.0 * np.exp(-np.clip(self.clearance, 0, None) / 0.4)
            rows, cols, weights = [], [], []
            for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
                a = idx[: self.ny - dy, max(0, -dx) : self.nx - max(0, dx)].ravel()
                b = idx[dy:, max(0, dx) : self.nx - max(0, -dx)].ravel()
                ok = self.free.ravel()[a] & self.free.ravel()[b]
                a, b = a[ok], b[ok]
                w = math.hypot(dx, dy) * self.cell * (penalty.ravel()[a] + penalty.ravel()[b]) / 2
                rows += [a, b]
                cols += [b, a]
                weights += [w, w]
            n = self.nx * self.ny
            self._graph = coo_matrix(
                (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
            ).tocsr()
        return self._graph

    def path(self, start: int, goal: int) -> np.ndarray:
        """(N, 2) cell centres of the cheapest path from cell ``start`` to cell ``goal``."""
        from scipy.sparse.csgraph import dijkstra

        _, pred = dijkstra(self.graph(), indices=start, return_predecessors=True)
        cells = [goal]
        while cells[-1] != start:
            prev = pred[cells[-1]]
            if prev < 0:  # unreachable (cannot happen within one component)
                return self.xy.reshape(-1, 2)[[start, goal]]
            cells.append(int(prev))
        return self.xy.reshape(-1, 2)[cells[::-1]]


def resample(points: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` of arc length along a polyline (N, 2)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    if arc[-1] <= 0:
        return points[:1].copy()
    s = np.arange(0.0, arc[-1], step_m)
    return np.column_stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])])


def smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of (N, ...) ``values`` along N with ``sigma`` samples (edges held)."""
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(values, sigma, axis=0, mode="nearest") if sigma > 0 and len(values) > 1 else values


def walk_path(
    grid: FreeGrid, length_m: float, rng: np.random.Generator, *, ring_inset_m: float | None, lap_share: float = 0.75
) -> np.ndarray:
    """(N, 2) smoothed path at least ``length_m`` long: laps of a ring around the room, inset from
    the floor's edges so that one lap is about ``lap_share`` of the walk (by default things along the
    walls are then seen from 1-2.5 m, things in the middle from all sides), alternating direction and
    inset. A ``lap_share`` above 1 walks ``1 / lap_share`` of the ring, back and forth when that share
    is shorter than the walk (the ring cannot grow past the walls)."""
    lo, hi = grid.origin, grid.origin + np.array([grid.nx, grid.ny]) * grid.cell
    size = hi - lo
    if ring_inset_m is None:  # detours make up some of the rest of the walk
        ring_inset_m = (2 * (size[0] + size[1]) - lap_share * length_m) / 8
    partial = lap_share > 1.0
    largest = max(float(min(size)) / 2 - 0.4, 0.0)
    flat_xy = grid.xy.reshape(-1, 2)
    direction = 1 if rng.random() < 0.5 else -1
    phase = rng.uniform(0.0, 1.0)
    current = None
    pieces = []
    total, lap = 0.0, 0
    while total < length_m + 1.0 and lap < 50:
        inset = float(np.clip(ring_inset_m + (0.35 if lap % 2 else 0.0), 0.0, largest))
        ring = _rectangle_points(lo + inset, hi - inset, step_m=0.5, phase=phase, direction=direction)
        if partial:  # the share of the ring, forth on even laps and back on odd ones
            ring = ring[: max(2, math.ceil(len(ring) / lap_share))]
            ring = ring[::-1] if lap % 2 else ring
        goals: list[int] = []
        for point in ring:
            cell = grid.cell_of(point)
            if not goals or goals[-1] != cell:
                goals.append(cell)
        if current is None:
            current = goals[0]
            pieces.append(flat_xy[[current]])
        for goal in goals[1:] if partial else goals[1:] + goals[:1]:
            if goal == current:
                continue
            leg = grid.path(current, goal)
            pieces.append(leg[1:])
            total += float(np.sum(np.linalg.norm(np.diff(leg, axis=0), axis=1)))
            current = goal
        lap += 1
        direction = direction if partial else -direction
    path = np.concatenate(pieces)
    if len(path) < 2:
        return path
    # Smooth the grid path (corner cutting), keeping only smoothed points with enough clearance.
    dense = resample(path, grid.cell / 2)
    smoothed = smooth(dense, 0.35 / (grid.cell / 2))
    ij = np.clip(((smoothed - grid.origin) / grid.cell).astype(int), 0, [grid.nx - 1, grid.ny - 1])
    ok = grid.free[ij[:, 1], ij[:, 0]]
    smoothed[~ok] = dense[~ok]
    log.debug("walk: ring inset %.2f m, %d laps, %.1f m", ring_inset_m, lap, total)
    return smoothed


def _rectangle_points(lo: np.ndarray, hi: np.ndarray, *, step_m: float, phase: float, direction: int) -> np.ndarray:
    """Points every ``step_m`` around the rectangle [lo, hi] (degenerate: a segment or a point),
    starting ``phase`` (0-1) of the way round, counter-clockwise for ``direction`` 1."""
    corners = np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]], lo], dtype=np.float64)
    ring = resample(corners, step_m) if np.any(hi > lo) else corners[:1]
    ring = np.roll(ring, -int(phase * len(ring)), axis=0)
    return ring if direction > 0 else ring[::-1]
