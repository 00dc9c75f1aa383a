"""Plausible walks of a user holding an RGB-D camera through a room, looking at things.

Generic: the room is described only by its floor extent, obstacle footprints (x-y boxes) and target
points (object centres), so the same planner serves generated rooms and real scans. The world is z-up;
cameras follow OpenCV axes (x right, y down, z forward).

The walk: free floor is a grid (cells far enough from walls and obstacles). The user walks laps of
a ring inset from the floor's edges, sized so that a lap takes most of the walk (things along the
walls are passed at 1-2.5 m, things in the middle are circled), alternating direction and inset;
legs between ring points are shortest paths on the grid that prefer clearance, smoothed and walked
at a steady step. The head fixates one target at a time, turning at a bounded rate: each next
target is the one the turning head would hold in good view longest, weighed by how little it has
been seen, whether it will be in good view again, and whether this side of it is new; a final pass
gives any target still barely seen the stretch of the walk where it is best in view.

A ``WalkStyle`` varies how the user walks (``WalkStyle.sample`` draws one): eye height, speed, how
much of the ring the walk covers, how long a look lasts, glances at the floor and the ceiling, fast
turns of the head, and a hand-held camera's jitter. Without a style a walk is the default one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from arcloud.errors import InvalidInput

if TYPE_CHECKING:
    from arcloud.sim.room import Room

log = logging.getLogger(__name__)

UP = np.array([0.0, 0.0, 1.0])
#: Distance per metre of size for a thing to fit in a VGA view (half field of view about 28 degrees).
FIT_PER_SIZE = 0.5 / math.tan(math.radians(28.0))

#: Ranges ``WalkStyle.sample`` draws from, uniformly. Eye height: a child or a phone at chest height up
#: to a tall adult's eye; steps of 2-5 cm a frame are 0.6-1.5 m/s at 30 Hz.
EYE_HEIGHT_RANGE_M = (1.1, 1.9)
STEP_RANGE_M = (0.02, 0.05)
LAPS_RANGE = (0.35, 1.6)
FIXATION_RANGE_FRAMES = (8, 30)
GLANCES_RANGE_PER_100_FRAMES = (0.0, 1.0)
FAST_TURNS_RANGE_PER_100_FRAMES = (0.0, 1.0)
JITTER_RANGE_DEG = (0.1, 0.8)
JITTER_RANGE_M = (0.001, 0.005)
#: Seed word of a styled walk's own random stream (glances, fast turns, jitter), apart from the path's.
_STYLE_STREAM = 7


@dataclass(frozen=True)
class WalkStyle:
    """How one user walks (``plan_walk(..., style=...)``).

    eye_height_m: the camera's height above the floor (plus a small bob and sway).
    step_m: walking speed, metres per frame.
    laps: laps of the ring the walk makes. Below 1 only that share of the ring is walked (back and
        forth when the walk is longer), so part of the room is seen from afar or not at all; the ring
        cannot grow past the room's walls, so from 1 lap a long walk in a small room makes more laps.
    fixation_frames: the typical time one look at a target lasts (short: glances; long: long looks).
    glances_per_100_frames: mean number of glances at the floor or the ceiling (the head pitches
        down or up, holds a few frames and comes back).
    fast_turns_per_100_frames: mean number of fast head turns (60-150 degrees at 8-15 degrees a frame,
        held a few frames, then back).
    jitter_deg, jitter_m: a hand-held camera's jitter, standard deviations per frame and axis of its
        rotation and translation (high-frequency: correlated over about a frame).

    The defaults are the default walk's figures without any glance, turn or jitter."""

    eye_height_m: float = 1.5
    step_m: float = 0.05
    laps: float = 4 / 3
    fixation_frames: int = 20
    glances_per_100_frames: float = 0.0
    fast_turns_per_100_frames: float = 0.0
    jitter_deg: float = 0.0
    jitter_m: float = 0.0

    def __post_init__(self) -> None:
        limits = {
            "eye_height_m": (0.5, 2.5), "step_m": (1e-3, 0.5), "laps": (0.05, 20.0), "glances_per_100_frames": (0.0, 20.0),
            "fast_turns_per_100_frames": (0.0, 20.0), "jitter_deg": (0.0, 5.0), "jitter_m": (0.0, 0.05),
        }  # fmt: skip
        for name, (low, high) in limits.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
                raise InvalidInput(f"WalkStyle.{name}", f"a number in [{low}, {high}]", repr(value))
        frames = self.fixation_frames
        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
            raise InvalidInput("WalkStyle.fixation_frames", "an integer >= 1", repr(frames))

    @classmethod
    def sample(cls, rng: np.random.Generator) -> WalkStyle:
        """A style with every figure drawn uniformly from its range (``EYE_HEIGHT_RANGE_M``, ...)."""
        return cls(
            eye_height_m=round(float(rng.uniform(*EYE_HEIGHT_RANGE_M)), 3),
            step_m=round(float(rng.uniform(*STEP_RANGE_M)), 4),
            laps=round(float(rng.uniform(*LAPS_RANGE)), 3),
            fixation_frames=int(rng.integers(FIXATION_RANGE_FRAMES[0], FIXATION_RANGE_FRAMES[1] + 1)),
            glances_per_100_frames=round(float(rng.uniform(*GLANCES_RANGE_PER_100_FRAMES)), 3),
            fast_turns_per_100_frames=round(float(rng.uniform(*FAST_TURNS_RANGE_PER_100_FRAMES)), 3),
            jitter_deg=round(float(rng.uniform(*JITTER_RANGE_DEG)), 3),
            jitter_m=round(float(rng.uniform(*JITTER_RANGE_M)), 4),
        )


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
    eye_height_m: float | None = None,
    eye_height_jitter_m: float | None = None,
    obstacles_xy: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
    step_m: float | None = None,
    floor_z_m: float = 0.0,
    clearance_m: float = 0.3,
    wall_margin_m: float = 0.35,
    ring_inset_m: float | None = None,
    fixation_frames: int | None = None,
    cell_m: float = 0.1,
    target_extents_m: np.ndarray | Sequence[float] | None = None,
    style: WalkStyle | None = None,
) -> list[np.ndarray]:
    """One user's walk: ``n_frames`` (4, 4) cam2world poses, one every ``step_m`` of walking.

    floor_min_xy, floor_max_xy: (2,) the walkable floor's extent. targets: (N, 3) points to look at
    (object centres). obstacles_xy: (min_xy, max_xy) footprints to keep ``clearance_m`` from (walls:
    ``wall_margin_m``). The eye is ``eye_height_m`` (default 1.5, plus a per-walk offset within
    ``eye_height_jitter_m``, default 0.15, and a small bob) above ``floor_z_m``. step_m: default 0.05.
    ring_inset_m: the lap's distance from the floor's edges (None: sized so that a lap is about 3/4 of
    the walk). fixation_frames: the typical time spent looking at one target (default 20).
    target_extents_m: (N,) the size of each target (e.g. its box diagonal; default 0.8 m): fixations
    prefer distances from which most of it is in view.

    style: a ``WalkStyle`` sets the eye height (without a per-walk offset), the step, the ring (from
    its ``laps``) and the fixation time, so it cannot come with ``eye_height_m``,
    ``eye_height_jitter_m``, ``step_m``, ``ring_inset_m`` or ``fixation_frames``; its glances, fast
    turns and jitter are drawn from a stream of their own, so a style without them walks the same path
    and looks at the same things. None: the default walk (the same poses as before styles existed).
    Deterministic for a seed; a walk of a few hundred frames is planned in well under a second."""
    overridden = {"eye_height_m": eye_height_m, "eye_height_jitter_m": eye_height_jitter_m, "step_m": step_m,
                  "ring_inset_m": ring_inset_m, "fixation_frames": fixation_frames}  # fmt: skip
    lap_share = 0.75  # a lap's length over the walk's
    if style is None:
        eye_height_m = 1.5 if eye_height_m is None else eye_height_m
        eye_height_jitter_m = 0.15 if eye_height_jitter_m is None else eye_height_jitter_m
        step_m = 0.05 if step_m is None else step_m
        fixation_frames = 20 if fixation_frames is None else fixation_frames
    elif not isinstance(style, WalkStyle):
        raise InvalidInput("style", "a WalkStyle or None", type(style).__name__)
    elif any(value is not None for value in overridden.values()):
        given = sorted(name for name, value in overridden.items() if value is not None)
        raise InvalidInput("style", "no eye height, jitter, step, ring inset or fixation beside a WalkStyle (it sets them)", f"also {given}")
    else:
        eye_height_m, eye_height_jitter_m, step_m = style.eye_height_m, 0.0, style.step_m
        fixation_frames, lap_share = style.fixation_frames, 1.0 / style.laps
    lo = np.asarray(floor_min_xy, dtype=np.float64).reshape(2)
    hi = np.asarray(floor_max_xy, dtype=np.float64).reshape(2)
    if not np.all(hi - lo > 2 * wall_margin_m):
        raise InvalidInput("floor_max_xy", f"a floor wider than 2 * wall_margin_m beyond {lo}", np.array2string(hi))
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    if isinstance(n_frames, bool) or not isinstance(n_frames, (int, np.integer)) or n_frames < 1:
        raise InvalidInput("n_frames", "an integer >= 1", repr(n_frames))
    if step_m <= 0 or fixation_frames < 1:
        raise InvalidInput("step_m, fixation_frames", "> 0", f"{step_m}, {fixation_frames}")
    if target_extents_m is None:
        extents = np.full(len(targets), 0.8)
    else:
        extents = np.asarray(target_extents_m, dtype=np.float64).reshape(-1)
        if extents.shape != (len(targets),) or not np.all(np.isfinite(extents)) or np.any(extents < 0):
            raise InvalidInput("target_extents_m", f"{len(targets)} sizes >= 0 (one per target)", np.array2string(extents))
    rng = np.random.default_rng(seed)
    obstacles = [(np.asarray(a, np.float64).reshape(2), np.asarray(b, np.float64).reshape(2)) for a, b in obstacles_xy]
    grid = _FreeGrid(lo, hi, obstacles, cell_m=cell_m, clearance_m=clearance_m, wall_margin_m=wall_margin_m)

    xy = _walk_path(grid, n_frames * step_m, rng, ring_inset_m=ring_inset_m, lap_share=lap_share)
    positions = _resample(xy, step_m)[:n_frames]
    if len(positions) < n_frames:  # a tiny floor: stand at the end
        positions = np.concatenate([positions, np.repeat(positions[-1:], n_frames - len(positions), axis=0)])

    # Eye height: a per-walk offset, a slow sway and a step bob (about 0.7 m per step).
    base = eye_height_m + rng.uniform(-eye_height_jitter_m, eye_height_jitter_m)
    s = np.arange(n_frames) * step_m
    phase = rng.uniform(0, 2 * math.pi, 2)
    z = floor_z_m + base + 0.012 * np.sin(2 * math.pi * s / 0.7 + phase[0]) + 0.02 * np.sin(2 * math.pi * s / 6.0 + phase[1])
    eyes = np.column_stack([positions, z])
    yaw, pitch = _gaze_angles(eyes, targets, extents, rng, fixation_frames=fixation_frames)
    roll = np.radians(4.5) * _smooth(rng.normal(0.0, 1.0, n_frames), 12.0)  # about 0.7 degrees, slow
    if style is not None:
        pitch = _with_glances(pitch, style.glances_per_100_frames, np.random.default_rng([int(seed), _STYLE_STREAM, 1]))
        yaw = _with_fast_turns(yaw, style.fast_turns_per_100_frames, np.random.default_rng([int(seed), _STYLE_STREAM, 2]))
    poses = []
    for eye, y, p, r in zip(eyes, yaw, pitch, roll):
        direction = np.array([math.cos(p) * math.cos(y), math.cos(p) * math.sin(y), math.sin(p)])
        poses.append(look_at(eye, eye + direction, roll_rad=float(r)))
    if style is not None:
        poses = _with_jitter(poses, style.jitter_deg, style.jitter_m, np.random.default_rng([int(seed), _STYLE_STREAM, 3]))
    return poses


