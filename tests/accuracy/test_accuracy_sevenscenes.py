"""The 7-Scenes suite on the real redkitchen sequence and model (skipped without them): the quick mode's
record, figures that fail when the map or its frame is wrong, and its exports re-scored independently."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_accuracy_scannet import independent_map

from arcloud.accuracy.sevenscenes import CASES, run_suite
from arcloud.errors import DatasetError


def test_cases_are_the_sequence_its_halves_and_the_sequence_backwards() -> None:
    assert [(c.name, c.split) for c in CASES] == [
        ("redkitchen_000-999", "report"), ("redkitchen_000-499", "tune"), ("redkitchen_500-999", "tune"),
        ("redkitchen_000-999_backwards", "paths"),
    ]  # fmt: skip


def test_without_the_sequence_the_suite_says_where_it_looked(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="7scenes-redkitchen.*no gt-boxes.json"):
        run_suite(quick=True, out_dir=tmp_path / "out", shared=tmp_path)


@pytest.mark.shared
@pytest.mark.slow
def test_quick_suite_on_the_real_sequence(shared: type, tmp_path: Path) -> None:
    root = shared.path("data/7scenes-redkitchen/gt-boxes.json").parent
    shared.path("models/yolo11n-seg-fp32-640.onnx")
    result = run_suite(quick=True, out_dir=tmp_path, shared=shared.root)
    _check_record(result, tmp_path)
    _check_figures(result)
    _check_exports_rescored_independently(result, tmp_path, root)


def _check_record(result: dict[str, Any], out_dir: Path) -> None:
    assert result["suite"] == "7scenes" and result["quick"] and result["stride"] == 10 and result["runs"] == 1
    assert "aligned frame" in result["frame"] and result["primary_boxes"] == "observed"
    assert set(result["summary"]) == set(result["summary_amodal"]) == {"tune", "report", "paths"}
    whole, first, second, backwards = result["cases"]
    assert [c["frames"] for c in result["cases"]] == [100, 50, 50, 100]
    assert backwards["backwards"] and not whole["backwards"] and backwards["gt_objects"] == whole["gt_objects"]
    assert all(c["distributed"]["users"] == 10 and len(c["distributed"]["runs"]) == 1 for c in result["cases"])
    # ground truth by visible frames: chairs E (frames 0-51) and F (369-409) are not in the second half
    assert len(whole["gt_objects"]) == whole["centralized"]["n_gt"] == 9 and first["centralized"]["n_gt"] == 9
    assert set(whole["gt_objects"]) - set(second["gt_objects"]) == {"chair_E", "chair_F"} and second["centralized"]["n_gt"] == 7
    assert whole["amodal"]["centralized"]["n_gt"] == 9 and "mean" in whole["amodal"]["distributed"]
    assert all(Path(p).is_file() for c in result["cases"] for p in c["pictures"])
    assert len(list((out_dir / "exports").glob("*.json"))) == 8


def _check_figures(result: dict[str, Any]) -> None:
    for case in result["cases"]:
        # the table is seen in almost every frame: every map boxes it where the ground truth has it
        for run in [case["centralized"], *case["distributed"]["runs"]]:
            assert run["ap25_per_class"]["table"] == 1.0, case["case"]
        assert case["centralized"]["ap25_per_class"]["chair"] > 0.0, case["case"]
    whole = result["cases"][0]
    assert whole["centralized"]["map25"] >= 0.3 and whole["distributed"]["mean"]["map25"] >= 0.3


def _check_exports_rescored_independently(result: dict[str, Any], out_dir: Path, root: Path) -> None:
    """Boxes carried corner by corner from the export frame to the pose frame (``world_from_export``)
    and on to the ground truth's (its ``world_to_aligned``), scored by another mAP: the suite's figures."""
    gt_file = json.loads((root / "gt-boxes.json").read_text())
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    for case in result["cases"]:
        for users, run, figures, amodal in [(1, 0, case["centralized"], case["amodal"]["centralized"])] + [
            (10, r, fig, case["amodal"]["distributed"]["runs"][r]) for r, fig in enumerate(case["distributed"]["runs"])
        ]:
            export = json.loads((out_dir / "exports" / f"{case['case']}_{users}_{run}.json").read_text())
            assert export["gt_objects"] == case["gt_objects"]
            to_aligned = np.asarray(gt_file["gravity_aligned"]["world_to_aligned"]) @ np.asarray(export["world_from_export"])
            predictions = []
            for o in export["objects"] + export["tentative"]:
                corners = np.where(bits == 1, o["aabb_max"], o["aabb_min"]) @ to_aligned[:3, :3].T + to_aligned[:3, 3]
                predictions.append(
                    {"label": o["label"], "score": o["score"], "aabb_min": corners.min(0), "aabb_max": corners.max(0)}
                )
            chosen = [o for o in gt_file["gravity_aligned"]["objects"] if o["id"] in case["gt_objects"]]
            for prefix, expected in (("aabb_observed_", figures), ("aabb_", amodal)):
                truths = [{"label": o["label"], "aabb_min": o[f"{prefix}min"], "aabb_max": o[f"{prefix}max"]} for o in chosen]
                assert independent_map(predictions, truths, 0.25) == pytest.approx(expected["map25"], abs=0.01)
                assert independent_map(predictions, truths, 0.5) == pytest.approx(expected["map50"], abs=0.01)
