"""Plausible walks of a user holding an RGB-D camera through a room, looking at things.

Generic: the room is described only by its floor extent, obstacle footprints (x-y boxes) and target
points (object centres), so the same planner serves generated rooms and real scans. The world is z-up;
cameras follow OpenCV axes (x right, y down, z forward).

The walk: free floor is a grid (cells far enough from walls and obstacles); the user visits groups
of nearby targets in a nearest-first tour, stopping at a viewpoint 1.2-2.6 m from each group and
seeing it from a new side on every lap; legs between viewpoints are shortest paths on the grid that
prefer clearance, then smoothed and walked at a steady step. The head fixates one target at a time
(preferring the group being approached and targets not yet seen from this side), and the gaze point
is smoothed in time, so the head turns smoothly from one target to the next.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from arcloud.errors import InvalidInput

if TYPE_CHECKING:
    from arcloud.sim.room import Room

log = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray, *, roll_rad: float = 0.0) -> np.ndarray:
    """(4, 4) cam2world of a camera at ``eye`` (3,) whose optical axis (+z) points at ``target`` (3,),
    with image x to the right and image y down relative to the world's +z up; ``roll_rad`` turns the
    image about the optical axis. The view must not be vertical."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, UP)
    norm = np.linalg.norm(right)
    if norm < 1e-6:
        raise InvalidInput("target", "a target not straight above or below the eye", np.array2string(forward))
    right /= norm
    down = np.cross(forward, right)
    if roll_rad:
        c, s = math.cos(roll_rad), math.sin(roll_rad)
        right, down = c * right + s * down, -s * right + c * down
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


