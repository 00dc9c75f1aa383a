"""The 3D detection mAP against hand-computed cases and a plain-loop transcription of the reference."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from arcloud.core.types import LabelledBox
from arcloud.errors import InvalidInput
from arcloud.eval.metrics import average_precision, evaluate, iou_aabb, iou_matrix


def box(label: str, lo, hi, score: float = 1.0) -> LabelledBox:
    return LabelledBox(label, np.array(lo, float), np.array(hi, float), score)


def unit(label: str, x: float = 0.0, score: float = 1.0) -> LabelledBox:
    """A unit cube with its min corner at (x, 0, 0)."""
    return box(label, (x, 0, 0), (x + 1, 1, 1), score)


# IoU exactly 1/4 in floating point: 5 x 1 x 1 boxes offset by 3 along x (intersection 2, union 8).
QUARTER_A = ((0, 0, 0), (5, 1, 1))
QUARTER_B = ((3, 0, 0), (8, 1, 1))
# IoU exactly 1/2: a unit cube and its lower half.
HALF_A = ((0, 0, 0), (1, 1, 1))
HALF_B = ((0, 0, 0), (1, 1, 0.5))


# ---------------------------------------------------------------- IoU


def test_iou_of_hand_made_boxes():
    assert iou_aabb(*HALF_A, *HALF_A) == 1.0
    assert iou_aabb(*QUARTER_A, *QUARTER_B) == 0.25
    assert iou_aabb(*HALF_A, *HALF_B) == 0.5
    assert iou_aabb((0, 0, 0), (1, 1, 1), (0.5, 0, 0), (1.5, 1, 1)) == pytest.approx(1 / 3)
    assert iou_aabb((0, 0, 0), (1, 1, 1), (2, 0, 0), (3, 1, 1)) == 0.0
    assert iou_aabb((0, 0, 0), (1, 1, 1), (1, 0, 0), (2, 1, 1)) == 0.0  # touching faces
    assert iou_aabb((0, 0, 0), (0, 0, 0), (0, 0, 0), (0, 0, 0)) == 0.0  # degenerate, no NaN


def test_iou_matrix_matches_pairwise_and_is_symmetric():
    rng = np.random.default_rng(0)
    mins_a = rng.uniform(-2, 2, (7, 3))
    maxs_a = mins_a + rng.uniform(0.1, 2, (7, 3))
    mins_b = rng.uniform(-2, 2, (5, 3))
    maxs_b = mins_b + rng.uniform(0.1, 2, (5, 3))
    matrix = iou_matrix(mins_a, maxs_a, mins_b, maxs_b)
    assert matrix.shape == (7, 5)
    for i in range(7):
        for j in range(5):
            assert matrix[i, j] == pytest.approx(reference_iou(mins_a[i], maxs_a[i], mins_b[j], maxs_b[j]))
    np.testing.assert_allclose(iou_matrix(mins_b, maxs_b, mins_a, maxs_a), matrix.T)
    assert np.all((matrix >= 0) & (matrix <= 1)) and np.any(matrix > 0)
    assert iou_matrix(np.empty((0, 3)), np.empty((0, 3)), mins_b, maxs_b).shape == (0, 5)


def test_iou_matrix_rejects_wrong_shapes():
    with pytest.raises(InvalidInput, match=r"mins_a: expected shape \(N, 3\), got shape \(4,\)"):
        iou_matrix(np.zeros(4), np.zeros(4), np.zeros((1, 3)), np.zeros((1, 3)))


# ---------------------------------------------------------------- LabelledBox and AP


def test_box3d_normalises_and_validates():
    b = LabelledBox("chair", [0, 0, 0], (1, 2, 3), score=np.float32(0.5))
    assert b.min.dtype == np.float64 and not b.min.flags.writeable
    np.testing.assert_array_equal(b.size, (1, 2, 3))
    assert isinstance(b.score, float)
    with pytest.raises(InvalidInput, match="LabelledBox.max: expected max >= min"):
        LabelledBox("chair", (0, 0, 0), (1, -1, 1))
    with pytest.raises(InvalidInput, match=r"LabelledBox.min: expected shape \(3,\)"):
        LabelledBox("chair", (0, 0), (1, 1, 1))
    with pytest.raises(InvalidInput, match="LabelledBox.score: expected a finite number"):
        LabelledBox("chair", (0, 0, 0), (1, 1, 1), score=math.nan)


def test_average_precision_by_hand():
    assert average_precision([1.0], [1.0]) == 1.0
    assert average_precision([], []) == 0.0
    # FP then TP on one GT: envelope 0.5 over the whole recall range.
    assert average_precision([0.0, 1.0], [0.0, 0.5]) == 0.5
    # Precision envelope: the later, higher precision lifts the earlier dip.
    assert average_precision([0.5, 0.5, 1.0], [1.0, 0.5, 2 / 3]) == pytest.approx(0.5 + 0.5 * 2 / 3)
    # Recall that never reaches 1 leaves the rest of the area at 0.
    assert average_precision([0.25, 0.5], [1.0, 1.0]) == 0.5


# ---------------------------------------------------------------- evaluate, hand-computed


def test_perfect_predictions_give_ap_one():
    gt = {"s1": [unit("chair"), unit("table", 3)], "s2": [unit("chair", 6)]}
    pred = {"s1": [unit("chair", score=0.9), unit("table", 3, score=0.3)], "s2": [unit("chair", 6, score=0.8)]}
    result = evaluate(pred, gt, classes=("chair", "table"))
    for threshold in (0.25, 0.5):
        assert result.at(threshold).ap == {"chair": 1.0, "table": 1.0}
        assert result.at(threshold).recall == {"chair": 1.0, "table": 1.0}
        assert result.map_at(threshold) == 1.0
    assert result.n_gt == {"chair": 2, "table": 1} and result.n_predictions == {"chair": 2, "table": 1}


def test_iou_exactly_at_threshold_is_not_a_true_positive():
    gt = {"s": [box("chair", *QUARTER_A), box("table", *HALF_A)]}
    pred = {"s": [box("chair", *QUARTER_B), box("table", *HALF_B)]}
    result = evaluate(pred, gt, classes=("chair", "table"), iou_thresholds=(0.25, 0.5))
    assert result.at(0.25).ap == {"chair": 0.0, "table": 1.0}  # 1/4 is not > 0.25; 1/2 is
    assert result.at(0.5).ap == {"chair": 0.0, "table": 0.0}  # 1/2 is not > 0.5
    # Just below the threshold, the same boxes are true positives.
    below = evaluate(pred, gt, classes=("chair", "table"), iou_thresholds=(0.2499999,))
    assert below.at(0.2499999).ap == {"chair": 1.0, "table": 1.0}


def test_duplicate_on_a_matched_gt_is_a_false_positive():
    gt = {"s": [unit("chair", 0), unit("chair", 3)]}
    pred = {"s": [unit("chair", 0, 0.9), unit("chair", 0.1, 0.8), unit("chair", 3, 0.7)]}
    result = evaluate(pred, gt, classes=("chair",))
    # tp = 1, 0, 1: recall 0.5, 0.5, 1; precision 1, 1/2, 2/3 -> AP = 0.5 * 1 + 0.5 * 2/3.
    assert result.at(0.25).ap["chair"] == pytest.approx(5 / 6)
    np.testing.assert_allclose(result.at(0.25).curves["chair"][0], [0.5, 0.5, 1.0])
    np.testing.assert_allclose(result.at(0.25).curves["chair"][1], [1.0, 0.5, 2 / 3])
    # Without the duplicate, AP is 1.
    single = evaluate({"s": [pred["s"][0], pred["s"][2]]}, gt, classes=("chair",))
    assert single.at(0.25).ap["chair"] == 1.0


def test_duplicate_is_false_positive_even_when_another_gt_would_fit():
    # The prediction's best GT (IoU 1) is taken; its second-best (IoU 1/3 > 0.25) is free but unused.
    gt = {"s": [unit("chair", 0), unit("chair", 0.5)]}
    pred = {"s": [unit("chair", 0, 0.9), unit("chair", 0, 0.8)]}
    ap = evaluate(pred, gt, classes=("chair",)).at(0.25).ap["chair"]
    assert ap == 0.5  # tp = 1, 0; recall 0.5, 0.5; precision 1, 0.5


def test_class_without_predictions_has_ap_zero_and_lowers_the_mean():
    gt = {"s": [unit("chair"), unit("tv", 3)]}
    pred = {"s": [unit("chair", score=0.5)]}
    result = evaluate(pred, gt, classes=("chair", "tv"))
    assert result.at(0.25).ap == {"chair": 1.0, "tv": 0.0}
    assert result.at(0.25).recall == {"chair": 1.0, "tv": 0.0}
    assert result.map_at(0.25) == 0.5


def test_class_with_only_predictions_is_left_out_of_the_mean():
    gt = {"s": [unit("chair")]}
    pred = {"s": [unit("chair", score=0.5), unit("laptop", 3, score=0.99)]}
    result = evaluate(pred, gt)  # all five classes
    assert result.at(0.5).ap["laptop"] is None and result.at(0.5).recall["laptop"] is None
    assert result.at(0.5).ap["table"] is None  # neither GT nor predictions
    assert result.map_at(0.5) == 1.0
    assert result.n_predictions["laptop"] == 1


def test_ranking_a_high_scoring_false_positive_first_halves_ap():
    gt = {"s": [unit("chair")]}
    fp, tp = unit("chair", 5, score=0.9), unit("chair", score=0.8)
    assert evaluate({"s": [tp, fp]}, gt, classes=("chair",)).map_at(0.25) == 0.5  # order of input is irrelevant
    assert evaluate({"s": [unit("chair", 5, 0.7), tp]}, gt, classes=("chair",)).map_at(0.25) == 1.0


def test_equal_scores_keep_input_order():
    gt = {"s": [unit("chair")]}
    fp, tp = unit("chair", 5, score=0.8), unit("chair", score=0.8)
    assert evaluate({"s": [fp, tp]}, gt, classes=("chair",)).map_at(0.25) == 0.5
    assert evaluate({"s": [tp, fp]}, gt, classes=("chair",)).map_at(0.25) == 1.0


def test_a_prediction_cannot_match_gt_of_another_scene():
    gt = {"a": [unit("chair")], "b": []}
    wrong_scene = evaluate({"b": [unit("chair")]}, gt, classes=("chair",))
    assert wrong_scene.map_at(0.25) == 0.0
    right_scene = evaluate({"a": [unit("chair")]}, gt, classes=("chair",))
    assert right_scene.map_at(0.25) == 1.0
    # Pooling: scene a perfect (score 0.9), scene b has a GT and a missed prediction ranked between.
    gt2 = {"a": [unit("chair")], "b": [unit("chair")]}
    pred2 = {"a": [unit("chair", score=0.9)], "b": [unit("chair", 5, score=0.8), unit("chair", score=0.7)]}
    # tp = 1, 0, 1 over 2 GT: AP = 0.5 * 1 + 0.5 * 2/3.
    assert evaluate(pred2, gt2, classes=("chair",)).map_at(0.25) == pytest.approx(5 / 6)


def test_empty_inputs():
    nothing = evaluate({}, {})
    assert all(v is None for v in nothing.at(0.25).ap.values())
    assert math.isnan(nothing.map_at(0.25)) and nothing.to_dict()["map25"] is None
    only_gt = evaluate({}, {"s": [unit("couch")]})
    assert only_gt.map_at(0.5) == 0.0 and only_gt.at(0.5).ap["couch"] == 0.0
    only_pred = evaluate({"s": [unit("couch")]}, {"s": []})
    assert math.isnan(only_pred.map_at(0.5))


def test_to_dict_is_json_friendly():
    gt = {"s": [unit("chair"), box("tv", *QUARTER_A)]}
    pred = {"s": [unit("chair"), box("tv", *QUARTER_B), unit("laptop", 9)]}
    out = json.loads(json.dumps(evaluate(pred, gt).to_dict(), allow_nan=False))
    assert out["map25"] == 0.5 and out["map50"] == 0.5
    assert out["per_class"]["0.25"] == {"chair": 1.0, "table": None, "laptop": None, "couch": None, "tv": 0.0}
    assert set(out["per_class"]) == {"0.25", "0.5"}
    assert out["n_gt"]["tv"] == 1 and out["n_predictions"]["laptop"] == 1
    only_75 = evaluate(pred, gt, iou_thresholds=(0.75,)).to_dict()
    assert "map75" in only_75 and "map25" not in only_75


def test_labels_outside_the_classes_are_ignored():
    gt = {"s": [unit("chair"), unit("lamp", 3)]}
    pred = {"s": [unit("chair"), unit("lamp", 9)]}
    result = evaluate(pred, gt, classes=("chair",))
    assert result.at(0.25).ap == {"chair": 1.0} and result.n_gt == {"chair": 1}


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"iou_thresholds": (1.0,)}, r"iou_thresholds: expected values in \[0, 1\)"),
        ({"iou_thresholds": ()}, "iou_thresholds: expected at least one threshold"),
        ({"iou_thresholds": (0.5, 0.5)}, "iou_thresholds: expected distinct values"),
        ({"classes": ("chair", "chair")}, "classes: expected distinct"),
    ],
)
def test_evaluate_rejects_bad_options(kwargs, message):
    with pytest.raises(InvalidInput, match=message):
        evaluate({}, {}, **kwargs)


def test_evaluate_rejects_bad_boxes():
    with pytest.raises(InvalidInput, match=r"predictions\['s'\]\[0\]: expected a LabelledBox"):
        evaluate({"s": [((0, 0, 0), (1, 1, 1))]}, {})
    with pytest.raises(InvalidInput, match="ground_truth: expected a mapping"):
        evaluate({}, [unit("chair")])
    with pytest.raises(InvalidInput, match=r"iou_threshold: expected one of the evaluated thresholds \[0.25, 0.5\]"):
        evaluate({}, {}).at(0.7)


# ---------------------------------------------------------------- against the reference procedure


def reference_iou(a_min, a_max, b_min, b_max) -> float:
    inter = 1.0
    for k in range(3):
        inter *= max(0.0, min(a_max[k], b_max[k]) - max(a_min[k], b_min[k]))
    vol_a = float(np.prod(np.subtract(a_max, a_min)))
    vol_b = float(np.prod(np.subtract(b_max, b_min)))
    return inter / (vol_a + vol_b - inter)


def reference_ap(pred: dict, gt: dict, threshold: float) -> float:
    """The ScanNet procedure for one class, one prediction at a time, as the references loop."""
    n_gt = sum(len(v) for v in gt.values())
    matched = {scene: [False] * len(v) for scene, v in gt.items()}
    dets = [(scene, b) for scene, boxes in pred.items() for b in boxes]
    order = sorted(range(len(dets)), key=lambda i: -dets[i][1].score)  # sorted() is stable
    tp, fp = [], []
    for i in order:
        scene, b = dets[i]
        best, best_j = -np.inf, -1
        for j, g in enumerate(gt.get(scene, [])):
            iou = reference_iou(b.min, b.max, g.min, g.max)
            if iou > best:
                best, best_j = iou, j
        hit = best > threshold and not matched[scene][best_j]
        if hit:
            matched[scene][best_j] = True
        tp.append(float(hit))
        fp.append(float(not hit))
    tp_cum, fp_cum = np.cumsum(tp), np.cumsum(fp)
    rec = tp_cum / n_gt
    prec = tp_cum / np.maximum(tp_cum + fp_cum, np.finfo(np.float64).eps)
    mrec = np.concatenate(([0.0], rec, [1.0]))
    mpre = np.concatenate(([0.0], prec, [0.0]))
    for i in range(mpre.size - 1, 0, -1):
        mpre[i - 1] = max(mpre[i - 1], mpre[i])
    steps = np.where(mrec[1:] != mrec[:-1])[0]
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


@pytest.mark.parametrize("seed", range(5))
def test_matches_reference_procedure_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    classes = ("chair", "table", "tv")
    gt: dict[str, list[LabelledBox]] = {}
    pred: dict[str, list[LabelledBox]] = {}
    for s in range(4):
        scene = f"scene{s}"
        gt[scene], pred[scene] = [], []
        for _ in range(rng.integers(0, 8)):
            label = classes[rng.integers(len(classes))]
            lo = rng.uniform(0, 4, 3)
            g = LabelledBox(label, lo, lo + rng.uniform(0.3, 1.5, 3))
            gt[scene].append(g)
            for _ in range(rng.integers(0, 3)):  # noisy detections, sometimes duplicates
                jitter = rng.normal(0, 0.15, (2, 3))
                hi = np.maximum(g.max + jitter[1], g.min + jitter[0] + 0.05)
                score = round(float(rng.uniform()), 1)  # coarse scores: ties happen
                pred[scene].append(LabelledBox(label, g.min + jitter[0], hi, score))
        for _ in range(rng.integers(0, 4)):  # clutter
            lo = rng.uniform(0, 4, 3)
            label = classes[rng.integers(len(classes))]
            pred[scene].append(LabelledBox(label, lo, lo + rng.uniform(0.2, 1, 3), float(rng.uniform())))
    result = evaluate(pred, gt, classes=classes, iou_thresholds=(0.25, 0.5))
    for threshold in (0.25, 0.5):
        expected = {}
        for name in classes:
            g = {s: [b for b in v if b.label == name] for s, v in gt.items()}
            p = {s: [b for b in v if b.label == name] for s, v in pred.items()}
            if sum(len(v) for v in g.values()):
                expected[name] = reference_ap(p, g, threshold)
        for name in classes:
            if name in expected:
                assert result.at(threshold).ap[name] == pytest.approx(expected[name], abs=1e-12)
            else:
                assert result.at(threshold).ap[name] is None
        assert result.map_at(threshold) == pytest.approx(np.mean(list(expected.values())), abs=1e-12)


def test_precision_recall_matches_like_evaluate() -> None:
    from arcloud.eval.metrics import precision_recall

    gt = {"s": [LabelledBox("chair", [0, 0, 0], [1, 1, 1]), LabelledBox("table", [3, 0, 0], [5, 1, 1])]}
    preds = {
        "s": [
            LabelledBox("chair", [0, 0, 0], [1, 1, 1], 0.9),  # true positive
            LabelledBox("chair", [0.1, 0, 0], [1, 1, 1], 0.8),  # second on a matched box: false positive
            LabelledBox("table", [9, 9, 9], [10, 10, 10], 0.7),  # nowhere near: false positive
        ]
    }
    pr = precision_recall(preds, gt, iou_threshold=0.25)
    assert (pr.true_positives, pr.n_predictions, pr.n_gt) == (1, 3, 2)
    assert pr.precision == pytest.approx(1 / 3)
    assert pr.recall == pytest.approx(0.5)
    assert precision_recall({"s": []}, gt).precision == 1.0
    assert precision_recall({"s": []}, gt).recall == 0.0
