"""3D detection mAP on axis-aligned boxes, computed as the standard ScanNet evaluation does.

The procedure is the one of VoteNet's ``utils/eval_det.py`` (``eval_det_cls``, ``voc_ap`` with
``use_07_metric=False``) and mmdetection3d's ``indoor_eval``, written vectorised:

1. For one class, the predictions of every scene are pooled and sorted by score, highest first. The
   sort is stable: predictions with equal scores keep their input order (scenes in the order of the
   ``predictions`` mapping, boxes in the order of each scene's sequence). The references use an
   unstable ``argsort``, so their order among ties is unspecified.
2. Each prediction looks at the ground-truth boxes of the same scene and class and takes the one with
   the highest IoU (the first one on ties). It is a true positive when that IoU is strictly greater
   than the threshold and that ground-truth box is not matched yet; otherwise a false positive (a
   second prediction on a matched box is a false positive, even if another box would have fitted).
3. recall = cumsum(tp) / n_gt, precision = cumsum(tp) / (cumsum(tp) + cumsum(fp)); AP is the area
   under the precision envelope over the recall steps (VOC 2010+ all-point interpolation).
4. mAP is the mean over the classes that have ground truth. A class with ground truth but no
   prediction has AP 0 and lowers the mean; a class with predictions but no ground truth has no AP
   (``None``) and is left out of the mean (the references would give it NaN).

Boxes are ``arcloud.core.types.LabelledBox`` (axis-aligned, min and max corners, metres). For ScanNet,
both the ground truth and the predictions must be in the scene's axis-aligned frame.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from arcloud.core.checks import check_finite_number, describe
from arcloud.core.types import CLASSES, LabelledBox
from arcloud.errors import InvalidInput

logger = logging.getLogger(__name__)

DEFAULT_IOU_THRESHOLDS: tuple[float, ...] = (0.25, 0.5)


def _check_corners(field_name: str, value: object) -> np.ndarray:
    corners = np.asarray(value, dtype=np.float64)
    if corners.ndim != 2 or corners.shape[1] != 3:
        raise InvalidInput(field_name, "shape (N, 3)", f"shape {corners.shape}")
    return corners


def iou_matrix(mins_a: np.ndarray, maxs_a: np.ndarray, mins_b: np.ndarray, maxs_b: np.ndarray) -> np.ndarray:
    """IoU of every pair of axis-aligned boxes: (N, 3) corners of a and (M, 3) of b give (N, M).

    IoU = intersection volume / (volume a + volume b - intersection); 0 where the union is empty
    (two degenerate boxes)."""
    lo_a, hi_a = _check_corners("mins_a", mins_a), _check_corners("maxs_a", maxs_a)
    lo_b, hi_b = _check_corners("mins_b", mins_b), _check_corners("maxs_b", maxs_b)
    if lo_a.shape != hi_a.shape or lo_b.shape != hi_b.shape:
        raise InvalidInput("maxs", "the shape of the matching mins", f"{hi_a.shape} and {hi_b.shape}")
    overlap = np.minimum(hi_a[:, None], hi_b[None]) - np.maximum(lo_a[:, None], lo_b[None])  # (N, M, 3)
    intersection = np.prod(np.clip(overlap, 0.0, None), axis=-1)
    volume_a = np.prod(hi_a - lo_a, axis=-1)
    volume_b = np.prod(hi_b - lo_b, axis=-1)
    union = volume_a[:, None] + volume_b[None] - intersection
    return np.divide(intersection, union, out=np.zeros_like(intersection), where=union > 0)


def iou_aabb(a_min: object, a_max: object, b_min: object, b_max: object) -> float:
    """IoU of two axis-aligned boxes given by their (3,) corners."""
    corners = [np.asarray(c, dtype=np.float64).reshape(1, -1) for c in (a_min, a_max, b_min, b_max)]
    return float(iou_matrix(*corners)[0, 0])


def average_precision(recall: object, precision: object) -> float:
    """All-point interpolated AP (VOC 2010+, ``voc_ap(use_07_metric=False)``).

    recall, precision: (D,) per ranked detection. Sentinels (0, 0) and (1, 0) are added, precision is
    replaced by its envelope (the highest precision at any later rank), and the envelope is summed
    over the steps where recall changes. Empty input gives 0."""
    rec = np.asarray(recall, dtype=np.float64).ravel()
    prec = np.asarray(precision, dtype=np.float64).ravel()
    if rec.shape != prec.shape:
        raise InvalidInput("precision", f"the recall's shape {rec.shape}", f"shape {prec.shape}")
    mrec = np.concatenate(([0.0], rec, [1.0]))
    mpre = np.concatenate(([0.0], prec, [0.0]))
    envelope = np.maximum.accumulate(mpre[::-1])[::-1]
    steps = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * envelope[steps + 1]))


@dataclass(frozen=True, eq=False, slots=True)
class ThresholdResult:
    """The metrics at one IoU threshold.

    ap, recall: per class; ``None`` for a class without ground truth. ``recall`` is the final recall
    (all predictions kept). mean_ap, mean_recall: over the classes with ground truth; NaN when no class
    has any. curves: per class, (recall, precision) arrays (D,) along the ranked predictions."""

    iou_threshold: float
    ap: dict[str, float | None]
    recall: dict[str, float | None]
    mean_ap: float
    mean_recall: float
    curves: dict[str, tuple[np.ndarray, np.ndarray]] = field(repr=False)


@dataclass(frozen=True, eq=False, slots=True)
class EvalResult:
    """The result of ``evaluate``: one ``ThresholdResult`` per IoU threshold, and the box counts."""

    classes: tuple[str, ...]
    n_gt: dict[str, int]
    n_predictions: dict[str, int]
    thresholds: tuple[ThresholdResult, ...]

    def at(self, iou_threshold: float) -> ThresholdResult:
        """The metrics at an evaluated IoU threshold."""
        for result in self.thresholds:
            if math.isclose(result.iou_threshold, iou_threshold, abs_tol=1e-12):
                return result
        evaluated = [r.iou_threshold for r in self.thresholds]
        raise InvalidInput("iou_threshold", f"one of the evaluated thresholds {evaluated}", iou_threshold)

    def map_at(self, iou_threshold: float) -> float:
        """mAP at an evaluated IoU threshold (NaN when no class has ground truth)."""
        return self.at(iou_threshold).mean_ap

    def to_dict(self) -> dict[str, object]:
        """JSON-friendly: ``map25``/``map50`` (one ``mapNN`` per threshold), and per threshold (keyed
        "0.25", "0.5") the per-class AP and recall; NaN becomes None."""
        out: dict[str, object] = {}
        for result in self.thresholds:
            out[_map_key(result.iou_threshold)] = _json_float(result.mean_ap)
        out["per_class"] = {_threshold_key(r.iou_threshold): dict(r.ap) for r in self.thresholds}
        out["recall"] = {_threshold_key(r.iou_threshold): dict(r.recall) for r in self.thresholds}
        out["mean_recall"] = {_threshold_key(r.iou_threshold): _json_float(r.mean_recall) for r in self.thresholds}
        out["n_gt"] = dict(self.n_gt)
        out["n_predictions"] = dict(self.n_predictions)
        return out

    def curves_dict(self) -> dict[str, dict[str, dict[str, list[float]]]]:
        """JSON-friendly precision-recall curves: per threshold (keyed as ``to_dict``'s), each class with ground
        truth's ``{"recall": [...], "precision": [...]}`` along the ranked predictions (rounded to 4 places)."""
        return {
            _threshold_key(r.iou_threshold): {
                name: {"recall": np.round(rec, 4).tolist(), "precision": np.round(prec, 4).tolist()}
                for name, (rec, prec) in r.curves.items()
                if r.ap.get(name) is not None
            }
            for r in self.thresholds
        }


def _threshold_key(iou_threshold: float) -> str:
    return f"{iou_threshold:g}"


def _map_key(iou_threshold: float) -> str:
    return f"map{round(iou_threshold * 100):02d}"


def _json_float(value: float) -> float | None:
    return None if math.isnan(value) else value


def evaluate(
    predictions: Mapping[str, Sequence[LabelledBox]],
    ground_truth: Mapping[str, Sequence[LabelledBox]],
    *,
    iou_thresholds: Iterable[float] = DEFAULT_IOU_THRESHOLDS,
    classes: Sequence[str] = CLASSES,
) -> EvalResult:
    """mAP of ``predictions`` against ``ground_truth`` at each IoU threshold (see the module docstring).

    Both map a scene name to that scene's boxes; a scene may be missing from either side (its boxes on
    the other side are then all unmatched). Boxes whose label is not in ``classes`` are ignored."""
    thresholds = _check_thresholds(iou_thresholds)
    class_names = _check_classes(classes)
    pred_by_class = _boxes_by_class("predictions", predictions, class_names)
    gt_by_class = _boxes_by_class("ground_truth", ground_truth, class_names)
    scene_index = {name: i for i, name in enumerate(dict.fromkeys([*predictions, *ground_truth]))}

    ap: list[dict[str, float | None]] = [{} for _ in thresholds]
    recall: list[dict[str, float | None]] = [{} for _ in thresholds]
    curves: list[dict[str, tuple[np.ndarray, np.ndarray]]] = [{} for _ in thresholds]
    n_gt: dict[str, int] = {}
    n_pred: dict[str, int] = {}
    for name in class_names:
        preds = _stack(pred_by_class[name], scene_index)
        gts = _stack(gt_by_class[name], scene_index)
        n_gt[name] = gts.scene.size
        n_pred[name] = preds.scene.size
        tp = _true_positives(preds, gts, thresholds)  # (T, D), ranked
        for t in range(len(thresholds)):
            tp_cum = np.cumsum(tp[t], dtype=np.float64)
            fp_cum = np.cumsum(~tp[t], dtype=np.float64)
            precision = tp_cum / np.maximum(tp_cum + fp_cum, np.finfo(np.float64).eps)
            if n_gt[name] == 0:
                ap[t][name] = recall[t][name] = None
                curves[t][name] = (np.full(tp_cum.shape, np.nan), precision)
                continue
            rec = tp_cum / n_gt[name]
            ap[t][name] = average_precision(rec, precision)
            recall[t][name] = float(rec[-1]) if rec.size else 0.0
            curves[t][name] = (rec, precision)

    results = []
    for t, threshold in enumerate(thresholds):
        scored = [name for name in class_names if ap[t][name] is not None]
        mean_ap = float(np.mean([ap[t][n] for n in scored])) if scored else math.nan
        mean_recall = float(np.mean([recall[t][n] for n in scored])) if scored else math.nan
        results.append(ThresholdResult(threshold, ap[t], recall[t], mean_ap, mean_recall, curves[t]))
        logger.debug("mAP@%g = %.4f over %d classes with ground truth", threshold, mean_ap, len(scored))
    return EvalResult(class_names, n_gt, n_pred, tuple(results))


def variance(values: Iterable[float]) -> float:
    """The population variance (ddof 0) of mAPs over runs, rounded to 1e-12: equal runs give 0, not the
    1e-32 of float noise."""
    return round(float(np.var(np.asarray(list(values), dtype=np.float64))), 12)


@dataclass(frozen=True, slots=True)
class PrecisionRecall:
    """How well a set of boxes (what a client is served, scores ignored but for the matching order)
    matches the ground truth at one IoU threshold, pooled over scenes and classes: ``true_positives``
    of ``n_predictions`` predictions and ``n_gt`` ground-truth boxes. Precision is 1 and recall 0 for
    an empty prediction set; recall is NaN without ground truth."""

    iou_threshold: float
    true_positives: int
    n_predictions: int
    n_gt: int

    @property
    def precision(self) -> float:
        return self.true_positives / self.n_predictions if self.n_predictions else 1.0

    @property
    def recall(self) -> float:
        return self.true_positives / self.n_gt if self.n_gt else math.nan

    def to_dict(self) -> dict[str, object]:
        return {
            "iou_threshold": self.iou_threshold, "precision": self.precision, "recall": _json_float(self.recall),
            "true_positives": self.true_positives, "n_predictions": self.n_predictions, "n_gt": self.n_gt,
        }  # fmt: skip


def precision_recall(
    predictions: Mapping[str, Sequence[LabelledBox]],
    ground_truth: Mapping[str, Sequence[LabelledBox]],
    *,
    iou_threshold: float = 0.25,
    classes: Sequence[str] = CLASSES,
) -> PrecisionRecall:
    """Precision and recall of a prediction set, matched exactly as ``evaluate`` matches (by falling
    score, each ground-truth box to one prediction of its class, IoU strictly above the threshold)."""
    (threshold,) = _check_thresholds((iou_threshold,))
    class_names = _check_classes(classes)
    pred_by_class = _boxes_by_class("predictions", predictions, class_names)
    gt_by_class = _boxes_by_class("ground_truth", ground_truth, class_names)
    scene_index = {name: i for i, name in enumerate(dict.fromkeys([*predictions, *ground_truth]))}
    tp = n_pred = n_gt = 0
    for name in class_names:
        preds = _stack(pred_by_class[name], scene_index)
        gts = _stack(gt_by_class[name], scene_index)
        tp += int(_true_positives(preds, gts, (threshold,)).sum())
        n_pred += preds.scene.size
        n_gt += gts.scene.size
    return PrecisionRecall(threshold, tp, n_pred, n_gt)


@dataclass(frozen=True, slots=True)
class _Stacked:
    """The boxes of one class, stacked: scene (K,) int, mins and maxs (K, 3), scores (K,)."""

    scene: np.ndarray
    mins: np.ndarray
    maxs: np.ndarray
    scores: np.ndarray


def _stack(boxes: list[tuple[str, LabelledBox]], scene_index: Mapping[str, int]) -> _Stacked:
    if not boxes:
        empty = np.empty((0, 3))
        return _Stacked(np.empty(0, np.int64), empty, empty, np.empty(0))
    return _Stacked(
        scene=np.array([scene_index[scene] for scene, _ in boxes], dtype=np.int64),
        mins=np.stack([box.min for _, box in boxes]),
        maxs=np.stack([box.max for _, box in boxes]),
        scores=np.array([box.score for _, box in boxes], dtype=np.float64),
    )


def _true_positives(preds: _Stacked, gts: _Stacked, thresholds: tuple[float, ...]) -> np.ndarray:
    """(T, D) bool: whether each prediction, ranked by score (stable, highest first), is a true positive
    at each threshold."""
    n = preds.scene.size
    best_iou = np.full(n, -np.inf)
    best_gt = np.full(n, -1, dtype=np.int64)
    for scene in np.unique(preds.scene):
        p = np.flatnonzero(preds.scene == scene)
        g = np.flatnonzero(gts.scene == scene)
        if g.size == 0:
            continue
        ious = iou_matrix(preds.mins[p], preds.maxs[p], gts.mins[g], gts.maxs[g])  # (P, G)
        column = ious.argmax(axis=1)  # the first of equal IoUs, as the references' strict '>'
        best_iou[p] = ious[np.arange(p.size), column]
        best_gt[p] = g[column]

    ranked = np.argsort(-preds.scores, kind="stable")
    ranked_iou, ranked_gt = best_iou[ranked], best_gt[ranked]
    tp = np.zeros((len(thresholds), n), dtype=bool)
    for t, threshold in enumerate(thresholds):
        candidates = np.flatnonzero(ranked_iou > threshold)
        # Each ground-truth box goes to the first (highest-ranked) candidate that chose it.
        _, first = np.unique(ranked_gt[candidates], return_index=True)
        tp[t, candidates[first]] = True
    return tp


def _boxes_by_class(
    field_name: str, boxes_by_scene: Mapping[str, Sequence[LabelledBox]], classes: tuple[str, ...]
) -> dict[str, list[tuple[str, LabelledBox]]]:
    if not isinstance(boxes_by_scene, Mapping):
        raise InvalidInput(field_name, "a mapping of scene name to a sequence of LabelledBox", describe(boxes_by_scene))
    by_class: dict[str, list[tuple[str, LabelledBox]]] = {name: [] for name in classes}
    ignored: dict[str, int] = {}
    for scene, boxes in boxes_by_scene.items():
        if not isinstance(scene, str):
            raise InvalidInput(f"{field_name} key", "a scene name (str)", describe(scene))
        if isinstance(boxes, (str, bytes)) or not isinstance(boxes, Iterable):
            raise InvalidInput(f"{field_name}[{scene!r}]", "a sequence of LabelledBox", describe(boxes))
        for i, box in enumerate(boxes):
            if not isinstance(box, LabelledBox):
                raise InvalidInput(f"{field_name}[{scene!r}][{i}]", "a LabelledBox", describe(box))
            if box.label in by_class:
                by_class[box.label].append((scene, box))
            else:
                ignored[box.label] = ignored.get(box.label, 0) + 1
    if ignored:
        logger.info("%s: ignored boxes of classes not evaluated: %s", field_name, ignored)
    return by_class


def _check_thresholds(iou_thresholds: Iterable[float]) -> tuple[float, ...]:
    values = tuple(iou_thresholds) if isinstance(iou_thresholds, Iterable) else (iou_thresholds,)
    if not values:
        raise InvalidInput("iou_thresholds", "at least one threshold", "none")
    checked = tuple(check_finite_number("iou_thresholds", v) for v in values)
    if any(not 0.0 <= v < 1.0 for v in checked):
        raise InvalidInput("iou_thresholds", "values in [0, 1)", list(checked))
    if len(set(checked)) != len(checked):
        raise InvalidInput("iou_thresholds", "distinct values", list(checked))
    return checked


def _check_classes(classes: Sequence[str]) -> tuple[str, ...]:
    if isinstance(classes, str) or not isinstance(classes, Iterable):
        raise InvalidInput("classes", "a sequence of class names", describe(classes))
    names = tuple(classes)
    if not names or any(not isinstance(n, str) or not n for n in names) or len(set(names)) != len(names):
        raise InvalidInput("classes", "distinct non-empty class names", describe(names))
    return names


__all__ = [
    "DEFAULT_IOU_THRESHOLDS",
    "EvalResult",
    "PrecisionRecall",
    "ThresholdResult",
    "average_precision",
    "evaluate",
    "iou_aabb",
    "iou_matrix",
    "precision_recall",
    "variance",
]
