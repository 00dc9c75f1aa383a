"""The evaluation commands of the ``arcloud`` CLI: ``eval scannet``, ``eval recording`` and ``eval 7scenes``
(with the dataset command ``render-scannet`` of ``arcloud.datasets.cli``).

``add_eval_commands(subparsers)`` adds them to the CLI's sub-command parsers; every command sets
``handler`` (``args.handler(args)`` runs it and returns the exit status; ``ArcloudError`` is left to
the CLI's edge). Results are JSON::

    {"table1": [{"approach": "centralized"|"distributed", "users": K, "runs": M,
                 "map25_mean": .., "map25_var": .., "map50_mean": .., "map50_var": ..}, ...], ...}

The runs and their rows are ``arcloud.accuracy.dataset_runs``'s. ``eval recording`` reads any recording
(``arcloud.datasets.recording``: ScanNet, 7-Scenes or TUM RGB-D layout, a folder of any name); ``eval
7scenes`` is the same command on the 7-Scenes layout. With ground truth (``--gt-boxes``, the folder's
``gt-boxes.json``, or a ScanNet scene's annotation) boxes are fitted in its aligned frame and ``accuracy``
rows score every run against its boxes. Pictures are written next to ``--out``; every exported map
(``--export``) declares its frame (``arcloud.datasets.export``).

Adding the commands imports nothing heavy (``arcloud --help`` stays fast); each handler imports what it runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from arcloud.datasets.cli import add_render_command
from arcloud.errors import DatasetError, InvalidInput

if TYPE_CHECKING:
    from arcloud.core.types import Params
    from arcloud.ports import Detector

logger = logging.getLogger(__name__)

DEFAULT_SCANNET_USERS = (1, 10, 50, 100)
DEFAULT_7SCENES_USERS = (1, 10)
GT_MASKS = "gt-masks"


def parse_colour_camera(text: str) -> Any:
    """'fx,fy,cx,cy[,tx,ty,tz]' -> ``ColourCamera`` (intrinsics in pixels; depth->colour translation in m)."""
    import numpy as np

    from arcloud.core.types import Intrinsics
    from arcloud.datasets.frames import ColourCamera

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (4, 7) or not all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
        raise argparse.ArgumentTypeError(
            f"expected fx,fy,cx,cy[,tx,ty,tz] (7 or 4 finite numbers, positive focal lengths), got {text!r}"
        )
    depth2rgb = np.eye(4)
    depth2rgb[:3, 3] = values[4:7] if len(values) == 7 else (0.0, 0.0, 0.0)
    return ColourCamera(Intrinsics(*values[:4]), depth2rgb)


def parse_numbers(count: int, form: str) -> Any:
    """An argparse type reading ``count`` comma-separated finite numbers (``form`` names them) as a tuple."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if len(values) != count or not all(abs(v) < float("inf") for v in values):
            raise argparse.ArgumentTypeError(f"expected {form} ({count} finite numbers, comma-separated), got {text!r}")
        return values

    return parse


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


def _workers(value: int | None) -> int:
    return value if value and value > 0 else max(1, os.cpu_count() or 1)


def _params(args: argparse.Namespace) -> Params:
    """``--params`` (default ``$ARCLOUD_PARAMS``), then ``--voxel-size-m`` on top."""
    from arcloud.argtypes import params_given

    params = params_given(getattr(args, "params", None))
    if getattr(args, "voxel_size_m", None):
        params = params.replace(voxel_size_m=float(args.voxel_size_m))
    return params


def _add_root(parser: argparse.ArgumentParser, what: str) -> None:
    """The folder an ``eval`` reads, as ROOT or ``--root``."""
    parser.add_argument("root_given", nargs="?", default=None, metavar="ROOT", help=f"{what} (or --root)")
    parser.add_argument("--root", default=None, help=argparse.SUPPRESS)


