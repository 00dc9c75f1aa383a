"""Evaluating any recording: the layout is found from the files, folders may have any name, and ``eval
recording`` reports through the one path ``eval 7scenes`` takes (agreement, accuracy on all objects and
the served set, per class, pictures): on a TUM-layout copy of real 7-Scenes frames with the real model
against the 7-Scenes ground truth, and on a rendered ScanNet scene; ``eval scannet --gt-boxes`` on a scene
folder of any name."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
from datasets_builders import (
    ALIGNMENT,
    ROOM_PARTS,
    build_room_scene,
    build_seven_scenes,
    build_tum_from_seven_scenes,
    circle_walk,
    write_room_tum,
)

from arcloud.accuracy.cli import add_eval_commands
from arcloud.core.types import Frame, Intrinsics
from arcloud.datasets.recording import check_intrinsics, detect_layout, load_recording, register_colour
from arcloud.datasets.render_scannet import render_scannet
from arcloud.datasets.scannet import load_scannet_scene
from arcloud.errors import DatasetError, InvalidInput


def parser() -> argparse.ArgumentParser:
    root = argparse.ArgumentParser(prog="arcloud")
    add_eval_commands(root.add_subparsers(dest="command", required=True))
    return root


def test_the_layout_comes_from_the_files(tmp_path: Path) -> None:
    seven = build_seven_scenes(tmp_path / "any name", n_frames=2)
    assert detect_layout(seven) == "7scenes"
    assert detect_layout(build_seven_scenes(tmp_path / "scene", n_frames=2, sequences=2)) == "7scenes"
    (tmp_path / "tum").mkdir()
    for name in ("rgb.txt", "depth.txt"):
        (tmp_path / "tum" / name).write_text("")
    assert detect_layout(tmp_path / "tum") == "tum"
    (tmp_path / "tum" / "depth.txt").unlink()  # a new user's review: "got none of them" named no file
    with pytest.raises(DatasetError, match=r"tum: expected depth.txt beside rgb.txt \(TUM RGB-D layout\), got no such file"):
        detect_layout(tmp_path / "tum")
    (tmp_path / "tum" / "depth.txt").write_text("")
    (tmp_path / "my scan" / "pose").mkdir(parents=True)
    assert detect_layout(tmp_path / "my scan") == "scannet"
    with pytest.raises(
        DatasetError, match=r"expected a recording \(TUM: rgb.txt and depth.txt; 7-Scenes: frame-\*.pose.txt; ScanNet: pose/\)"
    ):
        detect_layout(tmp_path / "tum" / "..")
    with pytest.raises(DatasetError, match="--intrinsics, --depth-factor: not used by the 7scenes layout"):
        load_recording(seven, intrinsics=Intrinsics(1.0, 1.0, 1.0, 1.0), depth_factor=1000.0)
    with pytest.raises(DatasetError, match="--up: not used by the scannet layout"):
        load_recording(tmp_path / "my scan", up=(0.0, 0.0, 1.0))


@pytest.mark.shared
@pytest.mark.slow
def test_eval_recording_on_a_tum_recording_against_the_7scenes_ground_truth(
    shared: type, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seven = shared.path("data/7scenes-redkitchen/gt-boxes.json").parent
    model = shared.path("models/yolo11n-seg-fp32-640.onnx")
    root = build_tum_from_seven_scenes(seven, tmp_path / "my kitchen (TUM)", list(range(0, 1000, 60)))
    out = tmp_path / "out" / "tum.json"
    args = parser().parse_args(["eval", "recording", "--root", str(root), "--gt-boxes", str(seven / "gt-boxes.json"),
                                "--detector", f"onnx:{model}", "--users", "1,3", "--runs", "1", "--stride", "2",
                                "--out", str(out), "--no-progress", "--workers", "2"])  # fmt: skip
    assert args.handler(args) == 0
    results = json.loads(out.read_text())
    assert (results["dataset"], results["sequence"], results["frames"]) == ("tum", "my_kitchen__TUM_", 9)
    assert results["recording"]["dropped_frames"] == 1 and results["recording"]["depth_factor"] == 5000.0
    assert results["recording"]["colour_turn_deg"] == {"median": 0.0, "max": 0.0}  # no pose 8 ms after a depth image
    assert results["gravity"]["source"].endswith("gt-boxes.json (up_axis_world)")
    assert "gt-boxes.json aligned frame" in results["frame"]
    rows = results["accuracy"]
    assert [(r["approach"], r["users"], r["boxes"]) for r in rows] == [
        ("centralized", 1, "observed"), ("centralized", 1, "amodal"), ("distributed", 3, "observed"), ("distributed", 3, "amodal")
    ]  # fmt: skip
    for row in rows:
        assert all(math.isfinite(row[key]) for key in ("map25_mean", "map50_mean", "served_map25", "served_precision25"))
        assert row["n_gt"] == 9 and {k for k, v in row["ap25_per_class"].items() if v is not None} == {"chair", "table", "tv"}
    assert rows[0]["map25_mean"] > 0.0  # the frames, poses and ground truth line up: something matched
    assert results["agreement"][0]["users"] == 3 and all(Path(p).is_file() for p in results["pictures"])
    assert results["registration"]["frames"] == 17 and len(results["registration"]["move"]) == 4
    printed = capsys.readouterr().out
    assert "  depth factor   5000: 5000 by the depth" in printed and "  pose clock     +0.000 s: 0 s" in printed
    assert "  colour camera  focal x" in printed
    assert f"Accuracy against {seven / 'gt-boxes.json'} (observed boxes)" in printed
    assert f"AP per class against {seven / 'gt-boxes.json'} (amodal boxes), IoU 0.25 / 0.5" in printed
    assert f"wrote {out}" in printed


#: The ground truth file of the rendered scene: its aligned frame is the scene's turned 90 degrees about z
#: and moved; its world is the scan frame of the scene's poses.
SCAN_ALIGNED2GT = np.array([[0.0, -1.0, 0.0, 0.3], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def write_scene_gt(path: Path, visible: dict[str, list[int]] | None = None) -> Path:
    objects = []
    for label in ("chair", "table"):
        lo, hi = ROOM_PARTS[label]
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        moved = corners @ SCAN_ALIGNED2GT[:3, :3].T + SCAN_ALIGNED2GT[:3, 3]
        box = {"aabb_observed_min": moved.min(0).tolist(), "aabb_observed_max": moved.max(0).tolist()}
        objects.append({"id": label, "label": label, "visible_frames": (visible or {}).get(label, [0, 15]), **box,
                        "aabb_min": box["aabb_observed_min"], "aabb_max": box["aabb_observed_max"]})  # fmt: skip
    payload = {"gravity_aligned": {"world_to_aligned": (SCAN_ALIGNED2GT @ ALIGNMENT).tolist(), "objects": objects}}
    path.write_text(json.dumps(payload))
    return path


@pytest.fixture
def rendered_scene(tmp_path: Path) -> Path:
    """A rendered ScanNet-layout scene (2 users x 8 frames) in a folder named 'my room'."""
    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh"))
    render_scannet(scene, tmp_path / "data", users=2, frames_per_user=8, seed=0, width=160, height=120,
                   intrinsics=Intrinsics(120.0, 120.0, 79.5, 59.5), walk=circle_walk)  # fmt: skip
    (folder,) = [p for p in (tmp_path / "data").iterdir() if p.is_dir()]
    return folder.rename(folder.parent / "my room")


def test_eval_scannet_takes_a_scene_folder_of_any_name_and_a_ground_truth_file(rendered_scene: Path, tmp_path: Path) -> None:
    gt = write_scene_gt(tmp_path / "room-gt.json")
    out = tmp_path / "out" / "scannet.json"
    args = parser().parse_args(["eval", "scannet", "--root", str(rendered_scene), "--gt-boxes", str(gt), "--detector", "gt-masks",
                                "--users", "1,2", "--runs", "1", "--out", str(out), "--export", str(tmp_path / "exp"),
                                "--no-progress", "--workers", "2"])  # fmt: skip
    assert args.handler(args) == 0
    results = json.loads(out.read_text())
    assert results["table1"][0]["map25_mean"] == pytest.approx(1.0)
    assert results["ground_truth"] == {"file": str(gt), "objects": ["chair", "table"], "boxes": "observed"}
    (export,) = [json.loads(p.read_text()) for p in (tmp_path / "exp").glob("*_1_0.json")]
    assert export["frame"].startswith("room-gt.json aligned frame")
    np.testing.assert_allclose(export["world_from_export"], np.linalg.inv(SCAN_ALIGNED2GT @ ALIGNMENT), atol=1e-12)


def test_eval_recording_on_a_scannet_scene_scores_against_its_annotation(
    rendered_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # the folder as ROOT, the results where --out is by default: out/eval/<its name>.json
    args = parser().parse_args(["eval", "recording", str(rendered_scene), "--detector", f"gt-masks:{rendered_scene}",
                                "--users", "1,2", "--runs", "1", "--no-progress", "--workers", "2"])  # fmt: skip
    assert args.handler(args) == 0
    results = json.loads((tmp_path / "out" / "eval" / f"{rendered_scene.name}.json").read_text())
    assert results["dataset"] == "scannet" and results["ground_truth"]["box_kinds"] == ["observed"]
    assert [(r["users"], r["boxes"]) for r in results["accuracy"]] == [(1, "observed"), (2, "observed")]
    assert results["accuracy"][0]["map25_mean"] == pytest.approx(1.0)
    assert results["accuracy"][0]["ap25_per_class"]["chair"] == pytest.approx(1.0)
    assert "ScanNet axis-aligned frame" in results["frame"]
    printed = capsys.readouterr().out
    assert "(observed boxes)" in printed and "Agreement of distributed maps with the centralized one" in printed
    # one user, a few frames: no agreement to tell; the frames asked for
    args = parser().parse_args(["eval", "recording", "--root", str(rendered_scene), "--detector", f"gt-masks:{rendered_scene}",
                                "--users", "1", "--max-frames", "4", "--out", "few.json", "--no-progress"])  # fmt: skip
    assert args.handler(args) == 0
    assert json.loads((tmp_path / "few.json").read_text())["frames"] == 4 and "Agreement" not in capsys.readouterr().out
    with pytest.raises(InvalidInput, match="ROOT: expected the folder to evaluate, as ROOT or --root"):
        args = parser().parse_args(["eval", "recording", "--users", "1"])
        args.handler(args)


def test_fewer_frames_are_scored_against_the_objects_visible_in_them(
    rendered_scene: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A new user's review: ``eval recording --max-frames`` on the first 60 of 7-Scenes' frames scored against all 9
    objects, 3 of which those frames never see (recall at most 6/9). ``visible_frames`` counts by the frame numbers."""
    gt = write_scene_gt(tmp_path / "gt.json", {"chair": [0, 3], "table": [9, 15]})
    recording = load_recording(rendered_scene, gt_boxes=gt)
    assert recording.frame_numbers == tuple(range(16)) == tuple(int(n) for n in recording.frame_names)
    assert recording.scored_frames(recording.frame_names[:4]) == (0, 3)
    assert recording.scored_frames(recording.frame_names[::3]) is None  # 0 .. 15: the whole recording
    out = tmp_path / "few.json"
    args = parser().parse_args(["eval", "recording", str(rendered_scene), "--gt-boxes", str(gt), "--detector",
                                f"gt-masks:{rendered_scene}", "--users", "1", "--max-frames", "4", "--out", str(out),
                                "--no-progress"])  # fmt: skip
    assert args.handler(args) == 0
    results = json.loads(out.read_text())
    assert results["ground_truth"]["objects"] == ["chair"] and results["ground_truth"]["visible_within_frames"] == [0, 3]
    assert results["accuracy"][0]["n_gt"] == 1
    # a file that counts frames another way (timestamps, say): every object, said so
    odd = load_recording(rendered_scene, gt_boxes=write_scene_gt(tmp_path / "odd.json", {"table": [1000, 2000]}))
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.recording"):
        assert odd.scored_frames(odd.frame_names[:4]) is None
    assert "visible_frames of table lie outside this recording's frame numbers 0..15: every object is scored" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.recording"):  # all its frames: said all the same
        assert odd.scored_frames(odd.frame_names) is None
    assert "visible_frames of table lie outside" in caplog.text and "give --gt-boxes a file of the objects in it" in caplog.text