class _FreeGrid:
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
        obstacle_m = ndimage.distance_transform_edt(~blocked) * cell_m - cell_m / 2 if blocked.any() else np.full(blocked.shape, np.inf)
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
            self._graph = coo_matrix((np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
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


def _cluster(targets_xy: np.ndarray, radius_m: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Greedy groups of target indices whose x-y positions lie within ``radius_m`` of a seed target."""
    left = list(rng.permutation(len(targets_xy)))
    groups = []
    while left:
        seed = left[0]
        near = [i for i in left if np.linalg.norm(targets_xy[i] - targets_xy[seed]) <= radius_m]
        groups.append(np.array(sorted(near)))
        left = [i for i in left if i not in near]
    return groups


def _angle_gap(a: float, others: Sequence[float]) -> float:
    """Smallest absolute angle between ``a`` and any of ``others`` (pi when there are none)."""
    if not others:
        return math.pi
    d = np.abs((np.asarray(others) - a + math.pi) % (2 * math.pi) - math.pi)
    return float(d.min())


def _resample(points: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` of arc length along a polyline (N, 2)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    if arc[-1] <= 0:
        return points[:1].copy()
    s = np.arange(0.0, arc[-1], step_m)
    return np.column_stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])])


def _smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(values, sigma, axis=0, mode="nearest") if sigma > 0 and len(values) > 1 else values


def plan_walk(
    floor_min_xy: Sequence[float],
    floor_max_xy: Sequence[float],
    targets: np.ndarray,
    n_frames: int,
    seed: int,
    *,
    eye_height_m: float = 1.5,
    eye_height_jitter_m: float = 0.15,
    obstacles_xy: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
    step_m: float = 0.05,
    floor_z_m: float = 0.0,
    clearance_m: float = 0.3,
    wall_margin_m: float = 0.35,
    view_distance_m: tuple[float, float] = (1.2, 2.6),
    group_radius_m: float = 1.3,
    fixation_frames: int = 24,
    cell_m: float = 0.1,
) -> list[np.ndarray]:
    """One user's walk: ``n_frames`` (4, 4) cam2world poses, one every ``step_m`` of walking.

    floor_min_xy, floor_max_xy: (2,) the walkable floor's extent. targets: (N, 3) points to look at
    (object centres). obstacles_xy: (min_xy, max_xy) footprints to keep ``clearance_m`` from (walls:
    ``wall_margin_m``). The eye is ``eye_height_m`` (plus a per-walk offset within
    ``eye_height_jitter_m`` and a small bob) above ``floor_z_m``. Deterministic for a seed."""
    lo = np.asarray(floor_min_xy, dtype=np.float64).reshape(2)
    hi = np.asarray(floor_max_xy, dtype=np.float64).reshape(2)
    if not np.all(hi - lo > 2 * wall_margin_m):
        raise InvalidInput("floor_max_xy", f"a floor wider than 2 * wall_margin_m beyond {lo}", np.array2string(hi))
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise InvalidInput("n_frames", "an integer >= 1", repr(n_frames))
    if step_m <= 0 or fixation_frames < 1:
        raise InvalidInput("step_m, fixation_frames", "> 0", f"{step_m}, {fixation_frames}")
    rng = np.random.default_rng(seed)
    obstacles = [(np.asarray(a, np.float64).reshape(2), np.asarray(b, np.float64).reshape(2)) for a, b in obstacles_xy]
    grid = _FreeGrid(lo, hi, obstacles, cell_m=cell_m, clearance_m=clearance_m, wall_margin_m=wall_margin_m)

    xy = _walk_path(grid, targets, n_frames * step_m, rng, view_distance_m=view_distance_m, group_radius_m=group_radius_m)
    positions = _resample(xy, step_m)[:n_frames]
    if len(positions) < n_frames:  # a tiny floor: stand at the end
        positions = np.concatenate([positions, np.repeat(positions[-1:], n_frames - len(positions), axis=0)])

    # Eye height: a per-walk offset, a slow sway and a step bob (about 0.7 m per step).
    base = eye_height_m + rng.uniform(-eye_height_jitter_m, eye_height_jitter_m)
    s = np.arange(n_frames) * step_m
    phase = rng.uniform(0, 2 * math.pi, 2)
    z = floor_z_m + base + 0.012 * np.sin(2 * math.pi * s / 0.7 + phase[0]) + 0.02 * np.sin(2 * math.pi * s / 6.0 + phase[1])
    eyes = np.column_stack([positions, z])
    gaze = _gaze_points(eyes, targets, rng, fixation_frames=fixation_frames)
    roll = np.radians(1.5) * _smooth(rng.normal(0.0, 1.0, n_frames), 12.0) * 3.0
    poses = []
    for eye, point, r in zip(eyes, gaze, roll):
        direction = point - eye
        horizontal = np.linalg.norm(direction[:2])
        if horizontal < 1e-3:
            direction = np.array([1.0, 0.0, 0.0])
            horizontal = 1.0
        # Keep the pitch between looking 65 degrees down and 20 degrees up.
        pitch = np.clip(math.atan2(direction[2], horizontal), -math.radians(65), math.radians(20))
        direction = np.concatenate([direction[:2] / horizontal * math.cos(pitch), [math.sin(pitch)]])
        poses.append(look_at(eye, eye + direction, roll_rad=float(r)))
    return poses


def _walk_path(
    grid: _FreeGrid,
    targets: np.ndarray,
    length_m: float,
    rng: np.random.Generator,
    *,
    view_distance_m: tuple[float, float],
    group_radius_m: float,
) -> np.ndarray:
    """(N, 2) smoothed path at least ``length_m`` long (unless there is nothing to visit)."""
    start = grid.free_index[int(rng.integers(len(grid.free_index)))]
    flat_xy = grid.xy.reshape(-1, 2)
    if len(targets) == 0:
        groups: list[np.ndarray] = []
    else:
        groups = _cluster(targets[:, :2], group_radius_m, rng)
    centres = [targets[g, :2].mean(axis=0) for g in groups]
    seen_angles: list[list[float]] = [[] for _ in groups]
    waypoints = [start]
    current = start
    total = 0.0
    pieces = [flat_xy[[start]]]
    unvisited: list[int] = []
    lo_d, hi_d = view_distance_m
    guard = 0
    while total < length_m + 1.0 and guard < 200:
        guard += 1
        if groups:
            if not unvisited:
                unvisited = list(range(len(groups)))
            here = flat_xy[current]
            k = min(unvisited, key=lambda g: np.linalg.norm(centres[g] - here) + 0.3 * rng.random())
            unvisited.remove(k)
            offsets = grid.free_xy - centres[k]
            dist = np.linalg.norm(offsets, axis=1)
            angles = np.arctan2(offsets[:, 1], offsets[:, 0])
            novelty = np.array([_angle_gap(a, seen_angles[k]) for a in angles]) / math.pi
            in_range = (dist >= lo_d) & (dist <= hi_d)
            walk = np.linalg.norm(grid.free_xy - here, axis=1)
            score = 1.5 * novelty - 0.15 * walk + 0.3 * rng.random(len(dist)) - 2.0 * ~in_range - 0.5 * np.abs(dist - (lo_d + hi_d) / 2)
            choice = int(np.argmax(score))
            seen_angles[k].append(float(angles[choice]))
            goal = int(grid.free_index[choice])
        else:  # nothing to look at: wander
            goal = int(grid.free_index[int(rng.integers(len(grid.free_index)))])
        if goal == current:
            continue
        leg = grid.path(current, goal)
        pieces.append(leg[1:])
        total += float(np.sum(np.linalg.norm(np.diff(leg, axis=0), axis=1)))
        waypoints.append(goal)
        current = goal
    path = np.concatenate(pieces)
    if len(path) < 2:
        return path
    # Smooth the grid path (corner cutting), keeping only smoothed points with enough clearance.
    dense = _resample(path, grid.cell / 2)
    smooth = _smooth(dense, 0.35 / (grid.cell / 2))
    ij = np.clip(((smooth - grid.origin) / grid.cell).astype(int), 0, [grid.nx - 1, grid.ny - 1])
    ok = grid.free[ij[:, 1], ij[:, 0]]
    smooth[~ok] = dense[~ok]
    log.debug("walk: %d groups, %d viewpoints, %.1f m", len(groups), len(waypoints) - 1, total)
    return smooth


def _gaze_points(eyes: np.ndarray, targets: np.ndarray, rng: np.random.Generator, *, fixation_frames: int) -> np.ndarray:
    """(N, 3) smoothed points the head looks at, one per eye position."""
    n = len(eyes)
    heading = np.gradient(_smooth(eyes[:, :2], 5.0), axis=0) if n > 1 else np.array([[1.0, 0.0]])
    if len(targets) == 0:
        ahead = eyes[:, :2] + 2.0 * heading / np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
        return np.column_stack([ahead, eyes[:, 2] - 0.6])
    counts = np.zeros((len(targets), 8))
    points = np.empty((n, 3))
    i = 0
    previous = -1
    while i < n:
        length = int(rng.integers(max(1, fixation_frames * 2 // 3), fixation_frames * 4 // 3 + 1))
        mid = min(i + length // 2, n - 1)
        offset = eyes[mid, :2] - targets[:, :2]
        dist = np.linalg.norm(offset, axis=1)
        bucket = ((np.arctan2(offset[:, 1], offset[:, 0]) + math.pi) / (2 * math.pi) * 8).astype(int) % 8
        h = heading[mid] / max(np.linalg.norm(heading[mid]), 1e-9)
        bearing = np.arccos(np.clip((-offset @ h) / np.maximum(dist, 1e-9), -1, 1))
        novelty = 1.0 / (1.0 + counts[np.arange(len(targets)), bucket])
        score = (
            1.5 * novelty
            - 1.0 * (bearing / math.pi) ** 2
            - 0.4 * np.abs(dist - 2.0)
            - 3.0 * ((dist < 0.7) | (dist > 5.0))
            - 0.8 * (np.arange(len(targets)) == previous)
            + 0.4 * rng.random(len(targets))
        )
        k = int(np.argmax(score))
        counts[k, bucket[k]] += 1
        previous = k
        points[i : i + length] = targets[k] + rng.normal(0.0, 0.05, 3)
        i += length
    return _smooth(points, max(fixation_frames / 4, 1.0))


def room_walk(room: Room, n_frames: int = 300, seed: int = 0, **kwargs: object) -> list[np.ndarray]:
    """A walk through a generated room looking at its objects (see ``plan_walk`` for ``kwargs``)."""
    targets = np.array([o.center for o in room.objects]).reshape(-1, 3)
    return plan_walk(
        room.floor_min_xy, room.floor_max_xy, targets, n_frames, seed, obstacles_xy=room.obstacles_xy(), **kwargs  # type: ignore[arg-type]
    )
