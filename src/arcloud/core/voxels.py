"""Voxel keys and back-projection: masks with depth and a pose -> world voxels.

A voxel is addressed by integer indices (i, j, k) = floor(xyz / voxel_size_m), packed into one int64
key with 21 bits per axis (offset 2**20), which spans +-52 km at 5 cm. Packed keys sort by (i, j, k).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from arcloud.core.gravity import Gravity
from arcloud.core.types import CLASS_INDEX, Detection, Frame, Params, VoxelDetection, WallVote
from arcloud.core.walls import Wall, wall_vote

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1


def pack_keys(ijk: np.ndarray) -> np.ndarray:
    """(N, 3) integer voxel indices -> (N,) int64 keys."""
    shifted = np.asarray(ijk, dtype=np.int64) + KEY_OFFSET
    if shifted.size and (shifted.min() < 0 or shifted.max() > KEY_MASK):
        raise ValueError(f"voxel indices outside +-{KEY_OFFSET}: {ijk.min()}..{ijk.max()}")
    return (shifted[:, 0] << (2 * KEY_BITS)) | (shifted[:, 1] << KEY_BITS) | shifted[:, 2]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 keys -> (N, 3) int64 voxel indices."""
    keys = np.asarray(keys, dtype=np.int64)
    ijk = np.empty((keys.size, 3), np.int64)
    ijk[:, 0] = keys >> (2 * KEY_BITS)
    ijk[:, 1] = keys >> KEY_BITS
    ijk[:, 2] = keys
    ijk &= KEY_MASK  # all fields at once, then the offset, in place (no temporaries)
    ijk -= KEY_OFFSET
    return ijk


