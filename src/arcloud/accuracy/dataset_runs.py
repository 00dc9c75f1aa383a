"""Evaluation runs on dataset recordings (``arcloud eval scannet``, ``eval recording`` and ``eval 7scenes``):
Table 1 pooled over ScanNet scenes, the agreement of distributed maps with the centralized one, accuracy
rows against ground-truth boxes, and callbacks that export or score every run.

Table 1: mAP against the scenes' ground truth, predictions pooled across scenes (the standard ScanNet
evaluation). One recording: ``agreement`` rows hold the mAP of each distributed map taken against the
centralized map as ground truth; ``accuracy_rows`` score every run against the ground truth's boxes
(observed and amodal).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from arcloud.core.types import CLASSES, Frame, MapObject, Params
from arcloud.datasets.export import ExportFrame, export_payload
from arcloud.eval.metrics import variance
from arcloud.ports import Detector

if TYPE_CHECKING:
    from arcloud.datasets.gt_boxes import GroundTruthBoxes

OnRun = Callable[[str, int, int, list[MapObject]], None]

logger = logging.getLogger(__name__)


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
    from arcloud.stores.memory import MemoryStore

    distributed = tuple(k for k in users if k > 1)
    total = sum(len(frames) for _, frames, _, _ in sequences) * (1 + runs * len(distributed))
    with _progress_bar(total, progress, "eval") as bar:
        for name, frames, detector, gt in sequences:
            collector.start()
            table1(
                frames, detector, gt, params, new_store=MemoryStore, users=distributed, runs=runs, seed=seed, workers=workers,
                scene=name, progress=bar.update,
                on_run=lambda approach, k, run, objects, name=name: collector(name, approach, k, run, objects),  # type: ignore[misc]  # name=name: the loop's scene
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
            centralized["curves"] = results[0].curves_dict()
        scores25, scores50 = [r.map_at(0.25) for r in results], [r.map_at(0.5) for r in results]
        logger.info("users %d: mAP@0.25 %s mAP@0.5 %s", k, np.round(scores25, 4), np.round(scores50, 4))
        rows.append(_row("centralized" if k == 1 else "distributed", k, scores25, scores50, collector.wall_s.get(k, 0.0)))
    out: dict[str, object] = {"table1": rows}
    if centralized is not None:
        out["centralized"] = centralized
    return out


def export_runs(export_dir: Path | None, frames: Mapping[str, ExportFrame]) -> OnRun | None:
    """Writes every run's map as ``<export_dir>/<scene>_<users>_<run>.json`` (``export_payload``)."""
    if export_dir is None:
        return None
    export_dir.mkdir(parents=True, exist_ok=True)

    def write(scene: str, users: int, run: int, objects: list[MapObject]) -> None:
        payload = export_payload(objects, frames[scene], scene=scene, users=users, run=run)
        (export_dir / f"{scene}_{users}_{run}.json").write_text(json.dumps(payload, indent=1))

    return write


def each_run(*callbacks: OnRun | None) -> OnRun | None:
    chosen = [c for c in callbacks if c is not None]
    if not chosen:
        return None

    def call(scene: str, users: int, run: int, objects: list[MapObject]) -> None:
        for callback in chosen:
            callback(scene, users, run, objects)

    return call


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
    _table1_runs(
        [(name, frames, detector, [])], params, collector, users=users, runs=runs, seed=seed, workers=workers, progress=progress
    )
    centralized = collector.first.pop(1)
    # scores are ignored on the ground-truth side, beyond the threshold
    reference = {name: [b for b in collector.boxes[(1, 0)][name] if b.score >= reference_min_score]}
    logger.info("centralized map: %d objects (%d as reference)", len(collector.boxes[(1, 0)][name]), len(reference[name]))
    rows: list[dict[str, object]] = []
    for k in (k for k in users if k > 1):
        results = [evaluate(collector.boxes[(k, run)], reference) for run in range(runs)]
        row = _row("distributed", k, [r.map_at(0.25) for r in results], [r.map_at(0.5) for r in results], collector.wall_s[k])
        row["ap25_per_class"] = mean_per_class([r.at(0.25).ap for r in results])
        rows.append(row)
    return rows, centralized, collector.first


def mean_per_class(per_run: Sequence[Mapping[str, float | None]]) -> dict[str, float | None]:
    """Each class's AP averaged over runs; None where a run has none (no ground truth of the class)."""
    out: dict[str, float | None] = {}
    for label in CLASSES:
        aps = [run.get(label) for run in per_run]
        out[label] = (
            None if not aps or any(ap is None for ap in aps) else float(np.mean([float(ap) for ap in aps if ap is not None]))
        )
    return out


def accuracy_rows(scores: Mapping[int, Sequence[Mapping[str, Mapping[str, Any]]]]) -> list[dict[str, object]]:
    """Rows of the runs' figures against ground truth: ``scores[K]`` holds each run's
    ``arcloud.accuracy.sevenscenes.score_against`` (``score_run`` figures per box kind). One row per K
    and box kind: mean and variance over runs of mAP (every object with a box), the means of the served
    set's mAP, precision and recall at IoU 0.25 and 0.5 (a missing figure, e.g. recall without ground
    truth, reads as NaN), and each class's AP at 0.25 and 0.5 (``mean_per_class``)."""
    rows: list[dict[str, object]] = []
    for k, runs in sorted(scores.items()):
        for kind in runs[0]:
            figures = [run[kind] for run in runs]
            values = {
                key: [float("nan") if f[key] is None else float(f[key]) for f in figures]
                for key in ("map25", "map50", *_SERVED_FIGURES)
            }
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
                "ap25_per_class": mean_per_class([f["ap25_per_class"] for f in figures]),
                "ap50_per_class": mean_per_class([f["ap50_per_class"] for f in figures]),
            })  # fmt: skip
    return rows


_SERVED_FIGURES = (
    "served_map25", "served_map50", "served_precision25", "served_recall25", "served_precision50", "served_recall50"
)  # fmt: skip


def score_runs(
    ground_truth: GroundTruthBoxes | None,
    scores: dict[int, list[dict[str, dict[str, Any]]]],
    *,
    frames: tuple[int, int] | None = None,
) -> OnRun | None:
    """Appends each run's ``score_against`` (the objects visible within ``frames``; None: all) to ``scores[K]``
    (None without ground truth)."""
    if ground_truth is None:
        return None
    from arcloud.accuracy.sevenscenes import score_against

    def score(scene: str, users: int, run: int, objects: list[MapObject]) -> None:
        scores.setdefault(users, []).append(score_against(objects, ground_truth, frames=frames, scene=scene))

    return score
