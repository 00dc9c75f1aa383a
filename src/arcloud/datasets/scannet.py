"""ScanNet scenes in the standard export layout, parsed once into typed dataclasses.

A scene folder ``<root>/<scene>/`` may hold (everything but the poses is optional):

- ``color/N.jpg`` (any size; resized to the depth size), ``depth/N.png`` (uint16 millimetres, 0 = invalid),
  ``pose/N.txt`` (4x4 camera-to-world in the *unaligned* scan frame; ScanNet marks lost tracking with
  -inf/NaN poses, and those frames are skipped with a logged count),
  ``intrinsic/intrinsic_depth.txt`` and ``intrinsic_color.txt`` (4x4; frames use the depth intrinsics);
- ``<scene>.txt``: sensor metadata with ``axisAlignment`` (scan2aligned, 16 numbers, row-major; identity
  when absent, logged) and the ``*_depth`` intrinsics used when ``intrinsic/`` is absent;
- ``<scene>_vh_clean_2.ply`` (mesh with vertex colours, scan frame), ``<scene>.aggregation.json``
  (instances as groups of over-segments, raw category labels), ``<scene>_vh_clean_2.0.010000.segs.json``
  (the over-segment of every vertex);
- ``labels_v2/<scene>_ins_label_all.npy`` and ``<scene>_sem_label_all.npy``: the ScanNet v2 annotation,
  one instance id (0 = none) and one nyu40 id per mesh vertex, in the mesh's vertex order;
- ``instance-filt/N.png`` (8-bit: aggregation ``objectId + 1``, 0 = none) and ``label-filt/N.png``
  (16-bit: ScanNet label ids, the ``id`` column of the labels tsv), the 2D ground truth.

The 3D annotation is v1 (aggregation + segs: instances with raw categories) or v2 (``labels_v2/``: the
annotation of the ScanNet v2 benchmark, which fixes v1 instances such as a table boxed as its top only);
``annotation="auto"`` takes v2 when its two files are there.

The world of every frame and box is the scene's *aligned* frame (``axisAlignment`` applied to the poses),
so predictions and ground truth share a frame. Raw categories become arcloud's ``CLASSES`` through
``ClassMapping`` (see docs/datasets.md for the mapping and why).
"""

from __future__ import annotations

import csv
import json
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.types import CLASSES, Frame, Intrinsics
from arcloud.datasets.files import (
    map_id_of,
    natural_key,
    read_key_values,
    read_matrix,
    read_ply_mesh,
    read_png_u16,
    read_rgb,
)
from arcloud.datasets.frames import FrameSequence
from arcloud.errors import DatasetError, InvalidInput

if TYPE_CHECKING:
    from arcloud.core.types import LabelledBox
    from arcloud.datasets.gt_boxes import GroundTruthBoxes

logger = logging.getLogger(__name__)

LABEL_TSV_NAMES = ("scannetv2-labels.combined.tsv", "scannet-labels.combined.tsv")
ANNOTATIONS = ("auto", "v1", "v2")
Annotation = Literal["auto", "v1", "v2"]
V2_LABELS_DIR = "labels_v2"
FRAME_RATE_HZ = 30.0
DEFAULT_DEVICE_ID = "user-0"


@dataclass(frozen=True)
class ClassMapping:
    """Raw ScanNet categories -> arcloud classes: ``raw`` (exact raw category, lower case) wins over
    ``nyu40`` (the nyu40 id of the category in the labels tsv)."""

    nyu40: Mapping[int, str]
    raw: Mapping[str, str]

    def __post_init__(self) -> None:
        bad = sorted({*self.nyu40.values(), *self.raw.values()} - set(CLASSES))
        if bad:
            raise InvalidInput("ClassMapping", f"classes among {CLASSES}", bad)

    def class_of(self, raw_category: str, nyu40_id: int) -> str | None:
        """The arcloud class of a raw category with its nyu40 id, or None when it is none of ours."""
        return self.raw.get(raw_category.strip().lower()) or self.nyu40.get(int(nyu40_id))


