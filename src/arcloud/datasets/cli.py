"""The dataset commands of the ``arcloud`` CLI: ``eval scannet``, ``eval 7scenes`` and ``render-scannet``.

``add_eval_commands(subparsers)`` adds them to the CLI's sub-command parsers; every command sets
``handler`` (``args.handler(args)`` runs it and returns the exit status; ``ArcloudError`` is left to
the CLI's edge). Results are JSON::

    {"table1": [{"approach": "centralized"|"distributed", "users": K, "runs": M,
                 "map25_mean": .., "map25_var": .., "map50_mean": .., "map50_var": ..}, ...], ...}

ScanNet: mAP against the scenes' ground truth, predictions pooled across scenes (the standard ScanNet
evaluation). 7-Scenes: ``agreement`` rows hold the mAP of each distributed map taken against the
centralized map as ground truth; with ``gt-boxes.json`` in the sequence folder, boxes are fitted in its
aligned frame and ``accuracy`` rows score every run against its observed and amodal boxes. Pictures are
written next to ``--out``.

Every exported map (``--export``) declares its frame: ``"world_from_export"`` (4x4, row-major) maps its
coordinates to the dataset's pose frame, and ``"frame"`` says which frame that is in words.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from arcloud.core.types import CLASSES, Frame, MapObject, Params
from arcloud.errors import DatasetError
from arcloud.eval.metrics import variance
from arcloud.ports import Detector

if TYPE_CHECKING:
    from arcloud.core.types import LabelledBox
    from arcloud.datasets.scannet import ScanNetScene
    from arcloud.datasets.sevenscenes import SevenScenesGroundTruth, SevenScenesSequence

OnRun = Callable[[str, int, int, list[MapObject]], None]

logger = logging.getLogger(__name__)

DEFAULT_SCANNET_USERS = (1, 10, 50, 100)
DEFAULT_7SCENES_USERS = (1, 10)
GT_MASKS = "gt-masks"
#: Frames kept in memory when a sequence has at most this many (about 2.2 MB each at 640x480).
CACHE_FRAMES_UP_TO = 1500


class LazyFrames(Sequence[Frame]):
    """Frames of a dataset by index, read on first access (and kept when ``cache``). Thread-safe."""

    def __init__(self, names: Sequence[str], load: Callable[[str], Frame], *, cache: bool) -> None:
        self.names = tuple(names)
        self._load = load
        self._cache: dict[int, Frame] | None = {} if cache else None
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> Frame:  # type: ignore[override]
        if isinstance(index, slice):
            raise TypeError("LazyFrames does not slice; pick names and build another")
        if self._cache is None:
            return self._load(self.names[index])
        with self._lock:
            frame = self._cache.get(index)
        if frame is None:
            frame = self._load(self.names[index])
            with self._lock:
                self._cache[index] = frame
        return frame

    def __iter__(self) -> Iterator[Frame]:
        return (self[i] for i in range(len(self)))


def parse_colour_camera(text: str) -> Any:
    """'fx,fy,cx,cy[,tx,ty,tz]' -> ``ColourCamera`` (intrinsics in pixels; depth->colour translation in m)."""
    from arcloud.core.types import Intrinsics
    from arcloud.datasets.sevenscenes import ColourCamera

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (4, 7) or not all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
        raise argparse.ArgumentTypeError(f"expected fx,fy,cx,cy[,tx,ty,tz] (7 or 4 finite numbers, positive focal lengths), got {text!r}")
    depth2rgb = np.eye(4)
    depth2rgb[:3, 3] = values[4:7] if len(values) == 7 else (0.0, 0.0, 0.0)
    return ColourCamera(Intrinsics(*values[:4]), depth2rgb)


def parse_scenes(text: str) -> tuple[str, ...]:
    """'scene0000_00,scene0011_00' or '@file' (one name a line, '#' starts a comment) -> scene names."""
    if text.startswith("@"):
        try:
            lines = Path(text[1:]).read_text().splitlines()
        except OSError as exc:
            raise argparse.ArgumentTypeError(f"expected a readable scene list {text[1:]!r} ({exc})") from exc
        names = (line.split("#", 1)[0].strip() for line in lines)
        return tuple(name for name in names if name)
    return tuple(part.strip() for part in text.split(",") if part.strip())


def objects_json(objects: Sequence[MapObject]) -> list[dict[str, object]]:
    """The reportable objects (label and box) as JSON-friendly dicts, highest score first."""
    boxed = sorted((o for o in objects if o.aabb is not None and o.label), key=lambda o: -o.score)
    return [
        {
            "label": o.label,
            "score": round(float(o.score), 6),
            "aabb_min": [round(float(v), 4) for v in o.aabb.min],  # type: ignore[union-attr]
            "aabb_max": [round(float(v), 4) for v in o.aabb.max],  # type: ignore[union-attr]
        }
        for o in boxed
    ]


@dataclass(frozen=True, eq=False)
class ExportFrame:
    """The frame a dataset's maps are boxed and exported in.

    description: the frame in words. world2export: (4, 4) maps the map's world to it, for
    ``Params.world2aligned`` (None: the map's world itself). export2pose: (4, 4) maps it to the
    dataset's pose frame (the frame of its pose files), written as ``world_from_export``."""

    description: str
    export2pose: np.ndarray
    world2export: np.ndarray | None = None

    def params(self, params: Params) -> Params:
        """``params`` fitting boxes in this frame."""
        if self.world2export is None:
            return params
        return params.replace(world2aligned=tuple(tuple(float(v) for v in row) for row in self.world2export))


def scannet_export_frame(scene: ScanNetScene) -> ExportFrame:
    """ScanNet maps are built in the scene's aligned frame (the reader aligns the poses)."""
    return ExportFrame("ScanNet axis-aligned frame (axisAlignment applied to the scan frame)", np.linalg.inv(scene.scan2aligned))


def seven_scenes_export_frame(sequence: SevenScenesSequence) -> ExportFrame:
    """With ground truth, its aligned frame (the sequence's declared evaluation frame, as ScanNet's
    axisAlignment is); without, the sequence's (gravity-aligned) world."""
    if sequence.ground_truth is not None:
        return ExportFrame(
            f"{sequence.ground_truth.path.name} aligned frame (gravity_aligned.world_to_aligned: z up, floor at z = 0, x along the walls)",
            np.linalg.inv(sequence.ground_truth.file2aligned),
            sequence.world2gt,
        )  # fmt: skip
    if np.allclose(sequence.world2file, np.eye(4)):
        return ExportFrame("7-Scenes pose frame", sequence.world2file)
    return ExportFrame("gravity-aligned world (the pose frame turned by the smallest rotation that takes up to +z)", sequence.world2file)


def export_payload(objects: Sequence[MapObject], frame: ExportFrame, **facts: object) -> dict[str, object]:
    """An exported map: ``facts`` (scene, users, run...), the frame (``frame`` in words,
    ``world_from_export``), the served objects (``MapObject.confirmed``) under ``objects`` and the
    tentative ones under ``tentative`` (both as ``objects_json``)."""
    return {
        **facts,
        "frame": frame.description,
        "world_from_export": [[float(v) for v in row] for row in frame.export2pose],
        "objects": objects_json([o for o in objects if o.confirmed]),
        "tentative": objects_json([o for o in objects if not o.confirmed]),
    }


def _row(approach: str, users: int, scores25: list[float], scores50: list[float], wall_s: float) -> dict[str, object]:
    return {
        "approach": approach,
        "users": users,
        "runs": len(scores25),
        "map25_mean": float(np.mean(scores25)),
        "map25_var": variance(scores25),
        "map50_mean": float(np.mean(scores50)),
        "map50_var": variance(scores50),
        "wall_s": round(wall_s, 2),
    }


def _progress_bar(total: int, enabled: bool, desc: str) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, disable=not enabled, desc=desc, unit="frame", leave=False)


