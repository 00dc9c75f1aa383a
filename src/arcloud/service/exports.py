"""A map's objects in the formats of ``arcloud.formats`` (``GET /v1/maps/{map}/export``): the objects come
from the store, the bytes from the format's encoder. Every export is in the map's world frame (metres, z
up; glTF's own axes for GLB) and says so.

Exports are bounded (``export_from_store``): before any voxel is read, the objects' metadata says how many objects
and voxels the export would carry, and one of more than ``max_export_objects`` objects or (PLY, JSON with voxels)
``max_export_voxels`` voxels is refused (``InvalidInput``, field ``export``: 422 naming the limit). Within them the
objects are read and encoded ``READ_BATCH`` at a time, so memory holds the output and one batch (a JSON export with
voxels of a 1,500-object map took 26.6 s and 240 MB before, and no limit stopped it).

Each export, snapshot or restore holds a map's file in memory while it is built or read: ``ExportPlaces`` bounds how
many an API process runs at once (``max_exports``), and how many of them one key holds."""

from __future__ import annotations

import io
import json
import threading
import zipfile
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, Literal

import numpy as np

from arcloud.core.types import MapObject, Params
from arcloud.core.voxels import key_centers
from arcloud.errors import InvalidInput
from arcloud.formats.colors import OTHER_COLOR, class_color, object_color
from arcloud.formats.gltf import Box, boxes_glb
from arcloud.formats.ply import points_ply
from arcloud.formats.scannet import Prediction, scannet_files
from arcloud.ports import ObjectMeta, ObjectStore
from arcloud.service.schemas import object_out

ExportFormat = Literal["json", "ply", "glb", "scannet"]
#: What a refused export, snapshot or restore is told to wait, in seconds.
EXPORT_RETRY_AFTER_S = 2
ColorBy = Literal["object", "class", "rgb"]

#: Media type and file extension of each format.
MEDIA: dict[str, tuple[str, str]] = {
    "json": ("application/json", "json"),
    "ply": ("application/octet-stream", "ply"),
    "glb": ("model/gltf-binary", "glb"),
    "scannet": ("application/zip", "zip"),
}
WORLD_FRAME = (
    "the map's world frame: metres, z up (the frame of the poses sent, turned by the device's convention, world_up and "
    "alignment: arcloud.core.conventions.world2map takes a device's world into it)"
)
READ_BATCH = 64  # objects read from the store (voxels decoded) and encoded at a time


def export_json(map_id: str, objects: Iterable[MapObject | ObjectMeta], params: Params, *, voxels: bool) -> bytes:
    """The objects as the API lists them (with voxel centres and weights when ``voxels``), in a declared frame.
    Each object is encoded alone (its voxels as Python lists only while it is encoded)."""
    listed = []
    for obj in objects:
        out = object_out(obj)
        if voxels and isinstance(obj, MapObject):
            out["voxels"] = {
                "voxel_size_m": params.voxel_size_m,
                "centers": np.round(key_centers(obj.keys, params.voxel_size_m), 5).tolist(),
                "weights": obj.weights.astype(float).tolist(),
                "colors": voxel_colors_out(obj),
            }
        listed.append(json.dumps(out))
    document = {"map_id": map_id, "frame": WORLD_FRAME, "world_from_export": np.eye(4).tolist(), "objects": []}
    head = json.dumps(document).removesuffix("[]}")
    return (head + "[" + ", ".join(listed) + "]}").encode()


def voxel_colors_out(obj: MapObject) -> list[list[int]] | None:
    """The object's voxel colours as 0-255 (r, g, b) lists, aligned with its voxels; None when unknown."""
    return None if obj.colors is None else obj.colors.tolist()


