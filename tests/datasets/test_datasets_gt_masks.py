"""The ground-truth-mask detector replays instance-filt/label-filt as detections of our classes."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from datasets_builders import DEPTH_WH, TinyScanNet, build_scannet

from arcloud.datasets.gt_masks import GroundTruthMaskDetector
from arcloud.datasets.scannet import load_scannet_scene
from arcloud.errors import DatasetError, InvalidInput
from arcloud.ports import Detector


def test_replays_instances_of_our_classes(tiny_scannet: TinyScanNet) -> None:
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    detector = GroundTruthMaskDetector(scene, min_mask_px=4)
    assert isinstance(detector, Detector)
    frame = scene.load_frame("2")
    detections = detector.detect(frame)
    # chair and table; the floor is none of our classes and the desk speck is below min_mask_px
    assert [d.label for d in detections] == ["chair", "table"]
    assert all(d.score == 1.0 and d.mask.shape == (DEPTH_WH[1], DEPTH_WH[0]) and d.mask.dtype == bool for d in detections)
    chair, table = (d.mask for d in detections)
    expected_chair = np.zeros((24, 32), bool)
    expected_chair[:10, :12] = True  # the 20x24 block at colour size, halved
    np.testing.assert_array_equal(chair, expected_chair)
    assert table.sum() == 10 * 14 and table[23, 31] and not (chair & table).any()


def test_nyu40_label_images(tiny_scannet: TinyScanNet) -> None:
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    label_dir = tiny_scannet.scene_dir / "label-filt"
    instance = cv2.imread(str(tiny_scannet.scene_dir / "instance-filt" / "0.png"), cv2.IMREAD_UNCHANGED)
    # nyu40 ids: chair 5, table 7 -> swap them to check that the nyu40 table is the one used
    cv2.imwrite(str(label_dir / "0.png"), np.select([instance == 1, instance == 2], [7, 5], 2).astype(np.uint16))
    detections = GroundTruthMaskDetector(scene, label_ids="nyu40").detect(scene.load_frame("0"))
    assert [d.label for d in detections] == ["table", "chair"]


def test_without_label_images_classes_come_from_the_aggregation(tiny_scannet: TinyScanNet) -> None:
    for path in (tiny_scannet.scene_dir / "label-filt").iterdir():
        path.unlink()
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    detections = GroundTruthMaskDetector(scene, min_mask_px=1).detect(scene.load_frame("0"))
    assert [d.label for d in detections] == ["chair", "table", "table"]  # the desk speck counts now


def test_missing_2d_ground_truth(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    tiny = build_scannet(tmp_path)
    scene = load_scannet_scene(tiny.scene_dir)
    (tiny.scene_dir / "instance-filt" / "10.png").unlink()
    frame = scene.load_frame("10")
    with caplog.at_level(logging.WARNING):
        assert GroundTruthMaskDetector(scene).detect(frame) == []
    assert "no 2D ground truth for frame 10" in caplog.text
    with pytest.raises(DatasetError, match="10.png"):
        GroundTruthMaskDetector(scene, strict=True).detect(frame)
    with pytest.raises(InvalidInput, match="label_ids"):
        GroundTruthMaskDetector(scene, label_ids="coco")  # type: ignore[arg-type]
    (tmp_path / "b").mkdir()
    bare = build_scannet(tmp_path / "b", labels_2d=False)
    for path in (bare.scene_dir / "instance-filt", bare.scene_dir / "label-filt"):
        path.rmdir()
    with pytest.raises(DatasetError, match="instance-filt"):
        GroundTruthMaskDetector(load_scannet_scene(bare.scene_dir))


def test_detector_spec(tiny_scannet: TinyScanNet) -> None:
    from arcloud.detectors import make_detector

    detector = make_detector(f"gt-masks:{tiny_scannet.scene_dir}", min_mask_px=4)
    assert isinstance(detector, GroundTruthMaskDetector) and detector.min_mask_px == 4
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    assert [d.label for d in detector.detect(scene.load_frame("0"))] == ["chair", "table"]
    with pytest.raises(InvalidInput, match="SCENE_DIR"):
        make_detector("gt-masks")