class _RunCollector:
    """Collects the runs of ``arcloud.eval.protocol.table1`` through its ``on_run``: each run's boxes,
    its wall time (since the previous run of the same sequence ended), and the first map of each K."""

    def __init__(self, on_run: OnRun | None) -> None:
        self.on_run = on_run
        self.boxes: dict[tuple[int, int], dict[str, list[Any]]] = {}
        self.wall_s: dict[int, float] = {}
        self.first: dict[int, list[MapObject]] = {}
        self._last = time.perf_counter()

    def start(self) -> None:
        self._last = time.perf_counter()

    def __call__(self, name: str, approach: str, users: int, run: int, objects: list[MapObject]) -> None:
        from arcloud.eval.protocol import object_boxes

        now = time.perf_counter()
        self.wall_s[users] = self.wall_s.get(users, 0.0) + now - self._last
        self.boxes.setdefault((users, run), {})[name] = object_boxes(objects)
        self.first.setdefault(users, objects)
        if self.on_run is not None:
            self.on_run(name, users, run, objects)
        self._last = time.perf_counter()


def _table1_runs(
    sequences: Sequence[tuple[str, Sequence[Frame], Detector, Sequence[Any]]],
    params: Params,
    collector: _RunCollector,
    *,
    users: Sequence[int],
    runs: int,
    seed: int,
    workers: int,
    progress: bool,
) -> None:
    """Every run of ``table1`` on every sequence (the centralized run always comes first)."""
    from arcloud.eval.protocol import table1

    distributed = tuple(k for k in users if k > 1)
    total = sum(len(frames) for _, frames, _, _ in sequences) * (1 + runs * len(distributed))
    with _progress_bar(total, progress, "eval") as bar:
        for name, frames, detector, gt in sequences:
            collector.start()
            table1(
                frames, detector, gt, params, users=distributed, runs=runs, seed=seed, workers=workers,
                scene=name, progress=bar.update,
                on_run=lambda approach, k, run, objects, name=name: collector(name, approach, k, run, objects),
            )  # fmt: skip


