"""Refinement: drop noisy voxels and fit robust boxes; derive the object's label and score."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull

from arcloud.core.confirm import EXACT_DIGITS, label_purity, plausible, with_evidence
from arcloud.core.floor import floor_height
from arcloud.core.fusion import keep_voxels, object_label_index
from arcloud.core.gravity import Gravity
from arcloud.core.types import AABB, CLASSES, OBB, MapObject, Params
from arcloud.core.voxels import ijk_bounds, ijk_centers, ijk_extent, points_extent, sorted_unique, unpack_keys
from arcloud.core.walls import Wall, object_wall, outside_wall

MAX_COMPONENT_GRID_CELLS = 8_000_000  # larger objects skip the component filter (memory bound)
_CONNECTIVITY_26 = np.ones((3, 3, 3), bool)
#: A small part this few empty voxels from a large one stays with it: what a camera sees of a thing it looks up or
#: down at thinly (a TV's back above the eye, a couch's arm beside its seat) is often cut from the rest by a
#: voxel or two no mask covered; stray voxels lie further out.
COMPONENT_GAP_VOXELS = 2
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
    connected parts smaller than ``min_component_fraction`` of the largest (26-neighbourhood, connected
    through any of the object's voxels, kept or not; sizes count kept voxels), but for those within
    ``COMPONENT_GAP_VOXELS`` empty voxels of a part kept (``box_voxel_masks``)."""
    if obj.keys.size == 0:
        return np.zeros(0, bool)
    return box_voxel_masks([obj], params, [unpack_keys(obj.keys)], [None], [None])[0]


def box_voxel_masks(
    objects: Sequence[MapObject],
    params: Params,
    ijks: Sequence[np.ndarray],
    floors: Sequence[float | None],
    walls: Sequence[Wall | None],
) -> list[np.ndarray]:
    """``box_voxel_mask`` of non-empty objects whose keys unpack to ``ijks`` (each (N, 3)); with an object's
    floor (``floors``: ``core.floor``, or None), voxels within ``floor_clearance_m`` above it are floor a mask
    bled onto, not the object; with its wall (``walls``: ``screen_wall``, or None), voxels behind it are the
    wall. The parts of all the objects are found by one labelling (``label_side_by_side``)."""
    keeps: list[np.ndarray] = []
    grids: list[tuple[list[int], np.ndarray, np.ndarray] | None] = []  # (shape, cells of all voxels, kept voxels)
    for obj, ijk_all, floor_m, wall in zip(objects, ijks, floors, walls):
        k = int(0.9 * (obj.weights.size - 1))
        reference = float(np.partition(obj.weights, k)[k])  # the 90th percentile, without interpolation
        keep = (obj.weights >= params.box_rel_weight * reference) & (obj.weights >= params.box_min_occupancy * obj.seen_counts)
        if floor_m is not None:
            up = params.voxel_size_m * params.gravity.up  # a voxel's lowest corner: its own corner plus the steps down
            bottoms = ijk_all @ up + np.minimum(up, 0.0).sum()
            keep &= bottoms.round(EXACT_DIGITS) > round(floor_m + params.floor_clearance_m, EXACT_DIGITS)  # on the line: below
        if wall is not None:
            keep &= outside_wall(ijk_centers(ijk_all, params.voxel_size_m), wall, params.voxel_size_m)
        keeps.append(keep)
        grids.append(None)
        if np.count_nonzero(keep) < 2:
            continue
        ijk = ijk_all[keep]
        origin, top = ijk_extent(ijk)
        shape = (top - origin + 1).tolist()
        if math.prod(shape) > MAX_COMPONENT_GRID_CELLS:
            continue
        # Parts are found over all the object's voxels in that extent: a voxel short of the occupancy rule (which
        # the frames' order decides) still joins the parts it touches; empty space does not.
        local_all = ijk_all - origin
        below = local_all.view(np.uint64) < np.array(shape, np.uint64)  # a negative index reads as a huge one
        grids[-1] = (shape, local_all[below[:, 0] & below[:, 1] & below[:, 2]], ijk - origin)
    labelled = iter(label_side_by_side([(grid[0], grid[1]) for grid in grids if grid is not None]))
    for obj, ijk_all, keep, grid in zip(objects, ijks, keeps, grids):
        if grid is None:
            continue
        labels, local = next(labelled), grid[2]
        part = labels[local[:, 0], local[:, 1], local[:, 2]]
        if part.min() == part.max():  # one part: nothing to drop
            continue
        small = ~large_parts(part, params)
        if not small.any():
            continue
        kept_idx = np.flatnonzero(keep)
        heights = ijk_all[kept_idx] @ params.gravity.up
        lowest, highest = heights[~small].min(), heights[~small].max()
        reach = COMPONENT_GAP_VOXELS + 0.5
        off = small & ((heights < lowest - reach) | (heights > highest + reach))  # the shelf under a TV, say
        stays = small & parts_near(labels, part, part[~small], part[off])[part]
        joined = kept_idx[small & ~stays]
        apart = kept_idx[small]
        keep[
            joined if joined.size < apart.size and not grows_implausible(obj, ijk_all, keep, apart, joined, params) else apart
        ] = False
    return keeps


