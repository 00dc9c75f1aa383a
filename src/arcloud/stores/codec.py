"""Binary encoding of objects for the Redis store (never pickle).

Voxels: one blob, a header and the arrays after it, zlib-compressed (level 6) from 256 bytes (``FLAG_ZLIB``):

    header  <4s B B H I    magic b"ARCV", format version (5), flags, n_classes, n_voxels
            <B B B I H     the planes' kinds: weights, seen, votes; n_votes; the votes a unit of weight
                           predicts (``FLAG_VOTES_PREDICTED``)
            <3i 3I         with ``FLAG_KEYS_GRID``: the first voxel index (i, j, k) of the keys' box, its extent
    keys                   ``FLAG_KEYS_GRID``: a bit a cell of the box, i then j then k (the order of sorted
                           keys: bit order little); else int64 (N,): the first key, then the differences of
                           the sorted unique keys (all > 0)
    weights (N,)           in their plane kind (below)
    seen    (N,)           in their plane kind; with ``FLAG_SEEN_EXTRA``: seen - weights
    votes   uint8 (N, ceil(C / 8)), then (n_votes,): which of a voxel's C votes are not zero (bits, class 0
                           in the lowest bit of the first byte), then those votes row by row, in their plane
                           kind, in steps of ``core.fusion.VOTE_STEP``; with ``FLAG_VOTES_PREDICTED``: what
                           each differs from its prediction (``_predicted_votes``)
    colors  uint8 (3, N)   exact, only with ``FLAG_COLORS`` (else unknown: None): green, red - green and
                           blue - green, each as what a voxel differs from the one before (modulo 256)

A plane holds float32 values exactly, in the narrowest of: ``KIND_U16`` / ``KIND_U32`` (the values times
the plane's scale are integers that fit: counts, and votes in their steps) or ``KIND_F32``; its bytes are
stored most significant last, one byte position after another (all first bytes, then all second ones...),
which zlib compresses far better than interleaved numbers. The seen counts and the votes are stored as
what they differ from a prediction only when all three planes hold integers and every value comes back
bit for bit; the codec stays lossless for any input (NaN and -0.0 included). Nearly every voxel votes for
one label only, with about the same score each frame: its votes are about its weight times a number.

Measured on the 20 objects (4,992 voxels) of a map of 7-Scenes redkitchen from YOLO masks (1000 frames):
6.0 bytes a voxel (keys as bits 0.6, counts 1.6, votes from their prediction 1.3, colours as differences
2.4), metadata 208 bytes an object; encoding the 20 takes 3.9-4.0 ms, decoding 1.8-1.9 ms (quiet 2-core
machine).

Only format 5 is read: formats 1-4 were written by development versions alone (no deployment holds
them), and their readers went with issue 23. A blob of another version raises ``StoreError`` naming it,
and a map whose header names another codec version is refused (``core.header``).

Metadata: compact JSON of the object without its voxels (floats written by ``repr``: exact round
trip; boxes as lists of floats; devices as a sorted list), zlib-compressed against ``META_DICTIONARY``.
``arcloud.ports.ObjectMeta`` is that, decoded.
Bounds: 6 little-endian float64 (min xyz, max xyz), the spatial index's entry of an object.
"""

from __future__ import annotations

import dataclasses
import json
import struct
import zlib
from collections.abc import Sequence
from typing import Any, cast, get_args

import numpy as np

from arcloud.core.fusion import VOTE_STEP
from arcloud.core.types import AABB, N_CLASSES, OBB, EventKind, MapObject, ObjectEvent, ObjectMeta
from arcloud.core.voxels import KEY_BITS, KEY_MASK, KEY_OFFSET, pack_keys, unpack_keys
from arcloud.errors import InvalidInput, StoreError

