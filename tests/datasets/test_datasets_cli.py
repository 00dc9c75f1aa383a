"""The dataset commands: argument parsing, eval scannet end to end on a rendered tiny scene (results
format and exports), eval 7scenes on a tiny sequence with a replayed detector (agreement, pictures)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from datasets_builders import SCENE_ID, build_room_scene, build_seven_scenes, circle_walk

from arcloud.core.types import Detection, Frame, Intrinsics
from arcloud.datasets.cli import LazyFrames, add_eval_commands, parse_scenes
from arcloud.datasets.render_scannet import render_scannet
from arcloud.datasets.scannet import load_scannet_scene

ROW_KEYS = {"approach", "users", "runs", "map25_mean", "map25_var", "map50_mean", "map50_var", "wall_s"}


def parser() -> argparse.ArgumentParser:
    root = argparse.ArgumentParser(prog="arcloud")
    add_eval_commands(root.add_subparsers(dest="command", required=True))
    return root


def test_parsing() -> None:
    args = parser().parse_args(["eval", "scannet", "--root", "r", "--detector", "gt-masks", "--out", "o.json", "--scenes", "a,b"])
    assert args.users == (1, 10, 50, 100) and args.runs == 10 and args.scenes == ("a", "b") and args.stride == 1
    args = parser().parse_args(["eval", "7scenes", "--root", "r", "--detector", "onnx:m.onnx", "--out", "o.json"])
    assert args.users == (1, 10) and callable(args.handler)
    args = parser().parse_args(["render-scannet", "--mesh-dir", "m", "--out", "o", "--users", "3", "--frames", "5", "--seed", "2"])
    assert (args.users, args.frames, args.seed, args.width, args.height) == (3, 5, 2, 640, 480)
    args = parser().parse_args(["eval", "scannet", "--root", "r", "--detector", "gt-masks", "--out", "o", "--users", "1, 10"])
    assert args.users == (1, 10)
    base = ["eval", "scannet", "--root", "r", "--out", "o.json"]
    for bad in ([], ["--detector", "x", "--users", "0,10"], ["--detector", "x", "--runs", "0"]):
        with pytest.raises(SystemExit):  # no --detector; K = 0; no runs
            parser().parse_args(base + bad)


def test_parse_scenes_from_file(tmp_path: Path) -> None:
    listing = tmp_path / "scenes.txt"
    listing.write_text("scene0011_00\n# a comment\nscene0015_00\n")
    assert parse_scenes(f"@{listing}") == ("scene0011_00", "scene0015_00")


def test_lazy_frames_load_once_when_cached() -> None:
    loads: list[str] = []

    def load(name: str) -> str:
        loads.append(name)
        return name.upper()

    cached = LazyFrames(["a", "b"], load, cache=True)  # type: ignore[arg-type]
    assert list(cached) == ["A", "B"] and cached[1] == "B" and len(cached) == 2 and loads == ["a", "b"]
    uncached = LazyFrames(["a"], load, cache=False)  # type: ignore[arg-type]
    assert uncached[0] == uncached[0] == "A" and loads == ["a", "b", "a", "a"]


def test_eval_scannet_command(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh"))
    render_scannet(scene, tmp_path / "data", users=2, frames_per_user=8, seed=0, width=160, height=120,
                   intrinsics=Intrinsics(120.0, 120.0, 79.5, 59.5), walk=circle_walk)  # fmt: skip
    out = tmp_path / "results" / "r.json"
    args = parser().parse_args([
        "eval", "scannet", "--root", str(tmp_path / "data"), "--detector", "gt-masks", "--users", "1,2",
        "--runs", "2", "--out", str(out), "--export", str(tmp_path / "exp"), "--no-progress", "--workers", "2",
    ])  # fmt: skip
    assert args.handler(args) == 0
    results = json.loads(out.read_text())
    assert [(r["approach"], r["users"], r["runs"]) for r in results["table1"]] == [("centralized", 1, 1), ("distributed", 2, 2)]
    assert all(set(r) == ROW_KEYS for r in results["table1"])
    assert results["table1"][0]["map25_mean"] == pytest.approx(1.0)
    assert results["scenes"] == [SCENE_ID] and results["frames"] == {SCENE_ID: 16}
    assert results["centralized"]["n_gt"]["chair"] == 1 and results["centralized"]["n_gt"]["table"] == 1
    exported = sorted(p.name for p in (tmp_path / "exp").iterdir())
    assert exported == [f"{SCENE_ID}_1_0.json", f"{SCENE_ID}_2_0.json", f"{SCENE_ID}_2_1.json"]
    payload = json.loads((tmp_path / "exp" / f"{SCENE_ID}_1_0.json").read_text())
    assert payload["scene"] == SCENE_ID and {o["label"] for o in payload["objects"]} == {"chair", "table"}
    chair = next(o for o in payload["objects"] if o["label"] == "chair")
    assert set(chair) == {"label", "score", "aabb_min", "aabb_max"}
    np.testing.assert_allclose(chair["aabb_min"], [0.8, 0.8, 0.0], atol=0.1)
    np.testing.assert_allclose(chair["aabb_max"], [1.3, 1.3, 0.9], atol=0.1)


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
    import arcloud.datasets.cli as cli

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