def _settle_folders(args: argparse.Namespace) -> None:
    """``args.root`` from ROOT or ``--root`` (one of them, or both the same), and ``args.out`` by default
    ``out/eval/<the folder's name>.json``."""
    given = {str(root) for root in (args.root_given, args.root) if root is not None}
    if len(given) != 1:
        raise InvalidInput("ROOT", "the folder to evaluate, as ROOT or --root (once)", sorted(given) or "none")
    args.root = given.pop()
    if args.out is None:
        args.out = str(Path("out") / "eval" / f"{Path(args.root).resolve().name or 'root'}.json")


def _colour_move(args: argparse.Namespace) -> tuple[float, ...] | None:
    """``--colour-move``; else none for ground-truth masks (the mesh seen from the depth camera's pose: no colour
    camera to move), else None: where the recording's edges say (``register_colour``)."""
    if args.colour_move is None and args.detector.partition(":")[0] == GT_MASKS:
        return (1.0, 0.0, 0.0, 0.0)
    return args.colour_move


def _make_detector(spec: str) -> Detector:
    from arcloud.datasets.gt_masks import register_gt_masks_detector
    from arcloud.detectors import make_detector

    register_gt_masks_detector()  # the eval commands take gt-masks:SCENE besides the models

    return make_detector(spec)


def run_eval_scannet(args: argparse.Namespace) -> int:
    """``arcloud eval scannet``: Table 1 on ScanNet-layout scenes, against each scene's annotation or
    ``--gt-boxes`` (one scene); writes ``--out`` (and ``--export``)."""
    from arcloud.accuracy.dataset_runs import evaluate_scenes, export_runs
    from arcloud.datasets.export import scannet_export_frame
    from arcloud.datasets.frames import CACHE_FRAMES_UP_TO, LazyFrames
    from arcloud.datasets.gt_boxes import load_ground_truth
    from arcloud.datasets.gt_masks import GroundTruthMaskDetector, gt_masks_options
    from arcloud.datasets.recording import register_colour
    from arcloud.datasets.scannet import find_scene_dirs, load_scannet_scene

    started = time.perf_counter()
    _settle_folders(args)
    scene_dirs = find_scene_dirs(args.root, args.scenes)
    if args.axis_alignment and len(scene_dirs) != 1:
        raise DatasetError(f"--axis-alignment: expected one scene, got {len(scene_dirs)}")
    if args.gt_boxes and len(scene_dirs) != 1:
        raise DatasetError(f"--gt-boxes: expected one scene, got {len(scene_dirs)}")
    ground_truth = load_ground_truth(args.gt_boxes) if args.gt_boxes else None
    prefix, _, argument = args.detector.partition(":")
    gt_options = gt_masks_options(argument)[0] if prefix == GT_MASKS else {}
    shared_detector = None if prefix == GT_MASKS else _make_detector(args.detector)
    params = _params(args)
    entries, frame_counts, export_frames, registrations = [], {}, {}, {}
    alignments = {}
    for scene_dir in scene_dirs:
        scene = load_scannet_scene(scene_dir, scan2aligned=args.axis_alignment, labels_tsv=args.labels_tsv)
        if scene.labels is None and (prefix == GT_MASKS or (ground_truth is None and scene.annotation == "v1")):
            raise DatasetError(
                f"{scene_dir}: expected ScanNet's labels tsv (scannetv2-labels.combined.tsv) in the scene's folder, its "
                "two parents or a meta_data/ beside them, or --labels-tsv: without it chairs, tables and couches are "
                "no class of ours"
            )
        names = scene.frame_names[:: args.stride]
        load_frame, registrations[scene.scene_id] = register_colour(
            scene.frame_names, scene.load_frame, _colour_move(args), where=scene_dir
        )
        alignments[scene.scene_id] = scene.alignment_source
        frames = LazyFrames(names, load_frame, cache=len(names) <= CACHE_FRAMES_UP_TO)
        detector = GroundTruthMaskDetector(scene, **gt_options) if shared_detector is None else shared_detector
        export_frames[scene.scene_id] = scannet_export_frame(scene, ground_truth)
        if ground_truth is not None:  # one scene: its boxes are fitted in the file's aligned frame
            params = export_frames[scene.scene_id].params(params)
        entries.append(
            (scene.scene_id, frames, detector, scene.gt_boxes() if ground_truth is None else ground_truth.boxes("observed"))
        )
        frame_counts[scene.scene_id] = len(names)
        if ground_truth is None and not scene.objects:
            logger.warning("scene %s has no ground truth of our classes", scene.scene_id)
    export_dir = Path(args.export) if args.export else None
    result = evaluate_scenes(
        entries, params, users=args.users, runs=args.runs, seed=args.seed,
        workers=_workers(args.workers), on_run=export_runs(export_dir, export_frames), progress=not args.no_progress,
    )  # fmt: skip
    out = {
        **result,
        "dataset": "scannet",
        "detector": args.detector,
        "scenes": list(frame_counts),
        "frames": frame_counts,
        "stride": args.stride,
        "seed": args.seed,
        "registration": registrations,
        "axis_alignment": alignments,
        "wall_s": round(time.perf_counter() - started, 2),
    }
    if ground_truth is not None:
        out["ground_truth"] = {
            "file": str(ground_truth.path),
            "objects": [o.id for o in ground_truth.objects],
            "boxes": "observed",
        }
    centralized = out.get("centralized")
    out["charts"] = _write_charts(
        Path(args.out),
        title=", ".join(frame_counts),
        rows=out["table1"],
        ap_per_class=centralized["per_class"] if centralized else None,
        curves=centralized["curves"] if centralized else None,
    )
    _write_json(Path(args.out), out)
    source = ground_truth.path if ground_truth is not None else "each scene's annotation"
    print(f"Table 1: mAP against {source} ({len(frame_counts)} scenes, {sum(frame_counts.values())} frames)")
    _print_table(out["table1"])
    print(f"wrote {args.out}")
    return 0