def point_colors(obj: MapObject, color: ColorBy) -> np.ndarray:
    """(N, 3) 0-255 colours of the object's voxels: its own, its class's or each voxel's mean RGB (grey,
    ``OTHER_COLOR``, for an object whose colours are unknown: stored before codec version 3)."""
    if color == "rgb" and obj.colors is not None:
        return obj.colors
    flat = {"object": object_color(obj.id), "class": class_color(obj.label), "rgb": OTHER_COLOR}[color]
    return np.tile(np.array(flat, np.uint8), (len(obj.keys), 1))


def export_ply(map_id: str, objects: Iterable[MapObject], params: Params, *, color: ColorBy) -> bytes:
    """Every voxel of the objects as a point at its centre, coloured by object, by class or by its mean RGB (each
    object's points taken as it comes: its other arrays are not kept)."""
    parts: list[np.ndarray] = [np.zeros((0, 3))]
    colors: list[np.ndarray] = [np.zeros((0, 3), np.uint8)]
    ids: list[np.ndarray] = [np.zeros(0, np.int32)]
    for obj in objects:
        parts.append(key_centers(obj.keys, params.voxel_size_m))
        colors.append(point_colors(obj, color))
        ids.append(np.full(len(obj.keys), obj.id, np.int32))
    comment = f"arcloud map {map_id}: voxel centres of {len(parts) - 1} objects, {params.voxel_size_m} m voxels\n{WORLD_FRAME}"
    return points_ply(np.concatenate(parts), np.concatenate(colors), np.concatenate(ids), comment=comment)


def export_glb(map_id: str, objects: Sequence[MapObject | ObjectMeta]) -> bytes:
    """One node per boxed object: its oriented box (its axis-aligned one when it has none)."""
    boxes = []
    for obj in objects:
        row = object_out(obj)
        if obj.obb is not None:
            center, size, yaw = obj.obb.center, obj.obb.size, float(obj.obb.yaw_rad)
        elif obj.aabb is not None:
            center, size, yaw = (obj.aabb.min + obj.aabb.max) / 2, obj.aabb.max - obj.aabb.min, 0.0
        else:
            continue
        boxes.append(
            Box(
                obj.id,
                obj.label,
                float(obj.score),
                tuple(float(v) for v in center),  # type: ignore[arg-type]  # three coordinates
                tuple(float(v) for v in size),  # type: ignore[arg-type]  # three lengths
                yaw,
                {"status": row["status"], "version": row["version"], "n_voxels": row["n_voxels"]},
            )
        )
    return boxes_glb(boxes, scene_extras={"map_id": map_id, "frame": WORLD_FRAME})


def export_scannet(map_id: str, objects: Sequence[MapObject | ObjectMeta]) -> bytes:
    """The ScanNet prediction files of the map as one scene named after it, zipped (no masks: the service
    holds no scene mesh; ``arcloud export --format scannet --mesh`` writes them)."""
    predictions = [Prediction(o.label, float(o.score), o.aabb.min, o.aabb.max) for o in objects if o.aabb is not None and o.label]
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as out:
        for name, data in scannet_files(map_id, predictions).items():
            out.writestr(name, data)
    return archive.getvalue()


def export_map(
    map_id: str, objects: Iterable[Any], params: Params, fmt: ExportFormat, *, color: ColorBy = "object", voxels: bool = False
) -> bytes:
    """``objects``: ``MapObject`` for ply (and json with voxels; any iterable, read once), else a sequence of
    ``ObjectMeta`` will do."""
    if fmt == "json":
        return export_json(map_id, objects, params, voxels=voxels)
    if fmt == "ply":
        return export_ply(map_id, objects, params, color=color)
    if fmt == "glb":
        return export_glb(map_id, list(objects))
    return export_scannet(map_id, list(objects))


def needs_voxels(fmt: ExportFormat, voxels: bool) -> bool:
    """Whether the export reads the objects' voxels (slower than their metadata)."""
    return fmt == "ply" or (fmt == "json" and voxels)