#: Glances: the head pitches to the floor (60 % of glances) or the ceiling at about this rate, holds, comes back.
GLANCE_RATE_DEG = 6.0
GLANCE_FLOOR_DEG, GLANCE_CEILING_DEG = (-80.0, -55.0), (35.0, 65.0)
GLANCE_HOLD_FRAMES = (3, 15)
#: Fast turns: this much yaw at this mean rate (degrees a frame), held, then back.
FAST_TURN_DEG, FAST_TURN_RATE_DEG = (60.0, 150.0), (8.0, 15.0)
FAST_TURN_HOLD_FRAMES = (3, 15)


def _excursion(n: int, start: int, ramp_frames: int, hold_frames: int) -> np.ndarray:
    """(n,) weights in [0, 1]: a raised-cosine rise over ``ramp_frames`` from ``start``, a hold of
    ``hold_frames``, the same fall."""
    t = np.arange(n) - start
    rise = 0.5 - 0.5 * np.cos(np.pi * np.clip(t / ramp_frames, 0.0, 1.0))
    fall = 0.5 - 0.5 * np.cos(np.pi * np.clip((ramp_frames + hold_frames + ramp_frames - t) / ramp_frames, 0.0, 1.0))
    return np.minimum(rise, fall)


def _with_glances(pitch: np.ndarray, per_100_frames: float, rng: np.random.Generator) -> np.ndarray:
    """``pitch`` (N,) radians with glances at the floor and the ceiling, one at a time: exponential
    gaps (mean ``100 / per_100_frames`` frames) from the end of one to the start of the next."""
    n = len(pitch)
    out = pitch.copy()
    t = 0.0
    while per_100_frames > 0:
        t += float(rng.exponential(100.0 / per_100_frames))
        if t >= n:
            break
        start, floor, hold = int(t), rng.random() < 0.6, int(rng.integers(GLANCE_HOLD_FRAMES[0], GLANCE_HOLD_FRAMES[1] + 1))
        target = math.radians(float(rng.uniform(*(GLANCE_FLOOR_DEG if floor else GLANCE_CEILING_DEG))))
        ramp = max(2, math.ceil(abs(math.degrees(target - out[start])) / GLANCE_RATE_DEG))
        out = out + _excursion(n, start, ramp, hold) * (target - out)
        t = start + 2 * ramp + hold
    return out