def run_eval_recording(args: argparse.Namespace) -> int:
    """``arcloud eval recording`` (and ``eval 7scenes``, the same on the 7-Scenes layout): agreement of
    distributed maps with the centralized one, accuracy against the ground truth when the recording has
    one (all objects and the served set, per class), and pictures."""
    from arcloud.accuracy.dataset_runs import accuracy_rows, agreement, each_run, export_runs, score_runs
    from arcloud.core.types import Intrinsics
    from arcloud.datasets.export import objects_json
    from arcloud.datasets.frames import CACHE_FRAMES_UP_TO, LazyFrames
    from arcloud.datasets.recording import check_intrinsics, load_recording, register_colour
    from arcloud.eval.map_pictures import write_pictures

    started = time.perf_counter()
    _settle_folders(args)
    recording = load_recording(
        args.root, layout=args.layout, gt_boxes=args.gt_boxes, up=args.up,
        intrinsics=None if args.intrinsics is None else Intrinsics(*args.intrinsics), depth_factor=args.depth_factor,
        pose_time_offset_s=args.pose_time_offset_s, colour=args.colour_camera,
    )  # fmt: skip
    intrinsics_check = check_intrinsics(recording)
    load_frame, registration = register_colour(recording.frame_names, recording.load_frame, _colour_move(args), where=args.root)
    recording = dataclasses.replace(recording, load_frame=load_frame)
    ground_truth = recording.ground_truth
    names = recording.frame_names[:: args.stride][: args.max_frames]
    frames = LazyFrames(names, recording.load_frame, cache=len(names) <= CACHE_FRAMES_UP_TO)
    scored = recording.scored_frames(names)  # the objects visible in the frames used (all, for the whole recording)
    out_path = Path(args.out)
    export_dir = Path(args.export) if args.export else None
    frame = recording.export_frame
    scores: dict[int, list[dict[str, dict[str, Any]]]] = {}
    rows, centralized, first_runs = agreement(
        frames, _make_detector(args.detector), frame.params(_params(args)), name=recording.name, users=args.users,
        runs=args.runs, seed=args.seed, workers=_workers(args.workers), progress=not args.no_progress,
        on_run=each_run(export_runs(export_dir, {recording.name: frame}), score_runs(ground_truth, scores, frames=scored)),
        reference_min_score=args.reference_min_score,
    )  # fmt: skip
    gt_boxes = ground_truth.boxes("observed", frames=scored) if ground_truth is not None else []
    pictures = write_pictures(
        out_path.with_suffix(""),
        frames,
        centralized,
        first_runs,
        title=recording.name,
        gt=gt_boxes,
        world2boxes=frame.world2export,
    )
    out: dict[str, Any] = {"agreement": rows}
    if ground_truth is not None:
        out["accuracy"] = accuracy_rows(scores)
        out["ground_truth"] = {
            "file": str(ground_truth.path),
            "objects": [o.id for o in ground_truth.objects_within(scored)],
            "visible_within_frames": scored,  # null: every object
            "box_kinds": list(ground_truth.box_kinds),
            "primary": "observed",
        }
    out |= {
        "dataset": recording.layout,
        "root": str(recording.root),
        "detector": args.detector,
        "sequence": recording.name,
        "frames": len(names),
        "stride": args.stride,
        "seed": args.seed,
        "gravity_aligned": recording.gravity.up_file is not None,
        "gravity": recording.gravity.to_json(),
        "recording": dict(recording.facts),
        "intrinsics_check": intrinsics_check,
        "registration": registration,
        "frame": frame.description,
        "reference_min_score": args.reference_min_score,
        "centralized_objects": [
            {**o, "size": [round(b - a, 3) for a, b in zip(o["aabb_min"], o["aabb_max"])]} for o in objects_json(centralized)
        ],
        "pictures": pictures,
        "wall_s": round(time.perf_counter() - started, 2),
    }
    if ground_truth is not None:  # the charts of the primary boxes' rows; the centralized run's AP per class
        primary = [r for r in out["accuracy"] if r["boxes"] == "observed"]
        one_user = next((r for r in primary if r["users"] == 1), None)
        out["charts"] = _write_charts(
            out_path,
            title=recording.name,
            rows=primary,
            ap_per_class=None if one_user is None else {"0.25": one_user["ap25_per_class"], "0.5": one_user["ap50_per_class"]},
        )
    _write_json(out_path, out)
    print(f"{recording.name}: {recording.layout} layout, {len(names)} frames")
    if rows:
        print("\nAgreement of distributed maps with the centralized one")
        _print_table(rows)
    _print_camera(out["recording"], registration)
    if ground_truth is not None:
        for kind in ground_truth.box_kinds:
            chosen = [r for r in out["accuracy"] if r["boxes"] == kind]
            print(f"\nAccuracy against {ground_truth.path} ({kind} boxes)")
            _print_accuracy(chosen)
            print(f"\nAP per class against {ground_truth.path} ({kind} boxes), IoU 0.25 / 0.5")
            _print_per_class(chosen)
    print(f"\nwrote {out_path} and {len(pictures)} pictures beside it")
    return 0


