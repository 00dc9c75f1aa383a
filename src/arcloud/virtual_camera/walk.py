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

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from arcloud.errors import InvalidInput
from arcloud.virtual_camera.gaze import gaze_angles, look_at, with_fast_turns, with_glances, with_jitter
from arcloud.virtual_camera.path import FreeGrid, resample, smooth, walk_path

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


def plan_walk(
    floor_min_xy: np.ndarray | Sequence[float],
    floor_max_xy: np.ndarray | Sequence[float],
    targets: np.ndarray,
    n_frames: int,
    seed: int,
    *,
    eye_height_m: float | None = None,
    eye_height_jitter_m: float | None = None,
    obstacles_xy: Sequence[tuple[np.ndarray | Sequence[float], np.ndarray | Sequence[float]]] = (),
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
        raise InvalidInput(
            "style", "no eye height, jitter, step, ring inset or fixation beside a WalkStyle (it sets them)", f"also {given}"
        )
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
    grid = FreeGrid(lo, hi, obstacles, cell_m=cell_m, clearance_m=clearance_m, wall_margin_m=wall_margin_m)

    xy = walk_path(grid, n_frames * step_m, rng, ring_inset_m=ring_inset_m, lap_share=lap_share)
    positions = resample(xy, step_m)[:n_frames]
    if len(positions) < n_frames:  # a tiny floor: stand at the end
        positions = np.concatenate([positions, np.repeat(positions[-1:], n_frames - len(positions), axis=0)])

    # Eye height: a per-walk offset, a slow sway and a step bob (about 0.7 m per step).
    base = eye_height_m + rng.uniform(-eye_height_jitter_m, eye_height_jitter_m)
    s = np.arange(n_frames) * step_m
    phase = rng.uniform(0, 2 * math.pi, 2)
    z = floor_z_m + base + 0.012 * np.sin(2 * math.pi * s / 0.7 + phase[0]) + 0.02 * np.sin(2 * math.pi * s / 6.0 + phase[1])
    eyes = np.column_stack([positions, z])
    yaw, pitch = gaze_angles(eyes, targets, extents, rng, fixation_frames=fixation_frames)
    roll = np.radians(4.5) * smooth(rng.normal(0.0, 1.0, n_frames), 12.0)  # about 0.7 degrees, slow
    if style is not None:
        pitch = with_glances(pitch, style.glances_per_100_frames, np.random.default_rng([int(seed), _STYLE_STREAM, 1]))
        yaw = with_fast_turns(yaw, style.fast_turns_per_100_frames, np.random.default_rng([int(seed), _STYLE_STREAM, 2]))
    poses = []
    for eye, y, p, r in zip(eyes, yaw, pitch, roll):
        direction = np.array([math.cos(p) * math.cos(y), math.cos(p) * math.sin(y), math.sin(p)])
        poses.append(look_at(eye, eye + direction, roll_rad=float(r)))
    if style is not None:
        poses = with_jitter(poses, style.jitter_deg, style.jitter_m, np.random.default_rng([int(seed), _STYLE_STREAM, 3]))
    return poses


def scan_walk(
    floor_min_xy: np.ndarray | Sequence[float],
    floor_max_xy: np.ndarray | Sequence[float],
    targets: np.ndarray,
    n_frames: int,
    seed: int,
    **walk_options: object,
) -> list[np.ndarray]:
    """An operator scanning the room rather than a user looking at things: ``plan_walk``'s path (same
    arguments), but the camera swings along the walls and what stands before them, looking at nothing in
    particular: outward from the floor's centre, yaw swinging +-70 degrees over 60 frames, every third
    stretch of 90 frames turned to face the room instead, pitch sweeping 10-55 degrees down over 37 frames.
    Objects are seen in passing, cut by the image border, from one side at a time."""
    path = plan_walk(floor_min_xy, floor_max_xy, targets, n_frames, seed, **walk_options)  # type: ignore[arg-type]  # plan_walk checks its options
    centre = (np.asarray(floor_min_xy, np.float64).reshape(2) + np.asarray(floor_max_xy, np.float64).reshape(2)) / 2
    phase = np.random.default_rng([int(seed), _STYLE_STREAM, 4]).uniform(0, 2 * math.pi, 2)
    poses = []
    for i, walked in enumerate(path):
        eye = walked[:3, 3]
        outward = math.atan2(eye[1] - centre[1], eye[0] - centre[0]) + (math.pi if (i // 90) % 3 == 2 else 0.0)
        yaw = outward + math.radians(70) * math.sin(2 * math.pi * i / 60 + phase[0])
        pitch = -math.radians(10 + 45 * (0.5 + 0.5 * math.sin(2 * math.pi * i / 37 + phase[1])))
        direction = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
        poses.append(look_at(eye, eye + direction))
    return poses