def parts_near(labels: np.ndarray, kept: np.ndarray, large: np.ndarray, off: np.ndarray) -> np.ndarray:
    """By part label (index 0 empty space): whether the part of a grid ``labels`` (an object's voxels, kept or not,
    labelled by part) lies within ``COMPONENT_GAP_VOXELS`` empty voxels of a ``large`` part, or of a part so found
    (a chain of small parts: a TV's back seen in pieces). Only parts with ``kept`` voxels (the labels of the voxels
    the occupancy rules keep) carry a chain: a part of voxels they all leave out is what a mask bled onto, and
    hopping through such parts a stray voxel 0.35 m in front of a screen joined it. The ``off`` parts neither join
    nor carry a chain."""
    present = np.zeros(int(labels.max()) + 1, bool)
    present[kept] = True
    present[off] = False
    solid = present[labels]
    # Every voxel grown by half the gap (a filter of gap + 1 cells a side): parts up to the gap apart then touch.
    bridged, _ = ndimage.label(ndimage.maximum_filter(solid, size=COMPONENT_GAP_VOXELS + 1), _CONNECTIVITY_26)
    group = np.zeros(present.size, bridged.dtype)
    group[labels[solid]] = bridged[solid]
    return present & np.isin(group, group[large])


def large_parts(part: np.ndarray, params: Params) -> np.ndarray:
    """(N,) bool: which of N voxels labelled by ``part`` lie in a part of at least ``min_component_fraction`` of the
    largest's voxels."""
    sizes = np.bincount(part)
    return (sizes >= params.min_component_fraction * sizes.max())[part]


def grows_implausible(
    obj: MapObject, ijk: np.ndarray, keep: np.ndarray, apart: np.ndarray, joined: np.ndarray, params: Params
) -> bool:
    """Whether keeping the small parts near a large one (dropping only ``joined`` of the kept voxels rather than
    ``apart``) would give the object a box its class cannot have, where the large parts alone give one it can:
    a laptop's part beside the keyboard a mask bled onto is a gap away, and kept makes a 0.75 m laptop."""
    labelled = obj.replace(label=CLASSES[object_label_index(obj)])  # the label refining will give it
    boxes = []
    for dropped in (joined, apart):
        mask = keep.copy()
        mask[dropped] = False
        box_ijk = ijk[mask]
        box_obb = fit_voxels_obb(box_ijk, params.voxel_size_m, params.gravity, params.box_pad_voxels * params.voxel_size_m)
        boxes.append(plausible(labelled.replace(obb=box_obb), params))
    return not boxes[0] and boxes[1]


