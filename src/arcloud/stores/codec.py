"""Binary encoding of objects for the Redis store (never pickle).

Voxels: one blob with a 12-byte header and three arrays, optionally zlib-compressed:

    header  <4s B B H I   magic b"ARCV", format version (1), flags, n_classes, n_voxels
    keys    int64 (N,)     first key, then the differences of the sorted unique keys (all > 0)
    weights float32 (N,)   exact
    votes   float32 (N, C) exact; or float16 with ``FLAG_VOTES_F16`` (relative error <= 2**-11,
                           largest vote 65504: only for maps whose voxels get fewer than ~60000 votes)
    (flags: ``FLAG_ZLIB`` = the arrays after the header are one zlib stream)

Sorted keys of one object are close together, so their differences are small and compress well; the
votes of a voxel are zero except for the few labels it received. Typical size: 6-12 bytes per voxel.

Metadata: a flat mapping of ASCII field names to bytes (the fields of the object's Redis HASH):
numbers as decimal text (floats as ``repr``: exact round trip), the devices as a JSON list, boxes
as packed little-endian float64. ``ObjectMeta`` is an object without its voxels (cheap to list).
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from arcloud.core.types import AABB, N_CLASSES, OBB, MapObject
from arcloud.errors import InvalidInput, StoreError

MAGIC = b"ARCV"
FORMAT_VERSION = 1
FLAG_ZLIB = 1
FLAG_VOTES_F16 = 2
ZLIB_MIN_BYTES = 256  # smaller payloads are stored raw (zlib would not pay for its own overhead)
ZLIB_LEVEL = 1
_HEADER = struct.Struct("<4sBBHI")
_BOX = struct.Struct("<6d")  # min xyz, max xyz
_OBB = struct.Struct("<16d")  # center xyz, size xyz, rotation 3x3 row-major, yaw

# Field names of an object's HASH (the Lua scripts read "version" and "cells").
VOXELS_FIELD = "voxels"
META_FIELDS = (
    "label", "score", "version", "n_voxels", "n_frames", "devices", "score_sum",
    "created_at_s", "updated_at_s", "aabb", "obb", "bounds",
)


def encode_voxels(keys: np.ndarray, weights: np.ndarray, votes: np.ndarray, *, votes_f16: bool = False) -> bytes:
    """keys (N,) int64 sorted unique, weights (N,) float32, votes (N, C) float32 -> bytes."""
    keys = np.asarray(keys)
    n = keys.size
    if keys.ndim != 1 or keys.dtype != np.int64:
        raise InvalidInput("keys", "(N,) int64", f"shape {keys.shape} and dtype {keys.dtype}")
    weights = np.asarray(weights)
    votes = np.asarray(votes)
    if weights.shape != (n,):
        raise InvalidInput("weights", f"shape ({n},)", f"shape {weights.shape}")
    if votes.ndim != 2 or votes.shape[0] != n:
        raise InvalidInput("votes", f"shape ({n}, n_classes)", f"shape {votes.shape}")
    deltas = np.empty(n, np.int64)
    if n:
        deltas[0] = keys[0]
        np.subtract(keys[1:], keys[:-1], out=deltas[1:])
        if n > 1 and deltas[1:].min() <= 0:
            raise InvalidInput("keys", "sorted unique voxel keys", "keys out of order or repeated")
    flags = FLAG_VOTES_F16 if votes_f16 else 0
    votes_dtype = np.dtype("<f2") if votes_f16 else np.dtype("<f4")
    payload = b"".join((
        deltas.astype("<i8", copy=False).tobytes(),
        weights.astype("<f4", copy=False).tobytes(),
        np.ascontiguousarray(votes, dtype=votes_dtype).tobytes(),
    ))
    if len(payload) >= ZLIB_MIN_BYTES:
        payload = zlib.compress(payload, ZLIB_LEVEL)
        flags |= FLAG_ZLIB
    return _HEADER.pack(MAGIC, FORMAT_VERSION, flags, votes.shape[1], n) + payload


def decode_voxels(blob: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """bytes -> (keys (N,) int64, weights (N,) float32, votes (N, C) float32)."""
    if len(blob) < _HEADER.size:
        raise StoreError(f"voxel blob of {len(blob)} bytes is shorter than its {_HEADER.size}-byte header")
    magic, version, flags, n_classes, n = _HEADER.unpack_from(blob)
    if magic != MAGIC or version != FORMAT_VERSION:
        raise StoreError(f"voxel blob: expected magic {MAGIC!r} version {FORMAT_VERSION}, got {magic!r} version {version}")
    payload = memoryview(blob)[_HEADER.size :]
    if flags & FLAG_ZLIB:
        try:
            payload = memoryview(zlib.decompress(payload))
        except zlib.error as exc:
            raise StoreError(f"voxel blob: corrupt zlib stream ({exc})") from exc
    votes_dtype = np.dtype("<f2") if flags & FLAG_VOTES_F16 else np.dtype("<f4")
    expected = n * 8 + n * 4 + n * n_classes * votes_dtype.itemsize
    if len(payload) != expected:
        raise StoreError(f"voxel blob: expected {expected} bytes for {n} voxels, got {len(payload)}")
    keys = np.cumsum(np.frombuffer(payload, "<i8", n, 0), dtype=np.int64)
    weights = np.frombuffer(payload, "<f4", n, n * 8).astype(np.float32)
    votes = np.frombuffer(payload, votes_dtype, n * n_classes, n * 12).astype(np.float32).reshape(n, n_classes)
    return keys, weights, votes


def pack_box(box: AABB) -> bytes:
    return _BOX.pack(*np.asarray(box.min, np.float64), *np.asarray(box.max, np.float64))


def unpack_box(blob: bytes) -> AABB:
    values = np.array(_BOX.unpack(blob))
    return AABB(values[:3], values[3:])


def pack_obb(obb: OBB) -> bytes:
    return _OBB.pack(
        *np.asarray(obb.center, np.float64), *np.asarray(obb.size, np.float64),
        *np.asarray(obb.rotation, np.float64).reshape(9), float(obb.yaw_rad),
    )


def unpack_obb(blob: bytes) -> OBB:
    values = np.array(_OBB.unpack(blob))
    return OBB(center=values[:3], size=values[3:6], rotation=values[6:15].reshape(3, 3), yaw_rad=float(values[15]))


@dataclass(frozen=True, eq=False, slots=True)
class ObjectMeta:
    """An object without its voxels: what listing the map needs."""

    id: int
    label: str
    score: float
    version: int
    n_voxels: int
    n_frames: int
    devices: frozenset[str]
    score_sum: float
    created_at_s: float
    updated_at_s: float
    aabb: AABB | None
    obb: OBB | None
    bounds: AABB | None

    @property
    def n_devices(self) -> int:
        return len(self.devices)


def meta_of(obj: MapObject) -> ObjectMeta:
    """The metadata of an object (what ``object_meta`` returns for it)."""
    return ObjectMeta(
        id=obj.id, label=obj.label, score=obj.score, version=obj.version, n_voxels=obj.n_voxels,
        n_frames=obj.n_frames, devices=obj.devices, score_sum=obj.score_sum, created_at_s=obj.created_at_s,
        updated_at_s=obj.updated_at_s, aabb=obj.aabb, obb=obj.obb, bounds=obj.bounds,
    )


def encode_object(obj: MapObject, *, votes_f16: bool = False) -> dict[str, bytes]:
    """The fields of an object's HASH: metadata and ``voxels``."""
    fields = {
        "label": obj.label.encode(),
        "score": repr(float(obj.score)).encode(),
        "version": str(int(obj.version)).encode(),
        "n_voxels": str(obj.n_voxels).encode(),
        "n_frames": str(int(obj.n_frames)).encode(),
        "devices": json.dumps(sorted(obj.devices)).encode(),
        "score_sum": repr(float(obj.score_sum)).encode(),
        "created_at_s": repr(float(obj.created_at_s)).encode(),
        "updated_at_s": repr(float(obj.updated_at_s)).encode(),
        VOXELS_FIELD: encode_voxels(obj.keys, obj.weights, obj.votes, votes_f16=votes_f16),
    }
    if obj.aabb is not None:
        fields["aabb"] = pack_box(obj.aabb)
    if obj.obb is not None:
        fields["obb"] = pack_obb(obj.obb)
    if obj.bounds is not None:
        fields["bounds"] = pack_box(obj.bounds)
    return fields


