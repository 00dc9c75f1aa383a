"""The ground-truth-mask detector replays instance-filt/label-filt as detections of our classes, exactly
or with the faults of a model's masks."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from datasets_builders import DEPTH_WH, TinyScanNet, build_scannet

from arcloud.datasets.gt_masks import GroundTruthMaskDetector, gt_masks_options, register_gt_masks_detector
from arcloud.datasets.mask_faults import MaskFaults, faulty_detections, instance_rng, move_border, parse_mask_faults, split_mask
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


def test_label_ids_come_from_render_json(tiny_scannet: TinyScanNet) -> None:
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    assert GroundTruthMaskDetector(scene).label_ids == "scannet"  # a ScanNet export: no render.json
    record = tiny_scannet.scene_dir / "render.json"
    record.write_text(json.dumps({"frames": 3}))  # a render from before label_ids was recorded: v1, ScanNet ids
    assert GroundTruthMaskDetector(scene).label_ids == "scannet"
    record.write_text(json.dumps({"annotation": "v2", "label_ids": "nyu40"}))
    assert GroundTruthMaskDetector(scene).label_ids == "nyu40"
    # the tiny scene's label ids read as nyu40 ids: chair 2 and table 4 are floor and cabinet, none of ours
    assert GroundTruthMaskDetector(scene).detect(scene.load_frame("0")) == []
    assert GroundTruthMaskDetector(scene, label_ids="scannet").label_ids == "scannet"  # an explicit value wins
    record.write_text(json.dumps({"label_ids": "coco"}))
    with pytest.raises(DatasetError, match=r"render\.json: expected label_ids 'scannet' or 'nyu40', got 'coco'"):
        GroundTruthMaskDetector(scene)
    record.write_text("{")
    with pytest.raises(DatasetError, match=r"render\.json: expected a JSON render record"):
        GroundTruthMaskDetector(scene)


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
        GroundTruthMaskDetector(scene, label_ids="coco")  # type: ignore[arg-type]  # on purpose: a refused label set
    (tmp_path / "b").mkdir()
    bare = build_scannet(tmp_path / "b", labels_2d=False)
    for path in (bare.scene_dir / "instance-filt", bare.scene_dir / "label-filt"):
        path.rmdir()
    with pytest.raises(DatasetError, match="instance-filt"):
        GroundTruthMaskDetector(load_scannet_scene(bare.scene_dir))


def test_detector_spec(tiny_scannet: TinyScanNet) -> None:
    from arcloud.detectors import make_detector

    register_gt_masks_detector()  # explicit: importing the module registers nothing
    detector = make_detector(f"gt-masks:{tiny_scannet.scene_dir}", min_mask_px=4)
    assert isinstance(detector, GroundTruthMaskDetector) and detector.min_mask_px == 4
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    assert [d.label for d in detector.detect(scene.load_frame("0"))] == ["chair", "table"]
    with pytest.raises(InvalidInput, match="SCENE_DIR"):
        make_detector("gt-masks")


# Faults: what a model's masks look like, on hand-made masks


def _rectangle(
    shape: tuple[int, int] = (120, 160), top_left: tuple[int, int] = (30, 40), size: tuple[int, int] = (50, 70)
) -> np.ndarray:
    mask = np.zeros(shape, bool)
    mask[top_left[0] : top_left[0] + size[0], top_left[1] : top_left[1] + size[1]] = True
    return mask


def _border_distance_px(mask: np.ndarray) -> np.ndarray:
    """(H, W) distance of each pixel centre to the border of ``mask`` (half a pixel beyond the nearest centre across it)."""
    m = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.maximum(inside, outside) - 0.5


def test_no_faults_give_the_exact_mask() -> None:
    mask = _rectangle()
    (detection,) = faulty_detections("chair", mask, MaskFaults.none(), instance_rng(0, "0", 1))
    assert detection.label == "chair" and detection.score == 1.0
    np.testing.assert_array_equal(detection.mask, mask)
    np.testing.assert_array_equal(move_border(mask, 0.0, 0.0, 24.0, np.random.default_rng(0)), mask)


def test_borders_grow_and_shrink_by_whole_pixels() -> None:
    mask = _rectangle()
    rng = np.random.default_rng(0)
    grown = move_border(mask, 3.0, 0.0, 24.0, rng)
    # a 3 px ring around 50x70, its corners rounded (3 px of each 3x3 corner are more than 3.5 px away)
    assert grown.sum() == 56 * 76 - 4 * 3 and (grown & mask).sum() == mask.sum()
    shrunk = move_border(mask, -2.0, 0.0, 24.0, rng)
    assert shrunk.sum() == 46 * 66 and not (shrunk & ~mask).any()
    # a thin part (a 3 px chair leg) vanishes when the border moves in by 2 px
    leg = mask.copy()
    leg[80:110, 60:63] = True
    assert not move_border(leg, -2.0, 0.0, 24.0, rng)[85:110, 55:70].any()


def test_ragged_borders_stay_within_a_few_pixels() -> None:
    mask = _rectangle()
    ragged = move_border(mask, 0.0, 1.5, 24.0, np.random.default_rng(3))
    changed = ragged ^ mask
    distance = _border_distance_px(mask)[changed]
    assert changed.sum() > 40  # about a third of the 240 px border moved by a pixel or more
    assert distance.max() <= 6.0 and np.median(distance) <= 2.0


def test_default_faults_look_like_a_coco_model_on_vga_frames() -> None:
    """Over many draws on a large instance: borders 1-6 px off, about one miss in ten, rare splits,
    scores mostly 0.7-1.0; small instances are missed more."""
    mask = _rectangle((240, 320), (60, 80), (100, 140))
    faults = MaskFaults()
    drawn = [faulty_detections("table", mask, faults, instance_rng(0, str(frame), 1)) for frame in range(300)]
    missed = sum(not d for d in drawn) / len(drawn)
    splits = sum(len(d) == 2 for d in drawn) / len(drawn)
    assert 0.05 <= missed <= 0.16 and 0.01 <= splits <= 0.1
    distance = _border_distance_px(mask)
    errors = [float(np.mean(distance[np.logical_or.reduce([x.mask for x in d]) ^ mask])) for d in drawn if len(d) == 1]
    assert 1.0 <= np.median(errors) <= 4.0 and max(errors) <= 6.5
    scores = np.array([x.score for d in drawn for x in d[:1]])
    assert np.all((scores >= faults.min_score) & (scores <= 1.0)) and 0.8 <= np.median(scores) <= 0.95
    small = _rectangle((240, 320), (60, 80), (20, 25))  # 500 px
    small_missed = sum(not faulty_detections("tv", small, faults, instance_rng(0, str(f), 1)) for f in range(300)) / 300
    assert small_missed > missed + 0.2


def test_misses_and_splits() -> None:
    mask = _rectangle()
    assert faulty_detections("tv", mask, MaskFaults.none().replace(drop_rate=1.0), instance_rng(0, "0", 1)) == []
    only_small = MaskFaults.none().replace(small_area_px=5000, small_drop_rate=1.0)
    assert faulty_detections("tv", _rectangle(size=(10, 10)), only_small, instance_rng(0, "0", 1)) == []
    assert len(faulty_detections("tv", mask, only_small, instance_rng(0, "0", 1))) == 1  # 3,500 px: kept 30 % of the time
    split = MaskFaults.none().replace(split_rate=1.0, split_min_area_px=100, score_jitter=0.1)
    first, second = faulty_detections("couch", mask, split, instance_rng(0, "0", 1))
    assert first.label == second.label == "couch" and second.score < first.score
    assert not (first.mask & second.mask).any() and np.array_equal(first.mask | second.mask, mask)
    assert first.mask.sum() >= second.mask.sum() > 0
    small = _rectangle(size=(5, 5))
    assert len(faulty_detections("couch", small, split.replace(split_min_area_px=4000), instance_rng(0, "0", 1))) == 1


def test_split_mask_cuts_through_the_centre() -> None:
    mask = _rectangle()
    left, right = split_mask(mask, np.pi / 2)  # a vertical line
    assert left.sum() == right.sum() == 25 * 70 and not (left & right).any()
    top, bottom = split_mask(mask, 0.0)
    assert top.sum() == bottom.sum() == 50 * 35


def test_mask_faults_are_checked() -> None:
    with pytest.raises(InvalidInput, match="drop_rate"):
        MaskFaults(drop_rate=1.5)
    with pytest.raises(InvalidInput, match="grow_px"):
        MaskFaults(grow_px=-1.0)
    with pytest.raises(InvalidInput, match="faults"):
        parse_mask_faults("harsh")
    with pytest.raises(InvalidInput, match="MaskFaults.drop_rate"):
        parse_mask_faults("default", {"drop_rate": "often"})
    assert parse_mask_faults("default", {"drop_rate": "0.3", "small_area_px": "100"}) == MaskFaults(
        drop_rate=0.3, small_area_px=100
    )


def test_faulty_detector_does_not_depend_on_processing_order(tiny_scannet: TinyScanNet) -> None:
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    faults = MaskFaults(
        grow_px=2.0, shrink_px=2.0, ragged_px=0.5, ragged_period_px=4.0, drop_rate=0.3, small_area_px=0, score_jitter=0.2
    )
    names = list(scene.frame_names) * 4
    forward = [
        GroundTruthMaskDetector(scene, faults=faults, fault_seed=5, min_mask_px=4).detect(scene.load_frame(n)) for n in names
    ]
    backward_detector = GroundTruthMaskDetector(scene, faults=faults, fault_seed=5, min_mask_px=4)
    backward = [backward_detector.detect(scene.load_frame(n)) for n in reversed(names)][::-1]
    for a, b in zip(forward, backward):
        assert [(d.label, d.score) for d in a] == [(d.label, d.score) for d in b]
        assert all(np.array_equal(x.mask, y.mask) for x, y in zip(a, b))
    exact = GroundTruthMaskDetector(scene, min_mask_px=4)
    outputs = {
        seed: GroundTruthMaskDetector(scene, faults=faults, fault_seed=seed, min_mask_px=4).detect(scene.load_frame("2"))
        for seed in range(8)
    }
    # the faults change from seed to seed, and each faulty mask stays near its exact one
    assert len({tuple((d.label, d.score) for d in dets) for dets in outputs.values()}) > 1
    exact_masks = {d.label: d.mask for d in exact.detect(scene.load_frame("2"))}
    for dets in outputs.values():
        for d in dets:
            assert d.score < 1.0 and (d.mask & exact_masks[d.label]).sum() > 0.3 * exact_masks[d.label].sum()
    with pytest.raises(InvalidInput, match="faults"):
        GroundTruthMaskDetector(scene, faults="default")  # type: ignore[arg-type]  # on purpose: a name is refused


def test_detector_spec_with_faults(tiny_scannet: TinyScanNet) -> None:
    from arcloud.detectors import make_detector

    register_gt_masks_detector()
    assert gt_masks_options(str(tiny_scannet.scene_dir)) == ({}, str(tiny_scannet.scene_dir))
    assert gt_masks_options("faults=default") == ({"faults": MaskFaults()}, "")
    options, folder = gt_masks_options(f"faults=none,seed=3:{tiny_scannet.scene_dir}")
    assert options == {"faults": MaskFaults.none(), "fault_seed": 3} and folder == str(tiny_scannet.scene_dir)
    assert gt_masks_options("drop_rate=0.5,seed=2")[0] == {"faults": MaskFaults(drop_rate=0.5), "fault_seed": 2}
    detector = make_detector(f"gt-masks:faults=default,seed=7:{tiny_scannet.scene_dir}", min_mask_px=4)
    assert isinstance(detector, GroundTruthMaskDetector) and detector.faults == MaskFaults() and detector.fault_seed == 7
    with pytest.raises(InvalidInput, match="no folder"):
        make_detector("gt-masks:faults=default")
    with pytest.raises(InvalidInput, match="integer seed"):
        gt_masks_options("faults=default,seed=x")
    with pytest.raises(InvalidInput, match="seed= with faults="):
        gt_masks_options("seed=1")


def test_label_images_are_resized_to_the_depth_size_pixel_centre_to_pixel_centre() -> None:
    from arcloud.datasets.files import resize_nearest

    columns = np.tile(np.arange(1296, dtype=np.uint16), (968, 1))  # ScanNet's colour-size labels: each pixel its column
    resized = resize_nearest(columns, (480, 640))  # onto the 640 x 480 depth
    centres = (np.arange(640) + 0.5) * 1296 / 640 - 0.5  # the column under each depth pixel's centre
    assert np.abs(resized[0] - centres).max() <= 0.5 and abs(float(np.mean(resized[0] - centres))) < 0.01
    assert set(np.unique(resized)) <= set(range(1296))  # ids kept exact, none blended