def _print_camera(facts: Mapping[str, Any], registration: Mapping[str, Any]) -> None:
    """What the recording's depth and poses decided of its camera (each decision's reason is in the results)."""
    print("\nCamera (as the recording's depth and poses decided; results.recording and .registration say why)")
    if "intrinsics" in facts:
        print(f"  intrinsics     {', '.join(f'{v:g}' for v in facts['intrinsics'])}: {facts['intrinsics_source'].split(':')[0]}")
    if "depth_factor" in facts:
        print(f"  depth factor   {facts['depth_factor']:.6g}: {facts['depth_factor_source'].split(':')[0]}")
    if "pose_time_offset_s" in facts:
        print(f"  pose clock     {facts['pose_time_offset_s']:+.3f} s: {facts['pose_time_offset_source'].split(':')[0]}")
    if "colour_turn_deg" in facts:
        turn = facts["colour_turn_deg"]
        print(
            f"  colour motion  the camera turned {turn['median']:g} degrees (median, largest {turn['max']:g}) between a frame's two images"
        )
    scale, du, dv, tx = registration["move"]
    found = "given" if "edge_strength" not in registration else "by the edges" if registration["move"] != [1, 0, 0, 0] else "kept"
    print(f"  colour camera  focal x{scale:g}, principal point {du:+g}, {dv:+g} px, {tx:+g} m along x: {found}")