def label_side_by_side(grids: Sequence[tuple[list[int], np.ndarray]]) -> list[np.ndarray]:
    """The connected parts (26-neighbourhood) of each of several boolean grids, given as (shape, indices (N, 3) of
    its cells that are set): a labelled array of the grid's shape each, by one ``ndimage.label`` of all the grids
    side by side along the first axis, an empty layer between two (a call costs several times more inside the
    step than alone). When their other two sides differ so much that the shared array would hold four times
    their cells, or it would exceed ``MAX_COMPONENT_GRID_CELLS``, each is labelled on its own."""
    if not grids:
        return []
    heights = [shape[0] for shape, _ in grids]
    width, depth = max(shape[1] for shape, _ in grids), max(shape[2] for shape, _ in grids)
    starts = list(itertools.accumulate((h + 1 for h in heights[:-1]), initial=0))
    side_by_side = (starts[-1] + heights[-1], width, depth)
    size = math.prod(side_by_side)
    if len(grids) == 1 or size > MAX_COMPONENT_GRID_CELLS or size > 4 * sum(math.prod(shape) for shape, _ in grids):
        labelled = []
        for shape, cells in grids:
            grid = np.zeros(shape, bool)
            grid[tuple(cells.T)] = True
            labelled.append(ndimage.label(grid, structure=_CONNECTIVITY_26)[0])
        return labelled
    together = np.zeros(side_by_side, bool)
    for start, (_, cells) in zip(starts, grids):
        together[cells[:, 0] + start, cells[:, 1], cells[:, 2]] = True
    parts = ndimage.label(together, structure=_CONNECTIVITY_26)[0]
    return [parts[start : start + shape[0], : shape[1], : shape[2]] for start, (shape, _) in zip(starts, grids)]


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


