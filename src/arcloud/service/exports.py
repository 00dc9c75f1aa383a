"""A map's objects in the formats of ``arcloud.formats`` (``GET /v1/maps/{map}/export``): the objects come
from the store, the bytes from the format's encoder. Every export is in the map's world frame (metres, z
up; glTF's own axes for GLB) and says so."""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np

from arcloud.core.types import MapObject, Params
from arcloud.core.voxels import key_centers
from arcloud.formats.colors import OTHER_COLOR, class_color, object_color
from arcloud.formats.gltf import Box, boxes_glb
from arcloud.formats.ply import points_ply
from arcloud.formats.scannet import Prediction, scannet_files
from arcloud.ports import ObjectMeta
from arcloud.service.schemas import object_out

ExportFormat = Literal["json", "ply", "glb", "scannet"]
ColorBy = Literal["object", "class", "rgb"]

#: Media type and file extension of each format.
MEDIA: dict[str, tuple[str, str]] = {
    "json": ("application/json", "json"),
    "ply": ("application/octet-stream", "ply"),
    "glb": ("model/gltf-binary", "glb"),
    "scannet": ("application/zip", "zip"),
}
WORLD_FRAME = "the map's world frame: metres, z up (the frame of the devices' cam2world poses)"


def export_json(map_id: str, objects: Sequence[MapObject | ObjectMeta], params: Params, *, voxels: bool) -> bytes:
    """The objects as the API lists them (with voxel centres and weights when ``voxels``), in a declared frame."""
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
        listed.append(out)
    document = {"map_id": map_id, "frame": WORLD_FRAME, "world_from_export": np.eye(4).tolist(), "objects": listed}
    return json.dumps(document).encode()


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


def export_ply(map_id: str, objects: Sequence[MapObject], params: Params, *, color: ColorBy) -> bytes:
    """Every voxel of the objects as a point at its centre, coloured by object, by class or by its mean RGB."""
    parts = [key_centers(o.keys, params.voxel_size_m) for o in objects]
    points = np.concatenate(parts) if parts else np.zeros((0, 3))
    colors = np.concatenate([point_colors(o, color) for o in objects]) if objects else np.zeros((0, 3), np.uint8)
    ids = np.concatenate([np.full(len(o.keys), o.id, np.int32) for o in objects]) if objects else np.zeros(0, np.int32)
    comment = f"arcloud map {map_id}: voxel centres of {len(objects)} objects, {params.voxel_size_m} m voxels\n{WORLD_FRAME}"
    return points_ply(points, colors, ids, comment=comment)


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
    map_id: str, objects: Sequence[Any], params: Params, fmt: ExportFormat, *, color: ColorBy = "object", voxels: bool = False
) -> bytes:
    """``objects``: ``MapObject`` for ply (and json with voxels), else ``ObjectMeta`` will do."""
    if fmt == "json":
        return export_json(map_id, objects, params, voxels=voxels)
    if fmt == "ply":
        return export_ply(map_id, objects, params, color=color)
    if fmt == "glb":
        return export_glb(map_id, objects)
    return export_scannet(map_id, objects)


def needs_voxels(fmt: ExportFormat, voxels: bool) -> bool:
    """Whether the export reads the objects' voxels (slower than their metadata)."""
    return fmt == "ply" or (fmt == "json" and voxels)


__all__ = ["MEDIA", "ColorBy", "ExportFormat", "export_map", "needs_voxels"]