def evaluate_scenes(
    scenes: Sequence[tuple[str, Sequence[Frame], Detector, Sequence[Any]]],
    params: Params,
    *,
    users: Sequence[int],
    runs: int,
    seed: int = 0,
    workers: int = 1,
    on_run: OnRun | None = None,
    progress: bool = False,
) -> dict[str, object]:
    """Table 1 over several scenes ``(name, frames, detector, gt_boxes)``: each scene's runs come from
    ``arcloud.eval.protocol.table1`` (the centralized run, then ``runs`` distributed runs per K > 1 in
    ``users``; run r uses seed ``seed * 1000 + r``; detections computed once per frame), and the
    predictions of all scenes are evaluated together, run by run (the standard pooled ScanNet mAP).
    K = 1 in ``users`` reports the centralized run (which is always computed)."""
    from arcloud.eval.metrics import evaluate

    collector = _RunCollector(on_run)
    _table1_runs(scenes, params, collector, users=users, runs=runs, seed=seed, workers=workers, progress=progress)
    ground_truth = {name: list(gt) for name, _, _, gt in scenes}
    rows, centralized = [], None
    for k in users:
        results = [evaluate(collector.boxes[(k, run)], ground_truth) for run in range(1 if k == 1 else runs)]
        if k == 1:
            centralized = results[0].to_dict()
        scores25, scores50 = [r.map_at(0.25) for r in results], [r.map_at(0.5) for r in results]
        logger.info("users %d: mAP@0.25 %s mAP@0.5 %s", k, np.round(scores25, 4), np.round(scores50, 4))
        rows.append(_row("centralized" if k == 1 else "distributed", k, scores25, scores50, collector.wall_s.get(k, 0.0)))
    out: dict[str, object] = {"table1": rows}
    if centralized is not None:
        out["centralized"] = centralized
    return out


def _export(export_dir: Path | None, frames: Mapping[str, ExportFrame]) -> OnRun | None:
    """Writes every run's map as ``<export_dir>/<scene>_<users>_<run>.json`` (``export_payload``)."""
    if export_dir is None:
        return None
    export_dir.mkdir(parents=True, exist_ok=True)

    def write(scene: str, users: int, run: int, objects: list[MapObject]) -> None:
        payload = export_payload(objects, frames[scene], scene=scene, users=users, run=run)
        (export_dir / f"{scene}_{users}_{run}.json").write_text(json.dumps(payload, indent=1))

    return write