MAGIC = b"ARCV"
FORMAT_VERSION = 5
FLAG_ZLIB = 1
FLAG_COLORS = 4
FLAG_KEYS_GRID = 8  # keys as occupancy bits over their box (else key differences)
FLAG_SEEN_EXTRA = 16  # the seen plane holds seen - weights
FLAG_VOTES_PREDICTED = 32  # the votes plane holds what a voxel's votes differ from its prediction
ZLIB_MIN_BYTES = 256  # smaller payloads are stored raw (zlib would not pay for its own overhead)
ZLIB_LEVEL = 6
KIND_F32, KIND_U16, KIND_U32 = 0, 1, 2
_KIND_DTYPES: dict[int, np.dtype[Any]] = {KIND_F32: np.dtype("<f4"), KIND_U16: np.dtype("<u2"), KIND_U32: np.dtype("<u4")}
_U16_MAX, _U32_MAX = (1 << 16) - 1, (1 << 32) - 1
_KIND_MAX = {KIND_U16: _U16_MAX, KIND_U32: _U32_MAX}
VOTES_SCALE = 1.0 / VOTE_STEP  # votes are stored in steps
_HEADER = struct.Struct("<4sBBHI")
_PLANES = struct.Struct("<BBBIH")  # kinds of weights, seen, votes; n_votes; the votes a unit of weight predicts, in steps
_GRID = struct.Struct("<3i3I")  # with FLAG_KEYS_GRID: the box's first voxel index (i, j, k) and its extent
_BOX = struct.Struct("<6d")  # min xyz, max xyz
#: Keys go as occupancy bits when their box holds at most this many cells a voxel (a bit a cell against
#: about 1 compressed byte a key difference), and at most ``MAX_GRID_CELLS`` cells in all.
GRID_CELLS_PER_VOXEL = 64
MAX_GRID_CELLS = 1 << 27  # 16 MiB of bits: what decoding a crafted blob's grid may allocate


