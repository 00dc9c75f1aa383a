"""The dataset commands: argument parsing, eval scannet end to end on a rendered tiny scene (results
format and exports in a declared frame), eval 7scenes on a tiny sequence with a replayed detector
(agreement, pictures; with hand-made ground truth: accuracy, re-scored from the exports by an
independent scorer)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from datasets_builders import ALIGNMENT, SCENE_ID, build_room_scene, build_seven_scenes, circle_walk

from arcloud.accuracy.cli import add_eval_commands, parse_scenes
from arcloud.core.types import Detection, Frame, Intrinsics
from arcloud.datasets.frames import LazyFrames
from arcloud.datasets.render_scannet import render_scannet
from arcloud.datasets.scannet import load_scannet_scene
from arcloud.errors import DatasetError

ROW_KEYS = {"approach", "users", "runs", "map25_mean", "map25_var", "map50_mean", "map50_var", "wall_s"}


def parser() -> argparse.ArgumentParser:
    root = argparse.ArgumentParser(prog="arcloud")
    add_eval_commands(root.add_subparsers(dest="command", required=True))
    return root


def assert_charts(paths: list[str], names: list[str]) -> None:
    """The charts are these PNGs, each a picture: hundreds of pixels a side, more than one colour."""
    import cv2

    assert sorted(Path(p).name for p in paths) == sorted(names)
    for path in paths:
        image = cv2.imread(path)
        assert image is not None and image.shape[0] >= 300 and image.shape[1] >= 400, path
        assert len(np.unique(image.reshape(-1, 3), axis=0)) > 10, f"{path}: nearly one colour"


def test_parsing() -> None:
    args = parser().parse_args(["eval", "scannet", "--root", "r", "--detector", "gt-masks", "--out", "o.json", "--scenes", "a,b"])
    assert args.users == (1, 10, 50, 100) and args.runs == 10 and args.scenes == ("a", "b") and args.stride == 1
    args = parser().parse_args(["eval", "7scenes", "--root", "r", "--detector", "onnx:m.onnx", "--out", "o.json"])
    assert args.users == (1, 10) and callable(args.handler)
    args = parser().parse_args(
        ["render-scannet", "--mesh-dir", "m", "--out", "o", "--users", "3", "--frames", "5", "--seed", "2"]
    )
    assert (args.users, args.frames, args.seed, args.width, args.height) == (3, 5, 2, 640, 480)
    args = parser().parse_args(["eval", "scannet", "--root", "r", "--detector", "gt-masks", "--out", "o", "--users", "1, 10"])
    assert args.users == (1, 10)
    base = ["eval", "scannet", "--root", "r", "--out", "o.json"]
    assert parser().parse_args(base).detector == "onnx"  # the model cache's default model, as `serve` runs it
    for bad in (base + ["--users", "0,10"], base + ["--runs", "0"], ["eval", "recording", "r", "--max-frames", "0"]):
        with pytest.raises(SystemExit):  # K = 0; no runs; no frames
            parser().parse_args(bad)


def test_parse_scenes_from_file(tmp_path: Path) -> None:
    listing = tmp_path / "scenes.txt"
    listing.write_text("scene0011_00\n# a comment\nscene0015_00\n")
    assert parse_scenes(f"@{listing}") == ("scene0011_00", "scene0015_00")


def test_lazy_frames_load_once_when_cached() -> None:
    loads: list[str] = []

    def load(name: str) -> str:
        loads.append(name)
        return name.upper()

    cached = LazyFrames(["a", "b"], load, cache=True)  # type: ignore[arg-type]  # strings stand in for frames
    assert list(cached) == ["A", "B"] and cached[1] == "B" and len(cached) == 2 and loads == ["a", "b"]
    uncached = LazyFrames(["a"], load, cache=False)  # type: ignore[arg-type]  # strings stand in for frames
    assert uncached[0] == uncached[0] == "A" and loads == ["a", "b", "a", "a"]


def test_eval_scannet_command(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh"))
    render_scannet(scene, tmp_path / "data", users=2, frames_per_user=8, seed=0, width=160, height=120,
                   intrinsics=Intrinsics(120.0, 120.0, 79.5, 59.5), walk=circle_walk)  # fmt: skip
    out = tmp_path / "results" / "r.json"
    argv = [
        "eval", "scannet", "--root", str(tmp_path / "data"), "--detector", "gt-masks", "--users", "1,2",
        "--runs", "2", "--out", str(out), "--export", str(tmp_path / "exp"), "--no-progress", "--workers", "2",
    ]  # fmt: skip
    args = parser().parse_args(argv)
    assert args.handler(args) == 0
    results = json.loads(out.read_text())
    assert [(r["approach"], r["users"], r["runs"]) for r in results["table1"]] == [("centralized", 1, 1), ("distributed", 2, 2)]
    assert all(set(r) == ROW_KEYS for r in results["table1"])
    assert results["table1"][0]["map25_mean"] == pytest.approx(1.0)
    assert results["scenes"] == [SCENE_ID] and results["frames"] == {SCENE_ID: 16}
    assert results["registration"][SCENE_ID]["move"] == [1.0, 0.0, 0.0, 0.0]  # rendered: colour and depth from one camera
    assert results["centralized"]["n_gt"]["chair"] == 1 and results["centralized"]["n_gt"]["table"] == 1
    curves = results["centralized"]["curves"]["0.25"]
    assert set(curves) == {"chair", "table"} and all(c["recall"][-1] == 1.0 for c in curves.values())
    assert_charts(results["charts"], ["r_ap_per_class.png", "r_pr_curves.png", "r_map_vs_users.png"])
    exported = sorted(p.name for p in (tmp_path / "exp").iterdir())
    assert exported == [f"{SCENE_ID}_1_0.json", f"{SCENE_ID}_2_0.json", f"{SCENE_ID}_2_1.json"]
    payload = json.loads((tmp_path / "exp" / f"{SCENE_ID}_1_0.json").read_text())
    assert set(payload) == {"scene", "users", "run", "frame", "world_from_export", "objects", "tentative"}
    assert payload["scene"] == SCENE_ID and "axis-aligned" in payload["frame"]
    boxed = payload["objects"] + payload["tentative"]
    assert {o["label"] for o in boxed} == {"chair", "table"}
    chair = next(o for o in boxed if o["label"] == "chair")
    assert set(chair) == {"label", "score", "aabb_min", "aabb_max"}
    np.testing.assert_allclose(chair["aabb_min"], [0.8, 0.8, 0.0], atol=0.1)
    np.testing.assert_allclose(chair["aabb_max"], [1.3, 1.3, 0.9], atol=0.1)
    # export coordinates (the aligned frame) -> the scan frame of ScanNet's poses and mesh
    np.testing.assert_allclose(payload["world_from_export"], np.linalg.inv(ALIGNMENT), atol=1e-12)
    assert results["axis_alignment"] == {SCENE_ID: f"{SCENE_ID}.txt axisAlignment"}
    # ground-truth masks without ScanNet's labels tsv would have no chair or table: refused, not scored as nothing
    tsv = next((tmp_path / "data").glob("*.tsv"))
    (tmp_path / "elsewhere").mkdir()
    tsv = tsv.rename(tmp_path / "elsewhere" / tsv.name)
    with pytest.raises(DatasetError, match="expected ScanNet's labels tsv .* or --labels-tsv"):
        args.handler(args)
    args = parser().parse_args([*argv, "--labels-tsv", str(tsv), "--users", "1"])
    assert args.handler(args) == 0 and json.loads(out.read_text())["table1"][0]["map25_mean"] == pytest.approx(1.0)


class BoxDetector:
    """Detects one 'table' wherever depth is closer than 1.4 m (the near block of the tiny sequence)."""

    def detect(self, frame: Frame) -> list[Detection]:
        mask = (frame.depth_m > 0) & (frame.depth_m < 1.4)
        return [Detection("table", 0.9, mask)] if mask.sum() > 50 else []


def test_eval_7scenes_agreement_and_pictures(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import cv2

    root = build_seven_scenes(tmp_path / "kitchen", n_frames=13, gravity=np.array([0.0, 0.0, -1.0]))
    for index in range(12):  # a near block in the middle of every picture
        depth = np.full((48, 64), 2500, np.uint16)
        depth[16:32, 24:40] = 1200
        cv2.imwrite(str(root / f"frame-{index:06d}.depth.png"), depth)
    import arcloud.accuracy.cli as cli

    monkeypatch.setattr(cli, "_make_detector", lambda spec: BoxDetector())
    out = tmp_path / "out" / "seven.json"
    args = parser().parse_args(["eval", "7scenes", "--root", str(root), "--detector", "onnx:unused", "--users", "1,3",
                                "--runs", "2", "--out", str(out), "--no-progress"])  # fmt: skip
    assert args.handler(args) == 0
    results = json.loads(out.read_text())
    assert [(r["approach"], r["users"], r["runs"]) for r in results["agreement"]] == [("distributed", 3, 2)]
    assert results["agreement"][0]["map25_mean"] == pytest.approx(1.0)
    assert results["agreement"][0]["ap25_per_class"] == {"chair": None, "table": 1.0, "laptop": None, "couch": None, "tv": None}
    assert results["reference_min_score"] == 0.0
    assert [o["label"] for o in results["centralized_objects"]] == ["table"] and results["frames"] == 12
    assert results["gravity_aligned"] is True
    names = sorted(Path(p).name for p in results["pictures"])
    assert names == ["seven_frame_000000.png", "seven_frame_000004.png", "seven_frame_000007.png", "seven_frame_000011.png",
                     "seven_topdown_users1.png", "seven_topdown_users3.png"]  # fmt: skip
    assert all(Path(p).is_file() for p in results["pictures"])


# ---------------------------------------------------------------- 7-Scenes with ground truth, re-scored


def _iou(a_min: np.ndarray, a_max: np.ndarray, b_min: np.ndarray, b_max: np.ndarray) -> float:
    inter = np.prod(np.clip(np.minimum(a_max, b_max) - np.maximum(a_min, b_min), 0.0, None))
    return float(inter / (np.prod(a_max - a_min) + np.prod(b_max - b_min) - inter))


def _matches(predictions: list[dict], truths: list[dict], threshold: float) -> np.ndarray:
    """1 for each prediction (by falling score) that takes a not yet taken ground truth of its class
    with the highest IoU, above ``threshold`` (VoteNet's eval_det rule); predictions sorted."""
    taken: set[int] = set()
    hits = []
    for p in sorted(predictions, key=lambda p: -p["score"]):
        ious = [_iou(p["min"], p["max"], g["min"], g["max"]) if g["label"] == p["label"] else -1.0 for g in truths]
        best = int(np.argmax(ious)) if ious else -1
        hit = best >= 0 and ious[best] > threshold and best not in taken
        taken |= {best} if hit else set()
        hits.append(1.0 if hit else 0.0)
    return np.array(hits)


def rescore_export(export: dict, gt_file: dict, threshold: float, *, gt_ids: list[str] | None = None) -> dict[str, float]:
    """The independent scorer: an export's boxes carried corner by corner through ``world_from_export``
    (to the pose frame) and the ground truth's ``world_to_aligned``, boxed again, and scored against the
    observed boxes of ``gt-boxes.json`` (those of ``gt_ids`` when given) as VoteNet's eval_det scores:
    mAP over the classes with ground truth (served and tentative objects, by score), and the served
    objects' precision and recall."""
    to_aligned = np.asarray(gt_file["gravity_aligned"]["world_to_aligned"]) @ np.asarray(export["world_from_export"])
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1

    def carried(o: dict) -> dict:
        corners = np.where(bits == 1, np.asarray(o["aabb_max"]), np.asarray(o["aabb_min"]))
        aligned = corners @ to_aligned[:3, :3].T + to_aligned[:3, 3]
        return {"label": o["label"], "score": o["score"], "min": aligned.min(axis=0), "max": aligned.max(axis=0)}

    truths = [
        {"label": o["label"], "min": np.asarray(o["aabb_observed_min"]), "max": np.asarray(o["aabb_observed_max"])}
        for o in gt_file["gravity_aligned"]["objects"] if gt_ids is None or o["id"] in gt_ids
    ]  # fmt: skip
    served = [carried(o) for o in export["objects"]]
    every = served + [carried(o) for o in export["tentative"]]
    aps = []
    for label in sorted({g["label"] for g in truths}):
        hits = _matches([p for p in every if p["label"] == label], [g for g in truths if g["label"] == label], threshold)
        recall = np.concatenate([[0.0], np.cumsum(hits) / sum(g["label"] == label for g in truths), [1.0]])
        precision = np.concatenate([[0.0], np.cumsum(hits) / np.arange(1, len(hits) + 1), [0.0]])
        for j in range(len(precision) - 2, -1, -1):
            precision[j] = max(precision[j], precision[j + 1])
        steps = np.flatnonzero(recall[1:] != recall[:-1])
        aps.append(float(np.sum((recall[steps + 1] - recall[steps]) * precision[steps + 1])))
    served_hits = sum(_matches([p for p in served if p["label"] == label], [g for g in truths if g["label"] == label], threshold).sum()
                      for label in {g["label"] for g in truths})  # fmt: skip
    return {
        "map": float(np.mean(aps)),
        "precision": served_hits / len(served) if served else 1.0,
        "recall": served_hits / len(truths),
    }


#: The tiny sequence's ground truth: its aligned frame is the pose frame turned so that up
#: (-y, the camera's image up) is +z, turned 30 degrees about it and moved.
YAW_RAD = np.radians(30.0)
TINY_FILE2ALIGNED = np.array([
    [np.cos(YAW_RAD), -np.sin(YAW_RAD), 0.0, 0.4],
    [np.sin(YAW_RAD), np.cos(YAW_RAD), 0.0, -0.2],
    [0.0, 0.0, 1.0, 1.0],
    [0.0, 0.0, 0.0, 1.0],
]) @ np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])  # fmt: skip
#: A board 1.2 m in front of the first camera (pose frame), seen by every frame.
BOARD_MIN_FILE, BOARD_MAX_FILE = np.array([-0.1, -0.1, 1.175]), np.array([0.3, 0.2, 1.225])


