"""ScanNet benchmark prediction files for one scene, and the boxes read back.

    <scene>.txt                  the benchmark's instance list: ``pred_mask/<scene>_<k>.txt <label id> <score>``
    pred_mask/<scene>_<k>.txt    one 0/1 line per vertex of the scene's mesh (only when a mesh is given:
                                 a vertex belongs to an object when it falls in one of its voxels)
    <scene>_boxes.txt            ``<label id> <score> <xmin> <ymin> <zmin> <xmax> <ymax> <zmax>`` per object, metres,
                                 in the map's frame: what the 3D detection evaluation reads (``read_boxes``)

Label ids are nyu40 ids, as ScanNet's label file gives them: chair 5, couch (sofa) 6, table 7, tv
(television) 25; laptops, which nyu40 files as otherprop, are 40 (and 40 reads back as laptop).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from arcloud.core.errors import InvalidInput
from arcloud.core.types import LabelledBox
from arcloud.core.voxels import points_to_keys

NYU40_OF_CLASS: dict[str, int] = {"chair": 5, "couch": 6, "table": 7, "tv": 25, "laptop": 40}
CLASS_OF_NYU40: dict[int, str] = {v: k for k, v in NYU40_OF_CLASS.items()}


@dataclass(frozen=True, eq=False)
class Prediction:
    """One object: its box, and its voxels' keys (for masks over a mesh)."""

    label: str
    score: float
    aabb_min: np.ndarray
    aabb_max: np.ndarray
    voxel_keys: np.ndarray | None = None


def vertex_mask(vertices_m: np.ndarray, voxel_keys: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(V,) bool: the vertices that fall in one of these voxels."""
    return np.isin(points_to_keys(np.asarray(vertices_m, np.float64), voxel_size_m), voxel_keys)


def scannet_files(
    scene: str, predictions: Sequence[Prediction], *, vertices_m: np.ndarray | None = None, voxel_size_m: float = 0.05
) -> dict[str, bytes]:
    """File name (relative) -> bytes. Objects of classes without a label id are left out."""
    if not scene or "/" in scene:
        raise InvalidInput("scene", "a scene name without '/'", repr(scene))
    kept = [p for p in predictions if p.label in NYU40_OF_CLASS]
    files: dict[str, bytes] = {}
    box_lines = ["# nyu40_id score xmin ymin zmin xmax ymax zmax (metres, the map's frame)"]
    instance_lines = []
    for k, p in enumerate(kept):
        label_id = NYU40_OF_CLASS[p.label]
        corners = " ".join(f"{v:.4f}" for v in (*p.aabb_min, *p.aabb_max))
        box_lines.append(f"{label_id} {p.score:.6f} {corners}")
        if vertices_m is not None and p.voxel_keys is not None:
            mask_name = f"pred_mask/{scene}_{k:03d}.txt"
            mask = vertex_mask(vertices_m, p.voxel_keys, voxel_size_m)
            files[mask_name] = ("\n".join("1" if m else "0" for m in mask) + "\n").encode()
            instance_lines.append(f"{mask_name} {label_id} {p.score:.6f}")
    files[f"{scene}.txt"] = "".join(f"{line}\n" for line in instance_lines).encode()
    files[f"{scene}_boxes.txt"] = "".join(f"{line}\n" for line in box_lines).encode()
    return files


def read_boxes(text: str) -> list[LabelledBox]:
    """The boxes of a ``<scene>_boxes.txt`` (``InvalidInput`` naming the line that is not one)."""
    boxes = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        try:
            label_id, score, values = int(parts[0]), float(parts[1]), np.array([float(v) for v in parts[2:]])
        except (ValueError, IndexError):
            raise InvalidInput(f"line {number}", "nyu40_id score xmin ymin zmin xmax ymax zmax", repr(line[:80])) from None
        if values.shape != (6,) or label_id not in CLASS_OF_NYU40:
            raise InvalidInput(f"line {number}", f"a label id of {sorted(CLASS_OF_NYU40)} and 6 numbers", repr(line[:80]))
        boxes.append(LabelledBox(CLASS_OF_NYU40[label_id], values[:3], values[3:], score))
    return boxes
