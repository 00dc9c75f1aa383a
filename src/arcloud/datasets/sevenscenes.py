"""Microsoft 7-Scenes sequences (and any folder in the same layout), parsed once into a dataclass.

A sequence folder holds ``frame-NNNNNN.color.jpg``, ``frame-NNNNNN.depth.png`` (uint16 millimetres;
0 and 65535 = invalid) and ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world, OpenCV camera axes);
optionally ``camera-intrinsics.txt`` (3x3; default fx = fy = 585, cx = 320, cy = 240, the 7-Scenes
Kinect) and ``gravity-direction.txt`` (3 numbers: the direction gravity pulls, in world coordinates).
A scene folder with ``seq-XX`` sub-folders is read as those sequences one after the other.

7-Scenes worlds are not z-up: with ``align_gravity=True`` the poses are rotated (the smallest rotation,
``arcloud.core.gravity.up_rotation``) into a world whose +z is up (opposite gravity), so that gravity-aligned boxes are simply boxes in that world.

Optional 3D ground truth, ``gt-boxes.json`` (hand-checked boxes, see ``load_ground_truth``), is parsed into
``SevenScenesGroundTruth``: boxes in its own *aligned* frame (z up, floor at z = 0, x along the walls),
related to the file's world by ``file2aligned``. The map's world reaches it through
``SevenScenesSequence.world2gt`` (``file2aligned @ world2file``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import cast

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.gravity import up_rotation
from arcloud.core.types import CLASSES, Frame, Intrinsics, LabelledBox
from arcloud.datasets.files import natural_key, read_matrix, read_png_u16, read_rgb
from arcloud.errors import DatasetError, InvalidInput

logger = logging.getLogger(__name__)

DEFAULT_INTRINSICS = Intrinsics(585.0, 585.0, 320.0, 240.0)
INVALID_DEPTH_MM = 65535
FRAME_RATE_HZ = 30.0
_SUFFIX = ".pose.txt"
GT_BOXES_FILE = "gt-boxes.json"
#: The two boxes of every ground-truth object: what the sensor saw (the primary score) and amodal.
BOX_KINDS = ("observed", "amodal")
#: How far from orthonormal a file's rotation may be (its numbers are rounded to 4 decimals).
_GT_ROTATION_TOLERANCE = 1e-3


@dataclass(frozen=True, eq=False)
class SevenScenesObject:
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
class ColourCamera:
    """The colour camera of an unregistered RGB-D pair: its intrinsics (at the depth image's size) and
    ``depth2rgb`` (4, 4), depth camera coordinates to colour camera coordinates (see ``core.types.Frame``)."""

    intrinsics: Intrinsics
    depth2rgb: np.ndarray


@dataclass(frozen=True, eq=False)
class SevenScenesGroundTruth:
    """``gt-boxes.json`` parsed: ``file2aligned`` (4, 4) maps the file's (pose) world to the aligned
    frame of the boxes (the file's ``gravity_aligned.world_to_aligned``: z up, floor at z = 0, x along
    the walls); ``objects`` hold the boxes there. ``not_annotated``: things a detector may fire on that
    are none of our classes; ``method``: how the boxes were made; ``colour``: the colour camera as the
    annotation estimated it (``colour_intrinsics_estimated``), None when the file has none."""

    path: Path
    file2aligned: np.ndarray
    objects: tuple[SevenScenesObject, ...]
    not_annotated: tuple[str, ...]
    method: str
    colour: ColourCamera | None = None

    def boxes(self, kind: str = "observed", *, frames: tuple[int, int] | None = None) -> list[LabelledBox]:
        """The ``kind`` boxes (see ``BOX_KINDS``), of the objects visible within ``frames`` = (first,
        last) frame numbers when given."""
        return [o.box(kind) for o in self.objects_within(frames)]

    def objects_within(self, frames: tuple[int, int] | None = None) -> list[SevenScenesObject]:
        """The objects visible within ``frames`` = (first, last) frame numbers (all when None)."""
        return [o for o in self.objects if frames is None or o.visible_within(*frames)]


@dataclass(frozen=True, eq=False)
class SevenScenesSequence:
    """A parsed sequence. ``cam2world``: (N, 4, 4) poses of ``frame_names`` in the output world (the
    file world, or the gravity-aligned one when ``world2file`` is not the identity).

    up_file: (3,) unit up (opposite gravity) in the file's world, or None without gravity-direction.txt.
    world2file: (4, 4) maps output-world points to the file's world (identity unless gravity-aligned).
    ground_truth: ``gt-boxes.json`` parsed, or None when the folder has none.
    colour: the colour camera, when colour and depth are not registered (Kinect v1: frames then carry it,
    and masks drawn on colour land where the colour camera saw); None: registered pixel for pixel."""

    name: str
    root: Path
    intrinsics: Intrinsics
    frame_names: tuple[str, ...]
    frame_dirs: tuple[Path, ...]
    frame_stems: tuple[str, ...]
    cam2world: np.ndarray
    skipped_frames: tuple[str, ...]
    up_file: np.ndarray | None
    world2file: np.ndarray
    ground_truth: SevenScenesGroundTruth | None = None
    colour: ColourCamera | None = None
    device_id: str = "user-0"

    @cached_property
    def _index(self) -> dict[str, int]:
        return {name: i for i, name in enumerate(self.frame_names)}

    @property
    def n_frames(self) -> int:
        return len(self.frame_names)

    @property
    def up(self) -> tuple[float, float, float]:
        """Up in the output world, for ``Params.up`` (+z once gravity-aligned; +z when unknown)."""
        if self.up_file is None:
            return (0.0, 0.0, 1.0)
        up = self.world2file[:3, :3].T @ self.up_file
        x, y, z = up / np.linalg.norm(up)
        return float(x), float(y), float(z)

    @property
    def world2gt(self) -> np.ndarray | None:
        """(4, 4) maps output-world points to the ground truth's aligned frame (None without ground truth)."""
        if self.ground_truth is None:
            return None
        return self.ground_truth.file2aligned @ self.world2file

    def frame_number(self, name: str) -> int:
        """The number in a frame's file name (``frame-000123`` -> 123), as ground truth counts frames."""
        if name not in self._index:
            raise DatasetError(f"{self.root}: expected a frame named {name!r} with a valid pose, got none")
        return int(self.frame_stems[self._index[name]])

    def load_frame(self, name: str, *, device_id: str | None = None) -> Frame:
        """The frame ``name``: RGB resized to the depth size if they differ; invalid depth -> 0."""
        if name not in self._index:
            raise DatasetError(f"{self.root}: expected a frame named {name!r} with a valid pose, got none")
        index = self._index[name]
        folder, stem = self.frame_dirs[index], self.frame_stems[index]
        depth_mm = read_png_u16(folder / f"frame-{stem}.depth.png")
        depth_mm = np.where(depth_mm == INVALID_DEPTH_MM, 0, depth_mm).astype(np.uint16)
        rgb = read_rgb(folder / f"frame-{stem}.color.jpg", (depth_mm.shape[1], depth_mm.shape[0]))
        return make_frame(
            rgb,
            depth_mm,
            self.intrinsics,
            self.cam2world[index],
            timestamp_s=index / FRAME_RATE_HZ,
            map_id=self.name,
            device_id=device_id or self.device_id,
            frame_id=name,
            depth_scale=1000.0,
            rgb_intrinsics=None if self.colour is None else self.colour.intrinsics,
            depth2rgb=None if self.colour is None else self.colour.depth2rgb,
        )

    def frames(self, *, stride: int = 1, limit: int | None = None) -> Iterator[Frame]:
        for name in self.frame_names[:: max(1, int(stride))][:limit]:
            yield self.load_frame(name)


def _sequence_dirs(root: Path) -> list[Path]:
    subdirs = sorted((p for p in root.iterdir() if p.is_dir() and p.name.startswith("seq")), key=lambda p: natural_key(p.name))
    return subdirs or [root]


def _find_file(root: Path, folders: list[Path], name: str) -> Path | None:
    for folder in [*folders, root, root.parent]:
        if (folder / name).is_file():
            return folder / name
    return None


def load_seven_scenes(
    root: str | Path, *, align_gravity: bool = False, name: str | None = None, colour: ColourCamera | None = None
) -> SevenScenesSequence:
    """Parse a 7-Scenes sequence (or a scene of ``seq-XX`` folders), with its ``gt-boxes.json`` when the
    folder has one. Frames whose pose is not finite are skipped with a logged count.

    ``colour``: the colour camera (the 7-Scenes release does not calibrate it; its Kinect's colour and
    depth differ by focal length and a 3.5 cm baseline, so masks miss the depth by up to ~35 px near the
    borders). None takes the one ``gt-boxes.json`` estimated, when present, else treats the images as
    registered."""
    base = Path(root)
    if not base.is_dir():
        raise DatasetError(f"{base}: expected a 7-Scenes folder, got no such folder")
    folders = _sequence_dirs(base)
    intrinsics_path = _find_file(base, folders, "camera-intrinsics.txt")
    if intrinsics_path is not None:
        k = read_matrix(intrinsics_path, (3, 3))
        intrinsics = Intrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    else:
        logger.info("%s: no camera-intrinsics.txt; using the 7-Scenes default %s", base, DEFAULT_INTRINSICS)
        intrinsics = DEFAULT_INTRINSICS
    gravity_path = _find_file(base, folders, "gravity-direction.txt")
    up_file = None
    if gravity_path is not None:
        gravity = read_matrix(gravity_path, (3,))
        if not np.all(np.isfinite(gravity)) or np.linalg.norm(gravity) < 1e-9:
            raise DatasetError(f"{gravity_path}: expected a finite non-zero direction, got {gravity}")
        up_file = -gravity / np.linalg.norm(gravity)

    names, dirs, stems_kept, poses, skipped = [], [], [], [], []
    for folder in folders:
        stems = sorted((p.name[len("frame-") : -len(_SUFFIX)] for p in folder.glob(f"frame-*{_SUFFIX}")), key=natural_key)
        prefix = f"{folder.name}-" if folder != base else ""
        for stem in stems:
            pose = read_matrix(folder / f"frame-{stem}{_SUFFIX}", (4, 4))
            if not np.all(np.isfinite(pose)):
                skipped.append(prefix + stem)
                continue
            names.append(prefix + stem)
            dirs.append(folder)
            stems_kept.append(stem)
            poses.append(pose)
    if not names:
        raise DatasetError(f"{base}: expected frame-*.pose.txt files with finite poses, got none")
    if skipped:
        logger.warning("%s: skipped %d of %d frames with invalid poses", base, len(skipped), len(names) + len(skipped))

    world2file = np.eye(4)
    if align_gravity and up_file is not None:
        world2file[:3, :3] = up_rotation(up_file).T  # up_rotation takes up to +z: file -> world
    cam2file = np.asarray(poses)
    cam2world = np.einsum("ij,njk->nik", np.linalg.inv(world2file), cam2file)
    gt_path = base / GT_BOXES_FILE
    ground_truth = load_ground_truth(gt_path) if gt_path.is_file() else None
    return SevenScenesSequence(
        name=name or base.name,
        root=base,
        intrinsics=intrinsics,
        frame_names=tuple(names),
        frame_dirs=tuple(dirs),
        frame_stems=tuple(stems_kept),
        cam2world=cam2world,
        skipped_frames=tuple(skipped),
        up_file=up_file,
        world2file=world2file,
        ground_truth=ground_truth,
        colour=colour if colour is not None else (ground_truth.colour if ground_truth is not None else None),
    )


def load_ground_truth(path: str | Path) -> SevenScenesGroundTruth:
    """Parse ``gt-boxes.json``: ``gravity_aligned.world_to_aligned`` (4x4, rigid) and, per object of
    ``gravity_aligned.objects``, ``id``, ``label`` (one of ``CLASSES``), ``aabb_observed_min/max`` and
    ``aabb_min/max`` (the aligned frame), ``visible_frames`` ([first, last]). The top-level ``objects``
    (boxes in the tilted pose frame, much larger) are not read. Raises ``DatasetError`` naming the
    field that is missing or malformed."""
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
    return SevenScenesGroundTruth(file, file2aligned, objects, not_annotated, str(data.get("method", "")), colour)


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


def _ground_truth_object(file: Path, index: int, entry: object) -> SevenScenesObject:
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
    return SevenScenesObject(
        id=object_id,
        label=label,
        observed=boxes["observed"],
        amodal=boxes["amodal"],
        visible_frames=(int(frames[0]), int(frames[1])),
        confidence=str(entry.get("confidence", "")),
        uncertainty_m=None if uncertainty is None else float(_numbers(file, f"{where}.uncertainty_m", uncertainty, ())),
        notes=str(entry.get("notes", "")),
    )


__all__ = [
    "BOX_KINDS",
    "DEFAULT_INTRINSICS",
    "GT_BOXES_FILE",
    "SevenScenesGroundTruth",
    "SevenScenesObject",
    "SevenScenesSequence",
    "ColourCamera",
    "load_ground_truth",
    "load_seven_scenes",
]