def _each(*callbacks: OnRun | None) -> OnRun | None:
    chosen = [c for c in callbacks if c is not None]
    if not chosen:
        return None

    def call(scene: str, users: int, run: int, objects: list[MapObject]) -> None:
        for callback in chosen:
            callback(scene, users, run, objects)

    return call


def _workers(value: int | None) -> int:
    return value if value and value > 0 else max(1, os.cpu_count() or 1)


def _params(args: argparse.Namespace) -> Params:
    params = Params()
    if getattr(args, "voxel_size_m", None):
        params = params.replace(voxel_size_m=float(args.voxel_size_m))
    return params


def _make_detector(spec: str) -> Detector:
    from arcloud.detectors import make_detector

    return make_detector(spec)


def run_eval_scannet(args: argparse.Namespace) -> int:
    """``arcloud eval scannet``: Table 1 on ScanNet-layout scenes; writes ``--out`` (and ``--export``)."""
    from arcloud.datasets.gt_masks import GroundTruthMaskDetector, gt_masks_options
    from arcloud.datasets.scannet import find_scene_dirs, load_scannet_scene

    started = time.perf_counter()
    scene_dirs = find_scene_dirs(args.root, args.scenes)
    if args.axis_alignment and len(scene_dirs) != 1:
        raise DatasetError(f"--axis-alignment: expected one scene, got {len(scene_dirs)}")
    prefix, _, argument = args.detector.partition(":")
    gt_options = gt_masks_options(argument)[0] if prefix == GT_MASKS else {}
    shared_detector = None if prefix == GT_MASKS else _make_detector(args.detector)
    entries, frame_counts, export_frames = [], {}, {}
    for scene_dir in scene_dirs:
        scene = load_scannet_scene(scene_dir, scan2aligned=args.axis_alignment)
        names = scene.frame_names[:: args.stride]
        frames = LazyFrames(names, scene.load_frame, cache=len(names) <= CACHE_FRAMES_UP_TO)
        detector = GroundTruthMaskDetector(scene, **gt_options) if shared_detector is None else shared_detector  # type: ignore[arg-type]
        entries.append((scene.scene_id, frames, detector, scene.gt_boxes()))
        frame_counts[scene.scene_id] = len(names)
        export_frames[scene.scene_id] = scannet_export_frame(scene)
        if not scene.objects:
            logger.warning("scene %s has no ground truth of our classes", scene.scene_id)
    export_dir = Path(args.export) if args.export else None
    result = evaluate_scenes(
        entries, _params(args), users=args.users, runs=args.runs, seed=args.seed,
        workers=_workers(args.workers), on_run=_export(export_dir, export_frames), progress=not args.no_progress,
    )  # fmt: skip
    out = {
        **result,
        "dataset": "scannet",
        "detector": args.detector,
        "scenes": list(frame_counts),
        "frames": frame_counts,
        "stride": args.stride,
        "seed": args.seed,
        "wall_s": round(time.perf_counter() - started, 2),
    }
    _write_json(Path(args.out), out)
    _print_table(out["table1"])  # type: ignore[arg-type]
    return 0


