"""The 7-Scenes suite: the real redkitchen sequence (1000 frames, Kinect v1) through a real model
(YOLO11n-seg by default, YOLOv8n-seg beside it: ``MODELS_REL``), scored against its hand-checked boxes (``gt-boxes.json``: 1 table, 6 chairs, 2 TVs).

Boxes are fitted and scored in the ground truth's aligned frame (z up, floor at z = 0, x along the
walls): ``Params.world2aligned`` is the sequence's ``world2gt``, as ScanNet scores in its axis-aligned
frame. Every run is scored twice with ``arcloud.accuracy.common.score_run``: against the *observed*
boxes (what the sensor saw, ScanNet's convention: the primary figures of the record) and against the
*amodal* ones (chairs completed under the table, the table down to the floor: ``amodal`` beside them).

Cases: the whole sequence (``report``) and its two halves, frames 0-499 and 500-999 (``tune``), each
scored against the objects visible in it (the ground truth's ``visible_frames``), and the whole sequence played
backwards (``paths``: the same frames and objects along another camera path, nothing tuned on it; a review of
camera paths found the two TVs welded into one box that way, 0.611 against 0.944). Any other sequence in the
7-Scenes layout with a ``gt-boxes.json`` (``root``) is one ``report`` case, all its frames: the parameters are
tuned on redkitchen's cases only, so such a sequence tells how they carry to a room nobody tuned on. Each case is
mapped centralized and by ``USERS`` users (``runs`` runs, run r with seed r: ``arcloud.eval.protocol.run_map``).
The model runs once per frame (``CachedDetector``; the halves reuse the whole sequence's detections);
frames are read from disk for every run rather than kept (1000 VGA frames are 2 GB).

Written under ``out_dir``: every run's map as ``exports/<case>_<K>_<run>.json``
(``arcloud.datasets.export.export_payload``: ``world_from_export`` maps it to the pose frame of
``gt-boxes.json``, whose ``world_to_aligned`` then takes it to the boxes), and pictures of each case
with the ground truth in green under ``pictures/``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from arcloud.accuracy.common import USERS, case_record, case_runs, score_run, summarise
from arcloud.accuracy.scannet import default_shared_dir
from arcloud.core.types import MapObject, Params
from arcloud.errors import DatasetError

if TYPE_CHECKING:
    from arcloud.datasets.export import ExportFrame
    from arcloud.datasets.gt_boxes import GroundTruthBoxes
    from arcloud.datasets.sevenscenes import SevenScenesSequence
    from arcloud.ports import Detector

logger = logging.getLogger(__name__)

SEQUENCE_REL = "data/7scenes-redkitchen"
#: The models the suite runs, by name (the first is the default): YOLO11n-seg, and YOLOv8n-seg beside it.
MODELS_REL = {"yolo11n": "models/yolo11n-seg-fp32-640.onnx", "yolov8n": "models/yolov8n-seg-fp32-640.onnx"}
RUNS = 3
QUICK_RUNS = 1
#: The quick mode takes every ``QUICK_STRIDE``-th frame.
QUICK_STRIDE = 10


@dataclass(frozen=True)
class SequenceCase:
    """Frames numbered ``first_frame..last_frame`` (inclusive) of the sequence, in the ``tune`` or
    ``report`` split."""

    first_frame: int
    last_frame: int
    split: str
    sequence: str = "redkitchen"
    backwards: bool = False  # the frames in the reverse of the order they were recorded in

    @property
    def name(self) -> str:
        return f"{self.sequence}_{self.first_frame:03d}-{self.last_frame:03d}{'_backwards' if self.backwards else ''}"

    @property
    def frame_range(self) -> tuple[int, int]:
        return (self.first_frame, self.last_frame)


CASES = (
    SequenceCase(0, 999, "report"),
    SequenceCase(0, 499, "tune"),
    SequenceCase(500, 999, "tune"),
    SequenceCase(0, 999, "paths", backwards=True),
)


def whole_sequence_case(sequence: SevenScenesSequence) -> SequenceCase:
    """The one case of a sequence nobody tuned on: all its frames, in the ``report`` split."""
    numbers = [sequence.frame_number(n) for n in sequence.frame_names]
    return SequenceCase(min(numbers), max(numbers), "report", sequence.name)


def score_against(
    objects: Sequence[MapObject],
    ground_truth: GroundTruthBoxes,
    *,
    frames: tuple[int, int] | None = None,
    scene: str = "scene",
) -> dict[str, dict[str, Any]]:
    """``score_run`` of a map (boxed in the ground truth's aligned frame) against each kind of box the
    ground truth has (observed and amodal; a mesh annotation's: observed) of the objects visible within
    ``frames`` (first, last frame numbers; None: all)."""
    return {kind: score_run(objects, ground_truth.boxes(kind, frames=frames), scene=scene) for kind in ground_truth.box_kinds}


def run_suite(
    *,
    quick: bool,
    out_dir: Path,
    shared: Path | None = None,
    root: Path | None = None,
    cases: Sequence[SequenceCase] | None = None,
    params: Params | None = None,
    runs: int | None = None,
    stride: int | None = None,
    workers: int = 2,
    model: str = next(iter(MODELS_REL)),
) -> dict[str, Any]:
    """Map and score every case (see the module docstring) with the detector ``model`` (a name of
    ``MODELS_REL``): ``runs`` distributed runs per case (default
    ``QUICK_RUNS`` when ``quick``, else ``RUNS``) on every ``stride``-th frame (default ``QUICK_STRIDE``
    when ``quick``, else 1). Returns ``{"suite": "7scenes", "cases": [...], "summary": summarise(cases),
    "summary_amodal": ..., ...}`` (see ``arcloud.accuracy.common``). ``shared``: the folder holding
    ``data/7scenes-redkitchen`` and ``models/`` (default ``default_shared_dir()``); ``root``: another sequence
    in the 7-Scenes layout with its ``gt-boxes.json`` (``cases`` default: all its frames, one ``report`` case);
    raises ``DatasetError`` when the sequence, its ground truth or the model is not there."""
    from arcloud.datasets.export import seven_scenes_export_frame
    from arcloud.datasets.sevenscenes import load_seven_scenes
    from arcloud.detectors import make_detector
    from arcloud.eval.protocol import CachedDetector

    started = time.perf_counter()
    shared_dir = Path(shared if shared is not None else default_shared_dir())
    if model not in MODELS_REL:
        raise DatasetError(f"model: expected one of {list(MODELS_REL)}, got {model!r}")
    model_name, model_path = model, shared_dir / MODELS_REL[model]
    given = root is not None
    root = Path(root) if root is not None else shared_dir / SEQUENCE_REL
    if not (root / "gt-boxes.json").is_file():
        raise DatasetError(
            f"{root}: expected a sequence in the 7-Scenes layout with its gt-boxes.json, got no gt-boxes.json there"
        )
    if not model_path.is_file():
        raise DatasetError(f"{model_path}: expected the {model_name} ONNX model, got no such file")
    n_runs = runs if runs is not None else (QUICK_RUNS if quick else RUNS)
    step = stride if stride is not None else (QUICK_STRIDE if quick else 1)
    sequence = load_seven_scenes(root, align_gravity=True)
    if cases is None:
        cases = (whole_sequence_case(sequence),) if given else CASES
    frame = seven_scenes_export_frame(sequence)
    params = frame.params(params if params is not None else Params())
    detector = CachedDetector(make_detector(f"onnx:{model_path}"))
    out_dir = Path(out_dir)
    records = [
        evaluate_case(sequence, case, detector, params, frame, runs=n_runs, stride=step, workers=workers, out_dir=out_dir)
        for case in cases
    ]
    amodal = [{**r, "centralized": r["amodal"]["centralized"], "distributed": r["amodal"]["distributed"]} for r in records]
    return {
        "suite": "7scenes",
        "quick": quick,
        "sequence": sequence.name,
        "model": model_path.name,
        "ground_truth": str(root / "gt-boxes.json"),
        "primary_boxes": "observed",
        "frame": frame.description,
        "cases": records,
        "summary": summarise(records),
        "summary_amodal": summarise(amodal),
        "users": USERS,
        "runs": n_runs,
        "stride": step,
        "params": dataclasses.asdict(params),
        "wall_s": round(time.perf_counter() - started, 2),
    }


def evaluate_case(
    sequence: SevenScenesSequence,
    case: SequenceCase,
    detector: Detector,
    params: Params,
    frame: ExportFrame,
    *,
    runs: int,
    stride: int,
    workers: int,
    out_dir: Path,
) -> dict[str, Any]:
    """The case's record: its centralized map and ``runs`` maps of ``USERS`` users, scored against the
    objects visible in it (observed boxes; amodal ones under ``amodal``), exported and drawn."""
    from arcloud.datasets.export import export_payload
    from arcloud.datasets.frames import LazyFrames
    from arcloud.eval.map_pictures import write_pictures

    started = time.perf_counter()
    ground_truth = sequence.ground_truth
    if ground_truth is None:
        raise DatasetError(f"{sequence.root}: expected gt-boxes.json to score case {case.name}, got none")
    names = [n for n in sequence.frame_names[::stride] if case.first_frame <= sequence.frame_number(n) <= case.last_frame]
    if case.backwards:
        names.reverse()
    if len(names) < USERS:
        raise DatasetError(f"{sequence.root}: case {case.name}: expected at least {USERS} frames, got {len(names)}")
    frames = LazyFrames(names, sequence.load_frame, cache=False)
    gt_ids = [o.id for o in ground_truth.objects_within(case.frame_range)]
    exports = out_dir / "exports"
    exports.mkdir(parents=True, exist_ok=True)
    first_maps: dict[int, list[MapObject]] = {}

    def score(users: int, run: int, objects: list[MapObject]) -> dict[str, dict[str, Any]]:
        payload = export_payload(objects, frame, scene=sequence.name, case=case.name, users=users, run=run, gt_objects=gt_ids)
        (exports / f"{case.name}_{users}_{run}.json").write_text(json.dumps(payload, indent=1))
        first_maps.setdefault(users, objects)
        return score_against(objects, ground_truth, frames=case.frame_range, scene=sequence.name)

    centralized, distributed = case_runs(frames, detector, params, score, name=case.name, runs=runs, workers=workers, seed=0)
    eval_s = time.perf_counter() - started
    pictures = write_pictures(
        out_dir / "pictures" / case.name, frames, first_maps.pop(1), first_maps, title=case.name,
        gt=ground_truth.boxes("observed", frames=case.frame_range), world2boxes=frame.world2export,
    )  # fmt: skip
    amodal = case_record(case.name, case.split, centralized["amodal"], [d["amodal"] for d in distributed], users=USERS)
    record = case_record(
        case.name, case.split, centralized["observed"], [d["observed"] for d in distributed], users=USERS,
        amodal={"centralized": amodal["centralized"], "distributed": amodal["distributed"]},
        first_frame=case.first_frame, last_frame=case.last_frame, frames=len(names), stride=stride, gt_objects=gt_ids,
        backwards=case.backwards,
        pictures=pictures, eval_s=round(eval_s, 2),
    )  # fmt: skip
    mean = record["distributed"]["mean"]
    logger.info("case %s (%d frames): centralized mAP@0.25 %.3f @0.5 %.3f; K=%d mean %.3f / %.3f", case.name, len(names),
                centralized["observed"]["map25"] or 0.0, centralized["observed"]["map50"] or 0.0, USERS,
                mean.get("map25", 0.0), mean.get("map50", 0.0))  # fmt: skip
    return record


__all__ = ["CASES", "QUICK_STRIDE", "SequenceCase", "evaluate_case", "run_suite", "score_against", "whole_sequence_case"]