def voxels_outline(ijk: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """``footprint_outline`` of the centres of voxels at indices ``ijk`` (N, 3), N > 0, sorted by i then j
    (as their keys sort), on the voxels' own grid (a test holds them equal): a centre's ground cell is
    its (i, j) (floor((i + 0.5) * s / s) is i: the two roundings move it by far less than half a cell
    for any index a key holds), and a column's lowest and highest cells are its first and last voxels."""
    columns = ijk[:, 0]
    new_column = columns[1:] != columns[:-1]
    first, last = np.empty(columns.size, bool), np.empty(columns.size, bool)
    first[0] = last[-1] = True
    first[1:] = last[:-1] = new_column
    cells = ijk[:, :2]
    return (np.concatenate((cells[first], cells[last])) + 0.5) * voxel_size_m


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


def at_least_floats(lo: list[float], hi: list[float], min_size_m: float) -> tuple[list[float], list[float]]:
    """``at_least`` of corners as Python floats: the same arithmetic element by element, without numpy's
    cost per call on three numbers."""
    grow = [max(min_size_m - (h - low), 0.0) / 2 for low, h in zip(lo, hi)]
    return [low - g for low, g in zip(lo, grow)], [h + g for h, g in zip(hi, grow)]


def fit_aabb(centers: np.ndarray, pad_m: float, min_size_m: float) -> AABB:
    """The tightest axis-aligned box around voxel centres (N, 3), grown by ``pad_m`` on every side and
    at least ``min_size_m`` on every axis (one layer of voxels is one voxel thick, not flat)."""
    lo, hi = points_extent(centers)
    return AABB(*at_least(lo - pad_m, hi + pad_m, min_size_m))


def fit_voxels_aabb(ijk_lo: list[int], ijk_hi: list[int], voxel_size_m: float, pad_m: float) -> AABB:
    """``fit_aabb(centres, pad_m, voxel_size_m)`` of voxels whose indices span ``ijk_lo``..``ijk_hi`` (their
    ``ijk_extent``): the centres' extent is that of the extreme indices' centres (rounding is monotone;
    a test holds them equal)."""
    lo = [(i + 0.5) * voxel_size_m - pad_m for i in ijk_lo]
    hi = [(i + 0.5) * voxel_size_m + pad_m for i in ijk_hi]
    return AABB(*(np.array(corner) for corner in at_least_floats(lo, hi, voxel_size_m)))


def fit_gravity_obb(centers: np.ndarray, voxel_size_m: float, gravity: Gravity, pad_m: float | None = None) -> OBB:
    """The smallest-footprint box whose vertical axis is up (``gravity``): rotating calipers on the
    convex hull of the voxel centres projected on the ground plane, grown by ``pad_m`` (default half a
    voxel)."""
    rotation = gravity.world2gravity
    points = centers if gravity.is_identity else centers @ rotation.T
    xy = footprint_outline(points[:, :2], voxel_size_m) if voxel_size_m > 0 else points[:, :2]
    heights = points[:, 2]
    return footprint_obb(xy, float(heights.min()), float(heights.max()), voxel_size_m, rotation, pad_m)


def fit_voxels_obb(
    ijk: np.ndarray, voxel_size_m: float, gravity: Gravity, pad_m: float | None = None, k_range: tuple[int, int] | None = None
) -> OBB:
    """``fit_gravity_obb`` of the centres of voxels at indices ``ijk`` (N, 3), N > 0, sorted by i then j
    (as their keys sort); ``k_range``: their (min, max) k when the caller has it. Where up is +z, on the
    voxels' grid (a test holds them equal): the footprint is ``voxels_outline``, the heights' extent
    that of the lowest and highest layers' centres (rounding is monotone)."""
    if not gravity.is_identity or voxel_size_m <= 0:
        return fit_gravity_obb(ijk_centers(ijk, voxel_size_m), voxel_size_m, gravity, pad_m)
    k_min, k_max = (int(ijk[:, 2].min()), int(ijk[:, 2].max())) if k_range is None else k_range
    z_lo, z_hi = (k_min + 0.5) * voxel_size_m, (k_max + 0.5) * voxel_size_m
    return footprint_obb(voxels_outline(ijk, voxel_size_m), z_lo, z_hi, voxel_size_m, gravity.world2gravity, pad_m)


def footprint_obb(
    xy: np.ndarray, z_lo: float, z_hi: float, voxel_size_m: float, world2gravity: np.ndarray, pad_m: float | None = None
) -> OBB:
    """``fit_gravity_obb`` of points whose ground outline is ``xy`` (M, 2) and whose heights span
    ``z_lo``..``z_hi`` (in the gravity frame ``world2gravity``)."""
    hull = convex_hull_2d(xy) if len(xy) <= 64 or _collinear(xy) else xy[ConvexHull(xy).vertices]  # qhull wins beyond ~60 points
    yaw = 0.0
    if len(hull) == 2:  # collinear: the box lies along the line
        dx, dy = hull[1] - hull[0]
        yaw = float(np.mod(np.arctan2(dy, dx), np.pi / 2))
    elif len(hull) >= 3:
        yaw = min_area_yaw(hull)
    c, s = math.cos(yaw), math.sin(yaw)
    yaw_rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # box2gravity
    (x_lo, y_lo), (x_hi, y_hi) = (corner.tolist() for corner in points_extent(xy @ yaw_rotation[:2, :2]))
    half = voxel_size_m / 2 if pad_m is None else pad_m
    lo, hi = at_least_floats(
        [x_lo - half, y_lo - half, z_lo - half], [x_hi + half, y_hi + half, z_hi + half], voxel_size_m
    )  # Python floats: numpy's cost per call is most of the work on three numbers
    box2world = world2gravity.T @ yaw_rotation
    center = box2world @ np.array([(low + h) / 2 for low, h in zip(lo, hi)])
    return OBB(center=center, size=np.array([h - low for low, h in zip(lo, hi)]), rotation=box2world, yaw_rad=yaw)


def min_area_yaw(hull: np.ndarray) -> float:
    """The yaw in [0, pi/2) of the smallest-area rectangle around a convex polygon (H, 2), H >= 3, of
    finite points (rotating calipers: a side of that rectangle lies along an edge); the first such
    edge angle in increasing order on ties. The angles and their sines and cosines by numpy, the
    rectangles by Python floats (a few points and angles: numpy's cost per call would dominate)."""
    edges = np.concatenate((hull[1:], hull[:1])) - hull  # each point to the next, wrapping (np.roll costs 4x)
    # Sorted unique angles (np.mod by a positive divisor gives no -0.0, so equal means identical).
    angles = sorted(set(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2).tolist()))
    at = np.array(angles)
    points = hull.tolist()
    best_area, yaw = math.inf, angles[0]
    for angle, c, s in zip(angles, np.cos(at).tolist(), np.sin(at).tolist()):
        along = [x * c + y * s for x, y in points]  # the hull in the candidate frame, axis by axis
        across = [-x * s + y * c for x, y in points]
        area = (max(along) - min(along)) * (max(across) - min(across))
        if area < best_area:
            best_area, yaw = area, angle
    return yaw