def _text(fields: Mapping[bytes, bytes], name: str, default: str = "0") -> str:
    value = fields.get(name.encode())
    return default if value is None else value.decode()


def decode_meta(object_id: int, fields: Mapping[bytes, bytes]) -> ObjectMeta:
    """An object's HASH (as HGETALL/HMGET return it, bytes keys) -> ``ObjectMeta``."""
    boxes = {name: fields.get(name.encode()) for name in ("aabb", "obb", "bounds")}
    try:
        return ObjectMeta(
            id=int(object_id),
            label=_text(fields, "label", ""),
            score=float(_text(fields, "score")),
            version=int(_text(fields, "version")),
            n_voxels=int(_text(fields, "n_voxels")),
            n_frames=int(_text(fields, "n_frames")),
            devices=frozenset(json.loads(_text(fields, "devices", "[]"))),
            score_sum=float(_text(fields, "score_sum")),
            created_at_s=float(_text(fields, "created_at_s")),
            updated_at_s=float(_text(fields, "updated_at_s")),
            aabb=None if boxes["aabb"] is None else unpack_box(boxes["aabb"]),
            obb=None if boxes["obb"] is None else unpack_obb(boxes["obb"]),
            bounds=None if boxes["bounds"] is None else unpack_box(boxes["bounds"]),
        )
    except (ValueError, struct.error) as exc:
        raise StoreError(f"object {object_id}: corrupt metadata ({exc})") from exc


def decode_object(object_id: int, fields: Mapping[bytes, bytes]) -> MapObject:
    """An object's HASH (HGETALL, bytes keys) -> ``MapObject``."""
    meta = decode_meta(object_id, fields)
    blob = fields.get(VOXELS_FIELD.encode())
    if blob is None:
        raise StoreError(f"object {object_id}: no voxels field")
    keys, weights, votes = decode_voxels(blob)
    if votes.shape[1] != N_CLASSES:
        raise StoreError(f"object {object_id}: expected votes for {N_CLASSES} classes, got {votes.shape[1]}")
    return MapObject(
        id=meta.id, keys=keys, weights=weights, votes=votes, n_frames=meta.n_frames, devices=meta.devices,
        score_sum=meta.score_sum, version=meta.version, created_at_s=meta.created_at_s,
        updated_at_s=meta.updated_at_s, label=meta.label, score=meta.score, aabb=meta.aabb, obb=meta.obb,
        bounds=meta.bounds,
    )
