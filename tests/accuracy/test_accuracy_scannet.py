"""The ScanNet suite on the real scan (skipped without it): one small randomised render with mask faults,
scored against the v2 annotation centralized and with 10 users, its exports re-scored by an independent mAP."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from arcloud.accuracy.scannet import FULL_CASES, QUICK_CASES, TUNE_SEEDS, render_case, run_suite
from arcloud.datasets.scannet import load_axis_alignment
from arcloud.errors import DatasetError


def _iou(a_min: np.ndarray, a_max: np.ndarray, b_min: np.ndarray, b_max: np.ndarray) -> float:
    inter = np.prod(np.clip(np.minimum(a_max, b_max) - np.maximum(a_min, b_min), 0.0, None))
    return float(inter / (np.prod(a_max - a_min) + np.prod(b_max - b_min) - inter))


def independent_map(predictions: list[dict], ground_truth: list[dict], threshold: float) -> float:
    """mAP as VoteNet's eval_det computes it, written apart from arcloud.eval.metrics: per class,
    predictions by falling score; each matches the ground truth it overlaps most, a true positive when
    that IoU exceeds ``threshold`` and the ground truth is not taken yet; all-point interpolated AP;
    mean over the classes that have ground truth."""
    aps = []
    for label in sorted({g["label"] for g in ground_truth}):
        gts = [(np.array(g["aabb_min"]), np.array(g["aabb_max"])) for g in ground_truth if g["label"] == label]
        preds = sorted((p for p in predictions if p["label"] == label), key=lambda p: -p["score"])
        taken = [False] * len(gts)
        tp = np.zeros(len(preds))
        for i, p in enumerate(preds):
            ious = [_iou(np.array(p["aabb_min"]), np.array(p["aabb_max"]), lo, hi) for lo, hi in gts]
            best = int(np.argmax(ious))
            if ious[best] > threshold and not taken[best]:
                tp[i], taken[best] = 1.0, True
        recall = np.cumsum(tp) / len(gts)
        precision = np.cumsum(tp) / np.maximum(np.arange(1, len(preds) + 1), 1)
        mrec = np.concatenate([[0.0], recall, [1.0]])
        mpre = np.concatenate([[0.0], precision, [0.0]])
        for j in range(len(mpre) - 2, -1, -1):
            mpre[j] = max(mpre[j], mpre[j + 1])
        steps = np.flatnonzero(mrec[1:] != mrec[:-1])
        aps.append(float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1])))
    return float(np.mean(aps))


def test_cases_are_split_into_tune_and_report() -> None:
    assert {c.seed for c in FULL_CASES if c.split == "tune" and c.style == "random"} == set(TUNE_SEEDS)
    assert {c.eye_height_m for c in FULL_CASES if c.split == "report"} == {1.0, 1.5}  # low walks are reported too
    assert len({c.name for c in FULL_CASES}) == len(FULL_CASES) >= 5
    assert all(c.split == "report" for c in QUICK_CASES)


def test_without_the_scan_the_suite_says_where_it_looked(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="scannet-scene0000_00.*no mesh"):
        run_suite(quick=True, out_dir=tmp_path / "out", shared=tmp_path)


def test_renders_are_reused_only_with_the_same_settings_and_annotation(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import arcloud.datasets.render_scannet as render_module

    rendered: list[str] = []

    def record_render(source: SimpleNamespace, root: Path, **settings: object) -> Path:
        rendered.append(source.annotation)
        scene_dir = root / source.scene_id
        scene_dir.mkdir(parents=True, exist_ok=True)
        settings = {k: settings[k] for k in ("users", "frames_per_user", "seed", "style", "width", "height", "eye_height_m")}
        if settings["style"] == "random":
            settings["eye_height_m"] = None  # as render_scannet records it: the random style draws each user's
        (scene_dir / "render.json").write_text(json.dumps({**settings, "annotation": source.annotation}))
        return scene_dir

    monkeypatch.setattr(render_module, "render_scannet", record_render)
    case = QUICK_CASES[0]
    source = SimpleNamespace(scene_id="scene0000_00", annotation="v2")
    stale = tmp_path / case.name / source.scene_id / "render.json"
    stale.parent.mkdir(parents=True)
    stale.write_text(json.dumps(case.render_settings()))  # rendered before render.json named its annotation: v1
    assert render_case(source, case, tmp_path)[0] == stale.parent and rendered == ["v2"]
    assert render_case(source, case, tmp_path)[1] == 0.0 and rendered == ["v2"]  # reused
    render_case(SimpleNamespace(scene_id="scene0000_00", annotation="v1"), case, tmp_path)
    render_case(source, dataclasses.replace(case, seed=7), tmp_path / "other")
    assert rendered == ["v2", "v1", "v2"]
    low = dataclasses.replace(case, style="scan", eye_height_m=1.0)
    assert low.name.endswith("_eye1")
    render_case(source, low, tmp_path / "low")
    render_case(source, low, tmp_path / "low")  # reused
    render_case(source, dataclasses.replace(low, eye_height_m=1.1), tmp_path / "low")  # another eye, another render
    assert rendered == ["v2", "v1", "v2", "v2", "v2"]
    with pytest.raises(ValueError, match="random style draws"):
        dataclasses.replace(case, eye_height_m=1.0)


@pytest.mark.shared
@pytest.mark.slow
def test_quick_suite_on_the_real_scan(shared: type, tmp_path: Path) -> None:
    shared.path("data/scannet-scene0000_00/scene0000_00_vh_clean_2.ply")
    result = run_suite(quick=True, out_dir=tmp_path, shared=shared.root)
    (case,) = result["cases"]
    assert result["suite"] == "scannet" and case["split"] == "report" and result["report_seeds"] == [2]
    assert case["frames"] >= 190 and case["distributed"]["users"] == 10 and len(case["distributed"]["runs"]) == 2
    central, mean = case["centralized"], case["distributed"]["mean"]
    # the v2 annotation: six objects of our classes (four tables, one a desk, a couch, a tv)
    assert result["annotation"] == "v2" and case["annotation"] == "v2" and central["n_gt"] == 6
    assert central["map25"] >= 0.75 and mean["map25"] >= 0.75
    assert central["map50"] >= 0.45 and mean["map50"] >= 0.45
    assert central["served_recall25"] >= 0.6 and central["served_precision25"] >= 0.6
    # ten users map the room as well as one (better is fine: the couch comes out in two halves of about
    # the same score, and which ranks first moves its AP between 0.5 and 1)
    assert mean["map25"] >= central["map25"] - 0.05
    assert result["summary"]["report"]["cases"] == 1

    # the exports re-scored independently agree with the suite's figures: mAP of every object with a
    # box (served and tentative), and of the served ones alone
    exports = tmp_path / "exports"
    scan2aligned = load_axis_alignment(shared.path("data/scannet-scene0000_00/real_frames/frames.json"))
    gt = json.loads((exports / f"{case['case']}_gt.json").read_text())["objects"]
    runs = [("centralized", 1, 0, central)] + [("distributed", 10, r, run) for r, run in enumerate(case["distributed"]["runs"])]
    for _, users, run, figures in runs:
        export = json.loads((exports / f"{case['case']}_{users}_{run}.json").read_text())
        assert np.allclose(export["world_from_export"], np.linalg.inv(scan2aligned), atol=1e-6)
        every = export["objects"] + export["tentative"]
        assert len(export["objects"]) == figures["n_served"] and len(every) == figures["n_objects"]
        assert independent_map(every, gt, 0.25) == pytest.approx(figures["map25"], abs=0.01)
        assert independent_map(every, gt, 0.5) == pytest.approx(figures["map50"], abs=0.01)
        assert independent_map(export["objects"], gt, 0.25) == pytest.approx(figures["served_map25"], abs=0.01)

    # a second run reuses the render and gives the same centralized map (one distributed run: none is compared)
    again = run_suite(quick=True, out_dir=tmp_path, shared=shared.root, runs=1)
    (case_again,) = again["cases"]
    assert case_again["render_s"] == 0.0 and case_again["frames"] == case["frames"]
    assert case_again["centralized"]["map25"] == central["map25"] and case_again["centralized"]["map50"] == central["map50"]
