"""Refinement: drop noisy voxels and fit robust boxes; derive the object's label and score."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull

from arcloud.core.confirm import label_purity, with_evidence
from arcloud.core.floor import floor_height
from arcloud.core.fusion import keep_voxels, object_label_index
from arcloud.core.gravity import Gravity
from arcloud.core.types import AABB, CLASSES, OBB, MapObject, Params
from arcloud.core.voxels import ijk_bounds, ijk_centers, ijk_extent, points_extent, sorted_unique, unpack_keys

MAX_COMPONENT_GRID_CELLS = 8_000_000  # larger objects skip the component filter (memory bound)
_CONNECTIVITY_26 = np.ones((3, 3, 3), bool)
_CONNECTIVITY_26.setflags(write=False)


def prune_voxels(obj: MapObject, params: Params) -> MapObject:
    """Permanently drop noise: voxels seen at least ``prune_min_seen`` times with an occupancy below
    ``prune_max_occupancy`` (background that a few masks bled onto). A weight threshold relative to
    the object's strongest voxel would also delete parts that are rarely in view (table legs)."""
    if obj.keys.size == 0:
        return obj
    seen = obj.seen_counts
    keep = ~((seen >= params.prune_min_seen) & (obj.weights < params.prune_max_occupancy * seen))
    return obj if keep.all() else keep_voxels(obj, keep)


def box_voxel_mask(obj: MapObject, params: Params) -> np.ndarray:
    """(N,) bool: the voxels the boxes are fitted to. Keeps voxels that were mostly covered when
    visible (occupancy weights / seen >= ``box_min_occupancy``) and not hit too rarely compared with
    the object's well-observed voxels (``box_rel_weight`` of the 90th percentile weight), then drops
    connected parts (26-neighbourhood) smaller than ``min_component_fraction`` of the largest."""
    if obj.keys.size == 0:
        return np.zeros(0, bool)
    return _box_voxel_mask(obj, params, unpack_keys(obj.keys))


def _box_voxel_mask(obj: MapObject, params: Params, ijk_all: np.ndarray, floor_m: float | None = None) -> np.ndarray:
    """``box_voxel_mask`` of a non-empty object whose keys unpack to ``ijk_all`` (N, 3); with the
    object's ``floor_m`` (``core.floor``), voxels within ``floor_clearance_m`` above it are floor a mask
    bled onto, not the object."""
    k = int(0.9 * (obj.weights.size - 1))
    reference = float(np.partition(obj.weights, k)[k])  # the 90th percentile, without interpolation
    keep = (obj.weights >= params.box_rel_weight * reference) & (obj.weights >= params.box_min_occupancy * obj.seen_counts)
    if floor_m is not None:
        bottoms = ijk_all @ (params.voxel_size_m * params.gravity.up)  # (exactly so when up is +z)
        keep &= bottoms > floor_m + params.floor_clearance_m
    if np.count_nonzero(keep) < 2:
        return keep
    ijk = ijk_all[keep]
    origin, top = ijk_extent(ijk)
    shape = (top - origin + 1).tolist()
    if math.prod(shape) > MAX_COMPONENT_GRID_CELLS:
        return keep
    grid = np.zeros(shape, bool)
    local = ijk - origin
    grid[local[:, 0], local[:, 1], local[:, 2]] = True
    labelled, n_parts = ndimage.label(grid, structure=_CONNECTIVITY_26)
    if n_parts > 1:
        part = labelled[local[:, 0], local[:, 1], local[:, 2]]
        sizes = np.bincount(part)
        sizes[0] = 0
        large = sizes >= params.min_component_fraction * sizes.max()
        kept_idx = np.flatnonzero(keep)
        keep[kept_idx[~large[part]]] = False
    return keep