#: The mapping used by default (documented in docs/datasets.md): nyu40 chair -> chair, sofa -> couch,
#: table and desk -> table (COCO's "dining table" fires on desks and has no desk class), television -> tv;
#: raw monitors -> tv (COCO's "tv" covers monitors), raw laptops -> laptop (nyu40 files them as otherprop).
DEFAULT_CLASS_MAPPING = ClassMapping(
    nyu40=MappingProxyType({5: "chair", 6: "couch", 7: "table", 14: "table", 25: "tv"}),
    raw=MappingProxyType(
        {
            "laptop": "laptop",
            "laptop computer": "laptop",
            "tv": "tv",
            "television": "tv",
            "led tv": "tv",
            "flat-screen television": "tv",
            "flat screen television": "tv",
            "monitor": "tv",
            "computer monitor": "tv",
            "monitor from pc": "tv",
        }
    ),
)


@dataclass(frozen=True)
class LabelTable:
    """The ScanNet labels tsv: for every raw category its ScanNet label id and nyu40 id.

    ``by_raw``: raw category (lower case) -> (label id, nyu40 id). ``by_id``: label id -> raw category."""

    by_raw: Mapping[str, tuple[int, int]]
    by_id: Mapping[int, str]
    mapping: ClassMapping = DEFAULT_CLASS_MAPPING

    def nyu40_of(self, raw_category: str) -> int:
        """The nyu40 id of a raw category, 0 when the tsv does not list it."""
        return self.by_raw.get(raw_category.strip().lower(), (0, 0))[1]

    def label_id_of(self, raw_category: str) -> int:
        """The ScanNet label id (the tsv's ``id``) of a raw category, 0 when the tsv does not list it."""
        return self.by_raw.get(raw_category.strip().lower(), (0, 0))[0]

    def class_of(self, raw_category: str) -> str | None:
        return self.mapping.class_of(raw_category, self.nyu40_of(raw_category))

    def class_of_label_id(self, label_id: int) -> str | None:
        """The arcloud class of a ScanNet label id (as held by ``label-filt`` images), or None."""
        raw = self.by_id.get(int(label_id))
        return None if raw is None else self.class_of(raw)

    def class_of_nyu40(self, nyu40_id: int) -> str | None:
        return self.mapping.nyu40.get(int(nyu40_id))


def read_label_table(path: Path, mapping: ClassMapping = DEFAULT_CLASS_MAPPING) -> LabelTable:
    """Parse a labels tsv, v1 (``id, category, count, nyuId, nyu40id, ...``) or v2 (``id, raw_category,
    category, count, nyu40id, ...``)."""
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle, delimiter="\t"))
    except OSError as exc:
        raise DatasetError(f"{path}: expected a readable labels tsv ({exc})") from exc
    columns = set(rows[0]) if rows else set()
    raw_column = "raw_category" if "raw_category" in columns else "category"
    if not {"id", raw_column, "nyu40id"} <= columns:
        raise DatasetError(f"{path}: expected columns id, raw_category|category, nyu40id, got {sorted(columns)}")
    by_raw: dict[str, tuple[int, int]] = {}
    by_id: dict[int, str] = {}
    for row in rows:
        raw = (row[raw_column] or "").strip().lower()
        try:
            label_id = int(row["id"])
            nyu40 = int(row["nyu40id"]) if (row["nyu40id"] or "").strip() else 0
        except ValueError as exc:
            raise DatasetError(f"{path}: expected integer id and nyu40id, got row {row}") from exc
        by_raw.setdefault(raw, (label_id, nyu40))
        by_id[label_id] = raw
    return LabelTable(MappingProxyType(by_raw), MappingProxyType(by_id), mapping)