def _with_fast_turns(yaw: np.ndarray, per_100_frames: float, rng: np.random.Generator) -> np.ndarray:
    """``yaw`` (N,) radians with fast turns of the head away and back, one at a time (gaps as glances')."""
    n = len(yaw)
    out = yaw.copy()
    t = 0.0
    while per_100_frames > 0:
        t += float(rng.exponential(100.0 / per_100_frames))
        if t >= n:
            break
        start, hold = int(t), int(rng.integers(FAST_TURN_HOLD_FRAMES[0], FAST_TURN_HOLD_FRAMES[1] + 1))
        turn_deg = float(rng.uniform(*FAST_TURN_DEG)) * (1 if rng.random() < 0.5 else -1)
        ramp = max(2, math.ceil(abs(turn_deg) / float(rng.uniform(*FAST_TURN_RATE_DEG))))
        out = out + math.radians(turn_deg) * _excursion(n, start, ramp, hold)
        t = start + 2 * ramp + hold
    return out


def _with_jitter(poses: list[np.ndarray], jitter_deg: float, jitter_m: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Each (4, 4) cam2world pose times a small rigid motion in its camera frame: rotation and
    translation noise with standard deviations ``jitter_deg`` and ``jitter_m`` per axis, smoothed
    over about a frame (a hand's tremor)."""
    from scipy.spatial.transform import Rotation

    n = len(poses)
    if n == 0 or (jitter_deg == 0 and jitter_m == 0):
        return poses
    sigma_frames = 1.0
    gain = math.sqrt(2 * math.sqrt(math.pi) * sigma_frames)  # smoothing shrinks white noise by this much
    angles = _smooth(rng.normal(0.0, math.radians(jitter_deg), (n, 3)), sigma_frames) * gain
    offsets = _smooth(rng.normal(0.0, jitter_m, (n, 3)), sigma_frames) * gain
    motion = np.tile(np.eye(4), (n, 1, 1))
    motion[:, :3, :3] = Rotation.from_rotvec(angles).as_matrix()
    motion[:, :3, 3] = offsets
    return [pose @ m for pose, m in zip(poses, motion)]


def _walk_path(
    grid: _FreeGrid, length_m: float, rng: np.random.Generator, *, ring_inset_m: float | None, lap_share: float = 0.75
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
        goals = []
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
    dense = _resample(path, grid.cell / 2)
    smooth = _smooth(dense, 0.35 / (grid.cell / 2))
    ij = np.clip(((smooth - grid.origin) / grid.cell).astype(int), 0, [grid.nx - 1, grid.ny - 1])
    ok = grid.free[ij[:, 1], ij[:, 0]]
    smooth[~ok] = dense[~ok]
    log.debug("walk: ring inset %.2f m, %d laps, %.1f m", ring_inset_m, lap, total)
    return smooth


def _rectangle_points(lo: np.ndarray, hi: np.ndarray, *, step_m: float, phase: float, direction: int) -> np.ndarray:
    """Points every ``step_m`` around the rectangle [lo, hi] (degenerate: a segment or a point),
    starting ``phase`` (0-1) of the way round, counter-clockwise for ``direction`` 1."""
    corners = np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]], lo], dtype=np.float64)
    ring = _resample(corners, step_m) if np.any(hi > lo) else corners[:1]
    ring = np.roll(ring, -int(phase * len(ring)), axis=0)
    return ring if direction > 0 else ring[::-1]