def footprint_outline(xy: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Centres (M, 2) of the outermost ground cells under points (N, 2): per grid column, the cells at
    the lowest and highest row (by column). Their convex hull is the footprint's; M is at most twice the
    columns. ``footprint_outline_plain`` without the sort (a test holds them equal)."""
    cells = np.floor(xy / voxel_size_m).astype(np.int64)
    cols, rows = cells[:, 0], cells[:, 1]
    first_col = int(cols.min())
    column = cols - first_col
    n_cols = int(column.max()) + 1
    lowest, highest = np.empty(n_cols, np.int64), np.empty(n_cols, np.int64)  # np.full costs 3x
    lowest.fill(np.iinfo(np.int64).max)
    highest.fill(np.iinfo(np.int64).min)
    np.minimum.at(lowest, column, rows)
    np.maximum.at(highest, column, rows)
    present = np.flatnonzero(highest >= lowest)
    n = present.size
    outline = np.empty((2 * n, 2), np.int64)  # the lowest cells, then the highest (column_stack's cost 3x)
    outline[:n, 0] = outline[n:, 0] = present + first_col
    outline[:n, 1], outline[n:, 1] = lowest[present], highest[present]
    return (outline + 0.5) * voxel_size_m


def footprint_outline_plain(xy: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """``footprint_outline`` from the sorted unique cells: the first and last cell of each column."""
    cells = np.unique(np.floor(xy / voxel_size_m).astype(np.int64), axis=0)  # sorted by column, then row
    first = np.flatnonzero(np.r_[True, cells[1:, 0] != cells[:-1, 0]])
    last = np.r_[first[1:] - 1, len(cells) - 1]
    return (np.concatenate([cells[first], cells[last]]) + 0.5) * voxel_size_m


def _collinear(points: np.ndarray) -> bool:
    """Whether points (N, 2) lie on one line (qhull refuses them; the monotone chain does not)."""
    spread = points - points[0]
    return bool(np.linalg.matrix_rank(spread, tol=1e-9) < 2)


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (H, 2) of a few points (N, 2) by Andrew's monotone chain: faster
    than qhull (``scipy.spatial.ConvexHull``, its plain version) up to about 60 points, and it takes
    collinear points. A test holds the polygons equal: qhull's vertices in its order, plus the odd point
    on an edge that rounding makes look convex to the chain (qhull leaves those out)."""
    pts = sorted(set(map(tuple, points.tolist())))
    if len(pts) < 3:
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def half(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        # A stack in a list of fixed length with its height kept in a local: no len, append or pop
        # calls (the step runs ~800 points through here a frame).
        chain = list(seq)
        height = 0
        for p in seq:
            px, py = p
            while height >= 2:
                (ax, ay), (bx, by) = chain[height - 2], chain[height - 1]
                if (bx - ax) * (py - ay) - (by - ay) * (px - ax) > 0:
                    break
                height -= 1
            chain[height] = p
            height += 1
        return chain[:height]

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64)


def at_least(lo: np.ndarray, hi: np.ndarray, min_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) grown about their middle to ``min_size_m`` where they are thinner."""
    grow = np.maximum(min_size_m - (hi - lo), 0) / 2
    return lo - grow, hi + grow


def fit_aabb(centers: np.ndarray, pad_m: float, min_size_m: float) -> AABB:
    """The tightest axis-aligned box around voxel centres (N, 3), grown by ``pad_m`` on every side and
    at least ``min_size_m`` on every axis (one layer of voxels is one voxel thick, not flat)."""
    lo, hi = points_extent(centers)
    return AABB(*at_least(lo - pad_m, hi + pad_m, min_size_m))


def fit_gravity_obb(centers: np.ndarray, voxel_size_m: float, gravity: Gravity, pad_m: float | None = None) -> OBB:
    """The smallest-footprint box whose vertical axis is up (``gravity``): rotating calipers on the
    convex hull of the voxel centres projected on the ground plane, grown by ``pad_m`` (default half a
    voxel)."""
    rotation = gravity.world2gravity
    points = centers if gravity.is_identity else centers @ rotation.T
    xy = footprint_outline(points[:, :2], voxel_size_m) if voxel_size_m > 0 else points[:, :2]
    hull = convex_hull_2d(xy) if len(xy) <= 64 or _collinear(xy) else xy[ConvexHull(xy).vertices]  # qhull wins beyond ~60 points
    yaw = 0.0
    if len(hull) == 2:  # collinear: the box lies along the line
        dx, dy = hull[1] - hull[0]
        yaw = float(np.mod(np.arctan2(dy, dx), np.pi / 2))
    elif len(hull) >= 3:
        edges = np.concatenate((hull[1:], hull[:1])) - hull  # each point to the next, wrapping (np.roll costs 4x)
        # Sorted unique angles (np.mod by a positive divisor gives no -0.0, so equal means identical).
        angles = sorted_unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
        c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
        hull_x, hull_y = hull[:, 0], hull[:, 1]
        # Hull points in each candidate frame: (A, H) coordinates along the two box axes.
        u = hull_x * c + hull_y * s
        v = -hull_x * s + hull_y * c
        areas = (u.max(axis=1) - u.min(axis=1)) * (v.max(axis=1) - v.min(axis=1))  # np.ptp, without its wrapper
        yaw = float(angles[np.argmin(areas)])
    c, s = math.cos(yaw), math.sin(yaw)
    yaw_rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # box2gravity
    local_xy = xy @ yaw_rotation[:2, :2]
    half = voxel_size_m / 2 if pad_m is None else pad_m
    lo, hi = np.empty(3), np.empty(3)
    heights = points[:, 2]
    (lo[:2], hi[:2]), lo[2], hi[2] = points_extent(local_xy), heights.min(), heights.max()
    lo -= half
    hi += half
    lo, hi = at_least(lo, hi, voxel_size_m)
    box2world = rotation.T @ yaw_rotation
    return OBB(center=box2world @ ((lo + hi) / 2), size=hi - lo, rotation=box2world, yaw_rad=yaw)


def reach_floor(aabb: AABB, obb: OBB, floor_m: float, params: Params) -> tuple[AABB, OBB]:
    """The boxes of a floor-standing object extended down to the floor at height ``floor_m`` (along
    ``params.up``), when the gap is at most ``floor_reach_max_m``: legs are thin and often hidden (under a
    table, behind a seat), but the object stands on the floor. ``aabb`` is in the ``world2aligned``
    frame (whose z must be up for it to move); ``obb`` is gravity-aligned."""
    rotation = params.gravity.world2gravity
    bottom_world = obb.center - rotation[2] * obb.size[2] / 2
    gap = float(rotation[2] @ bottom_world) - floor_m
    if not 0 < gap <= params.floor_reach_max_m:
        return aabb, obb
    grown = obb.size.copy()
    grown[2] += gap
    obb = OBB(center=obb.center - rotation[2] * gap / 2, size=grown, rotation=obb.rotation, yaw_rad=obb.yaw_rad)
    if params.world2aligned is None:
        aligned_up, floor_aligned = rotation[2], floor_m
    else:
        world2aligned = np.asarray(params.world2aligned, np.float64)
        aligned_up = world2aligned[:3, :3] @ rotation[2]
        floor_aligned = float((world2aligned[:3, :3] @ (bottom_world - rotation[2] * gap) + world2aligned[:3, 3])[2])
    if aligned_up[2] > 0.99 and floor_aligned < aabb.min[2]:  # the aligned frame is z-up
        lo = aabb.min.copy()
        lo[2] = floor_aligned
        aabb = AABB(lo, aabb.max)
    return aabb, obb


def refine(obj: MapObject, params: Params) -> MapObject:
    """Prune noisy voxels, then derive label, score, bounds and boxes. An object left without voxels
    comes back empty (the caller deletes it)."""
    obj = prune_voxels(obj, params)
    if obj.keys.size == 0:
        return obj.replace(label="", score=0.0, aabb=None, obb=None, bounds=None, confirmed=False)
    ijk = unpack_keys(obj.keys)  # once: the component filter, the box's centres and the bounds use it
    floor_m = floor_height(obj.floor_votes, params)
    box_mask = _box_voxel_mask(obj, params, ijk, floor_m)
    if not box_mask.any():  # no voxel is solid enough yet: box what there is
        box_mask = np.ones(obj.keys.size, bool)
    voxel_labels = obj.votes.argmax(axis=1)  # once: the label and its purity use it
    label_index = object_label_index(obj, voxel_labels)
    centers = ijk_centers(ijk[box_mask], params.voxel_size_m)
    if params.world2aligned is not None:
        world2aligned = np.asarray(params.world2aligned, np.float64)
        aligned = centers @ world2aligned[:3, :3].T + world2aligned[:3, 3]
    else:
        aligned = centers
    lo, hi = ijk_bounds(ijk, params.voxel_size_m)
    label = CLASSES[label_index]
    aabb = fit_aabb(aligned, params.box_pad_voxels * params.voxel_size_m, params.voxel_size_m)
    obb = fit_gravity_obb(centers, params.voxel_size_m, params.gravity, params.box_pad_voxels * params.voxel_size_m)
    if floor_m is not None and label in params.floor_standing:
        aabb, obb = reach_floor(aabb, obb, floor_m, params)
    refined = obj.replace(
        label=label,
        label_purity=label_purity(obj.weights[box_mask], voxel_labels[box_mask], label_index),
        aabb=aabb,
        obb=obb,
        bounds=AABB(lo, hi),
    )
    return with_evidence(refined, params)
