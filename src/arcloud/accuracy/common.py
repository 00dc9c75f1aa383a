"""What every accuracy suite reports, and how.

A *run* is one map built from one case (centralized: one ordered user; distributed: K users fed
concurrently). ``score_run`` scores a run's objects against the case's ground truth:

- ``map25``/``map50``: mAP at 3D IoU 0.25/0.5 of every object with a box (tentative ones included,
  ranked by score, as the ScanNet evaluation ranks predictions);
- ``served``: the objects a client is served by default (``MapObject.confirmed``): their mAP, and
  precision and recall at IoU 0.25 and 0.5 (``arcloud.eval.metrics.precision_recall``).

A *case* record holds the centralized run and the distributed runs (and their mean); ``summarise``
gives, per split, the mean and the worst case of each figure, so that a suite cannot hide a bad room
behind good ones. Cases in the ``tune`` split are the ones parameters may be tuned on; figures are
reported on the ``report`` split.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from arcloud.core.types import Frame, LabelledBox, MapObject, Params
from arcloud.eval.metrics import evaluate, precision_recall
from arcloud.eval.protocol import object_boxes, run_map

if TYPE_CHECKING:
    from arcloud.ports import Detector

#: office: the simulated suite's held-out office (arcloud.accuracy.sim); paths: a real sequence's frames along another
#: camera path (arcloud.accuracy.sevenscenes), both reported apart and tuned on by nobody.
SPLITS = ("tune", "report", "office", "paths")
#: The users of a distributed run (K), in every suite.
USERS = 10
#: Figures of a run that ``summarise`` reports (mean and worst); higher is better for all of them.
FIGURES = (
    "map25",
    "map50",
    "served_map25",
    "served_map50",
    "served_precision25",
    "served_recall25",
    "served_precision50",
    "served_recall50",
)


Score = TypeVar("Score")


def case_runs(
    frames: Sequence[Frame],
    detector: Detector,
    params: Params,
    score: Callable[[int, int, list[MapObject]], Score],
    *,
    name: str,
    runs: int,
    workers: int,
    seed: int,
) -> tuple[Score, list[Score]]:
    """A case's centralized map (one user) and its ``runs`` maps of ``USERS`` users (``run_map`` seeded
    ``seed + run``, each map ``<name>-<users>-<run>`` in an embedded store), each scored by ``score(users, run,
    objects)``: (the centralized score, the distributed ones)."""
    from arcloud.stores.memory import MemoryStore

    def build(users: int, run: int) -> Score:
        map_id = f"{name}-{users}-{run}"
        objects = run_map(
            frames, detector, params, new_store=MemoryStore, users=users, seed=seed + run, workers=workers, map_id=map_id
        )
        return score(users, run, objects)

    return build(1, 0), [build(USERS, run) for run in range(runs)]


def score_run(objects: Sequence[MapObject], ground_truth: Sequence[LabelledBox], *, scene: str = "scene") -> dict[str, Any]:
    """The figures of one run (see the module docstring) as a flat JSON-friendly dict."""
    gt = {scene: list(ground_truth)}
    every = object_boxes(objects)
    served = object_boxes([o for o in objects if o.confirmed])
    all_result = evaluate({scene: every}, gt)
    served_result = evaluate({scene: served}, gt)
    pr25 = precision_recall({scene: served}, gt, iou_threshold=0.25)
    pr50 = precision_recall({scene: served}, gt, iou_threshold=0.5)
    return {
        "map25": _finite(all_result.map_at(0.25)),
        "map50": _finite(all_result.map_at(0.5)),
        "served_map25": _finite(served_result.map_at(0.25)),
        "served_map50": _finite(served_result.map_at(0.5)),
        "served_precision25": pr25.precision,
        "served_recall25": _finite(pr25.recall),
        "served_precision50": pr50.precision,
        "served_recall50": _finite(pr50.recall),
        "n_objects": len(every),
        "n_served": len(served),
        "n_gt": len(ground_truth),
        "ap25_per_class": all_result.at(0.25).ap,
        "ap50_per_class": all_result.at(0.5).ap,
    }


def case_record(
    case: str,
    split: str,
    centralized: Mapping[str, Any],
    distributed: Sequence[Mapping[str, Any]] = (),
    *,
    users: int = 10,
    **extra: Any,
) -> dict[str, Any]:
    """One case: its centralized run's figures, its distributed runs' (K = ``users``), their mean, and
    ``extra`` facts (frames, seeds, walk style...)."""
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
    record: dict[str, Any] = {"case": case, "split": split, "centralized": dict(centralized), **extra}
    if distributed:
        record["distributed"] = {"users": users, "runs": [dict(r) for r in distributed], "mean": _mean_runs(distributed)}
    return record


def summarise(cases: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per split: the number of cases and, for the centralized runs and the distributed means, the mean
    and the worst case (with its name) of every figure in ``FIGURES``; ``gap`` is the largest drop of
    a case's distributed mean below its centralized run."""
    out: dict[str, Any] = {}
    for split in SPLITS:
        chosen = [c for c in cases if c["split"] == split]
        if not chosen:
            continue
        entry: dict[str, Any] = {"cases": len(chosen)}
        for approach in ("centralized", "distributed"):
            rows = [
                (c["case"], c["centralized"] if approach == "centralized" else c.get("distributed", {}).get("mean"))
                for c in chosen
            ]
            rows = [(name, r) for name, r in rows if r]
            if not rows:
                continue
            entry[approach] = {figure: _mean_and_worst(rows, figure) for figure in FIGURES}
        gaps = [(c["case"], c["centralized"]["map25"] - c["distributed"]["mean"]["map25"]) for c in chosen if "distributed" in c]
        if gaps:
            name, worst = max(gaps, key=lambda item: item[1])
            entry["gap_map25"] = {"mean": float(np.mean([g for _, g in gaps])), "worst": float(worst), "worst_case": name}
        out[split] = entry
    return out


def _mean_runs(runs: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    keys = [k for k, v in runs[0].items() if isinstance(v, (int, float))]
    return {k: float(np.mean([r[k] for r in runs])) for k in keys}


def _mean_and_worst(rows: Sequence[tuple[str, Mapping[str, Any]]], figure: str) -> dict[str, Any]:
    values = [(name, float(r[figure])) for name, r in rows if r.get(figure) is not None]
    if not values:
        return {"mean": None, "worst": None, "worst_case": None}
    name, worst = min(values, key=lambda item: item[1])
    return {"mean": float(np.mean([v for _, v in values])), "worst": worst, "worst_case": name}


def _finite(value: float) -> float | None:
    return None if math.isnan(value) else float(value)