def fused_points(frames: Sequence[Frame], *, every: int = 20, stride_px: int = 8, max_depth_m: float = 4.0) -> np.ndarray:
    """(N, 3) world points back-projected from every ``every``-th frame (every ``stride_px``-th pixel)."""
    from arcloud.core.voxels import mask_points

    params = Params(depth_max_m=max_depth_m, erode_px=0)
    chunks = [
        mask_points(frames[i], np.ones(frames[i].shape, bool), params, stride_px)
        for i in range(0, len(frames), max(1, every))
    ]
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def agreement(
    frames: Sequence[Frame],
    detector: Detector,
    params: Params,
    *,
    name: str,
    users: Sequence[int],
    runs: int,
    seed: int = 0,
    workers: int = 1,
    progress: bool = False,
    on_run: OnRun | None = None,
    reference_min_score: float = 0.0,
) -> tuple[list[dict[str, object]], list[MapObject], dict[int, list[MapObject]]]:
    """The runs of ``table1``, each distributed map scored (mAP) against the centralized boxes (those
    scoring at least ``reference_min_score``) as ground truth. Returns one row per K > 1 (``approach`` "distributed", plus ``ap25_per_class``: each class's AP@0.25 averaged over
    runs, None without reference boxes), the centralized objects and the first run's objects per K."""
    from arcloud.eval.metrics import evaluate

    collector = _RunCollector(on_run)
    _table1_runs([(name, frames, detector, [])], params, collector, users=users, runs=runs, seed=seed, workers=workers, progress=progress)
    centralized = collector.first.pop(1)
    # scores are ignored on the ground-truth side, beyond the threshold
    reference = {name: [b for b in collector.boxes[(1, 0)][name] if b.score >= reference_min_score]}
    logger.info("centralized map: %d objects (%d as reference)", len(collector.boxes[(1, 0)][name]), len(reference[name]))
    rows: list[dict[str, object]] = []
    for k in (k for k in users if k > 1):
        results = [evaluate(collector.boxes[(k, run)], reference) for run in range(runs)]
        row = _row("distributed", k, [r.map_at(0.25) for r in results], [r.map_at(0.5) for r in results], collector.wall_s[k])
        per_class = {label: [r.at(0.25).ap[label] for r in results] for label in CLASSES}
        row["ap25_per_class"] = {
            label: None if any(ap is None for ap in aps) else float(np.mean(aps))  # type: ignore[arg-type]
            for label, aps in per_class.items()
        }
        rows.append(row)
    return rows, centralized, collector.first


def served(objects: Sequence[MapObject]) -> list[MapObject]:
    """What a client is served: the confirmed objects."""
    return [o for o in objects if o.confirmed]


def write_pictures(
    stem: Path,
    frames: Sequence[Frame],
    centralized: list[MapObject],
    first_runs: dict[int, list[MapObject]],
    *,
    title: str = "",
    n_frames: int = 4,
    gt: Sequence[LabelledBox] = (),
    world2boxes: np.ndarray | None = None,
) -> list[str]:
    """Top-down pictures (served boxes over fused points) of the centralized and first distributed maps, and
    the centralized boxes drawn into ``n_frames`` frames spread over the sequence; ground-truth boxes
    ``gt`` in green in all of them. ``world2boxes`` (4, 4) maps the world of the frames to the frame
    the boxes are in (``Params.world2aligned``; None: the world). Returns the paths."""
    from arcloud.eval.plot import GT_COLOR_RGB, draw_boxes_in_image, draw_top_down, write_png
    from arcloud.eval.protocol import object_boxes

    world2boxes = np.eye(4) if world2boxes is None else np.asarray(world2boxes, np.float64)
    points = fused_points(frames) @ world2boxes[:3, :3].T + world2boxes[:3, 3]
    written = [
        draw_top_down(f"{stem}_topdown_users1.png", gt=gt, predictions=object_boxes(served(centralized)), points_xyz=points,
                      title=f"{title or stem.name}: centralized, {len(frames)} frames, served objects")
    ]  # fmt: skip
    for k, objects in sorted(first_runs.items()):
        written.append(
            draw_top_down(f"{stem}_topdown_users{k}.png", gt=gt, predictions=object_boxes(served(objects)), points_xyz=points,
                          title=f"{title or stem.name}: {k} users, run 0, served objects")
        )  # fmt: skip
    boxes = object_boxes(served(centralized))
    for index in np.linspace(0, len(frames) - 1, n_frames).round().astype(int) if len(frames) else []:
        frame = frames[int(index)]
        cam2boxes = world2boxes @ frame.cam2world
        image = draw_boxes_in_image(frame.rgb, gt, cam2boxes, frame.intrinsics, color_rgb=GT_COLOR_RGB, show_labels=False)
        image = draw_boxes_in_image(image, boxes, cam2boxes, frame.intrinsics)
        written.append(write_png(f"{stem}_frame_{frame.frame_id}.png", image))
    return [str(p) for p in written]