def find_label_table(scene_dir: Path, levels: int = 2) -> Path | None:
    """The labels tsv in the scene folder or one of its ``levels`` parents, or in a ``meta_data/`` beside them
    (where ScanNet's own code keeps it; v2 name first)."""
    for folder in [scene_dir, *list(scene_dir.resolve().parents)[:levels]]:
        for where in (folder, folder / "meta_data"):
            for name in LABEL_TSV_NAMES:
                if (where / name).is_file():
                    return where / name
    return None


@dataclass(frozen=True, eq=False)
class ScanNetMesh:
    """The scene's mesh in the *scan* (unaligned) frame.

    vertices: (V, 3) float32. colors: (V, 3) uint8. triangles: (T, 3) int32."""

    vertices: np.ndarray
    colors: np.ndarray
    triangles: np.ndarray


@dataclass(frozen=True, eq=False)
class ScanNetInstance:
    """One annotated instance. 2D instance images hold ``object_id + 1``.

    v1: ``object_id`` is the aggregation's objectId, ``raw_category`` its label. v2: ``object_id`` is the
    instance id of ``labels_v2``, ``raw_category`` ``"nyu40:<id>"`` (v2 names no raw categories).

    vertex_indices: (N,) int64 into the mesh. aabb_min, aabb_max: (3,) float64 in the aligned frame."""

    object_id: int
    raw_category: str
    nyu40_id: int
    label: str | None
    vertex_indices: np.ndarray
    aabb_min: np.ndarray
    aabb_max: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return (self.aabb_min + self.aabb_max) / 2

    @property
    def size(self) -> np.ndarray:
        return self.aabb_max - self.aabb_min


@dataclass(frozen=True, eq=False)
class ScanNetScene(FrameSequence):
    """A parsed ScanNet scene. Images are read lazily by ``load_frame``/``frames``.

    scan2aligned: (4, 4) the axisAlignment (``alignment_source`` says whose). cam2world: (N, 4, 4) poses of ``frame_names`` in the
    aligned frame (invalid poses already dropped, their names in ``skipped_frames``). ``annotation``:
    the 3D annotation ``instances`` come from, ``"v1"`` or ``"v2"``; None when none was read."""

    scene_id: str
    root: Path
    scan2aligned: np.ndarray
    depth_intrinsics: Intrinsics | None
    color_intrinsics: Intrinsics | None
    frame_names: tuple[str, ...]
    cam2world: np.ndarray
    skipped_frames: tuple[str, ...]
    instances: tuple[ScanNetInstance, ...]
    mesh: ScanNetMesh | None
    labels: LabelTable | None
    annotation: Literal["v1", "v2"] | None = None
    device_id: str = DEFAULT_DEVICE_ID
    alignment_source: str = "given"

    @property
    def objects(self) -> tuple[ScanNetInstance, ...]:
        """The instances of arcloud's classes (the detection ground truth)."""
        return tuple(inst for inst in self.instances if inst.label is not None)

    @property
    def has_2d_labels(self) -> bool:
        return (self.root / "instance-filt").is_dir()

    def pose(self, name: str) -> np.ndarray:
        """(4, 4) cam2world (aligned frame) of a frame by name."""
        if name not in self._index:
            raise DatasetError(f"{self.root}: expected a frame with a valid pose named {name!r}, got none")
        return self.cam2world[self._index[name]]

    def load_frame(self, name: str, *, device_id: str | None = None) -> Frame:
        """The frame ``name`` at the depth resolution: colour resized to it, depth intrinsics."""
        if self.depth_intrinsics is None:
            raise DatasetError(f"{self.root}: expected depth intrinsics (intrinsic/ or {self.scene_id}.txt), got none")
        depth_mm = read_png_u16(self.root / "depth" / f"{name}.png")
        rgb = read_rgb(self.root / "color" / f"{name}.jpg", (depth_mm.shape[1], depth_mm.shape[0]))
        return make_frame(
            rgb,
            depth_mm,
            self.depth_intrinsics,
            self.pose(name),
            timestamp_s=max(natural_key(name)[0], 0) / FRAME_RATE_HZ,  # file numbers count 30 Hz frames
            map_id=map_id_of(self.scene_id),
            device_id=device_id or self.device_id,
            frame_id=name,
            depth_scale=1000.0,
        )

    def gt_boxes(self) -> list[LabelledBox]:
        """The ground truth as ``arcloud.core.types.LabelledBox`` (score 1), one per object of our classes."""
        from arcloud.core.types import LabelledBox

        return [LabelledBox(inst.label, inst.aabb_min, inst.aabb_max, 1.0) for inst in self.objects if inst.label is not None]

    def ground_truth(self) -> GroundTruthBoxes | None:
        """``gt_boxes`` as ``GroundTruthBoxes`` (its world the scan frame, its aligned frame the scene's),
        one box kind, ``observed`` (mesh vertices); None when the scene has no object of our classes."""
        from arcloud.datasets.gt_boxes import GroundTruthBoxes, GroundTruthObject

        if not self.objects:
            return None
        last_frame = max((max(natural_key(name)[0], 0) for name in self.frame_names), default=0)
        objects = tuple(
            GroundTruthObject(id=str(inst.object_id), label=box.label, observed=box, amodal=box, visible_frames=(0, last_frame),
                              confidence="", uncertainty_m=None, notes=inst.raw_category)
            for inst, box in zip(self.objects, self.gt_boxes(), strict=True)
        )  # fmt: skip
        source = self.root / (V2_LABELS_DIR if self.annotation == "v2" else f"{self.scene_id}.aggregation.json")
        method = f"ScanNet {self.annotation} annotation: axis-aligned bounds of each instance's mesh vertices"
        return GroundTruthBoxes(source, self.scan2aligned, objects, (), method, box_kinds=("observed",))


