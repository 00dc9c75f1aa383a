"""Ground-truth boxes of a recording, ``gt-boxes.json`` (any layout: 7-Scenes, TUM RGB-D, ScanNet), parsed
once into ``GroundTruthBoxes``.

The file's world is the frame of the recording's pose files (7-Scenes ``frame-*.pose.txt``, TUM
``groundtruth.txt``, ScanNet ``pose/``: the *unaligned* scan frame). Its boxes lie in its own *aligned*
frame (z up, floor at z = 0, x along the walls), related to the file's world by
``gravity_aligned.world_to_aligned`` (``file2aligned``). Required fields: ``gravity_aligned.world_to_aligned``
and, per object of ``gravity_aligned.objects``, ``id``, ``label``, ``aabb_observed_min/max``,
``aabb_min/max`` and ``visible_frames``; everything else is optional (see ``load_ground_truth``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from arcloud.core.types import CLASSES, Intrinsics, LabelledBox
from arcloud.datasets.frames import ColourCamera
from arcloud.errors import DatasetError, InvalidInput

GT_BOXES_FILE = "gt-boxes.json"
#: The two boxes of every ground-truth object: what the sensor saw (the primary score) and amodal.
BOX_KINDS = ("observed", "amodal")
#: How far from orthonormal a file's rotation may be (its numbers are rounded to 4 decimals).
_GT_ROTATION_TOLERANCE = 1e-3


@dataclass(frozen=True, eq=False)
class GroundTruthObject:
    """One hand-checked object of ``gt-boxes.json``; boxes in the ground truth's aligned frame.

    observed: the box of the depth points the sensor saw (ScanNet's convention for ground truth).
    amodal: completed (chairs under the table from a fitted template, the table down to the floor).
    visible_frames: (first, last) frame numbers in which it is visible, inclusive."""

    id: str
    label: str
    observed: LabelledBox
    amodal: LabelledBox
    visible_frames: tuple[int, int]
    confidence: str
    uncertainty_m: float | None
    notes: str

    def box(self, kind: str) -> LabelledBox:
        """The ``observed`` or ``amodal`` box."""
        if kind not in BOX_KINDS:
            raise InvalidInput("box kind", f"one of {BOX_KINDS}", repr(kind))
        return self.observed if kind == "observed" else self.amodal

    def visible_within(self, first_frame: int, last_frame: int) -> bool:
        """Whether its visible range meets the frame numbers ``first_frame..last_frame`` (inclusive)."""
        return self.visible_frames[0] <= last_frame and first_frame <= self.visible_frames[1]


@dataclass(frozen=True, eq=False)
class GroundTruthBoxes:
    """``gt-boxes.json`` parsed: ``file2aligned`` (4, 4) maps the file's (pose) world to the aligned
    frame of the boxes (the file's ``gravity_aligned.world_to_aligned``: z up, floor at z = 0, x along
    the walls); ``objects`` hold the boxes there. ``not_annotated``: things a detector may fire on that
    are none of our classes; ``method``: how the boxes were made; ``colour``: the colour camera as the
    annotation estimated it (``colour_intrinsics_estimated``), None when the file has none.
    ``up_axis_file``: (3,) unit up in the file's world (``up_axis_world``), None when the file has none.
    ``box_kinds``: the kinds of box its objects have apart (a mesh annotation has one: observed)."""

    path: Path
    file2aligned: np.ndarray
    objects: tuple[GroundTruthObject, ...]
    not_annotated: tuple[str, ...]
    method: str
    colour: ColourCamera | None = None
    up_axis_file: np.ndarray | None = None
    box_kinds: tuple[str, ...] = BOX_KINDS

    @property
    def up_file(self) -> np.ndarray:
        """(3,) unit up in the file's world: ``up_axis_world``, else the aligned frame's +z (declared up)."""
        return (
            self.up_axis_file
            if self.up_axis_file is not None
            else self.file2aligned[2, :3] / np.linalg.norm(self.file2aligned[2, :3])
        )

    @property
    def up_field(self) -> str:
        """The field ``up_file`` comes from."""
        return "up_axis_world" if self.up_axis_file is not None else "gravity_aligned.world_to_aligned +z"

    def boxes(self, kind: str = "observed", *, frames: tuple[int, int] | None = None) -> list[LabelledBox]:
        """The ``kind`` boxes (see ``BOX_KINDS``), of the objects visible within ``frames`` = (first,
        last) frame numbers when given."""
        return [o.box(kind) for o in self.objects_within(frames)]

    def objects_within(self, frames: tuple[int, int] | None = None) -> list[GroundTruthObject]:
        """The objects visible within ``frames`` = (first, last) frame numbers (all when None)."""
        return [o for o in self.objects if frames is None or o.visible_within(*frames)]


def load_ground_truth(path: str | Path) -> GroundTruthBoxes:
    """Parse ``gt-boxes.json``: ``gravity_aligned.world_to_aligned`` (4x4, rigid) and, per object of
    ``gravity_aligned.objects``, ``id``, ``label`` (one of ``CLASSES``), ``aabb_observed_min/max`` and
    ``aabb_min/max`` (the aligned frame), ``visible_frames`` ([first, last]); optionally ``up_axis_world``
    (3 numbers: up in the file's world), ``colour_intrinsics_estimated``, ``not_annotated``, ``method``
    and, per object, ``confidence``, ``uncertainty_m``, ``notes``. The top-level ``objects`` (boxes in
    the tilted pose frame, much larger) are not read. Raises ``DatasetError`` naming the field that is
    missing or malformed."""
    file = Path(path)
    try:
        data = json.loads(file.read_text())
    except OSError as exc:
        raise DatasetError(f"{file}: expected a readable ground-truth file, got {exc}") from exc
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{file}: expected JSON, got {exc}") from exc
    aligned = _field(file, data, "gravity_aligned", Mapping)
    file2aligned = _rigid(
        file, "gravity_aligned.world_to_aligned", _field(file, aligned, "world_to_aligned", list, "gravity_aligned.")
    )
    entries = cast(list, _field(file, aligned, "objects", list, "gravity_aligned."))
    if not entries:
        raise DatasetError(f"{file}: gravity_aligned.objects: expected at least one object, got none")
    objects = tuple(_ground_truth_object(file, i, entry) for i, entry in enumerate(entries))
    ids = [o.id for o in objects]
    if len(set(ids)) != len(ids):
        raise DatasetError(f"{file}: gravity_aligned.objects: expected distinct ids, got {ids}")
    not_annotated = tuple(
        f"{item.get('what', '')} ({item.get('why', '')})" if isinstance(item, Mapping) else str(item)
        for item in data.get("not_annotated", [])
    )
    colour = _colour_camera(file, data["colour_intrinsics_estimated"]) if "colour_intrinsics_estimated" in data else None
    up_axis = None
    if "up_axis_world" in data:
        up_axis = _numbers(file, "up_axis_world", data["up_axis_world"], (3,))
        if np.linalg.norm(up_axis) < 1e-9:
            raise DatasetError(f"{file}: up_axis_world: expected a non-zero direction, got {up_axis.tolist()}")
        up_axis = up_axis / np.linalg.norm(up_axis)
    return GroundTruthBoxes(file, file2aligned, objects, not_annotated, str(data.get("method", "")), colour, up_axis)


def _colour_camera(file: Path, entry: object) -> ColourCamera:
    """``colour_intrinsics_estimated``: fx, fy, cx, cy (pixels) and depth_to_colour_translation_m (3)."""
    where = "colour_intrinsics_estimated"
    if not isinstance(entry, Mapping):
        raise DatasetError(f"{file}: {where}: expected an object with fx, fy, cx, cy, got {type(entry).__name__}")
    values = _numbers(file, f"{where}.fx/fy/cx/cy", [entry.get(k) for k in ("fx", "fy", "cx", "cy")], (4,))
    if values[0] <= 0 or values[1] <= 0:
        raise DatasetError(f"{file}: {where}: expected positive focal lengths, got fx {values[0]}, fy {values[1]}")
    depth2rgb = np.eye(4)
    depth2rgb[:3, 3] = _numbers(
        file, f"{where}.depth_to_colour_translation_m", entry.get("depth_to_colour_translation_m", [0, 0, 0]), (3,)
    )
    return ColourCamera(Intrinsics(*(float(v) for v in values)), depth2rgb)


def _field(file: Path, data: object, key: str, kind: type, prefix: str = "") -> object:
    if not isinstance(data, Mapping) or key not in data:
        raise DatasetError(f"{file}: expected a field {prefix}{key}, got none")
    value = data[key]
    if not isinstance(value, kind):
        raise DatasetError(f"{file}: {prefix}{key}: expected a {kind.__name__}, got {type(value).__name__}")
    return value


def _numbers(file: Path, name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{file}: {name}: expected finite numbers of shape {shape}, got {value!r}") from exc
    if array.shape != shape or not np.all(np.isfinite(array)):
        raise DatasetError(f"{file}: {name}: expected finite numbers of shape {shape}, got {value!r}")
    return array


def _rigid(file: Path, name: str, value: object) -> np.ndarray:
    matrix = _numbers(file, name, value, (4, 4))
    rotation = matrix[:3, :3]
    error, det = float(np.abs(rotation.T @ rotation - np.eye(3)).max()), float(np.linalg.det(rotation))
    if not np.allclose(matrix[3], (0, 0, 0, 1)) or error > _GT_ROTATION_TOLERANCE or det < 0:
        raise DatasetError(f"{file}: {name}: expected a rigid transform (rotation, translation, last row 0 0 0 1), "
                           f"got last row {matrix[3].tolist()}, orthonormality error {error:.2g}, det {det:.3f}")  # fmt: skip
    return matrix


def _ground_truth_object(file: Path, index: int, entry: object) -> GroundTruthObject:
    where = f"gravity_aligned.objects[{index}]"
    if not isinstance(entry, Mapping):
        raise DatasetError(f"{file}: {where}: expected an object, got {type(entry).__name__}")
    object_id = str(_field(file, entry, "id", str, f"{where}."))
    where = f"{where} ({object_id})"
    label = str(_field(file, entry, "label", str, f"{where}."))
    if label not in CLASSES:
        raise DatasetError(f"{file}: {where}.label: expected one of {CLASSES}, got {label!r}")
    boxes = {}
    for kind, prefix in (("observed", "aabb_observed_"), ("amodal", "aabb_")):
        lo = _numbers(file, f"{where}.{prefix}min", entry.get(f"{prefix}min"), (3,))
        hi = _numbers(file, f"{where}.{prefix}max", entry.get(f"{prefix}max"), (3,))
        if np.any(hi <= lo):
            raise DatasetError(f"{file}: {where}.{prefix}max: expected above {prefix}min {lo.tolist()}, got {hi.tolist()}")
        boxes[kind] = LabelledBox(label, lo, hi)
    frames = _numbers(file, f"{where}.visible_frames", entry.get("visible_frames"), (2,))
    if np.any(frames != np.round(frames)) or frames[0] > frames[1] or frames[0] < 0:
        raise DatasetError(f"{file}: {where}.visible_frames: expected [first, last] frame numbers, got {frames.tolist()}")
    uncertainty = entry.get("uncertainty_m")
    return GroundTruthObject(
        id=object_id,
        label=label,
        observed=boxes["observed"],
        amodal=boxes["amodal"],
        visible_frames=(int(frames[0]), int(frames[1])),
        confidence=str(entry.get("confidence", "")),
        uncertainty_m=None if uncertainty is None else float(_numbers(file, f"{where}.uncertainty_m", uncertainty, ())),
        notes=str(entry.get("notes", "")),
    )


__all__ = ["BOX_KINDS", "GT_BOXES_FILE", "GroundTruthBoxes", "GroundTruthObject", "load_ground_truth"]
