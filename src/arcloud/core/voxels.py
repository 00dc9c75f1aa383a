"""Voxel keys and back-projection: masks with depth and a pose -> world voxels.

A voxel is addressed by integer indices (i, j, k) = floor(xyz / voxel_size_m), packed into one int64
key with 21 bits per axis (offset 2**20), which spans +-52 km at 5 cm. Packed keys sort by (i, j, k).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from arcloud.core.types import CLASS_INDEX, Detection, Frame, Params, VoxelDetection

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
    ijk[:, 0] = (keys >> (2 * KEY_BITS)) & KEY_MASK
    ijk[:, 1] = (keys >> KEY_BITS) & KEY_MASK
    ijk[:, 2] = keys & KEY_MASK
    return ijk - KEY_OFFSET


def points_to_keys(points_xyz: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(N, 3) points in metres -> (N,) keys of the voxels holding them (not unique)."""
    return pack_keys(np.floor(points_xyz / voxel_size_m).astype(np.int64))


def key_centers(keys: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(N,) keys -> (N, 3) voxel centres in metres."""
    return (unpack_keys(keys) + 0.5) * voxel_size_m


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """(M,) sorted unique values of a 1-D array (N,): what ``np.unique`` returns, by a sort and a
    comparison of neighbours, which costs a fraction of ``np.unique``'s hash pass on a few thousand keys."""
    ordered = np.sort(values)
    if ordered.size < 2:
        return ordered
    first = np.empty(ordered.size, bool)
    first[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    return ordered[first]


def coarsen_keys(keys: np.ndarray, factor: int) -> np.ndarray:
    """Sorted unique keys of the ``factor``-times coarser voxels holding ``keys``."""
    if factor == 1:
        return keys
    shift = factor.bit_length() - 1
    if factor != 1 << shift or shift >= KEY_BITS - 1:
        return sorted_unique(pack_keys(np.floor_divide(unpack_keys(keys), factor)))
    # A power of two divides the offset 2**20, so on each packed field s = i + 2**20 the coarse field is
    # floor(i / factor) + 2**20 = (s >> shift) + 2**20 - 2**(20 - shift): one shift of the whole key,
    # the bits that slid into a lower field cleared, and a constant added (no field overflows).
    slid = np.int64(sum(((1 << shift) - 1) << (KEY_BITS * f - shift) for f in (1, 2)))
    offset = KEY_OFFSET - (KEY_OFFSET >> shift)
    add = np.int64(offset | (offset << KEY_BITS) | (offset << (2 * KEY_BITS)))
    coarse = np.right_shift(np.asarray(keys, np.int64), shift)
    coarse &= ~slid
    coarse += add
    return sorted_unique(coarse)


def keys_bounds(keys: np.ndarray, voxel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Outer (min, max) corners in metres of the voxels ``keys`` (non-empty)."""
    ijk = unpack_keys(keys)
    return ijk.min(axis=0) * voxel_size_m, (ijk.max(axis=0) + 1) * voxel_size_m


def erode(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """Binary erosion by a (2r+1)^2 square (outside the array counts as background): a separable
    minimum filter."""
    if radius_px <= 0:
        return mask
    eroded = ndimage.minimum_filter(mask.view(np.uint8), size=2 * radius_px + 1, mode="constant", cval=0)
    return eroded.view(bool)


def erode_sampled(mask: np.ndarray, radius_px: int, stride_px: int) -> np.ndarray:
    """``erode(mask, radius_px)[::stride_px, ::stride_px]``, eroding along columns only the rows kept.

    The square's minimum is separable, so filtering along rows, keeping every n-th row, then filtering
    along columns gives the same booleans as the full erosion sampled afterwards."""
    if radius_px <= 0:
        return mask[::stride_px, ::stride_px]
    size = 2 * radius_px + 1
    rows = ndimage.minimum_filter1d(mask.view(np.uint8), size, axis=0, mode="constant", cval=0)[::stride_px]
    both = ndimage.minimum_filter1d(rows, size, axis=1, mode="constant", cval=0)[:, ::stride_px]
    return both.view(bool)


def mask_extent(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """The bounding box (row0, row1, col0, col1), ends exclusive, of an (H, W) bool mask's pixels; None
    when it has none.

    The first row comes from the first set pixel (argmax stops there); only the rows below it are
    reduced. A C-contiguous mask whose width is a multiple of 8 has its columns found on 64-bit words:
    OR-ing the rows' words keeps each pixel's byte non-zero exactly when its column has a pixel set."""
    height, width = mask.shape
    if mask.size == 0:
        return None
    if mask.flags.c_contiguous:
        first = int(mask.reshape(-1).argmax())
        if not mask.flat[first]:
            return None
        r0 = first // width
    else:
        rows = np.flatnonzero(mask.any(axis=1))
        if rows.size == 0:
            return None
        r0 = int(rows[0])
    r1 = r0 + int(np.flatnonzero(mask[r0:].any(axis=1))[-1]) + 1
    band = mask[r0:r1]
    if mask.flags.c_contiguous and width % 8 == 0 and mask.dtype == np.bool_:
        cols = np.flatnonzero(np.bitwise_or.reduce(band.view(np.uint64), axis=0).view(np.uint8))
    else:
        cols = np.flatnonzero(band.any(axis=0))
    return r0, r1, int(cols[0]), int(cols[-1]) + 1


def mask_points(frame: Frame, mask: np.ndarray, params: Params, stride_px: int = 1) -> np.ndarray:
    """World points (N, 3) of the mask's pixels with valid depth, after eroding the mask's border.

    Works on the mask's bounding box only. ``stride_px`` > 1 samples every n-th row and column."""
    extent = mask_extent(mask)
    if extent is None:
        return np.empty((0, 3))
    r0, r1, c0, c1 = extent
    crop = erode_sampled(mask[r0:r1, c0:c1], params.erode_px, stride_px)
    depth = frame.depth_m[r0:r1:stride_px, c0:c1:stride_px]
    keep = crop & (depth >= params.depth_min_m) & (depth <= params.depth_max_m)
    v, u = np.nonzero(keep)
    z = depth[v, u].astype(np.float64)
    intr = frame.intrinsics
    u = u * stride_px + c0
    v = v * stride_px + r0
    points_cam = np.stack(((u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z), axis=1)
    return points_cam @ frame.cam2world[:3, :3].T + frame.cam2world[:3, 3]


def sampling_stride_px(frame: Frame, params: Params) -> int:
    """A pixel stride that still puts several samples in every voxel at the nearest valid depth.

    A pixel at depth z spans z / f metres; sampling every n-th pixel keeps >= 2 samples per voxel edge
    while n * z_near / f <= voxel / 2."""
    sample = frame.depth_m[::8, ::8]
    valid = sample[sample >= params.depth_min_m]
    if valid.size == 0:
        return 1
    k = valid.size // 20
    near_m = float(np.partition(valid, k)[k])  # the 5th percentile
    focal = max(frame.intrinsics.fx, frame.intrinsics.fy)
    return int(max(1, min(4, np.floor(params.voxel_size_m / 2 * focal / max(near_m, 1e-3)))))


def voxelize_detections(frame: Frame, detections: Sequence[Detection], params: Params) -> list[VoxelDetection]:
    """Each detection's world voxels (sorted unique keys); detections with fewer than
    ``params.min_voxels_per_detection`` voxels are dropped. Order of the survivors is kept."""
    stride = sampling_stride_px(frame, params)
    voxelized = []
    for det in detections:
        points = mask_points(frame, det.mask, params, stride)
        if len(points) == 0:
            continue
        keys = sorted_unique(points_to_keys(points, params.voxel_size_m))
        if keys.size >= params.min_voxels_per_detection:
            voxelized.append(VoxelDetection(CLASS_INDEX[det.label], float(det.score), keys))
    return voxelized


def visible_voxels(frame: Frame, keys: np.ndarray, params: Params) -> np.ndarray:
    """(N,) bool: which voxels the frame saw: their centre projects into the image, in front of the
    camera, onto valid depth within ``visibility_tolerance_m`` (plus half a voxel) of the centre's
    depth. Voxels behind a nearer surface (occluded) or in front of the measured one are not."""
    if keys.size == 0:
        return np.zeros(0, bool)
    centers = key_centers(keys, params.voxel_size_m)
    rotation, origin = frame.cam2world[:3, :3], frame.cam2world[:3, 3]
    cam = (centers - origin) @ rotation  # world2cam of a rigid pose: R^T (x - t)
    z = cam[:, 2]
    intr = frame.intrinsics
    height, width = frame.depth_m.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(cam[:, 0] * intr.fx / z + intr.cx + 0.5)
        v = np.floor(cam[:, 1] * intr.fy / z + intr.cy + 0.5)
    inside = (z > params.depth_min_m) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    visible = np.zeros(keys.size, bool)
    idx = np.flatnonzero(inside)
    measured = frame.depth_m[v[idx].astype(np.int64), u[idx].astype(np.int64)]
    tolerance = params.visibility_tolerance_m + params.voxel_size_m / 2
    visible[idx] = (measured >= params.depth_min_m) & (np.abs(measured - z[idx]) <= tolerance)
    return visible