def test_a_recording_read_with_intrinsics_off_is_told_which_its_depth_agrees_with(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    made = Intrinsics(525.0, 525.0, 319.5, 239.5)
    root = write_room_tum(tmp_path / "my room", made, n_frames=12)
    (root / "intrinsics.txt").write_text("525 525 319.5 255.5\n")  # a camera calibrated 16 px off in cy
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.recording"):
        check = check_intrinsics(load_recording(root, estimate_up=False))
    assert check["intrinsics"] == [525.0, 525.0, 319.5, 255.5] and check["frames"] == 12 and check["pairs"] > 0
    fx, fy, cx, cy = check["agreeing"]
    assert fx == fy
    assert abs(fx / made.fx - 1) <= 0.01 and abs(cx - made.cx) <= 2 and abs(cy - made.cy) <= 2
    assert check["agreeing_disagreement_mm"] < 0.5 * check["disagreement_mm"]
    assert "the depth and poses agree better with" in caplog.text
    caplog.clear()
    (root / "intrinsics.txt").write_text("525 525 319.5 239.5\n")
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.recording"):
        right = check_intrinsics(load_recording(root, estimate_up=False))
    assert right["disagreement_mm"] < check["disagreement_mm"] and "agree better" not in caplog.text


def test_a_colour_camera_a_few_pixels_off_is_found_by_the_edges_and_moved(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    made = Intrinsics(525.0, 525.0, 319.5, 239.5)
    off = load_recording(
        write_room_tum(tmp_path / "off", made, 12, colour_shift_px=(4.0, -3.0)), intrinsics=made, estimate_up=False
    )
    with caplog.at_level(logging.WARNING, logger="arcloud.datasets.recording"):
        moved, found = register_colour(off.frame_names, off.load_frame, where=off.root)
    scale, du, dv, tx = found["move"]
    assert found["frames"] == 12 and found["strongest_move"] == found["move"]
    assert abs(scale - 1) <= 0.01 and abs(du - 4) <= 1 and abs(dv + 3) <= 1 and abs(tx) <= 0.01
    assert found["strongest_edge_strength"] > 1.1 * found["edge_strength"] and "moving it" in caplog.text
    name = off.frame_names[8]
    assert off.load_frame(name).registered
    assert moved(name).rgb_intrinsics == Intrinsics(525.0 * scale, 525.0 * scale, 319.5 + du, 239.5 + dv)
    # as made: nothing moves; told a move: that one
    as_made = load_recording(write_room_tum(tmp_path / "as made", made, 12), intrinsics=made, estimate_up=False)
    kept, found = register_colour(as_made.frame_names, as_made.load_frame)
    assert kept is as_made.load_frame and found["move"] == [1.0, 0.0, 0.0, 0.0]
    told, found = register_colour(as_made.frame_names, as_made.load_frame, (0.9, 1.0, 2.0, -0.035))
    assert found == {"move": [0.9, 1.0, 2.0, -0.035]}
    frame = told(name)
    assert frame.rgb_intrinsics == Intrinsics(472.5, 472.5, 320.5, 241.5)
    np.testing.assert_allclose(frame.depth2rgb[:3, 3], [-0.035, 0.0, 0.0])
    # further off than the search reaches: the edges meet best at its border, which is no peak, and nothing moves
    far = load_recording(
        write_room_tum(tmp_path / "far", made, 12, colour_shift_px=(30.0, 0.0)), intrinsics=made, estimate_up=False
    )
    kept, found = register_colour(far.frame_names, far.load_frame)
    assert kept is far.load_frame and found["strongest_move"][1] >= 20 and found["move"] == [1.0, 0.0, 0.0, 0.0]

    # frames without depth tell nothing: kept as they are
    def blind(n: str) -> Frame:
        return dataclasses.replace(as_made.load_frame(n), depth_m=np.zeros((480, 640), np.float32))

    kept, found = register_colour(as_made.frame_names, blind)
    assert kept is blind and found == {"frames": 12, "edge_strength": None, "move": [1.0, 0.0, 0.0, 0.0]}


@pytest.mark.shared
def test_a_real_kinect_recording_read_as_registered_with_its_clock_and_depth_off_is_put_right(
    shared: type, tmp_path: Path
) -> None:
    # 7-Scenes' real frames as a TUM recording: no colour camera (a Kinect v1's: focal x0.90 of the depth's, 3.5 cm
    # aside, gt-boxes.json's estimate), the trajectory's clock 20 ms ahead, the depth written 3 % long
    seven = shared.path("data/7scenes-redkitchen/gt-boxes.json").parent
    root = build_tum_from_seven_scenes(seven, tmp_path / "kitchen", list(range(0, 1000, 60)), trajectory_frames=list(range(1000)),
                                       pose_clock_s=0.02, depth_scale=1.03)  # fmt: skip
    recording = load_recording(root, estimate_up=False)
    assert recording.facts["pose_time_offset_s"] == pytest.approx(0.02)
    assert recording.facts["depth_factor"] == pytest.approx(5000 * 1.03, rel=0.012)
    _, found = register_colour(recording.frame_names, recording.load_frame)
    scale, du, dv, tx = found["move"]
    assert abs(scale - 0.9) <= 0.02 and abs(tx + 0.035) <= 0.01 and max(abs(du), abs(dv)) <= 6