def encode_voxels(
    keys: np.ndarray,
    weights: np.ndarray,
    votes: np.ndarray,
    *,
    seen: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> bytes:
    """keys (N,) int64 sorted unique, weights (N,) float32, votes (N, C) float32, seen (N,) float32
    (None: equal to weights), colors (N, 3) uint8 (None: unknown) -> bytes (format 5)."""
    keys = np.asarray(keys)
    n = keys.size
    if keys.ndim != 1 or keys.dtype != np.int64:
        raise InvalidInput("keys", "(N,) int64", f"shape {keys.shape} and dtype {keys.dtype}")
    weights = np.asarray(weights)
    votes = np.asarray(votes)
    if weights.shape != (n,):
        raise InvalidInput("weights", f"shape ({n},)", f"shape {weights.shape}")
    seen = weights if seen is None else np.asarray(seen)
    if seen.shape != (n,):
        raise InvalidInput("seen", f"shape ({n},)", f"shape {seen.shape}")
    if votes.ndim != 2 or votes.shape[0] != n:
        raise InvalidInput("votes", f"shape ({n}, n_classes)", f"shape {votes.shape}")
    if colors is not None and (np.shape(colors) != (n, 3) or np.asarray(colors).dtype != np.uint8):
        raise InvalidInput("colors", f"shape ({n}, 3) uint8", f"shape {np.shape(colors)} and dtype {np.asarray(colors).dtype}")
    if n > 1 and not np.all(keys[1:] > keys[:-1]):
        raise InvalidInput("keys", "sorted unique voxel keys", "keys out of order or repeated")
    flags = 0 if colors is None else FLAG_COLORS
    grid, keys_plane = _keys_plane(keys)
    if grid is not None:
        flags |= FLAG_KEYS_GRID
    weights = np.asarray(weights, np.float32)
    seen = np.asarray(seen, np.float32)
    votes = np.asarray(votes, np.float32)
    voting = votes != 0
    weights_kind, weights_plane, weight_counts = _narrowest(weights, 1.0)
    if weights_kind != KIND_F32:  # seen as seen - weights when that is an integer plane giving seen back exactly
        seen_kind, seen_plane, extra = _narrowest(seen - weights, 1.0)
        if seen_kind != KIND_F32 and np.array_equal((weights + _widened(extra, 1.0)).view(np.uint32), seen.view(np.uint32)):
            flags |= FLAG_SEEN_EXTRA
    if not flags & FLAG_SEEN_EXTRA:
        seen_kind, seen_plane, _ = _narrowest(seen, 1.0)
    votes_kind, votes_plane, vote_steps = _narrowest(votes[voting], VOTES_SCALE)
    votes_per_weight = 0
    if weights_kind != KIND_F32 and votes_kind != KIND_F32 and vote_steps.size:
        predicted = _predicted_votes(voting, weight_counts.astype(np.int64), vote_steps.astype(np.int64))
        if predicted is not None:
            votes_per_weight, votes_kind, votes_plane = predicted
            flags |= FLAG_VOTES_PREDICTED
    payload = b"".join(
        (
            keys_plane,
            weights_plane,
            seen_plane,
            np.packbits(voting, axis=1, bitorder="little").tobytes(),
            votes_plane,
            b"" if colors is None else _color_planes(np.asarray(colors)),
        )
    )
    if len(payload) >= ZLIB_MIN_BYTES:
        payload = zlib.compress(payload, ZLIB_LEVEL)
        flags |= FLAG_ZLIB
    header = _HEADER.pack(MAGIC, FORMAT_VERSION, flags, votes.shape[1], n)
    planes = _PLANES.pack(weights_kind, seen_kind, votes_kind, int(np.count_nonzero(voting)), votes_per_weight)
    return header + planes + (b"" if grid is None else _GRID.pack(*grid)) + payload


def _keys_plane(keys: np.ndarray) -> tuple[tuple[int, ...] | None, bytes]:
    """Sorted unique keys as the occupancy bits of their box in key order (i, then j, then k: the order of
    sorted keys), with the box (first index, extent) when that box is small enough, else as their
    differences (the first key, then each key minus the one before: all > 0), int64 byte positions apart."""
    n = keys.size
    if n:
        ijk = unpack_keys(keys)
        first = ijk.min(axis=0)
        extent = ijk.max(axis=0) - first + 1
        cells = int(extent[0]) * int(extent[1]) * int(extent[2])
        if cells <= min(GRID_CELLS_PER_VOXEL * n, MAX_GRID_CELLS):
            ijk -= first
            occupied = np.zeros(cells, bool)
            occupied[(ijk[:, 0] * extent[1] + ijk[:, 1]) * extent[2] + ijk[:, 2]] = True
            return (*first.tolist(), *extent.tolist()), np.packbits(occupied, bitorder="little").tobytes()
    deltas = np.empty(n, np.int64)
    if n:
        deltas[0] = keys[0]
        np.subtract(keys[1:], keys[:-1], out=deltas[1:])
    return None, _byte_planes(deltas.astype("<i8", copy=False))


def _predicted_votes(voting: np.ndarray, weight_counts: np.ndarray, vote_steps: np.ndarray) -> tuple[int, int, bytes] | None:
    """The votes of voxels that vote for one label only, predicted as their weight times the median votes a
    unit of weight gives (a detection votes its score: about the same score every time), stored as what
    they differ from that (zigzag: 0, -1, 1, -2... as 0, 1, 2, 3...); others as they are. ``weight_counts``
    (N,) and ``vote_steps`` (the votes in steps, row by row) int64 -> (votes a unit of weight predicts,
    plane kind, plane bytes), or None when the differences fit no integer plane."""
    weight_of_vote = _weights_of_lone_votes(voting, weight_counts)
    counted = np.flatnonzero(weight_of_vote > 0)
    if not counted.size:
        return None
    ratios = vote_steps[counted] / weight_of_vote[counted]
    middle = counted.size // 2
    per_weight = int(min(round(float(np.partition(ratios, middle)[middle])), _U16_MAX))  # the (upper) median
    differences = vote_steps - weight_of_vote * per_weight
    zigzag = (differences << 1) ^ (differences >> 63)
    if zigzag.max() > _U32_MAX:
        return None
    kind = KIND_U16 if zigzag.max() <= _U16_MAX else KIND_U32
    return per_weight, kind, _byte_planes(zigzag.astype(_KIND_DTYPES[kind]))


def _weights_of_lone_votes(voting: np.ndarray, weight_counts: np.ndarray) -> np.ndarray:
    """Row by row, for each vote: its voxel's weight when the voxel votes for this label only, else 0
    (the votes ``_predicted_votes`` predicts)."""
    n_labels = np.count_nonzero(voting, axis=1)
    return np.where(n_labels == 1, weight_counts, 0).repeat(n_labels)


def _unpredicted_votes(voting: np.ndarray, weight_counts: np.ndarray, zigzag: np.ndarray, per_weight: int) -> np.ndarray:
    """``_predicted_votes`` undone: the votes' steps (int64)."""
    zigzag = zigzag.astype(np.int64)
    steps: np.ndarray = (zigzag >> 1) ^ -(zigzag & 1)  # the differences
    steps += _weights_of_lone_votes(voting, weight_counts.astype(np.int64)) * per_weight
    return steps


def _color_planes(colors: np.ndarray) -> bytes:
    """(N, 3) uint8 RGB as green, red - green and blue - green (the channels move together: their
    differences vary less), each as what a voxel differs from the one before in key order (mostly its
    neighbour below it), modulo 256: three planes of N bytes."""
    channels = colors.T.astype(np.uint8)
    green = channels[1]
    decorrelated = np.stack((green, channels[0] - green, channels[2] - green))  # uint8: modulo 256
    return np.diff(decorrelated, axis=1, prepend=np.zeros((3, 1), np.uint8)).tobytes()


def _colors_of_planes(planes: np.ndarray) -> np.ndarray:
    """``_color_planes`` (3, N) uint8 undone -> (N, 3) uint8 RGB."""
    green, red, blue = np.cumsum(planes, axis=1, dtype=np.uint8)  # sums modulo 256
    red += green
    blue += green
    return np.stack((red, green, blue), axis=1)


def _narrowest(values: np.ndarray, scale: float) -> tuple[int, bytes, np.ndarray]:
    """Float32 ``values`` (M,) as the plane of the narrowest kind that holds them exactly (``values x
    scale`` as integers where they are; see the module docstring): its kind, its bytes (byte positions
    apart) and its values (the integers, or the float32 values)."""
    values = np.ascontiguousarray(values, np.float32)
    kind, plane = KIND_F32, values.astype("<f4", copy=False)
    scaled = values.astype(np.float64) * scale
    for candidate in (KIND_U16, KIND_U32):
        if values.size and not (scaled.min() >= 0 and scaled.max() <= _KIND_MAX[candidate]):  # (False for NaN)
            continue
        integers = scaled.astype(_KIND_DTYPES[candidate])
        if np.array_equal(_widened(integers, scale).view(np.uint32), values.view(np.uint32)):  # bit for bit
            kind, plane = candidate, integers
            break
    return kind, _byte_planes(plane), plane


def _byte_planes(values: np.ndarray) -> bytes:
    """(M,) numbers as their bytes, one byte position after another (all first bytes, then all second
    ones...): zlib compresses that far better than interleaved numbers."""
    return np.frombuffer(values.tobytes(), np.uint8).reshape(-1, values.dtype.itemsize).T.tobytes()


def _widened(integers: np.ndarray, scale: float) -> np.ndarray:
    """Plane integers back to float32 values (exact when ``_narrowest`` chose them)."""
    return integers.astype(np.float32) / np.float32(scale)


def _plane_numbers(payload: memoryview, dtype: np.dtype[Any], m: int, at: int) -> np.ndarray:
    """The (m,) numbers of ``dtype`` stored byte positions apart at byte ``at``."""
    columns = np.frombuffer(payload, np.uint8, m * dtype.itemsize, at).reshape(dtype.itemsize, m).T
    return np.ascontiguousarray(columns).view(dtype).reshape(m)


def _plane(payload: memoryview, kind: int, m: int, at: int, scale: float) -> np.ndarray:
    """The (m,) float32 values of a plane of ``kind`` at byte ``at`` (``_narrowest``'s bytes)."""
    values = _plane_numbers(payload, _KIND_DTYPES[kind], m, at)
    return values.astype(np.float32) if kind == KIND_F32 else _widened(values, scale)


#: The most a voxel blob may announce (a real object holds thousands of voxels; this bounds what decoding
#: a crafted blob, e.g. a snapshot upload's, may allocate: about 1 GiB).
MAX_BLOB_VOXELS = 20_000_000
MAX_BLOB_CLASSES = 256


def decode_voxels(blob: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """bytes -> (keys (N,) int64, weights (N,) float32, votes (N, C) float32, seen (N,) float32, colors
    (N, 3) uint8 or None: unknown)."""
    if len(blob) < _HEADER.size:
        raise StoreError(f"voxel blob of {len(blob)} bytes is shorter than its {_HEADER.size}-byte header")
    magic, version, flags, n_classes, n = _HEADER.unpack_from(blob)
    if magic != MAGIC or version != FORMAT_VERSION:
        raise StoreError(f"voxel blob: expected magic {MAGIC!r} version {FORMAT_VERSION}, got {magic!r} version {version}")
    if n > MAX_BLOB_VOXELS or n_classes > MAX_BLOB_CLASSES:
        raise StoreError(
            f"voxel blob: expected at most {MAX_BLOB_VOXELS} voxels of {MAX_BLOB_CLASSES} classes, got {n} of {n_classes}"
        )
    grid_size = _GRID.size if flags & FLAG_KEYS_GRID else 0
    if len(blob) < _HEADER.size + _PLANES.size + grid_size:
        raise StoreError(
            f"voxel blob of {len(blob)} bytes is shorter than its {_HEADER.size + _PLANES.size + grid_size}-byte header"
        )
    weights_kind, seen_kind, votes_kind, n_votes, votes_per_weight = _PLANES.unpack_from(blob, _HEADER.size)
    if not {weights_kind, seen_kind, votes_kind} <= _KIND_DTYPES.keys() or n_votes > n * n_classes:
        raise StoreError(f"voxel blob: corrupt header (plane kinds {weights_kind, seen_kind, votes_kind}, {n_votes} votes)")
    if flags & FLAG_VOTES_PREDICTED and (weights_kind == KIND_F32 or votes_kind == KIND_F32):
        raise StoreError("voxel blob: corrupt header (votes predicted from float planes)")
    grid = _grid_of(blob, _HEADER.size + _PLANES.size, n) if flags & FLAG_KEYS_GRID else None
    keys_bytes = n * 8 if grid is None else (grid[2] + 7) // 8
    mask_bytes = (n_classes + 7) // 8
    weights_at = keys_bytes
    seen_at = weights_at + n * _KIND_DTYPES[weights_kind].itemsize
    mask_at = seen_at + n * _KIND_DTYPES[seen_kind].itemsize
    votes_at = mask_at + n * mask_bytes
    colors_at = votes_at + n_votes * _KIND_DTYPES[votes_kind].itemsize
    has_colors = bool(flags & FLAG_COLORS)
    at = _HEADER.size + _PLANES.size + grid_size
    payload = _payload(blob, at, flags, colors_at + (n * 3 if has_colors else 0), n)
    keys = _keys_of_grid(payload, n, *grid) if grid is not None else _keys_of_differences(payload, n)
    weights = _plane(payload, weights_kind, n, weights_at, 1.0)
    seen = _plane(payload, seen_kind, n, seen_at, 1.0)
    if flags & FLAG_SEEN_EXTRA:
        seen += weights
    mask = np.frombuffer(payload, np.uint8, n * mask_bytes, mask_at).reshape(n, mask_bytes)
    voting = np.unpackbits(mask, axis=1, count=n_classes, bitorder="little").astype(bool)
    if int(np.count_nonzero(voting)) != n_votes:
        raise StoreError(f"voxel blob: its vote bits name {np.count_nonzero(voting)} votes, its header {n_votes}")
    votes = np.zeros((n, n_classes), np.float32)
    if flags & FLAG_VOTES_PREDICTED:
        numbers = _plane_numbers(payload, _KIND_DTYPES[votes_kind], n_votes, votes_at)
        weight_counts = _plane_numbers(payload, _KIND_DTYPES[weights_kind], n, weights_at)
        steps = _unpredicted_votes(voting, weight_counts, numbers, votes_per_weight)
        if steps.size and (steps.min() < 0 or steps.max() >= 1 << 32):
            raise StoreError("voxel blob: corrupt votes (predicted votes out of range)")
        votes[voting] = _widened(steps, VOTES_SCALE)
    else:
        votes[voting] = _plane(payload, votes_kind, n_votes, votes_at, VOTES_SCALE)
    colors = None
    if has_colors:
        planes = np.frombuffer(payload, np.uint8, n * 3, colors_at).reshape(3, n)
        colors = _colors_of_planes(planes)
    return keys, weights, votes, seen, colors


def _grid_of(blob: bytes, at: int, n: int) -> tuple[np.ndarray, np.ndarray, int]:
    """A grid header -> (first voxel index (3,), extent (3,), cells), checked against the key range."""
    values = _GRID.unpack_from(blob, at)
    first, extent = np.array(values[:3], np.int64), np.array(values[3:], np.int64)
    cells = int(extent[0]) * int(extent[1]) * int(extent[2])
    last = first + extent - 1
    if cells > MAX_GRID_CELLS or (n and cells < n) or first.min() < -KEY_OFFSET or last.max() > KEY_MASK - KEY_OFFSET:
        raise StoreError(f"voxel blob: corrupt grid (first voxel {first.tolist()}, extent {extent.tolist()} for {n} voxels)")
    return first, extent, cells


def _keys_of_grid(payload: memoryview, n: int, first: np.ndarray, extent: np.ndarray, cells: int) -> np.ndarray:
    """Keys from the occupancy bits of their box (``_keys_plane``): the box's first key plus each cell's offsets."""
    bits = np.frombuffer(payload, np.uint8, (cells + 7) // 8, 0)
    cell = np.flatnonzero(np.unpackbits(bits, count=cells, bitorder="little"))
    if cell.size != n:
        raise StoreError(f"voxel blob: its grid holds {cell.size} voxels, its header {n}")
    row, k = np.divmod(cell, extent[2])
    i, j = np.divmod(row, extent[1])
    keys: np.ndarray = pack_keys(first[None])[0] + (i << 2 * KEY_BITS) + (j << KEY_BITS) + k  # no field overflows: checked
    return keys


def _keys_of_differences(payload: memoryview, n: int) -> np.ndarray:
    """Keys from their differences, int64 byte positions apart; ``StoreError`` unless they are sorted unique keys
    (rising from a first >= 0): a blob of shuffled or repeated keys would read as an object whose voxels every later
    step miscounts."""
    keys = np.cumsum(_plane_numbers(payload, np.dtype("<i8"), n, 0), dtype=np.int64)
    # Every int64 >= 0 is a key. A sum past the largest one wraps to a negative number, which rising keys never reach.
    if n and (keys[0] < 0 or not np.all(keys[1:] > keys[:-1])):
        raise StoreError("voxel blob: its keys are not sorted unique voxel keys")
    return keys


def _payload(blob: bytes, at: int, flags: int, expected: int, n: int) -> memoryview:
    """The blob's arrays from byte ``at``, unpacked when compressed: exactly ``expected`` bytes, or ``StoreError``."""
    payload = memoryview(blob)[at:]
    if flags & FLAG_ZLIB:
        try:  # at most what the header announces (and one byte to tell more): a small blob cannot expand without bound
            payload = memoryview(zlib.decompressobj().decompress(payload, expected + 1))
        except zlib.error as exc:
            raise StoreError(f"voxel blob: corrupt zlib stream ({exc})") from exc
    if len(payload) != expected:
        raise StoreError(f"voxel blob: expected {expected} bytes for {n} voxels, got {len(payload)}")
    return payload


def pack_box(box: AABB) -> bytes:
    return _BOX.pack(*np.asarray(box.min, np.float64), *np.asarray(box.max, np.float64))


def unpack_boxes(blobs: Sequence[bytes]) -> np.ndarray:
    """Many packed boxes -> (N, 6) float64 rows (min xyz, max xyz)."""
    joined = b"".join(blobs)
    if len(joined) != _BOX.size * len(blobs):
        raise StoreError(f"bounds: expected {len(blobs)} boxes of {_BOX.size} bytes, got {len(joined)} bytes")
    return np.frombuffer(joined, "<f8").reshape(len(blobs), 6).astype(np.float64)


def meta_of(obj: MapObject) -> ObjectMeta:
    """The metadata of an object (what ``object_meta`` returns for it)."""
    return ObjectMeta(
        id=obj.id,
        label=obj.label,
        score=obj.score,
        version=obj.version,
        n_voxels=obj.n_voxels,
        n_frames=obj.n_frames,
        devices=obj.devices,
        score_sum=obj.score_sum,
        created_at_s=obj.created_at_s,
        updated_at_s=obj.updated_at_s,
        aabb=obj.aabb,
        obb=obj.obb,
        bounds=obj.bounds,
        confirmed=obj.confirmed,
        floor_votes=obj.floor_votes,
        wall_votes=obj.wall_votes,
        label_purity=obj.label_purity,
        apart=obj.apart,
        spanned=obj.spanned,
    )


#: The most a compressed metadata blob may unpack to (a real one is well under 1 kB; a long device list grows it).
MAX_META_BYTES = 1 << 20
META_ZLIB_LEVEL = 9  # the blobs are small: the best compression costs microseconds


#: What metadata JSON is compressed against (zlib's preset dictionary: a blob refers to these bytes
#: instead of spelling its field names out). Never edit it: a blob names its dictionary by checksum,
#: and a new one must be added beside it (``_META_DICTIONARIES``).
META_DICTIONARY = (
    b'"label":"laptop","label":"couch","label":"table","label":"tv","label":"chair",'
    b'"version":1,"n_voxels":1,"n_frames":1,"devices":[""],"score_sum":0.0,'
    b'"created_at_s":1,"updated_at_s":1,"aabb":[-0.0000000000000001,'
    b'"obb":[0.0,0.0,0.0,0.0,0.0,0.0,1.0,0.0,0.0,0.0,1.0,0.0,0.0,0.0,1.0,0.0],"bounds":[-0.0000000000000001,'
    b'"confirmed":false,"confirmed":true,"floor_votes":{},"label_purity":1.0}'
    b'{"label":"chair","score":0.'
)
_META_DICTIONARIES = {zlib.adler32(META_DICTIONARY): META_DICTIONARY}


def encode_meta(obj: MapObject) -> bytes:
    """The object's metadata (everything but the voxels) as compact JSON, compressed against
    ``META_DICTIONARY``."""
    compressor = zlib.compressobj(META_ZLIB_LEVEL, zdict=META_DICTIONARY)
    return compressor.compress(_meta_json(obj)) + compressor.flush()


def _meta_json(obj: MapObject | ObjectMeta) -> bytes:
    return json.dumps(_meta_fields(obj), separators=(",", ":")).encode()


def _meta_fields(obj: MapObject | ObjectMeta) -> dict[str, Any]:
    # left out when empty: the blobs of objects without them are the bytes they were
    apart = {"apart": {str(k): int(v) for k, v in sorted(obj.apart.items())}} if obj.apart else {}
    spanned = {"spanned": {str(k): int(v) for k, v in sorted(obj.spanned.items())}} if obj.spanned else {}
    walls = {"wall_votes": {str(k): [int(n), int(mm)] for k, (n, mm) in sorted(obj.wall_votes.items())}} if obj.wall_votes else {}
    return {
        "label": obj.label,
        "score": float(obj.score),
        "version": int(obj.version),
        "n_voxels": obj.n_voxels,
        "n_frames": int(obj.n_frames),
        "devices": sorted(obj.devices),
        "score_sum": float(obj.score_sum),
        "created_at_s": float(obj.created_at_s),
        "updated_at_s": float(obj.updated_at_s),
        "aabb": None if obj.aabb is None else _box_list(obj.aabb),
        "obb": None if obj.obb is None else _obb_list(obj.obb),
        "bounds": None if obj.bounds is None else _box_list(obj.bounds),
        "confirmed": bool(obj.confirmed),
        "floor_votes": {str(k): int(v) for k, v in sorted(obj.floor_votes.items())},
        "label_purity": float(obj.label_purity),
        **apart,
        **spanned,
        **walls,
    }


def _box_list(box: AABB) -> list[float]:
    return [float(v) for v in (*np.asarray(box.min).ravel(), *np.asarray(box.max).ravel())]


def _obb_list(obb: OBB) -> list[float]:
    return [float(v) for v in (*np.ravel(obb.center), *np.ravel(obb.size), *np.ravel(obb.rotation), obb.yaw_rad)]


def _box(values: list[float] | None) -> AABB | None:
    if values is None:
        return None
    array = np.array(values, np.float64)
    return AABB(array[:3], array[3:])


def _obb(values: list[float] | None) -> OBB | None:
    if values is None:
        return None
    array = np.array(values, np.float64)
    return OBB(center=array[:3], size=array[3:6], rotation=array[6:15].reshape(3, 3), yaw_rad=float(array[15]))


def decode_meta(object_id: int, blob: bytes) -> ObjectMeta:
    """The JSON of ``encode_meta`` -> ``ObjectMeta``."""
    return decode_metas([object_id], [blob])[0]


def decode_metas(object_ids: Sequence[int], blobs: Sequence[bytes]) -> list[ObjectMeta]:
    """Many ``encode_meta`` blobs at once (one JSON parse) -> ``ObjectMeta`` each."""
    try:
        parsed = json.loads(b"[" + b",".join(map(_unpacked_meta, blobs)) + b"]")
        return [_meta(int(i), fields) for i, fields in zip(object_ids, parsed, strict=True)]
    except (ValueError, KeyError, TypeError, IndexError, OverflowError, zlib.error) as exc:
        raise StoreError(f"objects {list(object_ids)[:5]}: corrupt metadata ({type(exc).__name__}: {exc})") from exc


def _unpacked_meta(blob: bytes) -> bytes:
    """A metadata blob's JSON, decompressed (at most ``MAX_META_BYTES``) against the dictionary it names."""
    if len(blob) < 6 or not blob[1] & 0x20:  # zlib's FDICT bit: the preset dictionary's checksum follows
        raise ValueError("metadata not compressed against a preset dictionary")
    checksum = int.from_bytes(blob[2:6], "big")
    if checksum not in _META_DICTIONARIES:
        raise ValueError(f"metadata compressed against an unknown dictionary (checksum {checksum:#010x})")
    unpacker = zlib.decompressobj(zdict=_META_DICTIONARIES[checksum])
    json_bytes = unpacker.decompress(blob, MAX_META_BYTES)
    if unpacker.unconsumed_tail:
        raise ValueError(f"metadata unpacks to more than {MAX_META_BYTES} bytes")
    return json_bytes


def _meta(object_id: int, fields: dict[str, Any]) -> ObjectMeta:
    return ObjectMeta(
        id=object_id,
        label=str(fields["label"]),
        score=float(fields["score"]),
        version=int(fields["version"]),
        n_voxels=int(fields["n_voxels"]),
        n_frames=int(fields["n_frames"]),
        devices=frozenset(_strings(fields["devices"])),
        score_sum=float(fields["score_sum"]),
        created_at_s=float(fields["created_at_s"]),
        updated_at_s=float(fields["updated_at_s"]),
        aabb=_box(fields["aabb"]),
        obb=_obb(fields["obb"]),
        bounds=_box(fields["bounds"]),
        confirmed=_boolean(fields.get("confirmed", False)),
        floor_votes={int(k): int(v) for k, v in fields.get("floor_votes", {}).items()},
        wall_votes={int(k): (int(n), int(mm)) for k, (n, mm) in fields.get("wall_votes", {}).items()},
        label_purity=float(fields.get("label_purity", 0.0)),
        apart={int(k): int(v) for k, v in fields.get("apart", {}).items()},
        spanned={int(k): int(v) for k, v in fields.get("spanned", {}).items()},
    )


def _strings(values: object) -> list[str]:
    """A JSON list of strings as it is (a string alone is no list of its letters); ``TypeError`` otherwise."""
    if not isinstance(values, list) or not all(isinstance(v, str) for v in values):
        raise TypeError(f"expected a list of strings, got {type(values).__name__}")
    return values


def _boolean(value: object) -> bool:
    """A JSON true or false as it is (the string "no" is not true); ``TypeError`` otherwise."""
    if not isinstance(value, bool):
        raise TypeError(f"expected true or false, got {type(value).__name__}")
    return value


def decode_object(object_id: int, meta_blob: bytes, voxels_blob: bytes, *, n_missed: int = 0, n_gone: int = 0) -> MapObject:
    """Metadata JSON and voxel blob -> ``MapObject`` (the counters ``n_missed``, ``n_gone`` are kept beside them)."""
    meta = decode_meta(object_id, meta_blob)
    keys, weights, votes, seen, colors = decode_voxels(voxels_blob)
    if votes.shape[1] != N_CLASSES:
        raise StoreError(f"object {object_id}: expected votes for {N_CLASSES} classes, got {votes.shape[1]}")
    if keys.size != meta.n_voxels:
        raise StoreError(f"object {object_id}: metadata says {meta.n_voxels} voxels, the voxels hold {keys.size}")
    return MapObject(
        id=meta.id,
        keys=keys,
        weights=weights,
        votes=votes,
        seen=seen,
        colors=colors,
        n_frames=meta.n_frames,
        devices=meta.devices,
        score_sum=meta.score_sum,
        version=meta.version,
        created_at_s=meta.created_at_s,
        updated_at_s=meta.updated_at_s,
        label=meta.label,
        score=meta.score,
        aabb=meta.aabb,
        obb=meta.obb,
        bounds=meta.bounds,
        confirmed=meta.confirmed,
        floor_votes=meta.floor_votes,
        wall_votes=meta.wall_votes,
        n_missed=n_missed,
        n_gone=n_gone,
        label_purity=meta.label_purity,
        apart=meta.apart,
        spanned=meta.spanned,
    )


# --- change log entries (``core.change``) ------------------------------------------------------------
def logged_events(events: Sequence[ObjectEvent]) -> tuple[ObjectEvent, ...]:
    """The events as a change log keeps them: each object's state as its ``ObjectMeta`` (no voxels)."""
    return tuple(dataclasses.replace(e, object=meta_of(e.object)) if isinstance(e.object, MapObject) else e for e in events)


def encode_events(events: Sequence[ObjectEvent]) -> bytes:
    """A change log entry's events as JSON (the map id is the log's): ``[{"kind", "id", "into", "was_confirmed",
    "meta"}, ...]``, ``into`` the object merged into (or null), ``meta`` the state's fields as ``encode_meta``
    writes them (or null)."""
    return json.dumps(
        [
            {
                "kind": e.kind,
                "id": int(e.object_id),
                "into": None if e.merged_into is None else int(e.merged_into),
                "was_confirmed": bool(e.was_confirmed),
                "meta": None if e.object is None else _meta_fields(e.object),
            }
            for e in events
        ],
        separators=(",", ":"),
    ).encode()


def decode_events(map_id: str, blob: bytes) -> tuple[ObjectEvent, ...]:
    """``encode_events``'s JSON -> the events, each state an ``ObjectMeta``; ``StoreError`` when it is not that."""
    try:
        return tuple(
            ObjectEvent(
                kind=check_event_kind(e["kind"]),
                map_id=map_id,
                object_id=int(e["id"]),
                object=None if e["meta"] is None else _meta(int(e["id"]), e["meta"]),
                merged_into=None if e["into"] is None else int(e["into"]),
                was_confirmed=bool(e["was_confirmed"]),
            )
            for e in json.loads(blob)
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise StoreError(f"map {map_id}: corrupt change log entry ({type(exc).__name__}: {exc})") from exc


def check_event_kind(kind: object) -> EventKind:
    if kind not in EVENT_KINDS:
        raise ValueError(f"event kind {kind!r}, expected one of {EVENT_KINDS}")
    return cast("EventKind", kind)


EVENT_KINDS: tuple[str, ...] = get_args(EventKind)