def check_export_size(
    objects: Sequence[ObjectMeta], fmt: ExportFormat, voxels: bool, *, max_voxels: int, max_objects: int
) -> None:
    """``InvalidInput`` (field ``export``) naming the limit when an export of ``objects`` would carry more than
    ``max_objects`` objects or, reading voxels, ``max_voxels`` voxels."""
    if len(objects) > max_objects:
        raise InvalidInput(
            "export",
            f"at most {max_objects} objects in one export (max_export_objects); export a part of the map "
            "(the served objects: no include=tentative)",
            f"{len(objects)} objects",
        )
    if needs_voxels(fmt, voxels) and (n_voxels := sum(o.n_voxels for o in objects)) > max_voxels:
        raise InvalidInput(
            "export",
            f"at most {max_voxels} voxels in one export of voxels (max_export_voxels); export without voxels (format=json "
            "or glb) or read the objects' voxels one by one (GET .../objects/{id}?voxels=true)",
            f"{n_voxels} voxels in {len(objects)} objects",
        )


def export_from_store(
    store: ObjectStore,
    map_id: str,
    params: Params,
    fmt: ExportFormat,
    *,
    include_tentative: bool,
    color: ColorBy = "object",
    voxels: bool = False,
    max_voxels: int,
    max_objects: int,
) -> bytes:
    """The map's served objects (every one with ``include_tentative``) as ``fmt``: refused by ``check_export_size``
    before any voxel is read, then read and encoded ``READ_BATCH`` objects at a time."""
    metas = [o for o in store.list_meta(map_id) if include_tentative or o.confirmed]
    check_export_size(metas, fmt, voxels, max_voxels=max_voxels, max_objects=max_objects)
    if not needs_voxels(fmt, voxels):
        return export_map(map_id, metas, params, fmt, color=color, voxels=voxels)
    return export_map(map_id, read_objects(store, map_id, [o.id for o in metas]), params, fmt, color=color, voxels=voxels)


def read_objects(store: ObjectStore, map_id: str, ids: Sequence[int]) -> Iterator[MapObject]:
    """The objects ``ids`` with their voxels, read ``READ_BATCH`` at a time (those gone since skipped)."""
    for first in range(0, len(ids), READ_BATCH):
        yield from store.get(map_id, ids[first : first + READ_BATCH])


__all__ = [
    "EXPORT_RETRY_AFTER_S",
    "MEDIA",
    "READ_BATCH",
    "ColorBy",
    "ExportFormat",
    "ExportPlaces",
    "check_export_size",
    "export_from_store",
    "export_map",
    "needs_voxels",
    "read_objects",
]


class ExportPlaces:
    """The ``places`` (``max_exports``) of an API process for exports, snapshots and restores under way, whoever asks;
    a key holds at most all but one of them when there are several, so that one key, asking again and again, cannot
    keep every other key's exports and its admin's snapshots waiting. Safe to call from many threads."""

    def __init__(self, places: int) -> None:
        self.places = places
        self.taken = 0
        self.by_key: Counter[str] = Counter()
        self._lock = threading.Lock()

    def take(self, key_id: str | None) -> str | None:
        """A place for ``key_id`` (None: no key, with auth none): None when taken, else why not."""
        with self._lock:
            if self.taken >= self.places:
                return (
                    f"{self.places} exports, snapshots or restores are under way in this API process, the most it runs "
                    "at once (max_exports)"
                )
            if key_id is not None and self.places > 1 and self.by_key[key_id] >= self.places - 1:
                return (
                    f"key {key_id} has {self.by_key[key_id]} of this API process's {self.places} exports, snapshots "
                    "or restores under way, the most one key may (all but one: max_exports)"
                )
            self.taken += 1
            if key_id is not None:
                self.by_key[key_id] += 1
            return None

    def give_back(self, key_id: str | None) -> None:
        """The place ``take`` gave ``key_id``."""
        with self._lock:
            self.taken -= 1
            if key_id is not None:
                self.by_key[key_id] -= 1
                if self.by_key[key_id] <= 0:
                    del self.by_key[key_id]