def write_gt_boxes(root: Path, file2aligned: np.ndarray, boxes_file: dict[str, tuple[str, np.ndarray, np.ndarray]]) -> None:
    """A gt-boxes.json whose objects (id -> label, min, max in the pose frame) are boxed in the aligned
    frame (the observed box; the amodal one 2 cm larger on every side)."""
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    objects = []
    for object_id, (label, lo, hi) in boxes_file.items():
        corners = np.where(bits == 1, hi, lo) @ file2aligned[:3, :3].T + file2aligned[:3, 3]
        lo_aligned, hi_aligned = corners.min(axis=0), corners.max(axis=0)
        objects.append({"id": object_id, "label": label, "visible_frames": [0, 11],
                        "aabb_observed_min": lo_aligned.tolist(), "aabb_observed_max": hi_aligned.tolist(),
                        "aabb_min": (lo_aligned - 0.02).tolist(), "aabb_max": (hi_aligned + 0.02).tolist()})  # fmt: skip
    payload = {"gravity_aligned": {"world_to_aligned": file2aligned.tolist(), "objects": objects}, "not_annotated": []}
    (root / "gt-boxes.json").write_text(json.dumps(payload))


class BoardDetector:
    """Detects one 'tv' wherever depth is closer than 1.4 m (the board of ``build_board_sequence``)."""

    def detect(self, frame: Frame) -> list[Detection]:
        mask = (frame.depth_m > 0) & (frame.depth_m < 1.4)
        return [Detection("tv", 0.9, mask)] if mask.sum() > 50 else []