def _write_charts(out_path: Path, **figures: Any) -> list[str]:
    """The charts of ``arcloud.eval.charts`` beside the results (``<out>_*.png``); none without matplotlib, said in
    one line."""
    from arcloud.eval.charts import write_charts

    try:
        paths = write_charts(out_path.with_suffix(""), **figures)
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] != "matplotlib":
            raise
        print("charts skipped: matplotlib is not installed (pip install matplotlib)")
        return []
    for path in paths:
        logger.info("wrote %s", path)
    return [str(p) for p in paths]


def _write_json(path: Path, payload: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2))
    logger.info("wrote %s", path)


def _print_table(rows: Sequence[dict[str, Any]]) -> None:
    import numpy as np

    print(f"{'approach':<12} {'users':>5} {'runs':>4} {'mAP@0.25':>16} {'mAP@0.5':>16} {'wall_s':>8}")
    for r in rows:
        map25 = f"{r['map25_mean']:.4f}±{np.sqrt(r['map25_var']):.4f}"
        map50 = f"{r['map50_mean']:.4f}±{np.sqrt(r['map50_var']):.4f}"
        print(f"{r['approach']:<12} {r['users']:>5} {r['runs']:>4} {map25:>16} {map50:>16} {r['wall_s']:>8}")


def _print_accuracy(rows: Sequence[dict[str, Any]]) -> None:
    """mAP of every object with a box and of the served set, the served set's precision and recall."""
    import numpy as np

    print(f"{'approach':<12} {'users':>5} {'runs':>4} {'mAP@0.25':>16} {'mAP@0.5':>16} {'served mAP@0.25':>15} "
          f"{'served mAP@0.5':>14} {'P@0.25':>7} {'R@0.25':>7} {'P@0.5':>7} {'R@0.5':>7}")  # fmt: skip
    for r in rows:
        map25 = f"{r['map25_mean']:.4f}±{np.sqrt(r['map25_var']):.4f}"
        map50 = f"{r['map50_mean']:.4f}±{np.sqrt(r['map50_var']):.4f}"
        print(f"{r['approach']:<12} {r['users']:>5} {r['runs']:>4} {map25:>16} {map50:>16} {r['served_map25']:>15.4f} "
              f"{r['served_map50']:>14.4f} {r['served_precision25']:>7.3f} {r['served_recall25']:>7.3f} "
              f"{r['served_precision50']:>7.3f} {r['served_recall50']:>7.3f}")  # fmt: skip


def _print_per_class(rows: Sequence[dict[str, Any]]) -> None:
    """Each class's AP at IoU 0.25 and 0.5 (mean over runs), for the classes with ground truth."""
    labels = [label for label in (rows[0]["ap25_per_class"] if rows else {}) if rows[0]["ap25_per_class"][label] is not None]
    print(f"{'approach':<12} {'users':>5} " + " ".join(f"{label:>13}" for label in labels))
    for r in rows:
        cells = [f"{r['ap25_per_class'][label]:.3f} / {r['ap50_per_class'][label]:.3f}" for label in labels]
        print(f"{r['approach']:<12} {r['users']:>5} " + " ".join(f"{cell:>13}" for cell in cells))