def accuracy_rows(scores: Mapping[int, Sequence[Mapping[str, Mapping[str, Any]]]]) -> list[dict[str, object]]:
    """Rows of the runs' figures against ground truth: ``scores[K]`` holds each run's
    ``arcloud.accuracy.sevenscenes.score_against`` (``score_run`` figures per box kind). One row per K
    and box kind: mean and variance over runs of mAP, and the means of the served set's precision and
    recall at IoU 0.25 and 0.5 (a missing figure, e.g. recall without ground truth, reads as NaN)."""
    rows: list[dict[str, object]] = []
    for k, runs in sorted(scores.items()):
        for kind in runs[0]:
            figures = [run[kind] for run in runs]
            values = {key: [float("nan") if f[key] is None else float(f[key]) for f in figures] for key in ("map25", "map50", *_SERVED_FIGURES)}
            rows.append({
                "approach": "centralized" if k == 1 else "distributed",
                "users": k,
                "runs": len(figures),
                "boxes": kind,
                "map25_mean": float(np.mean(values["map25"])),
                "map25_var": variance(values["map25"]),
                "map50_mean": float(np.mean(values["map50"])),
                "map50_var": variance(values["map50"]),
                **{key: float(np.mean(values[key])) for key in _SERVED_FIGURES},
                "n_gt": figures[0]["n_gt"],
                "n_served_mean": float(np.mean([f["n_served"] for f in figures])),
            })  # fmt: skip
    return rows


_SERVED_FIGURES = ("served_precision25", "served_recall25", "served_precision50", "served_recall50")


def _scorer(ground_truth: SevenScenesGroundTruth | None, scores: dict[int, list[dict[str, dict[str, Any]]]]) -> OnRun | None:
    """Appends each run's ``score_against`` to ``scores[K]`` (None without ground truth)."""
    if ground_truth is None:
        return None
    from arcloud.accuracy.sevenscenes import score_against

    def score(scene: str, users: int, run: int, objects: list[MapObject]) -> None:
        scores.setdefault(users, []).append(score_against(objects, ground_truth, scene=scene))

    return score


def run_eval_7scenes(args: argparse.Namespace) -> int:
    """``arcloud eval 7scenes``: agreement of distributed maps with the centralized one, accuracy against
    ``gt-boxes.json`` when the sequence has it, and pictures."""
    from arcloud.datasets.sevenscenes import load_seven_scenes

    started = time.perf_counter()
    sequence = load_seven_scenes(args.root, align_gravity=True, colour=args.colour_camera)
    ground_truth = sequence.ground_truth
    names = sequence.frame_names[:: args.stride]
    frames = LazyFrames(names, sequence.load_frame, cache=len(names) <= CACHE_FRAMES_UP_TO)
    out_path = Path(args.out)
    export_dir = Path(args.export) if args.export else None
    frame = seven_scenes_export_frame(sequence)
    scores: dict[int, list[dict[str, dict[str, Any]]]] = {}
    rows, centralized, first_runs = agreement(
        frames, _make_detector(args.detector), frame.params(_params(args)), name=sequence.name, users=args.users,
        runs=args.runs, seed=args.seed, workers=_workers(args.workers), progress=not args.no_progress,
        on_run=_each(_export(export_dir, {sequence.name: frame}), _scorer(ground_truth, scores)),
        reference_min_score=args.reference_min_score,
    )  # fmt: skip
    stem = out_path.with_suffix("")
    gt_boxes = ground_truth.boxes("observed") if ground_truth is not None else []
    pictures = write_pictures(stem, frames, centralized, first_runs, title=sequence.name, gt=gt_boxes, world2boxes=frame.world2export)
    out: dict[str, object] = {"agreement": rows}
    if ground_truth is not None:
        out["accuracy"] = accuracy_rows(scores)
        out["ground_truth"] = {"file": str(ground_truth.path), "objects": [o.id for o in ground_truth.objects], "primary": "observed"}
    out |= {
        "dataset": "7scenes",
        "detector": args.detector,
        "sequence": sequence.name,
        "frames": len(names),
        "stride": args.stride,
        "seed": args.seed,
        "gravity_aligned": sequence.up_file is not None,
        "frame": frame.description,
        "reference_min_score": args.reference_min_score,
        "centralized_objects": [
            {**o, "size": [round(b - a, 3) for a, b in zip(o["aabb_min"], o["aabb_max"])]}  # type: ignore[arg-type]
            for o in objects_json(centralized)
        ],
        "pictures": pictures,
        "wall_s": round(time.perf_counter() - started, 2),
    }
    _write_json(out_path, out)
    _print_table(rows)
    if ground_truth is not None:
        _print_accuracy(out["accuracy"])  # type: ignore[arg-type]
    return 0