def build_board_sequence(root: Path) -> Path:
    """12 frames (64x48) of a camera sliding 5 cm a frame along x, looking along +z with gravity along
    +y, at the board (depth 1.2 m) before a wall (2.5 m)."""
    import cv2

    build_seven_scenes(root, n_frames=13, gravity=np.array([0.0, 1.0, 0.0]))
    v, u = np.mgrid[0:48, 0:64]
    for index in range(12):
        x = (u - 32.0) / 58.5 * 1.2 + index * 0.05  # where each pixel's ray meets the board's plane
        y = (v - 24.0) / 58.5 * 1.2
        on_board = (x >= BOARD_MIN_FILE[0]) & (x <= BOARD_MAX_FILE[0]) & (y >= BOARD_MIN_FILE[1]) & (y <= BOARD_MAX_FILE[1])
        cv2.imwrite(str(root / f"frame-{index:06d}.depth.png"), np.where(on_board, 1200, 2500).astype(np.uint16))
    return root


def test_eval_7scenes_scores_against_ground_truth_in_its_frame(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import arcloud.accuracy.cli as cli

    root = build_board_sequence(tmp_path / "board")
    write_gt_boxes(root, TINY_FILE2ALIGNED, {"board": ("tv", BOARD_MIN_FILE, BOARD_MAX_FILE)})
    monkeypatch.setattr(cli, "_make_detector", lambda spec: BoardDetector())
    out = tmp_path / "out" / "board.json"
    args = parser().parse_args(["eval", "7scenes", "--root", str(root), "--detector", "onnx:unused", "--users", "1,3",
                                "--runs", "2", "--out", str(out), "--export", str(tmp_path / "exp"), "--no-progress"])  # fmt: skip
    assert args.handler(args) == 0
    results = json.loads(out.read_text())
    assert [(r["approach"], r["users"], r["runs"], r["boxes"]) for r in results["accuracy"]] == [
        ("centralized", 1, 1, "observed"), ("centralized", 1, 1, "amodal"),
        ("distributed", 3, 2, "observed"), ("distributed", 3, 2, "amodal"),
    ]  # fmt: skip
    assert results["ground_truth"]["objects"] == ["board"] and "gt-boxes.json aligned frame" in results["frame"]
    central = results["accuracy"][0]
    assert central["map25_mean"] == 1.0 and central["served_precision25"] == 1.0 and central["served_recall25"] == 1.0
    assert any(Path(p).name == "board_topdown_users1.png" for p in results["pictures"])
    assert_charts(results["charts"], ["board_ap_per_class.png", "board_map_vs_users.png"])

    gt_file = json.loads((root / "gt-boxes.json").read_text())
    for row in (r for r in results["accuracy"] if r["boxes"] == "observed"):
        runs = [json.loads((tmp_path / "exp" / f"board_{row['users']}_{run}.json").read_text()) for run in range(row["runs"])]
        for threshold, key in ((0.25, "map25_mean"), (0.5, "map50_mean")):
            assert np.mean([rescore_export(e, gt_file, threshold)["map"] for e in runs]) == pytest.approx(row[key], abs=0.01)
        rescored = [rescore_export(e, gt_file, 0.25) for e in runs]
        assert np.mean([r["precision"] for r in rescored]) == pytest.approx(row["served_precision25"], abs=0.01)
        assert np.mean([r["recall"] for r in rescored]) == pytest.approx(row["served_recall25"], abs=0.01)


def test_eval_7scenes_exports_declare_the_gravity_aligned_world_without_ground_truth(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import arcloud.accuracy.cli as cli
    from arcloud.datasets.sevenscenes import load_seven_scenes

    root = build_board_sequence(tmp_path / "board")
    monkeypatch.setattr(cli, "_make_detector", lambda spec: BoardDetector())
    out = tmp_path / "out" / "board.json"
    args = parser().parse_args(["eval", "7scenes", "--root", str(root), "--detector", "onnx:unused", "--users", "1",
                                "--out", str(out), "--export", str(tmp_path / "exp"), "--no-progress"])  # fmt: skip
    assert args.handler(args) == 0
    assert "accuracy" not in json.loads(out.read_text())
    export = json.loads((tmp_path / "exp" / "board_1_0.json").read_text())
    assert export["frame"].startswith("gravity-aligned world")
    world2file = np.asarray(export["world_from_export"])
    np.testing.assert_allclose(world2file, load_seven_scenes(root, align_gravity=True).world2file)
    # the board's box carried back to the pose frame is where the board is (its edges within a few
    # centimetres: 2 px of mask erosion are 4 cm there, boxes run centre to centre of 5 cm voxels)
    (board,) = export["objects"] + export["tentative"]
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    corners = np.where(bits == 1, board["aabb_max"], board["aabb_min"]) @ world2file[:3, :3].T + world2file[:3, 3]
    np.testing.assert_allclose(corners.min(axis=0), BOARD_MIN_FILE, atol=0.08)
    np.testing.assert_allclose(corners.max(axis=0), BOARD_MAX_FILE, atol=0.08)


def test_colour_camera_option_parses_or_says_what_it_expected() -> None:
    import argparse

    from arcloud.accuracy.cli import parse_colour_camera

    camera = parse_colour_camera("527,527,324,239,-0.035,0,0")
    assert camera.intrinsics.fx == 527.0 and camera.depth2rgb[0, 3] == -0.035
    assert parse_colour_camera("500,500,320,240").depth2rgb[0, 3] == 0.0
    for bad in ("527,527,324", "a,b,c,d", "-1,527,324,239", "1,2,3,4,5"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected fx,fy,cx,cy"):
            parse_colour_camera(bad)