def min_area_yaw_plain(hull: np.ndarray) -> float:
    """``min_area_yaw`` all in numpy: every candidate frame's coordinates (A, H) at once."""
    edges = np.concatenate((hull[1:], hull[:1])) - hull
    angles = sorted_unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), np.pi / 2))
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    u = hull[:, 0] * c + hull[:, 1] * s
    v = -hull[:, 0] * s + hull[:, 1] * c
    return float(angles[np.argmin(np.ptp(u, axis=1) * np.ptp(v, axis=1))])


def aligned_vertical(params: Params) -> tuple[int, float] | None:
    """The axis of the frame boxes are fitted in (``world2aligned``, else the world) that points up or down, and
    +1 (up) or -1 (down); None when none is within about 8 degrees of up."""
    to_aligned = np.eye(3) if params.world2aligned is None else np.asarray(params.world2aligned, np.float64)[:3, :3]
    aligned_up = to_aligned @ params.gravity.up
    axis = int(np.argmax(np.abs(aligned_up)))
    return (axis, float(np.sign(aligned_up[axis]))) if abs(aligned_up[axis]) >= 0.99 else None


def to_aligned(points: np.ndarray, params: Params) -> np.ndarray:
    """World points (..., 3) in the frame boxes are fitted in (``world2aligned``, else the world)."""
    if params.world2aligned is None:
        return points
    world2aligned = np.asarray(params.world2aligned, np.float64)
    return points @ world2aligned[:3, :3].T + world2aligned[:3, 3]


def reach_floor(aabb: AABB, obb: OBB, floor_m: float, params: Params) -> tuple[AABB, OBB]:
    """The boxes of a floor-standing object extended down to the floor at height ``floor_m`` (along
    ``params.up``), when the gap is at most ``floor_reach_max_m``: legs are thin and often hidden (under a
    table, behind a seat), but the object stands on the floor. ``aabb`` is in the ``world2aligned``
    frame (moved where one of its axes is vertical: ``aligned_vertical``); ``obb`` is gravity-aligned."""
    up = params.gravity.up
    bottom_world = obb.center - up * obb.size[2] / 2
    gap = float(up @ bottom_world) - floor_m
    if not 0 < gap <= params.floor_reach_max_m:
        return aabb, obb
    grown = obb.size.copy()
    grown[2] += gap
    obb = OBB(center=obb.center - up * gap / 2, size=grown, rotation=obb.rotation, yaw_rad=obb.yaw_rad)
    vertical = aligned_vertical(params)
    if vertical is not None:
        axis, rise = vertical
        floor_at = float(to_aligned(bottom_world - up * gap, params)[axis])
        lo, hi = aabb.min.copy(), aabb.max.copy()
        if rise > 0:
            lo[axis] = min(lo[axis], floor_at)
        else:
            hi[axis] = max(hi[axis], floor_at)
        aabb = AABB(lo, hi)
    return aabb, obb