def run_render_scannet(args: argparse.Namespace) -> int:
    """``arcloud render-scannet``: render an annotated ScanNet mesh into a ScanNet-layout scene."""
    from arcloud.datasets.render_scannet import render_scannet
    from arcloud.datasets.scannet import load_scannet_scene

    scene = load_scannet_scene(args.mesh_dir, scan2aligned=args.axis_alignment)
    scene_dir = render_scannet(
        scene, Path(args.out), users=args.users, frames_per_user=args.frames, seed=args.seed,
        width=args.width, height=args.height, progress=not args.no_progress, style=args.style,
    )  # fmt: skip
    print(f"wrote {scene_dir}")
    return 0


def _write_json(path: Path, payload: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2))
    logger.info("wrote %s", path)


def _print_table(rows: Sequence[dict[str, Any]]) -> None:
    print(f"{'approach':<12} {'users':>5} {'runs':>4} {'mAP@0.25':>16} {'mAP@0.5':>16} {'wall_s':>8}")
    for r in rows:
        map25 = f"{r['map25_mean']:.4f}±{np.sqrt(r['map25_var']):.4f}"
        map50 = f"{r['map50_mean']:.4f}±{np.sqrt(r['map50_var']):.4f}"
        print(f"{r['approach']:<12} {r['users']:>5} {r['runs']:>4} {map25:>16} {map50:>16} {r['wall_s']:>8}")


def _print_accuracy(rows: Sequence[dict[str, Any]]) -> None:
    print(f"{'approach':<12} {'users':>5} {'runs':>4} {'boxes':>8} {'mAP@0.25':>16} {'mAP@0.5':>16} {'P@0.25':>7} {'R@0.25':>7}")
    for r in rows:
        map25 = f"{r['map25_mean']:.4f}±{np.sqrt(r['map25_var']):.4f}"
        map50 = f"{r['map50_mean']:.4f}±{np.sqrt(r['map50_var']):.4f}"
        print(f"{r['approach']:<12} {r['users']:>5} {r['runs']:>4} {r['boxes']:>8} {map25:>16} {map50:>16} "
              f"{r['served_precision25']:>7.3f} {r['served_recall25']:>7.3f}")  # fmt: skip