def points_to_keys(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(N, 3) points in metres -> (N,) keys of the voxels holding them (not unique)."""
    return pack_keys(np.floor(points_xyz / voxel_size_m).astype(np.int64))


def key_centers(keys: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(N,) keys -> (N, 3) voxel centres in metres."""
    return ijk_centers(unpack_keys(keys), voxel_size_m)


def ijk_centers(ijk: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(N, 3) voxel indices -> (N, 3) voxel centres in metres (``key_centers`` of unpacked keys)."""
    return (ijk + 0.5) * voxel_size_m


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """(M,) sorted unique values of a 1-D array (N,): what ``np.unique`` returns (its plain version; a
    test holds them equal), by a sort and a comparison of neighbours, which costs a fraction of
    ``np.unique``'s hash pass on a few thousand keys."""
    ordered = np.sort(values)
    if ordered.size < 2:
        return ordered
    first = np.empty(ordered.size, bool)
    first[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    return ordered[first]


def in_sorted(values: np.ndarray, ordered: np.ndarray) -> np.ndarray:
    """(N,) bool: which of ``values`` (N,) are among ``ordered`` (sorted unique): ``np.isin``'s answer (its
    plain version; a test holds them equal) by a binary search, which costs a fraction of ``np.isin``'s
    sorting of both arrays together."""
    if ordered.size == 0:
        return np.zeros(np.shape(values), bool)
    at = np.searchsorted(ordered, values)
    np.minimum(at, ordered.size - 1, out=at)
    return ordered[at] == values


#: Cells of ``nearness``'s dense grid, at most (2 MB): past it, a set's stray voxel metres off would cost the grid's
#: whole extent (a 20 m cube: 125 MB, 0.4 s).
NEARNESS_GRID_CELLS = 2_000_000


def crop_index(keys: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Positions (ascending) of the keys (sorted) whose voxel indices lie within ``lo``..``hi`` (3,) on every axis:
    packed keys sort by their first index, so its range is one slice found by binary search; the other two are
    masked. Bounds past the packable range are clipped to it."""
    lo = np.maximum(lo, -KEY_OFFSET)
    hi = np.minimum(hi, KEY_MASK - KEY_OFFSET)
    start = int(np.searchsorted(keys, np.int64(lo[0] + KEY_OFFSET) << (2 * KEY_BITS)))
    top = hi[0] + 1 + KEY_OFFSET  # the first index past the range (past the last packable one: every key is before it)
    stop = keys.size if top > KEY_MASK else int(np.searchsorted(keys, np.int64(top) << (2 * KEY_BITS)))
    part = keys[start:stop]
    second = (part >> KEY_BITS) & KEY_MASK
    third = part & KEY_MASK
    inside = (second >= lo[1] + KEY_OFFSET) & (second <= hi[1] + KEY_OFFSET)
    inside &= (third >= lo[2] + KEY_OFFSET) & (third <= hi[2] + KEY_OFFSET)
    return start + np.flatnonzero(inside)


def nearness(
    keys: np.ndarray, others: np.ndarray, reach: int, extents: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """(N,) uint8: 2 where a key of ``keys`` (sorted unique) lies on a voxel of ``others`` (sorted unique), 1 where
    it lies only beside one (within ``reach`` voxels along every axis), else 0. It does not depend on where the
    world's grid falls (coarsened keys would: two voxels side by side share a coarse voxel only when they fall in
    the same aligned pair). ``extents``: the sets' known (lo, hi) voxel indices (or larger), keys' then others'.
    Keys on the other set are found by binary search; those beside it in a dense grid of the other set grown by
    ``reach``, or where that grid would exceed ``NEARNESS_GRID_CELLS``, by a binary search at every step."""
    out = np.zeros(keys.size, np.uint8)
    if not keys.size or not others.size:
        return out
    lo_k, hi_k, lo_o, hi_o = extents if extents is not None else (*keys_extent(keys), *keys_extent(others))
    lo, hi = np.maximum(lo_k, lo_o - reach), np.minimum(hi_k, hi_o + reach)
    if np.any(lo > hi):
        return out
    at = crop_index(keys, lo, hi)
    near = keys[at]
    around = others[crop_index(others, lo - reach, hi + reach)]
    on = in_sorted(near, around)
    out[at[on]] = 2
    if reach == 0 or on.all() or not around.size:
        return out
    beside = at[~on]
    shape = hi - lo + 1 + 2 * reach
    if math.prod(shape.tolist()) <= NEARNESS_GRID_CELLS:
        # A grid over lo - reach .. hi + reach holding the other set grown by ``reach``.
        origin = lo - reach
        grid = np.zeros(shape, bool)
        grid[tuple((unpack_keys(around) - origin).T)] = True
        grid = ndimage.maximum_filter(grid, size=2 * reach + 1, mode="constant")
        out[beside] = grid[tuple((unpack_keys(keys[beside]) - origin).T)]
        return out
    # Sets whose extents are large for their voxels (a stray voxel metres off): each key left is looked up at
    # every step within ``reach``, slower for compact sets, bounded by the keys.
    ijk = unpack_keys(keys[beside])
    hit = np.zeros(beside.size, bool)
    for step in itertools.product(range(-reach, reach + 1), repeat=3):
        moved = ijk + step
        open_ = ~hit & np.all((moved >= -KEY_OFFSET) & (moved <= KEY_MASK - KEY_OFFSET), axis=1)
        hit[open_] = in_sorted(pack_keys(moved[open_]), around)
    out[beside[hit]] = 1
    return out


def shared_count(
    keys: np.ndarray, others: np.ndarray, reach: int, extents: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
) -> float:
    """How much of ``keys`` the other set covers: a key on a voxel of ``others`` counts 1, one only beside it
    (``nearness``) a half, about how often the two would share a coarse voxel of twice the size over the grid's
    phases (always where they are one voxel, half the time where they are side by side). Sheets one voxel
    apart share half of themselves wherever the grid falls."""
    return int(nearness(keys, others, reach, extents).sum(dtype=np.int64)) / 2


def coarsen_keys(keys: np.ndarray, factor: int) -> np.ndarray:
    """Sorted unique keys of the ``factor``-times coarser voxels holding ``keys``: ``coarsen_keys_plain``,
    without unpacking when ``factor`` is a power of two (a test holds them equal)."""
    if factor == 1:
        return keys
    shift = factor.bit_length() - 1
    if factor != 1 << shift or shift >= KEY_BITS - 1:
        return coarsen_keys_plain(keys, factor)
    # A power of two divides the offset 2**20, so on each packed field s = i + 2**20 the coarse field is
    # floor(i / factor) + 2**20 = (s >> shift) + 2**20 - 2**(20 - shift): one shift of the whole key,
    # the bits that slid into a lower field cleared, and a constant added (no field overflows).
    low_bits = (1 << shift) - 1
    slid = np.int64((low_bits << (KEY_BITS - shift)) | (low_bits << (2 * KEY_BITS - shift)))
    offset = KEY_OFFSET - (KEY_OFFSET >> shift)
    add = np.int64(offset | (offset << KEY_BITS) | (offset << (2 * KEY_BITS)))
    coarse = np.right_shift(np.asarray(keys, np.int64), shift)
    coarse &= ~slid
    coarse += add
    return sorted_unique(coarse)


def coarsen_keys_plain(keys: np.ndarray, factor: int) -> np.ndarray:
    """Sorted unique keys of the ``factor``-times coarser voxels holding ``keys``: unpack, divide, pack."""
    return sorted_unique(pack_keys(np.floor_divide(unpack_keys(keys), factor)))


def coarsen_keys_unsorted(keys: np.ndarray, factor: int) -> np.ndarray:
    """(N,) keys of the ``factor``-times coarser voxel holding each key, in the order of ``keys``."""
    if factor == 1:
        return np.asarray(keys, np.int64)
    return pack_keys(np.floor_divide(unpack_keys(keys), factor))


def ground_cells(keys: np.ndarray, params: Params) -> np.ndarray:
    """Sorted unique ids of the ground cells (one voxel wide, across ``params.up``) under voxels ``keys`` (N,)."""
    ground = key_centers(keys, params.voxel_size_m) @ params.gravity.world2gravity[:2].T
    cells = np.zeros((keys.size, 3), np.int64)
    cells[:, :2] = np.floor(ground / params.voxel_size_m)
    return sorted_unique(pack_keys(cells))


def footprint_share(keys_a: np.ndarray, keys_b: np.ndarray, params: Params, reach_voxels: int | None = None) -> float:
    """The share of the smaller of two voxel sets' footprints (``ground_cells``) that lies on the other's
    or within ``reach_voxels`` (default ``association_tolerance_voxels``) of it: pieces of one object seen from
    different sides (a chair's back, its seat) stand on one footprint; neighbours side by side stand on two that
    meet, if at all, along an edge."""
    small, large = sorted((ground_cells(keys_a, params), ground_cells(keys_b, params)), key=len)
    if not small.size:
        return 0.0
    tolerance = params.association_tolerance_voxels if reach_voxels is None else reach_voxels
    reach = range(-tolerance, tolerance + 1)
    cells = unpack_keys(large)
    near = sorted_unique(np.concatenate([pack_keys(cells + (di, dj, 0)) for di in reach for dj in reach]))
    return np.count_nonzero(in_sorted(small, near)) / small.size


def keys_bounds(keys: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Outer (min, max) corners in metres of the voxels ``keys`` (non-empty)."""
    lo, hi = keys_extent(keys)
    return lo * voxel_size_m, (hi + 1) * voxel_size_m


def ijk_bounds(ijk: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Outer (min, max) corners in metres of the voxels at indices ``ijk`` (N, 3), N > 0."""
    lo, hi = ijk_extent(ijk)
    return lo * voxel_size_m, (hi + 1) * voxel_size_m


def ijk_extent(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) (3,) each of integer voxel indices ``ijk`` (N, 3), N > 0: ``ijk.min(axis=0)`` and
    ``ijk.max(axis=0)``, reduced along the rows of a transposed copy (a reduction down the columns of an
    (N, 3) array costs several times more: 25 us against 3 at N = 2000)."""
    columns = np.ascontiguousarray(ijk.T)
    return columns.min(axis=1), columns.max(axis=1)


def points_extent(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``points.min(axis=0)`` and ``points.max(axis=0)`` of float points (N, D), N > 0, reduced as
    ``ijk_extent`` does. A minimum that is not zero (nor NaN) is one value whatever the order of the
    comparisons; where one is (a minimum of -0.0 and +0.0 keeps whichever it met first), the axis
    reductions themselves."""
    lo, hi = ijk_extent(points)
    if all(v != 0 and v == v for v in lo.tolist() + hi.tolist()):
        return lo, hi
    return points.min(axis=0), points.max(axis=0)


def keys_extent(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``ijk_extent(unpack_keys(keys))`` of non-empty keys, without unpacking them all: packed keys sort
    by their first index, so the smallest and largest keys hold its extent; the other two fields are
    masked out one at a time."""
    keys = np.asarray(keys, dtype=np.int64)
    first = np.array((keys.min(), keys.max())) >> (2 * KEY_BITS)
    second = (keys >> KEY_BITS) & KEY_MASK
    third = keys & KEY_MASK
    lo = np.array((first[0], second.min(), third.min()))
    hi = np.array((first[1], second.max(), third.max()))
    lo -= KEY_OFFSET
    hi -= KEY_OFFSET
    return lo, hi


def erode(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """Binary erosion by a (2r+1)^2 square (outside the array counts as background): a separable
    minimum, rows then columns (``ndimage.binary_erosion`` with ``border_value=0`` is its plain version;
    a test holds them equal)."""
    if radius_px <= 0:
        return mask
    return eroded_lines(eroded_lines(mask, radius_px, 0, 1), radius_px, 1, 1)


def erode_sampled(mask: np.ndarray, radius_px: int, stride_px: int) -> np.ndarray:
    """``erode(mask, radius_px)[::stride_px, ::stride_px]`` (its plain version; a test holds them
    equal), eroding along columns only the rows kept.

    The square's minimum is separable, so filtering along rows, keeping every n-th row, then filtering
    along columns gives the same booleans as the full erosion sampled afterwards."""
    if radius_px <= 0:
        return mask[::stride_px, ::stride_px]
    return eroded_lines(eroded_lines(mask, radius_px, 0, stride_px), radius_px, 1, stride_px)


def eroded_lines(mask: np.ndarray, radius_px: int, axis: int, stride_px: int) -> np.ndarray:
    """Every ``stride_px``-th line across ``axis`` of an (H, W) bool mask, eroded along ``axis`` by
    ``2 * radius_px + 1`` pixels (outside the array counts as background): the AND of the lines within
    ``radius_px`` of it. A few ANDs of shifted slices of the padded mask cost a fraction of
    ``ndimage.minimum_filter1d``, which copies every line into a buffer of doubles and back."""
    n = mask.shape[axis]
    padded_shape = list(mask.shape)
    padded_shape[axis] = n + 2 * radius_px
    padded = np.zeros(padded_shape, bool)

    across = (slice(None),) * axis  # the index of a line along ``axis``: (along,) or (:, along)
    padded[(*across, slice(radius_px, radius_px + n))] = mask
    eroded = padded[(*across, slice(0, n, stride_px))].copy()
    for offset in range(1, 2 * radius_px + 1):
        eroded &= padded[(*across, slice(offset, offset + n, stride_px))]
    return eroded


Extent = tuple[int, int, int, int]  # a mask's (row0, row1, col0, col1), ends exclusive (``mask_extent``)


def mask_extent(mask: np.ndarray) -> Extent | None:
    """The bounding box (row0, row1, col0, col1), ends exclusive, of an (H, W) bool mask's pixels; None
    when it has none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    cols = np.flatnonzero(mask[r0:r1].any(axis=0))  # only the rows that hold it: one pass over the mask
    return r0, r1, int(cols[0]), int(cols[-1]) + 1


Samples = tuple[np.ndarray, np.ndarray, np.ndarray]  # v_px (N,), u_px (N,) depth pixels and z_m (N,)


def mask_samples(frame: Frame, mask: np.ndarray, params: Params, stride_px: int = 1, extent: Extent | None = None) -> Samples:
    """The depth samples (every ``stride_px``-th row and column) under a mask of a registered frame,
    after eroding the mask's border, with depth in range. Works on the mask's bounding box only
    (``extent``: its ``mask_extent``, when the caller has it)."""
    extent = extent or mask_extent(mask)
    if extent is None:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0)
    r0, r1, c0, c1 = extent
    crop = erode_sampled(mask[r0:r1, c0:c1], params.erode_px, stride_px)
    depth = frame.depth_m[r0:r1:stride_px, c0:c1:stride_px]
    keep = crop & (depth >= params.depth_min_m) & (depth <= params.depth_max_m)
    v, u = np.nonzero(keep)
    return v * stride_px + r0, u * stride_px + c0, depth[v, u].astype(np.float64)


def back_project(frame: Frame, v_px: np.ndarray, u_px: np.ndarray, z_m: np.ndarray) -> np.ndarray:
    """World points (N, 3) of depth pixels (v_px, u_px) at depths z_m."""
    intr = frame.intrinsics
    points_cam = np.empty((z_m.size, 3))  # filled column by column: np.stack's wrapper costs more
    points_cam[:, 0] = (u_px - intr.cx) * z_m / intr.fx
    points_cam[:, 1] = (v_px - intr.cy) * z_m / intr.fy
    points_cam[:, 2] = z_m
    return points_cam @ frame.cam2world[:3, :3].T + frame.cam2world[:3, 3]


def mask_points(frame: Frame, mask: np.ndarray, params: Params, stride_px: int = 1) -> np.ndarray:
    """World points (N, 3) of the mask's pixels with valid depth, after eroding the mask's border."""
    return back_project(frame, *mask_samples(frame, mask, params, stride_px))


@dataclass(frozen=True, eq=False, slots=True)
class RegisteredSamples:
    """The depth samples of an unregistered frame (every ``stride_px``-th pixel with depth in range),
    with the colour pixel each one lands on: v_px, u_px (N,) depth pixel; z_m (N,); rgb_v_px, rgb_u_px
    (N,) int, the colour pixel (samples landing outside the colour image are left out)."""

    stride_px: int
    v_px: np.ndarray
    u_px: np.ndarray
    z_m: np.ndarray
    rgb_v_px: np.ndarray
    rgb_u_px: np.ndarray


def register_samples(frame: Frame, params: Params, stride_px: int) -> RegisteredSamples:
    """Project the frame's strided depth samples into its colour image (``Frame.rgb_intrinsics``,
    ``Frame.depth2rgb``): each measured point is looked up where the colour camera saw it."""
    depth = frame.depth_m[::stride_px, ::stride_px]
    v, u = np.nonzero((depth >= params.depth_min_m) & (depth <= params.depth_max_m))
    z = depth[v, u].astype(np.float64)
    v, u = v * stride_px, u * stride_px
    intr = frame.intrinsics
    points = np.stack(((u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z), axis=1)
    if frame.depth2rgb is not None:
        points = points @ frame.depth2rgb[:3, :3].T + frame.depth2rgb[:3, 3]
    rgb = frame.rgb_intrinsics or intr
    height, width = frame.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        rgb_u = np.floor(points[:, 0] * rgb.fx / points[:, 2] + rgb.cx + 0.5)
        rgb_v = np.floor(points[:, 1] * rgb.fy / points[:, 2] + rgb.cy + 0.5)
    inside = np.flatnonzero((points[:, 2] > 0) & (rgb_u >= 0) & (rgb_u < width) & (rgb_v >= 0) & (rgb_v < height))
    rgb_v, rgb_u = rgb_v[inside].astype(np.int64), rgb_u[inside].astype(np.int64)
    # The colour camera sees only the nearest of the samples that land on one patch of its image: past
    # a depth edge, the two cameras see different things. Patches twice the samples' spacing there, so
    # that every patch of a surface holds a sample of it.
    patch_px = int(math.ceil(2 * stride_px * max(1.0, rgb.fx / intr.fx, rgb.fy / intr.fy)))
    cell = (rgb_v // patch_px) * (width // patch_px + 1) + rgb_u // patch_px
    range_m = points[inside, 2]
    nearest = np.full(int(cell.max()) + 1 if cell.size else 0, np.inf)
    np.minimum.at(nearest, cell, range_m)
    seen = range_m <= nearest[cell] + params.layer_jump_m + params.layer_jump_rel * range_m
    keep = inside[seen]
    return RegisteredSamples(stride_px, v[keep], u[keep], z[keep], rgb_v[seen], rgb_u[seen])


def registered_mask_indices(
    mask: np.ndarray, params: Params, samples: RegisteredSamples, extent: Extent | None = None
) -> np.ndarray:
    """Indices (ascending) into ``samples`` of the depth samples whose colour pixel lies in the mask (eroded by
    ``params.erode_px`` in the colour image); ``extent``: the mask's ``mask_extent``, when the caller has it."""
    extent = extent or mask_extent(mask)
    if extent is None:
        return np.empty(0, np.int64)
    r0, r1, c0, c1 = extent
    crop = erode(mask[r0:r1, c0:c1], params.erode_px)
    near = np.flatnonzero((samples.rgb_v_px >= r0) & (samples.rgb_v_px < r1) & (samples.rgb_u_px >= c0) & (samples.rgb_u_px < c1))
    return near[crop[samples.rgb_v_px[near] - r0, samples.rgb_u_px[near] - c0]]


def mean_colors(color_sums: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N, 3) uint8: weighted colour sums, channel first (3, N) float64, over their weights (N,) (> 0),
    rounded half up; ``color_sums`` is overwritten. (The result is a transposed view: (N, 3), not
    C-contiguous; channel first is what the sums are fastest to gather in.)"""
    color_sums /= weights
    color_sums += 0.5
    return np.floor(color_sums, out=color_sums).astype(np.uint8).T


def voxel_colors(sample_keys: np.ndarray, keys: np.ndarray, sample_rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8: the mean colour of the samples in each voxel of ``keys`` (N,) sorted unique, from
    each sample's voxel key (M,) (all among ``keys``) and colour (M, 3): one bincount per channel."""
    at = np.searchsorted(keys, sample_keys)
    channels = sample_rgb.T.astype(np.float64)  # (3, M), each channel contiguous
    # One bincount for the three channels: channel c's voxel k is bin c * N + k (each bin sums its
    # samples in their order, as a bincount per channel does).
    bins = np.concatenate((at, at + keys.size, at + 2 * keys.size))
    sums = np.bincount(bins, weights=channels.reshape(-1), minlength=3 * keys.size).reshape(3, keys.size)
    return mean_colors(sums, np.bincount(at, minlength=keys.size))


def depth_jumps(z_grid: np.ndarray, params: Params) -> tuple[np.ndarray, np.ndarray] | None:
    """Where neighbouring depth samples (along rows, then columns) of a grid, NaN where there is no
    sample, differ by more than ``layer_jump_m + layer_jump_rel * depth``; None when nowhere (NaN
    compares False: no jump)."""

    def threshold(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.abs(a - b) > params.layer_jump_m + params.layer_jump_rel * np.minimum(a, b)

    along_rows, along_cols = threshold(z_grid[:, :-1], z_grid[:, 1:]), threshold(z_grid[:-1], z_grid[1:])
    return (along_rows, along_cols) if along_rows.any() or along_cols.any() else None


def depth_layers(z_grid: np.ndarray, jumps: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, int]:
    """Regions of a mask's depth samples, (h, w) with NaN where there is no sample: neighbours (4-way)
    join unless there is a jump between them (``depth_jumps``); at a jump the farther sample is left out
    (it is background seen past an edge, or a mixed pixel). Returns the labels (h, w) (0: none) and
    their count."""
    along_rows, along_cols = jumps
    edge = np.zeros(z_grid.shape, bool)
    edge[:, :-1] |= along_rows & (z_grid[:, :-1] > z_grid[:, 1:])
    edge[:, 1:] |= along_rows & (z_grid[:, 1:] > z_grid[:, :-1])
    edge[:-1] |= along_cols & (z_grid[:-1] > z_grid[1:])
    edge[1:] |= along_cols & (z_grid[1:] > z_grid[:-1])
    labels, n = ndimage.label(~np.isnan(z_grid) & ~edge)
    return labels, int(n)


def front_samples(
    v_px: np.ndarray, u_px: np.ndarray, z_m: np.ndarray, stride_px: int, params: Params, points: np.ndarray
) -> np.ndarray:
    """(N,) bool: the samples of one mask that belong to the object, not to what lies behind it.

    A mask covers the object and whatever shows through its gaps (the wall between a chair's slats)
    or past its border: that lies *behind* the object, across a depth jump, and apart from it. Without
    any jump all samples are kept; else they are split into depth layers (``depth_layers``), and the
    object's layer is the nearest (by mean depth) of the large ones (at least ``layer_min_fraction`` of
    the largest). A layer is dropped when it lies deeper than that layer's 90th percentile depth plus
    ``layer_margin_m`` and does not touch the object in space (no point within the same
    ``layer_touch_m`` cell as a point of a kept layer): the far arm of a couch seen end on is deep but
    joined to the rest, the wall behind the slats is not.
    ``points``: (N, 3) the samples' world points."""
    if z_m.size == 0:
        return np.zeros(0, bool)
    rows, cols = v_px // stride_px, u_px // stride_px
    r0, c0 = rows.min(), cols.min()
    grid = np.full((rows.max() - r0 + 1, cols.max() - c0 + 1), np.nan, np.float32)
    grid[rows - r0, cols - c0] = z_m
    jumps = depth_jumps(grid, params)
    if jumps is None:  # one surface, however many pieces: nothing lies behind anything
        return np.ones(z_m.size, bool)
    labels, n = depth_layers(grid, jumps)
    label_of = labels[rows - r0, cols - c0]
    if n <= 1:
        return label_of > 0
    sizes = np.bincount(label_of, minlength=n + 1)[1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.bincount(label_of, weights=z_m, minlength=n + 1)[1:] / sizes
    large = np.flatnonzero(sizes >= params.layer_min_fraction * sizes.max())
    main = large[np.argmin(means[large])] + 1
    in_main = z_m[label_of == main]
    limit = np.partition(in_main, int(0.9 * (in_main.size - 1)))[int(0.9 * (in_main.size - 1))] + params.layer_margin_m
    kept = np.concatenate(([False], means <= limit))
    if not kept.all():
        kept = _touching_layers(label_of, points, kept, n, params.layer_touch_m)
    return kept[label_of]


def _touching_layers(label_of: np.ndarray, points: np.ndarray, kept: np.ndarray, n: int, touch_m: float) -> np.ndarray:
    """``kept`` (n + 1,) bool over layer labels, grown by every layer that shares a ``touch_m`` cell
    of space with a kept layer, repeatedly."""
    cells = points_to_keys(points, touch_m)
    order = np.lexsort((label_of, cells))
    cell, layer = cells[order], label_of[order]
    joined = np.flatnonzero((cell[1:] == cell[:-1]) & (layer[1:] != layer[:-1]))  # one cell, two layers
    edges = np.stack((layer[joined], layer[joined + 1]), axis=1)
    edges = edges[(edges > 0).all(axis=1)]
    kept = kept.copy()
    while edges.size:
        grow = kept[edges[:, 0]] ^ kept[edges[:, 1]]
        if not grow.any():
            break
        kept[edges[grow].ravel()] = True
    return kept


#: The wall behind a screen (``wall_plane``): a vertical plane that at least ``WALL_MIN_SHARE`` of the depth
#: samples in a ring around the mask (``WALL_RING_PX`` pixels out, for an image 640 pixels wide) lie within
#: ``WALL_INLIER_M`` of, the best of ``WALL_TRIALS`` lines through two of at most ``WALL_MAX_POINTS`` of them.
WALL_RING_PX = (8, 20)
WALL_INLIER_M = 0.03
WALL_MIN_SHARE = 0.4
WALL_TRIALS = 64
WALL_MAX_POINTS = 2000


def ring_points(
    frame: Frame,
    mask: np.ndarray,
    params: Params,
    stride_px: int,
    registered: RegisteredSamples | None,
    extent: Extent | None = None,
) -> np.ndarray:
    """World points (N, 3) of the depth samples that land in a ring around the mask, ``WALL_RING_PX``
    pixels out (scaled with the image's width): what the camera sees around the object. ``extent``:
    the mask's ``mask_extent``, when the caller has it."""
    extent = extent or mask_extent(mask)
    if extent is None:
        return np.empty((0, 3))
    inner, outer = (max(1, round(r * mask.shape[1] / 640)) for r in WALL_RING_PX)
    height, width = mask.shape
    r0, c0 = max(0, extent[0] - outer), max(0, extent[2] - outer)
    r1, c1 = min(height, extent[1] + outer), min(width, extent[3] + outer)
    counts = summed_area(mask[r0:r1, c0:c1])

    def ring(v: np.ndarray, u: np.ndarray) -> np.ndarray:  # v, u: crop pixels (broadcast together)
        return near_mask(counts, v, u, outer) & ~near_mask(counts, v, u, inner)

    if registered is None:
        v, u = np.arange(0, r1 - r0, stride_px), np.arange(0, c1 - c0, stride_px)
        depth = frame.depth_m[r0:r1:stride_px, c0:c1:stride_px]
        v, u = np.nonzero(ring(v[:, None], u[None, :]) & (depth >= params.depth_min_m) & (depth <= params.depth_max_m))
        return back_project(frame, v * stride_px + r0, u * stride_px + c0, depth[v, u].astype(np.float64))
    rgb_v, rgb_u = registered.rgb_v_px, registered.rgb_u_px
    near = np.flatnonzero((rgb_v >= r0) & (rgb_v < r1) & (rgb_u >= c0) & (rgb_u < c1))
    near = near[ring(rgb_v[near] - r0, rgb_u[near] - c0)]
    return back_project(frame, registered.v_px[near], registered.u_px[near], registered.z_m[near])


def summed_area(mask: np.ndarray) -> np.ndarray:
    """(H + 1, W + 1) int32: the summed-area table of an (H, W) bool mask, a zero row and column first
    (entry (v, u) counts the mask's pixels above and left of pixel (v, u))."""
    counts = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), np.int32)
    np.cumsum(mask, axis=0, dtype=np.int32, out=counts[1:, 1:])
    np.cumsum(counts[1:, 1:], axis=1, out=counts[1:, 1:])
    return counts


def near_mask(counts: np.ndarray, v: np.ndarray, u: np.ndarray, radius_px: int) -> np.ndarray:
    """Whether a mask pixel lies within ``radius_px`` (chessboard distance) of each pixel (v, u) (int
    arrays that broadcast together), from the mask's ``summed_area`` table: the count in the square
    around it, clipped to the mask. A square's maximum filter (``ndimage.maximum_filter`` is its plain
    version; a test holds them equal), read only where it is needed."""
    height, width = counts.shape[0] - 1, counts.shape[1] - 1
    top, bottom = np.maximum(v - radius_px, 0), np.minimum(v + radius_px + 1, height)
    left, right = np.maximum(u - radius_px, 0), np.minimum(u + radius_px + 1, width)
    return counts[bottom, right] - counts[top, right] - counts[bottom, left] + counts[top, left] > 0


def wall_plane(points: np.ndarray, gravity: Gravity, eye: np.ndarray) -> Wall | None:
    """The vertical plane most of ``points`` (N, 3) lie on (see ``WALL_MIN_SHARE``), as its horizontal
    unit normal facing the ``eye`` and its offset (``normal @ x == offset`` on it); None when there is
    none, or when the points on it spread less than ``WALL_INLIER_M`` across their main direction (they
    are a line, not a wall). Vertical planes are lines seen from above: RANSAC over pairs of points,
    seeded, so one frame always gives the same plane."""
    if len(points) > WALL_MAX_POINTS:
        points = points[:: -(-len(points) // WALL_MAX_POINTS)]
    n = len(points)
    if n < 2:
        return None
    level, up = gravity.world2gravity[:2], gravity.up  # level: (2, 3), a basis of the horizontal
    flat = points @ level.T  # (N, 2): the points seen from above
    pairs = np.random.default_rng(0).integers(0, n, size=(WALL_TRIALS, 2))
    along = flat[pairs[:, 1]] - flat[pairs[:, 0]]
    length = np.linalg.norm(along, axis=1)
    usable = length > 2 * WALL_INLIER_M
    normals = np.stack((-along[:, 1], along[:, 0]), axis=1) / np.maximum(length, 1e-12)[:, None]
    distances = np.abs(normals @ flat.T - np.einsum("tk,tk->t", normals, flat[pairs[:, 0]])[:, None])  # (trials, N)
    inliers = (distances < WALL_INLIER_M).sum(axis=1) * usable
    best = int(np.argmax(inliers))
    if inliers[best] < max(WALL_MIN_SHARE * n, 3):
        return None
    on_plane = points[distances[best] < WALL_INLIER_M]
    direction = normals[best] @ np.array([[0.0, 1.0], [-1.0, 0.0]]) @ level  # the line's, horizontal
    spread = np.linalg.eigvalsh(np.cov(np.stack((on_plane @ direction, on_plane @ up))))
    if spread[0] < WALL_INLIER_M**2:  # a line (the edge of a floor seen from above, a rail) is no wall
        return None
    normal = normals[best] @ level
    offset = float(np.median(on_plane @ normal))
    return (normal, offset) if normal @ eye >= offset else (-normal, -offset)


def off_wall_samples(
    points: np.ndarray, ring: np.ndarray, eye: np.ndarray, depth_share: float, params: Params
) -> tuple[np.ndarray, Wall | None]:
    """(N,) bool: the samples of a screen's mask (``points`` (N, 3), world) that are not the wall behind it,
    and the plane they were cut at (its unit normal, facing the eye, and offset; None: none were cut).

    A screen's mask takes in the wall past its edge, and a dark screen seen at an angle returns no depth:
    its mask's samples are the wall seen through it. Where the mask's surroundings (``ring``, from
    ``ring_points``) lie on a vertical plane (``wall_plane``), a sample on that plane or behind it, or
    in front of it by less than the screen's own depth off the wall (the median of its samples off the
    plane) less ``wall_screen_depth_m``, at most ``wall_margin_m``, is wall or a mixed pixel between the
    two. They are dropped when most samples are off the wall (``wall_front_share``: the screen stands out
    from it) or the mask has depth on few of its pixels (``depth_share`` below ``wall_depth_share``: the
    screen returned none); otherwise the plane is the object's own face or its neighbour's, and every
    sample is kept."""
    keep_all = np.ones(len(points), bool)
    if params.wall_margin_m is None or len(points) == 0 or len(ring) == 0:
        return keep_all, None
    plane = wall_plane(ring, params.gravity, eye)
    if plane is None:
        return keep_all, None
    normal, offset = plane
    off_wall_m = points @ normal - offset
    face = off_wall_m[off_wall_m > WALL_INLIER_M]
    cut_m = params.wall_margin_m
    if face.size:
        cut_m = min(cut_m, max(WALL_INLIER_M, float(np.median(face)) - params.wall_screen_depth_m))
    off = off_wall_m >= cut_m
    if off.mean() >= params.wall_front_share or depth_share < params.wall_depth_share:
        return off, (normal, offset + cut_m)
    return keep_all, None


def sampling_stride_px(frame: Frame, params: Params) -> int:
    """A pixel stride that still puts several samples in every voxel at the nearest valid depth, at
    most ``params.pixel_stride_max_px``.

    A pixel at depth z spans z / f metres; sampling every n-th pixel keeps >= 2 samples per voxel edge
    while n * z_near / f <= voxel / 2 (z_near: the 5th percentile of every 8th pixel's valid depth)."""
    sample = frame.depth_m[::8, ::8]
    valid = sample[sample >= params.depth_min_m]
    if valid.size == 0:
        return 1
    k = valid.size // 20
    near_m = float(np.partition(valid, k)[k])  # the 5th percentile
    focal = max(frame.intrinsics.fx, frame.intrinsics.fy)
    return int(max(1, min(params.pixel_stride_max_px, np.floor(params.voxel_size_m / 2 * focal / max(near_m, 1e-3)))))


def voxelize_detections(frame: Frame, detections: Sequence[Detection], params: Params) -> list[VoxelDetection]:
    """Each detection's world voxels (sorted unique keys); detections with fewer than
    ``params.min_voxels_per_detection`` voxels are dropped. Order of the survivors is kept.

    Each mask is sampled every n-th pixel row and column (``sampling_stride_px``: 1 to
    ``params.pixel_stride_max_px``) and cleaned with depth: samples of what lies behind or apart from
    the object (``front_samples``), and the wall behind a screen (``off_wall_samples``), are left out.
    Each voxel's colour is the mean of the colour pixels its samples land on (``voxel_colors``)."""
    stride = sampling_stride_px(frame, params)
    registered = None if frame.registered else register_samples(frame, params, stride)
    width = frame.rgb.shape[1]
    rgb_pixels = frame.rgb.reshape(-1, 3)  # (H * W, 3): a pixel by its flat index (a view when contiguous)
    kept: list[tuple[Detection, np.ndarray, np.ndarray, WallVote | None]] = []  # (detection, keys, colours, wall vote)
    extents: list[Extent] = []
    point_sets: list[np.ndarray] = []
    for det in detections:
        extent = mask_extent(det.mask)
        if extent is None:
            continue
        if registered is None:
            v_px, u_px, z_m = mask_samples(frame, det.mask, params, stride, extent)
            rgb_px = v_px * width + u_px
        else:
            near = registered_mask_indices(det.mask, params, registered, extent)
            v_px, u_px, z_m = registered.v_px[near], registered.u_px[near], registered.z_m[near]
            rgb_px = registered.rgb_v_px[near] * width + registered.rgb_u_px[near]
        points = back_project(frame, v_px, u_px, z_m)
        vote = None
        if params.layer_margin_m is not None and z_m.size and det.label in params.layer_classes:
            front = front_samples(v_px, u_px, z_m, stride, params, points)
            points, rgb_px = points[front], rgb_px[front]
        if params.wall_margin_m is not None and z_m.size and det.label in params.wall_classes:
            r0, r1, c0, c1 = extent
            depth_share = z_m.size * stride * stride / max(1, int(np.count_nonzero(det.mask[r0:r1, c0:c1])))
            ring = ring_points(frame, det.mask, params, stride, registered, extent)
            off, cut_at = off_wall_samples(points, ring, frame.cam2world[:3, 3], depth_share, params)
            points, rgb_px = points[off], rgb_px[off]
            vote = None if cut_at is None else wall_vote(*cut_at, params.gravity)
        if len(points) == 0:
            continue
        sample_keys = points_to_keys(points, params.voxel_size_m)
        keys = sorted_unique(sample_keys)
        if keys.size >= params.min_voxels_per_detection:
            kept.append((det, keys, voxel_colors(sample_keys, keys, np.take(rgb_pixels, rgb_px, axis=0)), vote))
            extents.append(extent)
            point_sets.append(points)
    weights = view_weights(frame, extents, point_sets, params, stride)
    return [
        VoxelDetection(CLASS_INDEX[det.label], float(det.score), keys, colors, weight, vote)
        for (det, keys, colors, vote), weight in zip(kept, weights)
    ]


def view_weights(
    frame: Frame, extents: Sequence[Extent], point_sets: Sequence[np.ndarray], params: Params, stride_px: int = 1
) -> list[float]:
    """How well a frame saw each of its detected objects, in (0, 1]: the product of
    - ``view_truncated_weight`` when the mask (its ``mask_extent``, in ``extents``) touches the image border
      (the object is cut off: its mask often takes in what lies beyond the cut, and a part looks like
      another class);
    - the share of the image its samples cover (each ``stride_px`` squared pixels) over
      ``view_full_mask_share``, at most 1 (a few pixels);
    - ``view_far_m`` over the mean distance of its points, at most 1 (far views are coarse);
    - for a flat object (its points' smallest spread well below the middle one), the cosine between its
      normal and the line of sight, scaled into [``view_oblique_min``, 1]: a screen seen edge-on looks
      like a laptop.
    ``point_sets``: each object's (N, 3) world points of its mask's samples (N > 0), taken every
    ``stride_px``-th row and column. The spreads of all objects are found by one eigendecomposition of
    their stacked scatter matrices (a call per object costs several times more inside the step)."""
    height, width = frame.shape
    eye = frame.cam2world[:3, 3]
    weights: list[float] = []
    flat: list[tuple[int, np.ndarray, np.ndarray]] = []  # (index, scatter matrix, mean from the eye)
    for extent, points in zip(extents, point_sets):
        weight = 1.0
        if extent[0] == 0 or extent[1] == height or extent[2] == 0 or extent[3] == width:
            weight *= params.view_truncated_weight
        share = len(points) * stride_px * stride_px / (height * width)
        if params.view_full_mask_share > 0:
            weight *= min(1.0, share / params.view_full_mask_share)
        sample = points[:: max(1, len(points) // 256)] - eye  # from the eye
        distance_m = float(np.sqrt(np.einsum("ij,ij->i", sample, sample)).mean())
        if distance_m > params.view_far_m:
            weight *= params.view_far_m / distance_m
        if params.view_oblique_min < 1 and len(sample) >= 16:
            mean = sample.mean(axis=0)
            centred = sample - mean
            flat.append((len(weights), centred.T @ centred, mean))
        weights.append(weight)
    if flat:
        spreads, axes = np.linalg.eigh(np.stack([scatter for _, scatter, _ in flat]))  # ascending
        for (i, _, sight), spread, axis in zip(flat, spreads, axes):
            if spread[1] > 0:
                flatness = 1.0 - float(np.sqrt(max(spread[0], 0.0) / spread[1]))
                cosine = abs(float(axis[:, 0] @ sight)) / max(float(np.linalg.norm(sight)), 1e-9)
                facing = params.view_oblique_min + (1 - params.view_oblique_min) * cosine
                weights[i] *= 1.0 - flatness * (1.0 - facing)
    return [max(weight, 1e-3) for weight in weights]


def project_centers(
    frame: Frame, keys: np.ndarray, params: Params, set_sizes: Sequence[int] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where the voxels' centres land in the frame: u_px, v_px (N,) the pixel (rounded, as floats),
    z_m (N,) the depth of the centre, and inside (N,) bool: in front of the camera (beyond
    ``depth_min_m``) and within the image. ``set_sizes``: ``keys`` are several sets one after another,
    of these sizes; each set is turned into the camera by a matrix product of its own, so that its
    results are those of a call of its own (a product's rounding may depend on its shape; the rest
    is elementwise)."""
    centers = key_centers(keys, params.voxel_size_m)
    rotation, origin = frame.cam2world[:3, :3], frame.cam2world[:3, 3]
    if set_sizes is None:
        cam = (centers - origin) @ rotation  # world2cam of a rigid pose: R^T (x - t)
    else:
        ends = list(itertools.accumulate(set_sizes))
        cam = np.concatenate([(centers[end - size : end] - origin) @ rotation for size, end in zip(set_sizes, ends)])
    z = cam[:, 2]
    intr = frame.intrinsics
    height, width = frame.depth_m.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(cam[:, 0] * intr.fx / z + intr.cx + 0.5)
        v = np.floor(cam[:, 1] * intr.fy / z + intr.cy + 0.5)
    inside = (z > params.depth_min_m) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return u, v, z, inside


def center_rays(
    frame: Frame, keys: np.ndarray, params: Params, set_sizes: Sequence[int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """What the depth on each voxel's centre ray says, (N,) bool each: ``visible_voxels``, and whether
    the ray lands in the image on depth more than ``visibility_tolerance_m`` (plus half a voxel) behind
    the centre. The centre ray is one of the rays ``free_voxels`` tests: a voxel free by
    ``free_voxels`` is free along it (a cheap test that rules voxels out). ``set_sizes``: see
    ``project_centers``."""
    visible, free = np.zeros(keys.size, bool), np.zeros(keys.size, bool)
    if keys.size == 0:
        return visible, free
    u, v, z, inside = project_centers(frame, keys, params, set_sizes)
    idx = np.flatnonzero(inside)
    measured = frame.depth_m[v[idx].astype(np.int64), u[idx].astype(np.int64)]
    tolerance = params.visibility_tolerance_m + params.voxel_size_m / 2
    visible[idx] = (measured >= params.depth_min_m) & (np.abs(measured - z[idx]) <= tolerance)
    free[idx] = measured > z[idx] + tolerance
    return visible, free


def visible_voxels(frame: Frame, keys: np.ndarray, params: Params) -> np.ndarray:
    """(N,) bool: which voxels the frame saw: their centre projects into the image, in front of the
    camera, onto valid depth within ``visibility_tolerance_m`` (plus half a voxel) of the centre's
    depth. Voxels behind a nearer surface (occluded) or in front of the measured one are not."""
    return center_rays(frame, keys, params)[0]


def visible_voxels_of_sets(frame: Frame, key_sets: Sequence[np.ndarray], params: Params) -> list[np.ndarray]:
    """``visible_voxels`` of each of several key sets, in one pass over all their voxels (each set's
    results are those of a call of its own: ``project_centers``' ``set_sizes``)."""
    if not key_sets:
        return []
    sizes = [keys.size for keys in key_sets]
    visible = center_rays(frame, np.concatenate(key_sets), params, sizes)[0]
    return np.split(visible, list(itertools.accumulate(sizes))[:-1])


def free_voxels(frame: Frame, keys: np.ndarray, params: Params) -> np.ndarray:
    """(N,) bool: which voxels the frame sees empty: the depth on the voxel's centre ray, and every valid
    depth of the voxel's image (a square around its centre's pixel that holds the image of its bounding
    sphere), lie more than ``visibility_tolerance_m`` (plus half a voxel) behind the voxel's centre, so
    the rays through the voxel pass it and meet nothing in it. Not only the centre's ray: that one slips
    past a thin rail (a chair's back) that the voxel holds off its centre. Pixels without depth (holes)
    say nothing either way. Voxels whose square leaves the image are not free. The square's minimum is
    read from ``min_pyramid`` (at most 3 x 3 blocks, which cover it and at most its own size more
    around it: the test errs towards "not free")."""
    free = np.zeros(keys.size, bool)
    if keys.size == 0:
        return free
    u, v, z, inside = project_centers(frame, keys, params)
    idx = np.flatnonzero(inside)
    u, v, z = u[idx], v[idx], z[idx]
    intr = frame.intrinsics
    height, width = frame.depth_m.shape
    radius_m = params.voxel_size_m * math.sqrt(3) / 2
    with np.errstate(divide="ignore"):
        near_m = np.maximum(z - radius_m, params.depth_min_m)
        half_px = np.ceil(radius_m * max(intr.fx, intr.fy) / near_m)
    u0, u1, v0, v1 = u - half_px, u + half_px, v - half_px, v + half_px
    beyond_m = z + params.visibility_tolerance_m + params.voxel_size_m / 2
    candidate = (u0 >= 0) & (u1 < width) & (v0 >= 0) & (v1 < height)
    candidate &= frame.depth_m[v.astype(np.int64), u.astype(np.int64)] > beyond_m  # the centre ray
    if not candidate.any():
        return free
    pyramid = min_pyramid(np.where(frame.depth_m >= params.depth_min_m, frame.depth_m, np.float32(np.inf)))
    # Blocks of 2**level pixels, level the smallest with 2**level > half_px: the square spans <= 3 per axis.
    level = np.minimum(np.ceil(np.log2(half_px + 1)), len(pyramid) - 1).astype(np.int64)
    nearest = np.full(idx.size, np.inf, np.float32)
    for lv in np.unique(level[candidate]):
        at = np.flatnonzero(candidate & (level == lv))
        blocks = pyramid[lv]
        b_u0, b_u1 = (u0[at].astype(np.int64) >> lv), (u1[at].astype(np.int64) >> lv)
        b_v0, b_v1 = (v0[at].astype(np.int64) >> lv), (v1[at].astype(np.int64) >> lv)
        for du in range(3):
            for dv in range(3):
                bu, bv = np.minimum(b_u0 + du, b_u1), np.minimum(b_v0 + dv, b_v1)
                nearest[at] = np.minimum(nearest[at], blocks[bv, bu])
    free[idx] = candidate & (nearest > beyond_m)
    return free


def min_pyramid(depth_m: np.ndarray) -> list[np.ndarray]:
    """Level l (l = 0, 1, ...): the minimum of a depth image (H, W) over blocks of 2**l x 2**l pixels,
    block (i, j) covering rows i * 2**l .. and columns j * 2**l ..; up to one block."""
    levels = [depth_m]
    while levels[-1].shape[0] > 1 or levels[-1].shape[1] > 1:
        below = levels[-1]
        rows, cols = below.shape
        if rows % 2 or cols % 2:  # an odd edge: pad it with +inf, which no minimum takes
            below = np.pad(below, ((0, rows % 2), (0, cols % 2)), constant_values=np.inf)
        # Four strided views, not a reshape and a reduction over two axes (about 30 times slower).
        levels.append(
            np.minimum(np.minimum(below[0::2, 0::2], below[1::2, 0::2]), np.minimum(below[0::2, 1::2], below[1::2, 1::2]))
        )
    return levels