#: A chair tucked under a table shows its back above the top while its seat and legs hide beneath: its box is a
#: thin slab beside the table. A seat is about as deep as it is wide, and a chair at a table faces it, so such a box
#: reaches under the table (``reach_under``) when its shorter side is under ``TUCKED_THIN_SHARE`` of its longer.
TUCKED_UNDER: dict[str, str] = {"chair": "table"}
TUCKED_THIN_SHARE = 0.6
TUCKED_GAP_VOXELS = 2  # the slab's face at most this many voxels from the table's edge (or over it)


def tucked_slab(obj: MapObject, params: Params) -> bool:
    """Whether ``reach_under`` looks for a table for ``obj``: a boxed object of a ``TUCKED_UNDER`` class whose box
    is a slab (its shorter horizontal side under ``TUCKED_THIN_SHARE`` of its longer), in a frame with an axis up."""
    if obj.label not in TUCKED_UNDER or obj.aabb is None or obj.obb is None or (vertical := aligned_vertical(params)) is None:
        return False
    depth, width = sorted(float(v) for axis, v in enumerate(obj.aabb.size) if axis != vertical[0])
    return depth < TUCKED_THIN_SHARE * width


def reach_under(objects: Sequence[MapObject], around: Sequence[MapObject], params: Params) -> list[MapObject]:
    """``objects`` with each ``tucked_slab``'s boxes reaching under the confirmed table of ``around`` it stands
    against: along its shorter side, toward the table, to as deep as it is wide but no further than the table's far
    edge. The table spans at least half its width, its top is no higher than the chair's, and the chair starts
    outside it; of several, the one spanning most of its width."""
    tables = [t for t in around if t.label in TUCKED_UNDER.values() and t.confirmed and t.aabb is not None]
    return [_reached_under(obj, tables, params) if tucked_slab(obj, params) else obj for obj in objects]


def _reached_under(obj: MapObject, tables: Sequence[MapObject], params: Params) -> MapObject:
    vertical = aligned_vertical(params)
    assert obj.aabb is not None and obj.obb is not None and vertical is not None  # a tucked_slab
    axis, rise = vertical
    lo, hi = obj.aabb.min, obj.aabb.max
    thin, wide = sorted((a for a in range(3) if a != axis), key=lambda a: float(hi[a] - lo[a]))
    width = float(hi[wide] - lo[wide])
    gap = TUCKED_GAP_VOXELS * params.voxel_size_m
    top = max(rise * lo[axis], rise * hi[axis])
    best: tuple[float, float, float] | None = None  # (width shared, the face reached, +1 or -1 along thin)
    for table in tables:
        assert table.aabb is not None
        t_lo, t_hi = table.aabb.min, table.aabb.max
        shared = min(hi[wide], t_hi[wide]) - max(lo[wide], t_lo[wide])
        if table.label != TUCKED_UNDER[obj.label] or shared < width / 2 or max(rise * t_lo[axis], rise * t_hi[axis]) > top:
            continue
        if lo[thin] < t_lo[thin] and hi[thin] >= t_lo[thin] - gap:
            candidate = (shared, min(lo[thin] + width, t_hi[thin]), 1.0)
        elif hi[thin] > t_hi[thin] and lo[thin] <= t_hi[thin] + gap:
            candidate = (shared, max(hi[thin] - width, t_lo[thin]), -1.0)
        else:
            continue
        if best is None or candidate[0] > best[0]:
            best = candidate
    if best is None:
        return obj
    _, face, side = best
    new_lo, new_hi = lo.copy(), hi.copy()
    reach = face - hi[thin] if side > 0 else lo[thin] - face
    if reach <= 0:  # the table's far edge is nearer than the slab's face
        return obj
    (new_hi if side > 0 else new_lo)[thin] = face
    # The oriented box (axis 2 up) grows along its horizontal axis nearest the direction reached in, as far as
    # takes its face as far along that direction.
    toward = np.eye(3)[thin] * side
    if params.world2aligned is not None:
        toward = np.asarray(params.world2aligned, np.float64)[:3, :3].T @ toward
    along = obj.obb.rotation[:, :2].T @ toward  # cosines with the box's two horizontal axes
    k = int(np.argmax(np.abs(along)))
    grow = reach / abs(float(along[k]))
    size = obj.obb.size.copy()
    size[k] += grow
    center = obj.obb.center + obj.obb.rotation[:, k] * np.sign(along[k]) * grow / 2
    obb = OBB(center=center, size=size, rotation=obj.obb.rotation, yaw_rad=obj.obb.yaw_rad)
    return obj.replace(aabb=AABB(new_lo, new_hi), obb=obb)


