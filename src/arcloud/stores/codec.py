"""Binary encoding of objects for the Redis store (never pickle).

Voxels: one blob with a 12-byte header and four or five arrays, optionally zlib-compressed:

    header  <4s B B H I   magic b"ARCV", format version (3), flags, n_classes, n_voxels
    keys    int64 (N,)     first key, then the differences of the sorted unique keys (all > 0)
    weights float32 (N,)   exact
    seen    float32 (N,)   exact (format 2 on; format 1 blobs, without it, read as seen = weights)
    votes   float32 (N, C) exact; or float16 with ``FLAG_VOTES_F16`` (relative error <= 2**-11,
                           largest vote 65504: only for maps whose voxels get fewer than ~60000 votes)
    colors  uint8 (3, N)   exact (the object's are uint8): all reds, then greens, then blues; only
                           with ``FLAG_COLORS`` (format 3 on; without it, or in format 1 and 2 blobs,
                           the colours are unknown: None)
    (flags: ``FLAG_ZLIB`` = the arrays after the header are one zlib stream, used from 256 bytes)

Sorted keys of one object are close together, so their differences are small and compress well; the
votes of a voxel are zero except for the few labels it received. Random weights and votes (the worst
case) take about 13 bytes a voxel. Colours add 3 bytes a voxel before zlib and about as much after it:
measured colours are noisy (a map of 7-Scenes redkitchen from YOLO masks, every 5th frame: 6.8 bytes a
voxel without colours, 10.0 with).

Blobs of every version in ``READABLE_VERSIONS`` are read, each by the version in its own header, so a
map whose header names an older codec version (``core.header``) stays readable and writable: the
stores accept it (``ObjectStore.readable_codec_versions``) and its objects move to the current format
as they are rewritten. A process older than the current format cannot read the new blobs (it raises
``StoreError`` naming the version): upgrade every process of a map together.

Metadata: compact JSON of the object without its voxels (floats written by ``repr``: exact round
trip; boxes as lists of floats; devices as a sorted list). ``arcloud.ports.ObjectMeta`` is that, decoded.
Bounds: 6 little-endian float64 (min xyz, max xyz), the spatial index's entry of an object.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from arcloud.core.types import AABB, N_CLASSES, OBB, MapObject
from arcloud.errors import InvalidInput, StoreError
from arcloud.ports import ObjectMeta

MAGIC = b"ARCV"
FORMAT_VERSION = 3
READABLE_VERSIONS: tuple[int, ...] = (1, 2, 3)
FLAG_ZLIB = 1
FLAG_VOTES_F16 = 2
FLAG_COLORS = 4
ZLIB_MIN_BYTES = 256  # smaller payloads are stored raw (zlib would not pay for its own overhead)
ZLIB_LEVEL = 1
_HEADER = struct.Struct("<4sBBHI")
_BOX = struct.Struct("<6d")  # min xyz, max xyz


def encode_voxels(
    keys: np.ndarray,
    weights: np.ndarray,
    votes: np.ndarray,
    *,
    seen: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    votes_f16: bool = False,
) -> bytes:
    """keys (N,) int64 sorted unique, weights (N,) float32, votes (N, C) float32, seen (N,) float32
    (None: equal to weights), colors (N, 3) uint8 (None: unknown) -> bytes."""
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
    flags = (FLAG_VOTES_F16 if votes_f16 else 0) | (0 if colors is None else FLAG_COLORS)
    votes_dtype = np.dtype("<f2") if votes_f16 else np.dtype("<f4")
    payload = b"".join(
        (
            deltas.astype("<i8", copy=False).tobytes(),
            weights.astype("<f4", copy=False).tobytes(),
            seen.astype("<f4", copy=False).tobytes(),
            np.ascontiguousarray(votes, dtype=votes_dtype).tobytes(),
            b"" if colors is None else np.asarray(colors).T.tobytes(),  # (3, N): one channel after another
        )
    )
    if len(payload) >= ZLIB_MIN_BYTES:
        payload = zlib.compress(payload, ZLIB_LEVEL)
        flags |= FLAG_ZLIB
    return _HEADER.pack(MAGIC, FORMAT_VERSION, flags, votes.shape[1], n) + payload


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
    votes_dtype = np.dtype("<f2") if flags & FLAG_VOTES_F16 else np.dtype("<f4")
    n_float_arrays = 2 if version >= 2 else 1
    has_colors = version >= 3 and bool(flags & FLAG_COLORS)
    votes_at = n * 8 + n * 4 * n_float_arrays
    colors_at = votes_at + n * n_classes * votes_dtype.itemsize
    expected = colors_at + (n * 3 if has_colors else 0)
    payload = memoryview(blob)[_HEADER.size :]
    if flags & FLAG_ZLIB:
        try:  # at most what the header announces (and one byte to tell more): a small blob cannot expand without bound
            payload = memoryview(zlib.decompressobj().decompress(payload, expected + 1))
        except zlib.error as exc:
            raise StoreError(f"voxel blob: corrupt zlib stream ({exc})") from exc
    if len(payload) != expected:
        raise StoreError(f"voxel blob: expected {expected} bytes for {n} voxels, got {len(payload)}")
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


def encode_meta(obj: MapObject) -> bytes:
    """The object's metadata (everything but the voxels) as compact JSON."""
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
    """Many ``encode_meta`` JSONs at once (one parse) -> ``ObjectMeta`` each."""
    try:
        parsed = json.loads(b"[" + b",".join(blobs) + b"]")
        return [_meta(int(i), fields) for i, fields in zip(object_ids, parsed, strict=True)]
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise StoreError(f"objects {list(object_ids)[:5]}: corrupt metadata ({type(exc).__name__}: {exc})") from exc


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