#: Half the field of view (horizontal, vertical) within which a target counts as in view: a VGA
#: camera with fx = fy = 525 px sees about 31 x 25 degrees either side of its axis.
VIEW_HALF_DEG = (28.0, 21.0)


def _gaze_angles(
    eyes: np.ndarray,
    targets: np.ndarray,
    extents: np.ndarray,
    rng: np.random.Generator,
    *,
    fixation_frames: int,
    max_turn_deg: float = 4.0,
    max_pitch_deg: float = 2.5,
    pitch_range_deg: tuple[float, float] = (-65.0, 20.0),
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) yaw and (N,) pitch of the view, in radians: the head fixates one target at a time,
    turning towards it at most ``max_turn_deg`` (yaw) and ``max_pitch_deg`` per frame. Each next
    target is the one that the turning head would hold in good view (far enough to fit, near enough
    to see) longest over the next fixation, weighed by how little it has been in view so far, whether
    it will be in good view again later, and whether this side of it is new."""
    n = len(eyes)
    heading = np.gradient(_smooth(eyes[:, :2], 5.0), axis=0) if n > 1 else np.array([[1.0, 0.0]])
    heading_yaw = np.unwrap(np.arctan2(heading[:, 1], heading[:, 0]))
    if len(targets) == 0:  # look ahead, a little down
        return _smooth(heading_yaw, 8.0), np.full(n, math.radians(-15.0))
    n_targets = len(targets)
    near = np.maximum(0.7, 0.6 * FIT_PER_SIZE * extents)  # most of it in view
    far = np.maximum(4.5, near + 1.0)
    low, high = np.radians(pitch_range_deg)
    # Per frame and target: direction (yaw, pitch) from the eye, and whether the distance suits.
    delta = targets[None, :, :] - eyes[:, None, :]  # (frames, targets, 3)
    dist = np.linalg.norm(delta, axis=2)
    yaw_to = np.arctan2(delta[..., 1], delta[..., 0])
    pitch_to = np.clip(np.arctan2(delta[..., 2], np.linalg.norm(delta[..., :2], axis=2)), low, high)
    in_range = (dist >= near) & (dist <= far)
    ahead = np.abs((yaw_to - heading_yaw[:, None] + math.pi) % (2 * math.pi) - math.pi) < math.radians(100)
    good = in_range & ahead
    later = np.concatenate([np.cumsum(good[::-1], axis=0)[::-1], np.zeros((1, n_targets))])  # frames i.. in good view
    half_yaw, half_pitch = np.radians(VIEW_HALF_DEG)
    max_turn, max_pitch = math.radians(max_turn_deg), math.radians(max_pitch_deg)

    def follow(k: int, start: int, stop: int, yaw0: float, pitch0: float) -> tuple[np.ndarray, np.ndarray]:
        """The head's yaw and pitch over frames [start, stop) turning from (yaw0, pitch0) to target k."""
        yaws, pitches = np.empty(stop - start), np.empty(stop - start)
        y, p = yaw0, pitch0
        for f in range(start, stop):
            dy = (yaw_to[f, k] - y + math.pi) % (2 * math.pi) - math.pi
            y += min(max(dy, -max_turn), max_turn)
            p += min(max(pitch_to[f, k] - p, -max_pitch), max_pitch)
            yaws[f - start], pitches[f - start] = y, p
        return yaws, pitches

    def in_view(frames: np.ndarray, yaws: np.ndarray, pitches: np.ndarray) -> np.ndarray:
        """(len(frames), targets) whether each target is in view and in range."""
        dy = np.abs((yaw_to[frames] - yaws[:, None] + math.pi) % (2 * math.pi) - math.pi)
        dp = np.abs(pitch_to[frames] - pitches[:, None])
        return (dy * np.cos(pitch_to[frames]) < half_yaw) & (dp < half_pitch) & in_range[frames]

    seen = np.zeros(n_targets)  # frames each target was in view
    sides = np.zeros((n_targets, 8))  # fixations per target and 45-degree side
    yaw, pitch = np.empty(n), np.empty(n)
    # Start facing what is in range now but rarely ahead later (the user may start facing anywhere).
    first = int(np.argmax(in_range[0] * (1.0 + fixation_frames / (later[0] + fixation_frames)) + 0.1 * rng.random(n_targets)))
    y0, p0 = float(yaw_to[0, first]), float(pitch_to[0, first])
    i, previous = 0, -1
    while i < n:
        hold = int(rng.integers(max(1, fixation_frames * 2 // 3), fixation_frames * 4 // 3 + 1))
        # Each candidate: turn towards it (up to another ``hold`` frames), then hold it ``hold`` frames.
        horizon = min(2 * hold, n - i)
        frames = np.arange(i, i + horizon)
        plans, spans, quality = [], [], np.zeros(n_targets)
        for k in range(n_targets):
            plan = follow(k, i, i + horizon, y0, p0)
            visible = in_view(frames, *plan)[:, k]
            start = int(np.argmax(visible)) if visible.any() else horizon
            span = min(horizon, start + hold) if visible.any() else min(hold, horizon)
            plans.append(plan)
            spans.append(span)
            quality[k] = visible[:span].mean()  # share of the time spent with it in view
        scarce = fixation_frames / (later[min(i + horizon, n)] + fixation_frames)  # 1 when never in good view again
        deficit = 1.0 / (1.0 + seen / fixation_frames)
        side = ((yaw_to[i + horizon // 2] + 2 * math.pi) / (2 * math.pi) * 8).astype(int) % 8
        novelty = 1.0 / (1.0 + sides[np.arange(n_targets), side])
        score = (
            4.0 * quality * (0.25 + deficit)
            + 1.0 * deficit * (quality > 0)
            + 2.0 * quality * scarce * deficit
            + 2.0 * novelty * quality
            - 0.8 * (np.arange(n_targets) == previous)
            + 0.3 * rng.random(n_targets)
        )
        k = int(np.argmax(score))
        span = spans[k]
        frames = frames[:span]
        yaw[frames], pitch[frames] = plans[k][0][:span], plans[k][1][:span]
        visible = in_view(frames, yaw[frames], pitch[frames])
        seen += visible.sum(axis=0)
        shown = visible.any(axis=0)
        sides[shown, side[shown]] += 1
        y0, p0, previous = float(yaw[frames[-1]]), float(pitch[frames[-1]]), k
        i += span
    # Repair: a target barely seen gets the stretch of the walk where it is longest in good view,
    # unless that stretch is where the only view of another target is; the head follows the rate limits.
    wanted_yaw, wanted_pitch = np.unwrap(yaw), pitch.copy()
    owner = np.full(n, -1)
    length = min(fixation_frames + 10, n)
    for j in np.argsort(seen):
        if seen[j] >= fixation_frames / 2 or length < 1:
            continue
        counts = np.convolve(good[:, j].astype(float), np.ones(length), mode="valid")
        counts[np.convolve((owner >= 0).astype(float), np.ones(length), mode="valid") > 0] = -1  # one repair per stretch
        a = int(np.argmax(counts))
        if counts[a] < length / 2:
            continue
        span = np.arange(a, a + length)
        wanted_yaw[span] = wanted_yaw[a] + (yaw_to[span, j] - wanted_yaw[a] + math.pi) % (2 * math.pi) - math.pi
        wanted_pitch[span] = pitch_to[span, j]
        owner[span] = j
    if np.any(owner >= 0):
        yaw = _rate_limited(np.unwrap(wanted_yaw), max_turn)
        pitch = _rate_limited(wanted_pitch, max_pitch)
    return _smooth(np.unwrap(yaw), 3.0), _smooth(pitch, 3.0)


def _rate_limited(wanted: np.ndarray, max_step: float) -> np.ndarray:
    """Follows ``wanted`` (N,) changing by at most ``max_step`` per sample."""
    out = np.empty_like(wanted)
    out[0] = wanted[0]
    for i in range(1, len(wanted)):
        out[i] = out[i - 1] + min(max(wanted[i] - out[i - 1], -max_step), max_step)
    return out


def room_walk(room: Room, n_frames: int = 300, seed: int = 0, *, style: WalkStyle | None = None, **kwargs: object) -> list[np.ndarray]:
    """A walk through a generated room looking at its objects, in ``style`` (None: the default walk;
    see ``plan_walk`` for ``kwargs``)."""
    targets = np.array([o.center for o in room.objects]).reshape(-1, 3)
    extents = np.array([np.linalg.norm(o.size) for o in room.objects])
    kwargs.setdefault("target_extents_m", extents)
    return plan_walk(
        room.floor_min_xy, room.floor_max_xy, targets, n_frames, seed, obstacles_xy=room.obstacles_xy(), style=style, **kwargs  # type: ignore[arg-type]
    )
