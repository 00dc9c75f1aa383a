"""Which intrinsics a recording's depth and poses agree with.

Depth back-projected from one frame with its pose and projected into another frame lands on that frame's
own depth where both see the same surface. With a wrong principal point or focal length each frame's rays
turn or scale about its own camera, so frames seen from different places disagree (16 px of cy turns the
rays by 1.8 degrees: 6 cm at 2 m), and the map fuses them into thick, smeared objects.
``depth_disagreement`` measures it over pairs of frames that look at the same place from viewpoints turned
apart (``view_pairs``: between frames that only step, the error moves the two reconstructions apart by the
step times its angle: 1.6 mm for 5 cm and 1.8 degrees), as the mean gap along the second frame's rays between where a
sample lands and the depth measured there, each gap capped at ``BAND_M`` (surfaces one frame hides from the
other count once, not by their distance). On 7-Scenes (every 5th frame) it is least at the published intrinsics,
within 4 px of cx and cy and 2 % of the focal length.

Where the colour camera stands against the depth camera (``colour_edge_strength``): a mask is drawn on the
colour image and looked up on the depth, so a colour camera a few pixels off puts every mask's border on the
wrong side of its object's edge (4 px moves 7-Scenes' served mAP@0.25 by up to 0.11). Where depth jumps, colour
changes too: the near side of each depth edge, carried into the colour image, lands on strong colour
gradients when the two cameras are where the frames say.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from arcloud.core.types import Frame, Intrinsics

#: Pairs of frames ``view_pairs`` draws, at most.
MAX_PAIRS = 40
#: A pair's frames are turned apart by this much (degrees), and stand at most ``PAIR_MAX_APART_M`` apart.
PAIR_TURN_DEG = (8.0, 35.0)
PAIR_MAX_APART_M = 1.0
#: ``stepped_pairs``: frames turned less than ``PAIR_TURN_DEG[0]`` apart that stand this far apart (metres).
STEP_APART_M = (0.2, 1.0)
#: Depth samples drawn from the first frame of a pair.
SAMPLES_PER_PAIR = 3000
#: A sample's gap counts up to this (metres).
BAND_M = 0.1
DEPTH_RANGE_M = (0.3, 4.0)
#: What ``agreeing_intrinsics`` tries: the focal lengths scaled by 0.9-1.1, the principal point moved by up to
#: 3.75 % of the image's width (24 px of 640) either way, in steps of 1 % and of 2 px at 640.
FIT_SCALES = np.linspace(0.9, 1.1, 21)
FIT_SHIFTS = np.linspace(-0.0375, 0.0375, 25)
FIT_ROUNDS = 6
#: A depth edge (``colour_edge_strength``): a pixel nearer than one of its 8 neighbours by this much (metres, plus
#: this share of its range: Kinect-like depth is noisier far away).
EDGE_JUMP_M, EDGE_JUMP_SHARE = 0.05, 0.03


def view_pairs(cam2world: np.ndarray, *, window: int = 60, seed: int = 0) -> list[tuple[int, int]]:
    """Up to ``MAX_PAIRS`` pairs (i, j), i < j < i + ``window``, of poses (N, 4, 4) turned apart by
    ``PAIR_TURN_DEG`` and standing within ``PAIR_MAX_APART_M``, drawn with a seeded generator."""
    low, high = np.cos(np.radians(PAIR_TURN_DEG[1])), np.cos(np.radians(PAIR_TURN_DEG[0]))
    return _pairs(cam2world, lambda cos_turn, apart: (cos_turn >= low) & (cos_turn <= high) & (apart <= PAIR_MAX_APART_M),
                  window=window, seed=seed)  # fmt: skip


def stepped_pairs(cam2world: np.ndarray, *, window: int = 60, seed: int = 0) -> list[tuple[int, int]]:
    """As ``view_pairs``, pairs of poses that turned less than ``PAIR_TURN_DEG[0]`` apart and stand
    ``STEP_APART_M`` apart: what a path that steps without turning offers. They tell a depth's scale and a
    trajectory's clock (both move what two frames measured of one surface by the step), and intrinsics only
    weakly (by the step times the rays' error)."""
    low = np.cos(np.radians(PAIR_TURN_DEG[0]))
    return _pairs(cam2world, lambda cos_turn, apart: (cos_turn > low) & (apart >= STEP_APART_M[0]) & (apart <= STEP_APART_M[1]),
                  window=window, seed=seed)  # fmt: skip


def _pairs(
    cam2world: np.ndarray, keep: Callable[[np.ndarray, np.ndarray], np.ndarray], *, window: int, seed: int
) -> list[tuple[int, int]]:
    """Up to ``MAX_PAIRS`` pairs (i, j), i < j < i + ``window``, that ``keep(cos_turn, apart_m)`` keeps (the
    cosine of the turn between the two poses, the distance between them), drawn with a seeded generator."""
    rotations, origins = cam2world[:, :3, :3], cam2world[:, :3, 3]
    candidates: list[tuple[int, int]] = []
    for i in range(len(cam2world) - 1):
        later = np.arange(i + 1, min(len(cam2world), i + window))
        relative = np.einsum("ji,njk->nik", rotations[i], rotations[later])  # R_i^T R_j
        cos_turn = (np.trace(relative, axis1=1, axis2=2) - 1) / 2
        apart = np.linalg.norm(origins[later] - origins[i], axis=1)
        candidates.extend((i, int(j)) for j in later[keep(cos_turn, apart)])
    if len(candidates) <= MAX_PAIRS:
        return candidates
    chosen = np.random.default_rng(seed).choice(len(candidates), MAX_PAIRS, replace=False)
    return [candidates[k] for k in sorted(chosen)]


def depth_disagreement(
    depths_m: Sequence[np.ndarray],
    cam2world: np.ndarray,
    intrinsics: Intrinsics,
    pairs: Sequence[tuple[int, int]],
    *,
    seed: int = 0,
) -> float:
    """The mean capped gap (metres, see the module docstring) of the frames' depth maps (each (H, W)) under
    their poses (N, 4, 4) and ``intrinsics``, over ``pairs``; nan when no sample lands on measured depth."""
    rng = np.random.default_rng(seed)
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    gaps = []
    for i, j in pairs:
        first, second = depths_m[i], depths_m[j]
        height, width = first.shape
        v, u = rng.integers(0, height, SAMPLES_PER_PAIR), rng.integers(0, width, SAMPLES_PER_PAIR)
        z = first[v, u].astype(np.float64)
        ok = (z > DEPTH_RANGE_M[0]) & (z < DEPTH_RANGE_M[1])
        v, u, z = v[ok], u[ok], z[ok]
        camera = np.stack(((u - cx) / fx * z, (v - cy) / fy * z, z), axis=1)
        world = camera @ cam2world[i, :3, :3].T + cam2world[i, :3, 3]
        seen = (world - cam2world[j, :3, 3]) @ cam2world[j, :3, :3]  # into the second camera: R^T (x - t)
        seen = seen[seen[:, 2] > DEPTH_RANGE_M[0]]
        uj = np.floor(fx * seen[:, 0] / seen[:, 2] + cx + 0.5)
        vj = np.floor(fy * seen[:, 1] / seen[:, 2] + cy + 0.5)
        height, width = second.shape  # the second image's own size (a recording may hold another by mistake)
        inside = (uj >= 0) & (uj < width) & (vj >= 0) & (vj < height)
        measured = second[vj[inside].astype(np.intp), uj[inside].astype(np.intp)].astype(np.float64)
        landed = measured > 0
        gaps.append(np.minimum(np.abs(measured[landed] - seen[inside, 2][landed]), BAND_M))
    every = np.concatenate(gaps) if gaps else np.empty(0)
    return float(every.mean()) if every.size else float("nan")


def agreeing_intrinsics(
    depths_m: Sequence[np.ndarray], cam2world: np.ndarray, intrinsics: Intrinsics, pairs: Sequence[tuple[int, int]]
) -> tuple[Intrinsics, float]:
    """Near ``intrinsics``, the ones the frames' depth and poses disagree with least (``depth_disagreement``), and
    that figure: the focal lengths scaled by each of ``FIT_SCALES``, then cx and cy each moved by each of
    ``FIT_SHIFTS`` (a share of the image's width), one after the other from the best so far, until a round
    finds none better (at most ``FIT_ROUNDS``: a principal point off in y and a focal length off trade against
    each other when the camera seldom pitches)."""
    best, best_gap = intrinsics, depth_disagreement(depths_m, cam2world, intrinsics, pairs)
    width = depths_m[0].shape[1] if len(depths_m) else 0
    for _ in range(FIT_ROUNDS):
        before = best
        for field in ("f", "cx", "cy"):
            start = best
            for value in FIT_SCALES if field == "f" else FIT_SHIFTS * width:
                if field == "f":
                    candidate = replace(start, fx=start.fx * float(value), fy=start.fy * float(value))
                else:
                    candidate = replace(start, **{field: getattr(start, field) + float(value)})
                gap = depth_disagreement(depths_m, cam2world, candidate, pairs)
                if gap < best_gap:
                    best, best_gap = candidate, gap
        if best == before:
            break
    return best, best_gap


def colour_edge_strength(frames: Sequence[Frame], moves: Sequence[Sequence[float]]) -> np.ndarray:
    """(M,): for each of ``moves`` (scale, du, dv, tx_m) of every frame's colour camera (``Frame.rgb_intrinsics``,
    else its depth intrinsics, and ``Frame.depth2rgb``: its focal lengths times ``scale``, its principal point
    moved by ``du``, ``dv`` pixels, the camera moved by ``tx_m`` metres along its x axis, as a baseline moves it),
    the mean colour gradient where the near sides of the frames' depth edges land (the grey image's Sobel
    magnitude, smoothed over a pixel; see the module docstring). Higher is better; nan where no edge lands in any
    colour image."""
    from scipy import ndimage

    moves_array = np.asarray(moves, np.float64).reshape(-1, 4)
    sums, counts = np.zeros(len(moves_array)), np.zeros(len(moves_array))
    for frame in frames:
        depth = frame.depth_m.astype(np.float64)
        nearest_far = ndimage.maximum_filter(depth, size=3)
        v, u = np.nonzero((depth > DEPTH_RANGE_M[0]) & (nearest_far - depth > EDGE_JUMP_M + EDGE_JUMP_SHARE * depth))
        z = depth[v, u]
        intr = frame.intrinsics
        points = np.stack(((u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z), axis=1)
        if frame.depth2rgb is not None:
            points = points @ frame.depth2rgb[:3, :3].T + frame.depth2rgb[:3, 3]
        points = points[points[:, 2] > 0]
        colour = frame.rgb_intrinsics or intr
        grey = frame.rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
        gradient = ndimage.gaussian_filter(np.hypot(ndimage.sobel(grey, axis=1), ndimage.sobel(grey, axis=0)), 1.0)
        height, width = gradient.shape
        inverse_z = 1.0 / points[:, 2]
        x, y = points[:, 0] * inverse_z, points[:, 1] * inverse_z
        for k, (scale, du, dv, tx) in enumerate(moves_array):
            cu = np.floor(colour.fx * scale * (x + tx * inverse_z) + colour.cx + du + 0.5)
            cv = np.floor(colour.fy * scale * y + colour.cy + dv + 0.5)
            inside = (cu >= 0) & (cu < width) & (cv >= 0) & (cv < height)
            sums[k] += gradient[cv[inside].astype(np.intp), cu[inside].astype(np.intp)].sum()
            counts[k] += np.count_nonzero(inside)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts


__all__ = [
    "BAND_M",
    "EDGE_JUMP_M",
    "EDGE_JUMP_SHARE",
    "FIT_SCALES",
    "FIT_SHIFTS",
    "MAX_PAIRS",
    "PAIR_TURN_DEG",
    "STEP_APART_M",
    "agreeing_intrinsics",
    "colour_edge_strength",
    "depth_disagreement",
    "stepped_pairs",
    "view_pairs",
]