def _add_common(parser: argparse.ArgumentParser, users: tuple[int, ...], runs: int) -> None:
    from arcloud.argtypes import PARAMS_HELP, params_overrides, parse_users, positive_int

    parser.add_argument(
        "--users",
        type=parse_users,
        default=users,
        help=f"user counts K, comma-separated; 1 = centralized (default {','.join(map(str, users))})",
    )
    parser.add_argument("--runs", type=positive_int, default=runs, help=f"distributed runs per K (default {runs})")
    parser.add_argument("--out", default=None, help="results JSON to write (default: out/eval/<ROOT's name>.json)")
    parser.add_argument(
        "--export", default=None, help="folder for every run's objects: <scene>_<K>_<run>.json (with world_from_export)"
    )
    parser.add_argument("--stride", type=positive_int, default=1, help="use every N-th frame (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=0, help="worker threads of distributed runs (default: CPU count)")
    parser.add_argument("--params", metavar="JSON", type=params_overrides, help=PARAMS_HELP)
    parser.add_argument("--voxel-size-m", type=float, default=None, help="override Params.voxel_size_m")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_colour_move(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--colour-move",
        type=parse_numbers(4, "scale,du,dv,tx"),
        default=None,
        metavar="SCALE,DU,DV,TX",
        help="move the colour camera: its focal lengths times SCALE, its principal point by DU, DV pixels, the camera TX "
        "metres along x (default: where the depth's edges meet the colour's best, when 10 %% better than as "
        "recorded; 1,0,0,0: as recorded)",
    )


def _add_recording_options(parser: argparse.ArgumentParser, *, layouts: bool) -> None:
    """What ``eval recording`` and ``eval 7scenes`` take besides ``_add_common``'s (the reader's options
    when ``layouts``; ``eval 7scenes`` reads the 7-Scenes layout only)."""
    from arcloud.argtypes import positive_int

    parser.add_argument(
        "--detector",
        default="onnx",
        help="onnx[:PATH]: a YOLO-seg or Mask R-CNN ONNX model (default: the model cache's default model, as `serve` "
        f"runs it: `arcloud models`); ScanNet layout: or {GT_MASKS}[:OPTIONS], the scene's own masks",
    )
    parser.add_argument(
        "--max-frames", type=positive_int, default=None, help="map at most N frames: the first N after --stride (default all)"
    )
    parser.add_argument(
        "--gt-boxes",
        default=None,
        metavar="FILE",
        help="ground-truth boxes (the gt-boxes.json format, its world the frame of the recording's poses; "
        "default: gt-boxes.json in --root, else a ScanNet scene's annotation)",
    )
    parser.add_argument(
        "--up",
        type=parse_numbers(3, "x,y,z"),
        default=None,
        metavar="X,Y,Z",
        help="up in the frame of the recording's poses (default: gravity-direction.txt, the ground truth's, "
        "else estimated from the depth; ScanNet: z)",
    )
    parser.add_argument(
        "--colour-camera",
        type=parse_colour_camera,
        default=None,
        metavar="FX,FY,CX,CY[,TX,TY,TZ]",
        help="7-Scenes: the colour camera's intrinsics (pixels, at the depth size) and the depth->colour translation "
        "(metres), when colour and depth are not registered (default: gt-boxes.json's estimate, else registered)",
    )
    _add_colour_move(parser)
    parser.add_argument(
        "--reference-min-score",
        type=float,
        default=0.0,
        help="agreement: take only centralized objects scoring at least this as ground truth (default 0: all)",
    )
    if not layouts:
        parser.set_defaults(layout="7scenes", intrinsics=None, depth_factor=None, pose_time_offset_s=None)
        return
    from arcloud.datasets.recording import LAYOUTS

    parser.add_argument(
        "--layout",
        choices=("auto", *LAYOUTS),
        default="auto",
        help="auto: TUM (rgb.txt and depth.txt), 7-Scenes (frame-*.pose.txt) or ScanNet (pose/)",
    )
    parser.add_argument(
        "--intrinsics",
        type=parse_numbers(4, "fx,fy,cx,cy"),
        default=None,
        metavar="FX,FY,CX,CY",
        help="TUM: the intrinsics in pixels (default: camera-intrinsics.txt or intrinsics.txt in --root, "
        "else TUM's by the folder's freiburg1/2/3 name, else 525,525,319.5,239.5)",
    )
    parser.add_argument(
        "--depth-factor",
        type=float,
        default=None,
        help="TUM: depth PNG units a metre (default: 5000, over the scale of 0.95-1.05 the depth and poses agree with best)",
    )
    parser.add_argument(
        "--pose-time-offset-s",
        type=float,
        default=None,
        help="TUM: added to each image's timestamp before its pose is interpolated (default: the one of -0.05 to "
        "0.05 s the depth and poses agree with best, else 0)",
    )


def add_eval_commands(subparsers: Any) -> Any:
    """Add ``eval scannet``, ``eval recording``, ``eval 7scenes`` and ``render-scannet`` to an argparse
    sub-parsers object.

    Returns the sub-parsers of ``eval`` so that other evaluations can join them."""
    evaluation = subparsers.add_parser("eval", help="evaluate on real datasets (ScanNet, 7-Scenes, TUM RGB-D layouts)")
    kinds = evaluation.add_subparsers(dest="dataset", required=True, metavar="{scannet,recording,7scenes}")

    scannet = kinds.add_parser(
        "scannet",
        help="Table 1 (centralized vs distributed mAP) on ScanNet-layout scenes",
        description="Table 1 on ScanNet-layout scenes. The default scene list is every scene folder under "
        "--root (the paper does not list its 41 scenes; see docs/datasets.md).",
    )
    _add_root(scannet, "a scene folder (any name), a folder of scenes, or one holding scans/")
    scannet.add_argument("--scenes", type=parse_scenes, default=None, help="scene names, comma-separated, or @FILE")
    scannet.add_argument(
        "--detector",
        default="onnx",
        help=f"onnx[:PATH] (an ONNX model; default: the model cache's default model), or {GT_MASKS}[:OPTIONS] (each scene's own masks; "
        "OPTIONS e.g. faults=default,seed=3: a model's mask faults, see docs/datasets.md)",
    )
    scannet.add_argument(
        "--axis-alignment",
        default=None,
        help="scan2aligned for a scene without one: 16 numbers, a JSON file with axis_align_matrix, or a ScanNet .txt",
    )
    scannet.add_argument(
        "--labels-tsv",
        default=None,
        metavar="FILE",
        help="ScanNet's scannetv2-labels.combined.tsv (default: in the scene's folder, its two parents or meta_data/)",
    )
    scannet.add_argument(
        "--gt-boxes",
        default=None,
        metavar="FILE",
        help="ground-truth boxes of one scene (the gt-boxes.json format, its world the scan frame of pose/) "
        "instead of the scene's annotation; boxes are fitted in its aligned frame",
    )
    _add_colour_move(scannet)
    _add_common(scannet, DEFAULT_SCANNET_USERS, 10)
    scannet.set_defaults(handler=run_eval_scannet)

    recording = kinds.add_parser(
        "recording",
        help="accuracy against ground-truth boxes (when given or found), agreement of distributed maps with the "
        "centralized map, and pictures, on any recording: ScanNet, 7-Scenes or TUM RGB-D layout",
        description="Evaluate one recording of any layout and any folder name (see docs/datasets.md).",
    )
    _add_root(recording, "the recording's folder")
    _add_recording_options(recording, layouts=True)
    _add_common(recording, DEFAULT_7SCENES_USERS, 3)
    recording.set_defaults(handler=run_eval_recording)

    seven = kinds.add_parser(
        "7scenes",
        help="eval recording on the 7-Scenes layout: accuracy against gt-boxes.json (when the sequence has it), "
        "agreement of distributed maps with the centralized map, and pictures",
    )
    _add_root(seven, "a 7-Scenes sequence folder (or a scene of seq-XX folders)")
    _add_recording_options(seven, layouts=False)
    _add_common(seven, DEFAULT_7SCENES_USERS, 3)
    seven.set_defaults(handler=run_eval_recording)

    add_render_command(subparsers)
    return kinds
