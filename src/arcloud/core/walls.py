"""The wall behind a screen, kept per object: where the frames that found it put it.

A frame finds the wall behind a screen's mask from the ring of depth around it, and drops the mask's
samples on it or near it (``core.voxels.off_wall_samples``). Frames that find none keep every sample, and
a dark screen seen at an angle returns none of its own: its mask's samples are the wall seen through it.
So each frame that found the wall votes for where the screen's samples were cut, as a vertical plane (its
horizontal normal's direction in whole degrees and its offset in millimetres), and the object keeps the
tally: direction -> (frames, the sum of their offsets). The object's wall is the direction most frames
voted for, pooled with the directions ``WALL_POOL_DEG`` either side of it (one wall read in two frames
turns by a degree or two), at its mean offset, once ``WALL_MIN_FRAMES`` frames and ``WALL_MIN_SHARE`` (half)
of the frames that detected the object found it. A screen on a wall has its wall found in most of its frames
(measured: 60-90 %); a monitor on a desk has a plane found behind it now and then (the monitor back to back
with it, a partition; 0-22 % in the simulated offices), and that is no wall to cut it at; nor is the
backsplash behind a screen-like thing on a kitchen counter, found in 44 % of its frames (7-Scenes). The
object's box leaves out its voxels behind that plane (``outside_wall``), whichever frames put them there.
Votes are integers that add up, so an object's wall does not depend on the order in which frames arrive.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from arcloud.core.gravity import Gravity
from arcloud.core.types import WallVote

WALL_POOL_DEG = 2
WALL_MIN_FRAMES = 2
WALL_MIN_SHARE = 0.5
_DIRECTIONS = 360

#: An object's tally: direction in whole degrees -> (frames, the sum of their cut offsets in millimetres).
WallVotes = Mapping[int, tuple[int, int]]
#: A vertical plane: its horizontal unit normal (facing the room) and offset (``normal @ x == offset`` on it).
Wall = tuple[np.ndarray, float]


def wall_vote(normal: np.ndarray, offset_m: float, gravity: Gravity) -> WallVote:
    """One frame's vote for the plane ``normal @ x == offset_m`` (``normal`` horizontal, unit)."""
    flat = gravity.world2gravity[:2] @ normal
    direction = int(math.floor(math.degrees(math.atan2(flat[1], flat[0])))) % _DIRECTIONS
    return direction, (1, round(offset_m * 1000))


def add_wall_votes(a: WallVotes, b: WallVotes) -> dict[int, tuple[int, int]]:
    """The sum of two tallies (a new dict)."""
    out = dict(a)
    for direction, (frames, offset_mm) in b.items():
        had_frames, had_mm = out.get(direction, (0, 0))
        out[direction] = (had_frames + frames, had_mm + offset_mm)
    return out


def object_wall(votes: WallVotes, n_frames: int, gravity: Gravity) -> Wall | None:
    """The plane the votes of an object detected in ``n_frames`` frames agree on, as its horizontal unit normal
    and offset; None before enough of its frames agree on one (see the module docstring)."""
    if not votes:
        return None

    def pooled(direction: int) -> list[tuple[int, int, int]]:  # (degrees from ``direction``, frames, offset sum)
        spread = range(-WALL_POOL_DEG, WALL_POOL_DEG + 1)
        return [(d, *votes[(direction + d) % _DIRECTIONS]) for d in spread if (direction + d) % _DIRECTIONS in votes]

    best = max(sorted(votes), key=lambda direction: sum(frames for _, frames, _ in pooled(direction)))
    pool = pooled(best)
    frames = sum(n for _, n, _ in pool)
    if frames < max(WALL_MIN_FRAMES, WALL_MIN_SHARE * n_frames):
        return None
    angle = math.radians(best + 0.5 + sum(d * n for d, n, _ in pool) / frames)
    level = gravity.world2gravity[:2]
    normal = math.cos(angle) * level[0] + math.sin(angle) * level[1]
    return normal, sum(mm for _, _, mm in pool) / frames / 1000


def outside_wall(centers: np.ndarray, wall: Wall, voxel_size_m: float) -> np.ndarray:
    """(N,) bool: the voxels (their centres, (N, 3)) not behind the wall's plane by more than half a voxel: a
    voxel that samples in front of the plane fell in has its centre up to half a voxel behind it where the wall
    runs along the grid (up to 0.71 voxel where it runs diagonally: such a voxel may be left out)."""
    normal, offset_m = wall
    return centers @ normal >= offset_m - voxel_size_m / 2