def _add_common(parser: argparse.ArgumentParser, users: tuple[int, ...], runs: int) -> None:
    from arcloud.argtypes import parse_users, positive_int

    parser.add_argument("--users", type=parse_users, default=users, help=f"user counts K, comma-separated; 1 = centralized (default {','.join(map(str, users))})")
    parser.add_argument("--runs", type=positive_int, default=runs, help=f"distributed runs per K (default {runs})")
    parser.add_argument("--out", required=True, help="results JSON to write")
    parser.add_argument("--export", default=None, help="folder for every run's objects: <scene>_<K>_<run>.json (with world_from_export)")
    parser.add_argument("--stride", type=positive_int, default=1, help="use every N-th frame (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=0, help="worker threads of distributed runs (default: CPU count)")
    parser.add_argument("--voxel-size-m", type=float, default=None, help="override Params.voxel_size_m")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def add_eval_commands(subparsers: Any) -> Any:
    """Add ``eval scannet``, ``eval 7scenes`` and ``render-scannet`` to an argparse sub-parsers object.

    Returns the sub-parsers of ``eval`` so that other evaluations can join them."""
    evaluation = subparsers.add_parser("eval", help="evaluate on real datasets (ScanNet layout, 7-Scenes)")
    kinds = evaluation.add_subparsers(dest="dataset", required=True, metavar="{scannet,7scenes}")

    scannet = kinds.add_parser(
        "scannet",
        help="Table 1 (centralized vs distributed mAP) on ScanNet-layout scenes",
        description="Table 1 on ScanNet-layout scenes. The default scene list is every scene folder under "
        "--root (the paper does not list its 41 scenes; see docs/datasets.md).",
    )
    scannet.add_argument("--root", required=True, help="a scene folder, a folder of scenes, or one holding scans/")
    scannet.add_argument("--scenes", type=parse_scenes, default=None, help="scene names, comma-separated, or @FILE")
    scannet.add_argument("--detector", required=True,
                         help=f"onnx:PATH (a YOLO-seg ONNX model), or {GT_MASKS}[:OPTIONS] (each scene's own masks; "
                         "OPTIONS e.g. faults=default,seed=3: a model's mask faults, see docs/datasets.md)")
    scannet.add_argument("--axis-alignment", default=None, help="scan2aligned for a scene without one: 16 numbers, a JSON file with axis_align_matrix, or a ScanNet .txt")
    _add_common(scannet, DEFAULT_SCANNET_USERS, 10)
    scannet.set_defaults(handler=run_eval_scannet)

    seven = kinds.add_parser(
        "7scenes",
        help="accuracy against gt-boxes.json (when the sequence has it), agreement of distributed maps with "
        "the centralized map, and pictures, on a 7-Scenes sequence",
    )
    seven.add_argument("--root", required=True, help="a 7-Scenes sequence folder (or a scene of seq-XX folders)")
    seven.add_argument("--detector", required=True, help="onnx:PATH (a YOLO-seg ONNX model)")
    seven.add_argument("--colour-camera", type=parse_colour_camera, default=None, metavar="FX,FY,CX,CY[,TX,TY,TZ]",
                       help="the colour camera's intrinsics (pixels, at the depth size) and the depth->colour translation "
                       "(metres), when colour and depth are not registered (default: gt-boxes.json's estimate, else registered)")
    seven.add_argument("--reference-min-score", type=float, default=0.0,
                       help="agreement: take only centralized objects scoring at least this as ground truth (default 0: all)")
    _add_common(seven, DEFAULT_7SCENES_USERS, 3)
    seven.set_defaults(handler=run_eval_7scenes)

    from arcloud.argtypes import positive_int

    render = subparsers.add_parser(
        "render-scannet",
        help="render an annotated ScanNet mesh into a ScanNet-layout scene walked by K users",
    )
    render.add_argument("--mesh-dir", required=True, help="the scene folder with the mesh, aggregation, segs (and labels tsv)")
    render.add_argument("--out", required=True, help="output root; the scene is written to OUT/<scene>/")
    render.add_argument("--users", type=positive_int, default=10, help="users walking the room, one after the other (default 10)")
    render.add_argument("--frames", type=positive_int, default=60, help="frames per user (default 60)")
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--style", choices=("default", "random"), default="default",
                        help="walks: default (every user at 1.5 m, plan_walk's defaults) or random (each user's eye height, "
                        "speed, coverage, glances and hand-held shake drawn from --seed; recorded in render.json)")
    render.add_argument("--width", type=int, default=640)
    render.add_argument("--height", type=int, default=480)
    render.add_argument("--axis-alignment", default=None, help="scan2aligned when the scene's .txt has none (as for eval scannet)")
    render.add_argument("--no-progress", action="store_true", help="no progress bar")
    render.set_defaults(handler=run_render_scannet)
    return kinds


__all__ = [
    "ExportFrame",
    "LazyFrames",
    "accuracy_rows",
    "add_eval_commands",
    "agreement",
    "evaluate_scenes",
    "export_payload",
    "fused_points",
    "objects_json",
    "parse_scenes",
    "scannet_export_frame",
    "seven_scenes_export_frame",
    "write_pictures",
]
