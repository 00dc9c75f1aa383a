"""The ScanNet suite: the real scanned room scene0000_00 rendered along randomised walks and replayed
through the ground-truth-mask detector with a model's mask faults.

A *case* is one render of the room's annotated mesh (``arcloud.datasets.render_scannet``): ``USERS``
users walk it one after the other, each with a walk style drawn from the case's seed (eye height,
speed, coverage, glances, hand-held jitter: ``style="random"``). Its frames are replayed through
``GroundTruthMaskDetector`` with ``MaskFaults`` (borders a few pixels off, missed and split instances,
scores below 1; fault seed = the case's seed), and maps are built with ``arcloud.eval.protocol.run_map``:
the centralized run (frames in order) and ``runs`` distributed runs with K = ``USERS`` users (run r:
seed ``case seed * 1000 + r``). Ground truth and frame are those of ``arcloud eval scannet``: the
axis-aligned boxes of the annotated instances of our classes, in the scene's aligned frame, from the
ScanNet v2 annotation (``ANNOTATION``), as the ScanNet v2 benchmark scores: its tables reach the floor,
where v1 has one as its top only (8 cm tall, which a map of the whole table cannot match at IoU 0.25),
and it has a fourth table v1 lacks (six objects: four tables, one a desk, a couch and a tv).

Cases with seeds in ``TUNE_SEEDS`` may be tuned on; the others are the ``report`` split. Renders are
written once under ``out_dir/renders/<case>/`` and reused while their settings and annotation
(``render.json``) are the same; every run's map is exported as ``out_dir/exports/<case>_<K>_<run>.json``
(``arcloud.datasets.export.export_payload``, the format of ``arcloud eval scannet --export``: served objects
under ``objects``, the others under ``tentative``) beside ``<case>_gt.json``, so that another scorer can
check the mAP.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from arcloud.accuracy.common import USERS, case_record, case_runs, score_run, summarise
from arcloud.core.types import MapObject, Params
from arcloud.datasets.mask_faults import MaskFaults
from arcloud.errors import DatasetError

if TYPE_CHECKING:
    from arcloud.datasets.scannet import Annotation, ScanNetScene

logger = logging.getLogger(__name__)

#: The real scan under the shared folder, and where its axis alignment is (its v1 .txt has none).
SCENE_REL = "data/scannet-scene0000_00"
ALIGNMENT_REL = "real_frames/frames.json"
SCENE_ID = "scene0000_00"
#: The 3D annotation scored against (``load_scannet_scene``'s ``annotation``).
ANNOTATION: Annotation = "v2"
#: Seeds of the full suite's renders; parameters may be tuned on ``TUNE_SEEDS``, figures are reported on the rest.
SEEDS = (0, 1, 2, 3, 4, 5)
TUNE_SEEDS = (0, 1)
RUNS = 3
QUICK_RUNS = 2


@dataclass(frozen=True)
class RenderCase:
    """One render of the room: ``users`` walks of ``frames_per_user`` frames from ``seed`` in ``style``
    (``render_scannet``'s), in the ``tune`` or ``report`` split; the ``default`` and ``scan`` styles walk with the
    eye at ``eye_height_m`` (the ``random`` style draws each user's)."""

    seed: int
    split: str
    style: str = "random"
    users: int = USERS
    frames_per_user: int = 60
    width: int = 640
    height: int = 480
    eye_height_m: float = 1.5

    def __post_init__(self) -> None:
        if self.style == "random" and self.eye_height_m != 1.5:
            raise ValueError(
                f"case seed {self.seed}: the random style draws each user's eye height; got eye_height_m {self.eye_height_m}"
            )

    @property
    def name(self) -> str:
        eye = "" if self.eye_height_m == 1.5 else f"_eye{self.eye_height_m:g}"
        return f"{SCENE_ID}_{self.style}_seed{self.seed}_{self.users}x{self.frames_per_user}{eye}"

    def render_settings(self) -> dict[str, Any]:
        """What ``render.json`` must record for a render of this case to be reused."""
        return {"users": self.users, "frames_per_user": self.frames_per_user, "seed": self.seed, "style": self.style,
                "width": self.width, "height": self.height,
                "eye_height_m": None if self.style == "random" else self.eye_height_m}  # fmt: skip


#: One user's 300-frame walk at 1.5 m (``plan_walk``'s defaults), shared out among K users by the evaluation:
#: a walk unlike the random ones, on which K = 10 once served a TV's box without its back (docs/accuracy.md).
ONE_WALK_CASE = RenderCase(6, "report", style="default", users=1, frames_per_user=300)
#: One operator's 300-frame scan (``style="scan"``: the camera swings along the walls, at no object in particular),
#: shared out among K users: objects seen in passing, cut by the image border, from one side at a time.
SCAN_CASE = RenderCase(1, "report", style="scan", users=1, frames_per_user=300)
#: One user's walk in each style, drawn after the rules were tuned (November 27): on all three the code issue 20 was
#: filed against (6911acd) served the TV's box half as deep as the TV (IoU 0.38-0.42), the held-out ScanNet path's failure.
UNTUNED_WALK_CASES = (
    RenderCase(10, "report", style="random", users=1, frames_per_user=400),
    RenderCase(6, "report", style="scan", users=1, frames_per_user=300),
    RenderCase(13, "report", style="default", users=1, frames_per_user=300),
)
#: Walks with the eye at 1.0 m (a child's, a seated user's, a phone held low): a TV's top is above the eye and its
#: back a thin edge masks rarely cover, a couch's arm is seen beside its seat. The thin-part rule (core.boxes.
#: parts_near) was worked out on a helper's renders of this kind (seeds 100-116, out of the suite); seed 7 may be
#: tuned on, seeds 8 and 9 were drawn after the rule was fixed (November 27).
LOW_EYE_CASES = (
    RenderCase(7, "tune", style="default", users=1, frames_per_user=300, eye_height_m=1.0),
    RenderCase(8, "report", style="default", users=1, frames_per_user=300, eye_height_m=1.0),
    RenderCase(9, "report", style="scan", users=1, frames_per_user=300, eye_height_m=1.0),
)
FULL_CASES = (
    tuple(RenderCase(seed, "tune" if seed in TUNE_SEEDS else "report") for seed in SEEDS)
    + (ONE_WALK_CASE, SCAN_CASE)
    + UNTUNED_WALK_CASES
    + LOW_EYE_CASES
)
#: One small render (200 frames) of a report seed: a minute's check of the whole path.
QUICK_CASES = (RenderCase(2, "report", frames_per_user=20),)


def default_shared_dir() -> Path:
    """The shared folder: ``ARCLOUD_SHARED``, else ``../shared`` beside the working directory's project."""
    return Path(os.environ.get("ARCLOUD_SHARED", Path.cwd().parent / "shared"))


def run_suite(
    *,
    quick: bool,
    out_dir: Path,
    shared: Path | None = None,
    cases: Sequence[RenderCase] | None = None,
    faults: MaskFaults = MaskFaults(),
    params: Params | None = None,
    runs: int | None = None,
    workers: int = 2,
    progress: bool = False,
) -> dict[str, Any]:
    """Render (or reuse) and evaluate every case (``QUICK_CASES`` when ``quick``, else ``FULL_CASES``);
    returns ``{"suite": "scannet", "cases": [...], "summary": summarise(cases), ...}`` (see
    ``arcloud.accuracy.common``). ``shared``: the folder holding ``data/scannet-scene0000_00``
    (default ``default_shared_dir()``); raises ``DatasetError`` when the scan or its v2 annotation is
    not there."""
    from arcloud.datasets.scannet import load_scannet_scene

    started = time.perf_counter()
    source_dir = Path(shared if shared is not None else default_shared_dir()) / SCENE_REL
    if not (source_dir / f"{SCENE_ID}_vh_clean_2.ply").is_file():
        raise DatasetError(f"{source_dir}: expected the ScanNet scan {SCENE_ID} (mesh, aggregation, segs), got no mesh there")
    chosen = tuple(cases) if cases is not None else (QUICK_CASES if quick else FULL_CASES)
    n_runs = runs if runs is not None else (QUICK_RUNS if quick else RUNS)
    params = params if params is not None else Params()
    source = load_scannet_scene(source_dir, scan2aligned=source_dir / ALIGNMENT_REL, annotation=ANNOTATION)
    out_dir = Path(out_dir)
    records = []
    for case in chosen:
        scene_dir, render_s = render_case(source, case, out_dir / "renders", progress=progress)
        records.append(
            evaluate_case(
                case, scene_dir, faults, params, runs=n_runs, workers=workers, export_dir=out_dir / "exports", render_s=render_s
            )
        )
    return {
        "suite": "scannet",
        "quick": quick,
        "scene": SCENE_ID,
        "annotation": source.annotation,
        "cases": records,
        "summary": summarise(records),
        "users": USERS,
        "runs": n_runs,
        "tune_seeds": [c.seed for c in chosen if c.split == "tune"],
        "report_seeds": [c.seed for c in chosen if c.split == "report"],
        "faults": dataclasses.asdict(faults),
        "params": dataclasses.asdict(params),
        "wall_s": round(time.perf_counter() - started, 2),
    }


def render_case(source: ScanNetScene, case: RenderCase, renders_dir: Path, *, progress: bool = False) -> tuple[Path, float]:
    """The case's render of ``source`` under ``renders_dir/<case>/``: reused when its ``render.json``
    records the case's settings and ``source``'s annotation, else rendered. Returns (scene folder,
    seconds spent)."""
    from arcloud.datasets.render_scannet import render_scannet

    root = renders_dir / case.name
    scene_dir = root / source.scene_id
    record_path = scene_dir / "render.json"
    if record_path.is_file():
        record = json.loads(record_path.read_text())
        wanted = {**case.render_settings(), "annotation": source.annotation}
        if all(record.get(key) == value for key, value in wanted.items()):
            logger.info("case %s: reusing the render in %s", case.name, scene_dir)
            return scene_dir, 0.0
        logger.info("case %s: the render in %s has other settings; rendering again", case.name, scene_dir)
    started = time.perf_counter()
    render_scannet(
        source, root, users=case.users, frames_per_user=case.frames_per_user, seed=case.seed, style=case.style,
        width=case.width, height=case.height, eye_height_m=case.eye_height_m, progress=progress,
    )  # fmt: skip
    return scene_dir, time.perf_counter() - started


def evaluate_case(
    case: RenderCase,
    scene_dir: Path,
    faults: MaskFaults,
    params: Params,
    *,
    runs: int,
    workers: int,
    export_dir: Path | None = None,
    render_s: float = 0.0,
) -> dict[str, Any]:
    """The case's record: its centralized map and ``runs`` maps of K = ``USERS`` users (whoever walked the
    render: one user's walk is shared out among them as a recording would be), scored
    against the render's ground truth (``arcloud.accuracy.common.case_record``)."""
    from arcloud.datasets.export import export_payload, scannet_export_frame
    from arcloud.datasets.frames import LazyFrames
    from arcloud.datasets.gt_masks import GroundTruthMaskDetector
    from arcloud.datasets.scannet import load_scannet_scene
    from arcloud.eval.protocol import CachedDetector

    started = time.perf_counter()
    scene = load_scannet_scene(scene_dir)
    frames = LazyFrames(scene.frame_names, scene.load_frame, cache=True)
    ground_truth = scene.gt_boxes()
    detector = CachedDetector(GroundTruthMaskDetector(scene, faults=faults, fault_seed=case.seed))
    frame = scannet_export_frame(scene)
    if export_dir is not None:
        export_dir.mkdir(parents=True, exist_ok=True)
        gt_json = [
            {"label": b.label, "aabb_min": [float(v) for v in b.min], "aabb_max": [float(v) for v in b.max]} for b in ground_truth
        ]
        gt_payload = {
            "scene": scene.scene_id,
            "case": case.name,
            "annotation": scene.annotation,
            "frame": frame.description,
            "objects": gt_json,
        }
        (export_dir / f"{case.name}_gt.json").write_text(json.dumps(gt_payload, indent=1))

    def score(users: int, run: int, objects: list[MapObject]) -> dict[str, Any]:
        if export_dir is not None:
            payload = export_payload(objects, frame, scene=scene.scene_id, case=case.name, users=users, run=run)
            (export_dir / f"{case.name}_{users}_{run}.json").write_text(json.dumps(payload, indent=1))
        return score_run(objects, ground_truth, scene=scene.scene_id)

    centralized, distributed = case_runs(
        frames, detector, params, score, name=case.name, runs=runs, workers=workers, seed=case.seed * 1000
    )
    render = json.loads((scene_dir / "render.json").read_text())
    record = case_record(
        case.name, case.split, centralized, distributed, users=USERS, walkers=case.users,
        seed=case.seed, style=case.style, annotation=scene.annotation, frames=len(frames), dropped_frames=render.get("dropped", 0),
        walk_styles=render.get("walk_styles"), render_s=round(render_s, 2), eval_s=round(time.perf_counter() - started, 2),
    )  # fmt: skip
    mean = record["distributed"]["mean"]
    logger.info("case %s: centralized mAP@0.25 %.3f @0.5 %.3f; K=%d mean %.3f / %.3f", case.name,
                centralized["map25"] or 0.0, centralized["map50"] or 0.0, USERS, mean.get("map25", 0.0), mean.get("map50", 0.0))  # fmt: skip
    return record


__all__ = ["ANNOTATION", "FULL_CASES", "QUICK_CASES", "RenderCase", "TUNE_SEEDS", "evaluate_case", "render_case", "run_suite"]
