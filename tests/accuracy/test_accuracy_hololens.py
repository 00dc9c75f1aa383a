"""The second real sequence kept in the repository (bench/data/hololens-office): it reads as a 7-Scenes layout
with its frames, camera and hand-checked boxes, its boxes lie where its depth saw them, its converter writes what
the reader reads, and the accuracy suite runs it as one report case of all its frames."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

from arcloud.accuracy.sevenscenes import CASES, SequenceCase
from arcloud.datasets.sevenscenes import load_seven_scenes

ROOT = Path(__file__).resolve().parents[2]
HOLOLENS = ROOT / "bench" / "data" / "hololens-office"


def test_the_sequence_reads_with_its_camera_and_ground_truth() -> None:
    sequence = load_seven_scenes(HOLOLENS, align_gravity=True)
    numbers = [sequence.frame_number(n) for n in sequence.frame_names]
    assert len(numbers) == 373 and (min(numbers), max(numbers)) == (3, 378)
    assert sorted(set(range(3, 379)) - set(numbers)) == [237, 272, 367]  # missing in the source too
    assert sequence.intrinsics.fx == pytest.approx(495.57, abs=0.01) and sequence.colour is None
    assert sequence.up_source.endswith("gt-boxes.json (up_axis_world)")  # up from the hand-checked file
    truth = sequence.ground_truth
    assert truth is not None
    labels = [o.label for o in truth.objects]
    assert (labels.count("table"), labels.count("couch"), labels.count("chair")) == (2, 1, 14)
    frame = sequence.load_frame(sequence.frame_names[100])
    assert frame.rgb.shape == (360, 540, 3) and frame.depth_m.shape == (360, 540)
    assert 0.3 < float(np.median(frame.depth_m[frame.depth_m > 0])) < 6.0  # metres: the PNGs hold millimetres


def test_the_tables_and_couch_boxes_hold_the_depth_the_frames_saw() -> None:
    """Each table's and the couch's observed box, carried into the frames' world, holds most of the depth points
    of a frame that sees it inside its footprint: the boxes and the poses are of one world."""
    sequence = load_seven_scenes(HOLOLENS, align_gravity=True)
    truth = sequence.ground_truth
    assert truth is not None
    world2gt = sequence.world2gt
    inside = dict.fromkeys(("table", "couch"), 0)
    for name in sequence.frame_names[::25]:
        frame = sequence.load_frame(name)
        v, u = np.nonzero(frame.depth_m[::4, ::4])
        z = frame.depth_m[::4, ::4][v, u]
        k = frame.intrinsics
        camera = np.stack([(u * 4 - k.cx) * z / k.fx, (v * 4 - k.cy) * z / k.fy, z, np.ones_like(z)])
        points = (world2gt @ frame.cam2world @ camera)[:3].T
        for box in truth.boxes("observed"):
            if box.label in inside:
                within = np.all((points >= box.min - 0.02) & (points <= box.max + 0.02), axis=1)
                inside[box.label] += int(within.sum())
    assert inside["table"] > 2000 and inside["couch"] > 500, inside


def test_the_converter_writes_what_the_reader_reads(tmp_path: Path) -> None:
    spec = importlib.util.spec_from_file_location("convert", HOLOLENS / "convert.py")
    assert spec is not None and spec.loader is not None
    convert = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(convert)
    source = tmp_path / "000"
    (source / "images").mkdir(parents=True)
    (source / "depth").mkdir()
    rng = np.random.default_rng(0)
    poses = []
    for i in (3, 4, 6):
        cv2.imwrite(str(source / "images" / f"{i:05d}.png"), rng.integers(0, 255, (36, 54, 3), dtype=np.uint8))
        cv2.imwrite(str(source / "depth" / f"{i:05d}.png"), np.full((36, 54), 1500 + i, np.uint16))
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * i, 0.0, 0.0]
        poses.append(pose.ravel())
    np.savetxt(source / "poses.txt", np.array(poses))
    np.savetxt(source / "K.txt", [[50.0, 0, 27.0], [0, 50.0, 18.0], [0, 0, 1]])
    assert convert.convert(source, tmp_path / "out") == 3
    sequence = load_seven_scenes(tmp_path / "out")
    assert [sequence.frame_number(n) for n in sequence.frame_names] == [3, 4, 6]
    frame = sequence.load_frame(sequence.frame_names[2])
    np.testing.assert_allclose(frame.depth_m, 1.506)
    np.testing.assert_allclose(frame.cam2world[:3, 3], [0.6, 0, 0])
    assert sequence.intrinsics.fx == 50.0 and sequence.intrinsics.cy == 18.0


def test_a_sequence_given_is_one_report_case_of_all_its_frames(tmp_path: Path) -> None:
    from arcloud.accuracy.sevenscenes import run_suite, whole_sequence_case
    from arcloud.errors import DatasetError

    sequence = load_seven_scenes(HOLOLENS, align_gravity=True)
    assert whole_sequence_case(sequence) == SequenceCase(3, 378, "report", "hololens-office")
    assert whole_sequence_case(sequence).name == "hololens-office_003-378"
    with pytest.raises(DatasetError, match="hololens-office.*no gt-boxes.json"):  # the root given is read, not redkitchen
        run_suite(quick=True, out_dir=tmp_path, shared=tmp_path, root=tmp_path / "hololens-office")
    assert CASES[0].name == "redkitchen_000-999"  # redkitchen keeps its own cases


@pytest.mark.shared
@pytest.mark.slow
def test_quick_suite_on_the_second_sequence(shared: type, tmp_path: Path) -> None:
    """The suite run as `make accuracy` runs it (``bench_accuracy``'s ``hololens``), quick: one report case of every
    10th frame, scored against its 17 objects."""
    from arcloud.accuracy.sevenscenes import run_suite

    shared.path("models/yolo11n-seg-fp32-640.onnx")
    result = run_suite(quick=True, out_dir=tmp_path, shared=shared.root, root=HOLOLENS)
    (case,) = result["cases"]
    assert (case["case"], case["split"], case["frames"]) == ("hololens-office_003-378", "report", 38)
    assert case["centralized"]["n_gt"] == 17 and set(result["summary"]) == {"report"}
    assert case["centralized"]["ap25_per_class"]["couch"] == 1.0, case["centralized"]  # seen whole in a few frames