def refine(obj: MapObject, params: Params) -> MapObject:
    """Prune noisy voxels, then derive label, score, bounds and boxes. An object left without voxels
    comes back empty (the caller deletes it)."""
    return refine_all([obj], params)[0]


def refine_all(objects: Sequence[MapObject], params: Params) -> list[MapObject]:
    """``refine`` of each object, their box voxels found together (``box_voxel_masks``)."""
    pruned = [prune_voxels(obj, params) for obj in objects]
    live = [obj for obj in pruned if obj.keys.size]
    ijks = [unpack_keys(obj.keys) for obj in live]  # once: the component filter, the box's centres and the bounds use it
    floors = [floor_height(obj.floor_votes, params) for obj in live]
    walls = [screen_wall(obj, params) for obj in live]
    fitted = iter(zip(ijks, floors, box_voxel_masks(live, params, ijks, floors, walls)))
    return [
        _boxed(obj, params, *next(fitted))
        if obj.keys.size
        else obj.replace(label="", score=0.0, aabb=None, obb=None, bounds=None, confirmed=False)
        for obj in pruned
    ]


def screen_wall(obj: MapObject, params: Params) -> Wall | None:
    """The wall behind an object labelled one of ``params.wall_classes`` (``core.walls.object_wall``), or None."""
    if not obj.wall_votes or params.wall_margin_m is None or CLASSES[object_label_index(obj)] not in params.wall_classes:
        return None
    return object_wall(obj.wall_votes, obj.n_frames, params.gravity)


def _boxed(obj: MapObject, params: Params, ijk: np.ndarray, floor_m: float | None, box_mask: np.ndarray) -> MapObject:
    """A pruned non-empty object's label, score, bounds and boxes, from its voxels' indices ``ijk``, its floor and
    its ``box_voxel_mask``."""
    if not box_mask.any():  # no voxel is solid enough yet: box what there is
        box_mask = np.ones(obj.keys.size, bool)
    voxel_labels = obj.votes.argmax(axis=1)  # once: the label and its purity use it
    label_index = object_label_index(obj, voxel_labels)
    box_ijk = ijk[box_mask]
    box_lo, box_hi = (corner.tolist() for corner in ijk_extent(box_ijk))
    size_m, pad_m = params.voxel_size_m, params.box_pad_voxels * params.voxel_size_m
    if params.world2aligned is not None:
        aabb = fit_aabb(to_aligned(ijk_centers(box_ijk, size_m), params), pad_m, size_m)
    else:
        aabb = fit_voxels_aabb(box_lo, box_hi, size_m, pad_m)
    obb = fit_voxels_obb(box_ijk, size_m, params.gravity, pad_m, (box_lo[2], box_hi[2]))
    lo, hi = ijk_bounds(ijk, size_m)
    label = CLASSES[label_index]
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
