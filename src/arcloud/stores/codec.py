"""Binary encoding of objects for the Redis store (never pickle).

Voxels: one blob, a header and the arrays after it, zlib-compressed (level 6) from 256 bytes (``FLAG_ZLIB``):

    header  <4s B B H I    magic b"ARCV", format version (4), flags, n_classes, n_voxels
            <B B B I       (format 4 on) the planes' kinds: weights, seen, votes; n_votes
    keys    int64 (N,)     first key, then the differences of the sorted unique keys (all > 0)
    weights (N,)           in their plane kind (below)
    seen    (N,)           in their plane kind
    votes   uint8 (N, ceil(C / 8)), then (n_votes,): which of a voxel's C votes are not zero (bits, class 0
                           in the lowest bit of the first byte), then those votes row by row, in their plane
                           kind, in steps of ``core.fusion.VOTE_STEP``
    colors  uint8 (3, N)   exact: all reds, then greens, then blues; only with ``FLAG_COLORS`` (else
                           unknown: None)

A plane holds float32 values exactly, in the narrowest of: ``KIND_U16`` / ``KIND_U32`` (the values times
the plane's scale are integers that fit: counts, and votes in their steps) or ``KIND_F32``; its bytes are
stored most significant last, one byte position after another (all first bytes, then all second ones...),
which zlib compresses far better than interleaved numbers. Nearly every voxel votes for one label only,
so the vote bits and the non-zero votes take about 1.6 bytes a voxel, not 20 (5 float32 votes).
Measured on the 21 objects of a map of 7-Scenes redkitchen from YOLO masks (1000 frames; votes
rounded to steps): 11.7 bytes a voxel in format 3, 7.2 in format 4, of which colours take about 2.7
(measured colours are noisy) and keys 1.1. Encoding them takes 2.4 ms against 1.6 ms in format 3 (zlib
level 6: 5 % fewer bytes than level 1 for 0.6 ms more), decoding 0.75 ms in both.

Older formats, read: format 1 (keys, weights, votes float32), 2 (and seen float32 after the weights),
3 (and colours; votes float16 with ``FLAG_VOTES_F16``), each with the 12-byte header alone.

Blobs of every version in ``READABLE_VERSIONS`` are read, each by the version in its own header, so a
map whose header names an older codec version (``core.header``) stays readable and writable: the
stores accept it (``ObjectStore.readable_codec_versions``) and its objects move to the current format
as they are rewritten. A process older than the current format cannot read the new blobs (it raises
``StoreError`` naming the version): upgrade every process of a map together.

Metadata: compact JSON of the object without its voxels (floats written by ``repr``: exact round
trip; boxes as lists of floats; devices as a sorted list), zlib-compressed (format 4 on: about half the
bytes; plain JSON, what formats 1-3 wrote, starts with ``{`` and is read as it is).
``arcloud.ports.ObjectMeta`` is that, decoded.
Bounds: 6 little-endian float64 (min xyz, max xyz), the spatial index's entry of an object.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from arcloud.core.fusion import VOTE_STEP
from arcloud.core.types import AABB, N_CLASSES, OBB, MapObject
from arcloud.errors import InvalidInput, StoreError
from arcloud.ports import ObjectMeta

MAGIC = b"ARCV"
FORMAT_VERSION = 4
READABLE_VERSIONS: tuple[int, ...] = (1, 2, 3, 4)
FLAG_ZLIB = 1
FLAG_VOTES_F16 = 2  # format 3: votes as float16 (read only)
FLAG_COLORS = 4
ZLIB_MIN_BYTES = 256  # smaller payloads are stored raw (zlib would not pay for its own overhead)
ZLIB_LEVEL = 6
KIND_F32, KIND_U16, KIND_U32 = 0, 1, 2
_KIND_DTYPES: dict[int, np.dtype[Any]] = {KIND_F32: np.dtype("<f4"), KIND_U16: np.dtype("<u2"), KIND_U32: np.dtype("<u4")}
VOTES_SCALE = 1.0 / VOTE_STEP  # votes are stored in steps
_HEADER = struct.Struct("<4sBBHI")
_PLANES = struct.Struct("<BBBI")  # format 4: kinds of weights, seen, votes; n_votes
_BOX = struct.Struct("<6d")  # min xyz, max xyz


def encode_voxels(
    keys: np.ndarray,
    weights: np.ndarray,
    votes: np.ndarray,
    *,
    seen: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> bytes:
    """keys (N,) int64 sorted unique, weights (N,) float32, votes (N, C) float32, seen (N,) float32
    (None: equal to weights), colors (N, 3) uint8 (None: unknown) -> bytes (format 4)."""
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
    deltas = np.empty(n, np.int64)
    if n:
        deltas[0] = keys[0]
        np.subtract(keys[1:], keys[:-1], out=deltas[1:])
        if n > 1 and deltas[1:].min() <= 0:
            raise InvalidInput("keys", "sorted unique voxel keys", "keys out of order or repeated")
    votes = np.asarray(votes, np.float32)
    voting = votes != 0
    weights_kind, weights_plane = _narrowest(weights, 1.0)
    seen_kind, seen_plane = _narrowest(seen, 1.0)
    votes_kind, votes_plane = _narrowest(votes[voting], VOTES_SCALE)
    payload = b"".join(
        (
            deltas.astype("<i8", copy=False).tobytes(),
            weights_plane,
            seen_plane,
            np.packbits(voting, axis=1, bitorder="little").tobytes(),
            votes_plane,
            b"" if colors is None else np.asarray(colors).T.tobytes(),  # (3, N): one channel after another
        )
    )
    flags = 0 if colors is None else FLAG_COLORS
    if len(payload) >= ZLIB_MIN_BYTES:
        payload = zlib.compress(payload, ZLIB_LEVEL)
        flags |= FLAG_ZLIB
    planes = _PLANES.pack(weights_kind, seen_kind, votes_kind, int(np.count_nonzero(voting)))
    return _HEADER.pack(MAGIC, FORMAT_VERSION, flags, votes.shape[1], n) + planes + payload


def _narrowest(values: np.ndarray, scale: float) -> tuple[int, bytes]:
    """Float32 ``values`` (M,) as the plane of the narrowest kind that holds them exactly (``values x
    scale`` as integers where they are; see the module docstring): its kind and its bytes, byte
    positions apart."""
    values = np.ascontiguousarray(values, np.float32)
    kind, plane = KIND_F32, values.astype("<f4", copy=False)
    scaled = values.astype(np.float64) * scale
    for candidate in (KIND_U16, KIND_U32):
        dtype = _KIND_DTYPES[candidate]
        if values.size and not (scaled.min() >= 0 and scaled.max() <= np.iinfo(dtype).max):  # (False for NaN)
            continue
        integers = scaled.astype(dtype)
        if np.array_equal(_widened(integers, scale).view(np.uint32), values.view(np.uint32)):  # bit for bit
            kind, plane = candidate, integers
            break
    return kind, np.frombuffer(plane.tobytes(), np.uint8).reshape(-1, plane.dtype.itemsize).T.tobytes()


def _widened(integers: np.ndarray, scale: float) -> np.ndarray:
    """Plane integers back to float32 values (exact when ``_narrowest`` chose them)."""
    return integers.astype(np.float32) / np.float32(scale)


def _plane(payload: memoryview, kind: int, m: int, at: int, scale: float) -> np.ndarray:
    """The (m,) float32 values of a plane of ``kind`` at byte ``at`` (``_narrowest``'s bytes)."""
    dtype = _KIND_DTYPES[kind]
    columns = np.frombuffer(payload, np.uint8, m * dtype.itemsize, at).reshape(dtype.itemsize, m).T
    values = np.ascontiguousarray(columns).view(dtype).reshape(m)
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
    if magic != MAGIC or version not in READABLE_VERSIONS:
        raise StoreError(f"voxel blob: expected magic {MAGIC!r} version in {READABLE_VERSIONS}, got {magic!r} version {version}")
    if n > MAX_BLOB_VOXELS or n_classes > MAX_BLOB_CLASSES:
        raise StoreError(
            f"voxel blob: expected at most {MAX_BLOB_VOXELS} voxels of {MAX_BLOB_CLASSES} classes, got {n} of {n_classes}"
        )
    if version < 4:
        return _decode_voxels_before_4(blob, version, flags, n_classes, n)
    if len(blob) < _HEADER.size + _PLANES.size:
        raise StoreError(f"voxel blob of {len(blob)} bytes is shorter than its {_HEADER.size + _PLANES.size}-byte header")
    weights_kind, seen_kind, votes_kind, n_votes = _PLANES.unpack_from(blob, _HEADER.size)
    if not {weights_kind, seen_kind, votes_kind} <= _KIND_DTYPES.keys() or n_votes > n * n_classes:
        raise StoreError(f"voxel blob: corrupt header (plane kinds {weights_kind, seen_kind, votes_kind}, {n_votes} votes)")
    mask_bytes = (n_classes + 7) // 8
    seen_at = n * 8 + n * _KIND_DTYPES[weights_kind].itemsize
    mask_at = seen_at + n * _KIND_DTYPES[seen_kind].itemsize
    votes_at = mask_at + n * mask_bytes
    colors_at = votes_at + n_votes * _KIND_DTYPES[votes_kind].itemsize
    has_colors = bool(flags & FLAG_COLORS)
    payload = _payload(blob, _HEADER.size + _PLANES.size, flags, colors_at + (n * 3 if has_colors else 0), n)
    keys = np.cumsum(np.frombuffer(payload, "<i8", n, 0), dtype=np.int64)
    weights = _plane(payload, weights_kind, n, n * 8, 1.0)
    seen = _plane(payload, seen_kind, n, seen_at, 1.0)
    mask = np.frombuffer(payload, np.uint8, n * mask_bytes, mask_at).reshape(n, mask_bytes)
    voting = np.unpackbits(mask, axis=1, count=n_classes, bitorder="little").astype(bool)
    if int(np.count_nonzero(voting)) != n_votes:
        raise StoreError(f"voxel blob: its vote bits name {np.count_nonzero(voting)} votes, its header {n_votes}")
    votes = np.zeros((n, n_classes), np.float32)
    votes[voting] = _plane(payload, votes_kind, n_votes, votes_at, VOTES_SCALE)
    colors = np.frombuffer(payload, np.uint8, n * 3, colors_at).reshape(3, n).copy().T if has_colors else None  # (N, 3) view
    return keys, weights, votes, seen, colors


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


def _decode_voxels_before_4(
    blob: bytes, version: int, flags: int, n_classes: int, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """``decode_voxels`` of a format 1, 2 or 3 blob (float32 arrays one after another)."""
    votes_dtype = np.dtype("<f2") if flags & FLAG_VOTES_F16 else np.dtype("<f4")
    n_float_arrays = 2 if version >= 2 else 1
    has_colors = version >= 3 and bool(flags & FLAG_COLORS)
    votes_at = n * 8 + n * 4 * n_float_arrays
    colors_at = votes_at + n * n_classes * votes_dtype.itemsize
    payload = _payload(blob, _HEADER.size, flags, colors_at + (n * 3 if has_colors else 0), n)
    keys = np.cumsum(np.frombuffer(payload, "<i8", n, 0), dtype=np.int64)
    weights = np.frombuffer(payload, "<f4", n, n * 8).astype(np.float32)
    seen = np.frombuffer(payload, "<f4", n, n * 12).astype(np.float32) if version >= 2 else weights.copy()
    votes = np.frombuffer(payload, votes_dtype, n * n_classes, votes_at).astype(np.float32).reshape(n, n_classes)
    colors = np.frombuffer(payload, np.uint8, n * 3, colors_at).reshape(3, n).copy().T if has_colors else None  # (N, 3) view
    return keys, weights, votes, seen, colors


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
        label_purity=obj.label_purity,
    )


#: The most a compressed metadata blob may unpack to (a real one is well under 1 kB; a long device list grows it).
MAX_META_BYTES = 1 << 20
META_ZLIB_LEVEL = 6  # the blobs are small: the best compression costs microseconds


def encode_meta(obj: MapObject) -> bytes:
    """The object's metadata (everything but the voxels) as compact JSON, compressed."""
    return zlib.compress(_meta_json(obj), META_ZLIB_LEVEL)


def _meta_json(obj: MapObject) -> bytes:
    return json.dumps(
        {
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
        },
        separators=(",", ":"),
    ).encode()


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
    except (ValueError, KeyError, TypeError, IndexError, zlib.error) as exc:
        raise StoreError(f"objects {list(object_ids)[:5]}: corrupt metadata ({type(exc).__name__}: {exc})") from exc


def _unpacked_meta(blob: bytes) -> bytes:
    """A metadata blob's JSON: as it is (formats 1-3), or decompressed (at most ``MAX_META_BYTES``)."""
    if blob[:1] == b"{":
        return blob
    unpacker = zlib.decompressobj()
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
        devices=frozenset(fields["devices"]),
        score_sum=float(fields["score_sum"]),
        created_at_s=float(fields["created_at_s"]),
        updated_at_s=float(fields["updated_at_s"]),
        aabb=_box(fields["aabb"]),
        obb=_obb(fields["obb"]),
        bounds=_box(fields["bounds"]),
        confirmed=bool(fields.get("confirmed", False)),
        floor_votes={int(k): int(v) for k, v in fields.get("floor_votes", {}).items()},
        label_purity=float(fields.get("label_purity", 0.0)),
    )


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
        n_missed=n_missed,
        n_gone=n_gone,
        label_purity=meta.label_purity,
    )