def parse_axis_alignment(text: str, source: object = "axisAlignment") -> np.ndarray:
    """(4, 4) from 16 numbers separated by spaces or commas (row-major)."""
    try:
        values = np.array(text.replace(",", " ").split(), dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(f"{source}: expected 16 numbers, got {text[:60]!r}") from exc
    if values.size != 16 or not np.all(np.isfinite(values)):
        raise DatasetError(f"{source}: expected 16 finite numbers, got {values.size} values")
    return values.reshape(4, 4)


def load_axis_alignment(value: str | Path | np.ndarray | Sequence[float]) -> np.ndarray:
    """An axis alignment from an array, a string of 16 numbers, or a file: a ScanNet ``<scene>.txt``,
    a JSON file with ``axis_align_matrix``/``axisAlignment``, or a text file of 16 numbers."""
    if isinstance(value, np.ndarray) or (isinstance(value, Sequence) and not isinstance(value, str)):
        array = np.asarray(value, dtype=np.float64)
        if array.size != 16:
            raise DatasetError(f"axis alignment: expected 16 numbers, got shape {array.shape}")
        return array.reshape(4, 4)
    path = Path(value)
    if not path.is_file():
        return parse_axis_alignment(str(value))
    if path.suffix == ".json":
        data = json.loads(path.read_text())
        for key in ("axis_align_matrix", "axisAlignment", "axis_alignment"):
            if key in data:
                return load_axis_alignment(np.asarray(data[key], dtype=np.float64))
        raise DatasetError(f"{path}: expected a key axis_align_matrix or axisAlignment, got {sorted(data)}")
    meta = read_key_values(path)
    if "axisAlignment" in meta:
        return parse_axis_alignment(meta["axisAlignment"], path)
    return parse_axis_alignment(path.read_text(), path)


def _intrinsics_from_matrix(matrix: np.ndarray) -> Intrinsics:
    return Intrinsics(float(matrix[0, 0]), float(matrix[1, 1]), float(matrix[0, 2]), float(matrix[1, 2]))


def _read_intrinsics(scene_dir: Path, meta: Mapping[str, str], which: str) -> Intrinsics | None:
    path = scene_dir / "intrinsic" / f"intrinsic_{which}.txt"
    if path.is_file():
        return _intrinsics_from_matrix(read_matrix(path, (4, 4)))
    keys = [f"fx_{which}", f"fy_{which}", f"mx_{which}", f"my_{which}"]
    if all(k in meta for k in keys):
        try:
            return Intrinsics(*(float(meta[k]) for k in keys))
        except ValueError as exc:
            raise DatasetError(f"{scene_dir}: expected numeric {', '.join(keys)}, got {[meta[k] for k in keys]}") from exc
    return None


def segments_file(scene_dir: Path, scene_id: str, aggregation_path: Path) -> Path | None:
    """The over-segmentation the aggregation's groups index: the file its ``segmentsFile`` names (ScanNet writes
    ``scannet.<scene>_vh_clean_2.0.010000.segs.json``), else the low-resolution mesh's, else None. Not any
    ``*_vh_clean*.segs.json``: ScanNet's download puts the high-resolution mesh's beside it, and that one sorts first."""
    named = ""
    if aggregation_path.is_file():
        try:
            named = str(json.loads(aggregation_path.read_text()).get("segmentsFile", ""))
        except (ValueError, AttributeError):
            named = ""
    for name in (named.removeprefix("scannet."), f"{scene_id}_vh_clean_2.0.010000.segs.json"):
        if name and (scene_dir / name).is_file():
            return scene_dir / name
    return None


def read_instances(
    scene_dir: Path,
    scene_id: str,
    vertices_scan: np.ndarray,
    scan2aligned: np.ndarray,
    labels: LabelTable | None,
    mapping: ClassMapping = DEFAULT_CLASS_MAPPING,
) -> tuple[ScanNetInstance, ...]:
    """Instances from the aggregation and over-segmentation files, boxes in the aligned frame.

    Empty when the scene has no aggregation. Without a labels tsv, nyu40 ids are 0 and only the raw
    entries of ``mapping`` give classes."""
    aggregation_path = scene_dir / f"{scene_id}.aggregation.json"
    segs_path = segments_file(scene_dir, scene_id, aggregation_path)
    if not aggregation_path.is_file() or segs_path is None:
        logger.info("scene %s: no aggregation/segs files, so no 3D ground truth", scene_id)
        return ()
    try:
        aggregation = json.loads(aggregation_path.read_text())
        seg_indices = np.asarray(json.loads(segs_path.read_text())["segIndices"], dtype=np.int64)
        groups = aggregation["segGroups"]
    except (OSError, ValueError, KeyError) as exc:
        raise DatasetError(
            f"{scene_dir}: expected aggregation.json with segGroups and segs.json with segIndices ({exc})"
        ) from exc
    if seg_indices.shape[0] != vertices_scan.shape[0]:
        raise DatasetError(
            f"{segs_path}: expected one segment index per mesh vertex ({vertices_scan.shape[0]}), got {seg_indices.shape[0]}"
        )
    vertices_aligned = _aligned(vertices_scan, scan2aligned)
    instances: list[ScanNetInstance] = []
    for group in groups:
        raw = str(group.get("label", ""))
        object_id = int(group.get("objectId", group.get("id", len(instances))))
        indices = np.flatnonzero(np.isin(seg_indices, np.asarray(group.get("segments", []), dtype=np.int64)))
        if indices.size == 0:
            logger.warning("scene %s: instance %d (%s) has no vertices; skipped", scene_id, object_id, raw)
            continue
        nyu40 = labels.nyu40_of(raw) if labels is not None else 0
        instances.append(_instance(object_id, raw, nyu40, mapping.class_of(raw, nyu40), indices, vertices_aligned))
    return tuple(instances)


def v2_label_paths(scene_dir: Path, scene_id: str) -> tuple[Path, Path]:
    """(instance ids, nyu40 ids) files of the v2 annotation: ``labels_v2/<scene>_{ins,sem}_label_all.npy``."""
    folder = scene_dir / V2_LABELS_DIR
    return folder / f"{scene_id}_ins_label_all.npy", folder / f"{scene_id}_sem_label_all.npy"


def _require_v2_files(scene_dir: Path, scene_id: str) -> tuple[Path, Path]:
    paths = v2_label_paths(scene_dir, scene_id)
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise DatasetError(f"{scene_dir / V2_LABELS_DIR}: expected the v2 annotation files {missing}, got none")
    return paths


def _read_vertex_labels(path: Path, n_vertices: int) -> np.ndarray:
    """(V,) int64 from a per-vertex .npy of non-negative integers, checked against the mesh."""
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: expected a numpy array of one integer per mesh vertex ({exc})") from exc
    if array.dtype.kind not in "ui":
        raise DatasetError(f"{path}: expected integer labels (ScanNet writes uint32), got dtype {array.dtype}")
    if array.ndim != 1:
        raise DatasetError(f"{path}: expected shape ({n_vertices},), one label per mesh vertex, got {array.shape}")
    if array.shape[0] != n_vertices:
        raise DatasetError(f"{path}: expected one label per mesh vertex ({n_vertices}), got {array.shape[0]}")
    if array.size and array.min() < 0:
        raise DatasetError(f"{path}: expected labels >= 0, got {array.min()}")
    return array.astype(np.int64)


def read_v2_instances(
    scene_dir: Path,
    scene_id: str,
    vertices_scan: np.ndarray,
    scan2aligned: np.ndarray,
    mapping: ClassMapping = DEFAULT_CLASS_MAPPING,
) -> tuple[ScanNetInstance, ...]:
    """Instances of the v2 annotation (``v2_label_paths``), boxes in the aligned frame: one per instance
    id > 0, its nyu40 id the most common of its vertices' (ties: the smallest), its class ``mapping.nyu40``'s."""
    instance_path, semantic_path = _require_v2_files(scene_dir, scene_id)
    instance_ids = _read_vertex_labels(instance_path, vertices_scan.shape[0])
    nyu40_ids = _read_vertex_labels(semantic_path, vertices_scan.shape[0])
    vertices_aligned = _aligned(vertices_scan, scan2aligned)
    order = np.argsort(instance_ids, kind="stable")
    ids, starts = np.unique(instance_ids[order], return_index=True)
    instances = []
    for instance_id, indices in zip(ids.tolist(), np.split(order, starts[1:])):
        if instance_id == 0:
            continue
        values, votes = np.unique(nyu40_ids[indices], return_counts=True)
        nyu40 = int(values[np.argmax(votes)])
        label = mapping.nyu40.get(nyu40)
        instances.append(_instance(instance_id, f"nyu40:{nyu40}", nyu40, label, np.sort(indices), vertices_aligned))
    return tuple(instances)


def _aligned(vertices_scan: np.ndarray, scan2aligned: np.ndarray) -> np.ndarray:
    """(V, 3) float64 vertices carried from the scan frame to the aligned frame."""
    return vertices_scan.astype(np.float64) @ scan2aligned[:3, :3].T + scan2aligned[:3, 3]


def _instance(
    object_id: int, raw: str, nyu40: int, label: str | None, indices: np.ndarray, vertices_aligned: np.ndarray
) -> ScanNetInstance:
    """An instance boxed by the aligned-frame axis-aligned bounds of its vertices."""
    points = vertices_aligned[indices]
    return ScanNetInstance(object_id, raw, nyu40, label, indices, points.min(axis=0), points.max(axis=0))


def choose_annotation(scene_dir: Path, scene_id: str, annotation: str) -> Literal["v1", "v2"]:
    """The annotation to read: ``"auto"`` takes v2 when both ``v2_label_paths`` exist, else v1;
    ``"v2"`` without them raises ``DatasetError``."""
    if annotation not in ANNOTATIONS:
        raise InvalidInput("annotation", f"one of {ANNOTATIONS}", repr(annotation))
    if annotation == "v1":
        return "v1"
    if annotation == "v2":
        _require_v2_files(scene_dir, scene_id)
        return "v2"
    present = [p.is_file() for p in v2_label_paths(scene_dir, scene_id)]
    if any(present) and not all(present):
        logger.warning("scene %s: only one of the two v2 label files in %s; using the v1 annotation", scene_id, V2_LABELS_DIR)
    return "v2" if all(present) else "v1"


def _read_poses(scene_dir: Path) -> tuple[list[str], list[np.ndarray], list[str]]:
    pose_dir = scene_dir / "pose"
    names = sorted((p.stem for p in pose_dir.glob("*.txt")), key=natural_key) if pose_dir.is_dir() else []
    valid_names, poses, skipped = [], [], []
    for name in names:
        pose = read_matrix(pose_dir / f"{name}.txt", (4, 4))
        if np.all(np.isfinite(pose)):
            valid_names.append(name)
            poses.append(pose)
        else:
            skipped.append(name)
    return valid_names, poses, skipped


def scene_id_of(scene_dir: Path) -> str:
    """The scene id: the folder's name, unless the files inside name another (``<id>.aggregation.json``,
    ``<id>_vh_clean_2.ply``, ``<id>.txt``)."""
    if (scene_dir / f"{scene_dir.name}.txt").is_file():
        return scene_dir.name
    for pattern, suffix in (("*.aggregation.json", ".aggregation.json"), ("*_vh_clean_2.ply", "_vh_clean_2.ply")):
        found = sorted(scene_dir.glob(pattern))
        if found:
            return found[0].name[: -len(suffix)]
    return scene_dir.name


def load_scannet_scene(
    scene_dir: str | Path,
    *,
    labels_tsv: str | Path | None = None,
    scan2aligned: str | Path | np.ndarray | Sequence[float] | None = None,
    mapping: ClassMapping = DEFAULT_CLASS_MAPPING,
    load_mesh: bool = True,
    annotation: Annotation = "auto",
) -> ScanNetScene:
    """Parse a scene folder (see the module docstring). ``labels_tsv`` defaults to the tsv found in the
    folder or its two parents; ``scan2aligned`` overrides the ``axisAlignment`` of ``<scene>.txt``;
    ``annotation`` picks the 3D annotation (``choose_annotation``; ``"v2"`` without its files raises)."""
    root = Path(scene_dir)
    if not root.is_dir():
        raise DatasetError(f"{root}: expected a ScanNet scene folder, got no such folder")
    scene_id = scene_id_of(root)
    chosen = choose_annotation(root, scene_id, annotation)
    meta_path = root / f"{scene_id}.txt"
    meta = read_key_values(meta_path) if meta_path.is_file() else {}
    if scan2aligned is not None:
        alignment, alignment_source = load_axis_alignment(scan2aligned), "given (--axis-alignment)"
    elif "axisAlignment" in meta:
        alignment, alignment_source = parse_axis_alignment(meta["axisAlignment"], meta_path), f"{meta_path.name} axisAlignment"
    else:
        logger.warning(
            "scene %s: no axisAlignment in %s: boxes are fitted in the scan's own frame, not ScanNet's aligned one "
            "(--axis-alignment gives it)", scene_id, meta_path.name,
        )  # fmt: skip
        alignment, alignment_source = np.eye(4), f"none ({meta_path.name} has no axisAlignment): the scan's frame"

    tsv = Path(labels_tsv) if labels_tsv is not None else find_label_table(root)
    labels = read_label_table(tsv, mapping) if tsv is not None else None
    if labels is None:
        logger.warning("scene %s: no labels tsv found; classes come from raw categories only", scene_id)

    names, poses_scan, skipped = _read_poses(root)
    if skipped:
        logger.warning(
            "scene %s: skipped %d of %d frames with invalid (inf/NaN) poses", scene_id, len(skipped), len(names) + len(skipped)
        )
    cam2world = np.einsum("ij,njk->nik", alignment, np.asarray(poses_scan).reshape(-1, 4, 4))

    mesh = None
    instances: tuple[ScanNetInstance, ...] = ()
    mesh_paths = sorted(root.glob(f"{scene_id}_vh_clean_2.ply")) or sorted(root.glob(f"{scene_id}*.ply"))
    if load_mesh and mesh_paths:
        vertices, colors, triangles = read_ply_mesh(mesh_paths[0])
        if colors is None:
            colors = np.full(vertices.shape, 128, np.uint8)
        mesh = ScanNetMesh(vertices, colors, triangles)
        if chosen == "v2":
            instances = read_v2_instances(root, scene_id, vertices, alignment, mapping)
        else:
            instances = read_instances(root, scene_id, vertices, alignment, labels, mapping)

    scene = ScanNetScene(
        scene_id=scene_id,
        root=root,
        scan2aligned=alignment,
        depth_intrinsics=_read_intrinsics(root, meta, "depth"),
        color_intrinsics=_read_intrinsics(root, meta, "color"),
        frame_names=tuple(names),
        cam2world=cam2world,
        skipped_frames=tuple(skipped),
        instances=instances,
        mesh=mesh,
        labels=labels,
        annotation=chosen if instances else None,
        alignment_source=alignment_source,
    )
    logger.info(
        "scene %s: %d frames, %d instances (%d of our classes) from the %s annotation",
        scene_id, scene.n_frames, len(instances), len(scene.objects), scene.annotation or "no",
    )  # fmt: skip
    return scene


def is_scene_dir(folder: Path) -> bool:
    """Whether a folder is a ScanNet-layout scene: it has ``pose/`` or a ``<name>.txt``."""
    return (folder / "pose").is_dir() or (folder / f"{folder.name}.txt").is_file()


def find_scene_dirs(root: str | Path, scenes: Sequence[str] | None = None) -> list[Path]:
    """Scene folders under ``root`` (itself a scene of any name, a folder of scenes, or one with
    ``scans/``), in name order: sub-folders that are scenes (``is_scene_dir``) or named ``scene*``;
    ``scenes`` picks those names (each must exist)."""
    base = Path(root)
    if not base.is_dir():
        raise DatasetError(f"{base}: expected a folder of ScanNet scenes, got no such folder")
    if is_scene_dir(base):
        candidates = {base.name: base}
    else:
        parent = base / "scans" if (base / "scans").is_dir() else base
        candidates = {p.name: p for p in parent.iterdir() if p.is_dir() and (p.name.startswith("scene") or is_scene_dir(p))}
    if scenes:
        missing = [s for s in scenes if s not in candidates]
        if missing:
            raise DatasetError(f"{base}: expected scene folders {missing}, got only {sorted(candidates)[:10]}")
        return [candidates[s] for s in scenes]
    if not candidates:
        raise DatasetError(f"{base}: expected a scene folder (with pose/) or folders of scenes, got none")
    return [candidates[name] for name in sorted(candidates)]


__all__ = [
    "ANNOTATIONS",
    "DEFAULT_CLASS_MAPPING",
    "ClassMapping",
    "LabelTable",
    "ScanNetInstance",
    "ScanNetMesh",
    "ScanNetScene",
    "choose_annotation",
    "find_label_table",
    "find_scene_dirs",
    "is_scene_dir",
    "load_axis_alignment",
    "load_scannet_scene",
    "read_instances",
    "read_label_table",
    "read_v2_instances",
    "v2_label_paths",
]
