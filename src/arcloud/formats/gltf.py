"""Boxes as a binary glTF 2.0 file (GLB): one node per object, a unit cube scaled, turned and moved to the
object's oriented box, with the object's ``id``, ``label``, ``score`` and ``status`` in the node's ``extras``.

glTF is y-up and the map z-up: each node's transform is the box's in glTF axes (x, z, -y), so the file
opens upright in any viewer; the scene's ``extras.gltf_from_world`` says so. One material per class (its
colour, half transparent), one mesh per class sharing one cube (8 corners, 12 triangles).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from arcloud.core.errors import InvalidInput
from arcloud.formats.colors import class_color

GLB_MAGIC = 0x46546C67  # "glTF"
JSON_CHUNK = 0x4E4F534A  # "JSON"
BIN_CHUNK = 0x004E4942  # "BIN\0"
#: Maps the map's world (z up) to glTF's axes (y up).
GLTF_FROM_WORLD = ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, -1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))

_CUBE_CORNERS = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], np.float32)
_CUBE_TRIANGLES = np.array(
    [0, 1, 3, 0, 3, 2, 4, 6, 7, 4, 7, 5, 0, 4, 5, 0, 5, 1, 2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4, 1, 5, 7, 1, 7, 3], np.uint16
)


@dataclass(frozen=True)
class Box:
    """An object's oriented box in the map's world: centre and size (m), yaw about z (rad)."""

    object_id: int
    label: str
    score: float
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw_rad: float = 0.0
    extras: dict[str, object] = field(default_factory=dict)


def boxes_glb(boxes: Sequence[Box], *, scene_extras: dict[str, object] | None = None) -> bytes:
    """The GLB file's bytes."""
    for box in boxes:
        values = (*box.center, *box.size, box.yaw_rad, box.score)
        if not all(math.isfinite(v) for v in values) or min(box.size) < 0:
            raise InvalidInput(f"box {box.object_id}", "finite centre, size >= 0, yaw and score", repr(values))
    binary = _CUBE_CORNERS.tobytes() + _CUBE_TRIANGLES.tobytes()
    labels = sorted({b.label for b in boxes})
    materials = []
    for label in labels:
        r, g, b = class_color(label)
        materials.append(
            {
                "name": label,
                "pbrMetallicRoughness": {"baseColorFactor": [r / 255, g / 255, b / 255, 0.5], "metallicFactor": 0.0},
                "alphaMode": "BLEND",
                "doubleSided": True,
            }
        )
    meshes = [
        {"name": label, "primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": k, "mode": 4}]}
        for k, label in enumerate(labels)
    ]
    nodes = []
    for box in boxes:
        x, y, z = box.center
        sx, sy, sz = box.size
        half = box.yaw_rad / 2  # a turn about the world's z is one about glTF's y
        nodes.append(
            {
                "name": f"{box.label} {box.object_id}",
                "mesh": labels.index(box.label),
                "translation": [x, z, -y],
                "rotation": [0.0, math.sin(half), 0.0, math.cos(half)],
                "scale": [max(sx, 1e-6), max(sz, 1e-6), max(sy, 1e-6)],
                "extras": {"id": int(box.object_id), "label": box.label, "score": float(box.score), **box.extras},
            }
        )
    document = {
        "asset": {"version": "2.0", "generator": "arcloud"},
        "scene": 0,
        "scenes": [
            {
                "name": "arcloud map",
                "nodes": list(range(len(nodes))),
                "extras": {"gltf_from_world": [list(row) for row in GLTF_FROM_WORLD], **(scene_extras or {})},
            }
        ],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": _CUBE_CORNERS.nbytes, "target": 34962},
            {"buffer": 0, "byteOffset": _CUBE_CORNERS.nbytes, "byteLength": _CUBE_TRIANGLES.nbytes, "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3", "min": [-0.5] * 3, "max": [0.5] * 3},
            {"bufferView": 1, "componentType": 5123, "count": len(_CUBE_TRIANGLES), "type": "SCALAR"},
        ],
    }
    if not nodes:  # a scene of nothing: no mesh, material or buffer to refer to
        for name in ("meshes", "materials", "buffers", "bufferViews", "accessors"):
            del document[name]
        binary = b""
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    chunks = struct.pack("<II", len(text), JSON_CHUNK) + text
    if binary:
        chunks += struct.pack("<II", len(binary), BIN_CHUNK) + binary
    return struct.pack("<III", GLB_MAGIC, 2, 12 + len(chunks)) + chunks
