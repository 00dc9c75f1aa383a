"""Mask R-CNN export adapter on tiny models with known outputs: decoding, the class map, thresholds."""

from __future__ import annotations

import numpy as np
import pytest
from tiny_onnx_models import BRIGHT_BOX_PX, FRAME_SHAPE, bright_box_image, bright_box_mask

from arcloud.detectors.coco import COCO80, COCO80_TO_CLASS, COCO91, COCO91_TO_CLASS
from arcloud.detectors.maskrcnn import MaskRCNNDetector
from arcloud.errors import ModelError
from arcloud.ports import Detector


def test_coco_id_schemes_map_the_five_classes() -> None:
    assert len(COCO80) == 80 and len(COCO91) == 91
    assert COCO80_TO_CLASS == {56: "chair", 57: "couch", 60: "table", 62: "tv", 63: "laptop"}
    assert COCO91_TO_CLASS == {62: "chair", 63: "couch", 67: "table", 72: "tv", 73: "laptop"}
    assert (COCO91[0], COCO91[1], COCO91[12], COCO91[90]) == ("__background__", "person", "N/A", "toothbrush")


def test_detect_keeps_the_mapped_class_above_threshold_with_its_mask(tiny_models) -> None:
    detector = MaskRCNNDetector(tiny_models["maskrcnn"])
    assert isinstance(detector, Detector)
    detections = detector.detect_image(bright_box_image())
    assert [(d.label, round(d.score, 2)) for d in detections] == [("chair", 0.9)]
    np.testing.assert_array_equal(detections[0].mask, bright_box_mask())  # brightness > 0.5
    assert set(detector.last_timing) == {"preprocess_s", "session_s", "postprocess_s"}


def test_detect_raw_gives_torchvision_ids_names_and_boxes(tiny_models) -> None:
    raw = MaskRCNNDetector(tiny_models["maskrcnn"]).detect_raw(bright_box_image())
    assert [(r.class_id, r.class_name) for r in raw] == [(1, "person"), (62, "chair")]  # by falling score
    np.testing.assert_allclose(raw[1].box_px, BRIGHT_BOX_PX)
    assert raw[0].mask.shape == FRAME_SHAPE and raw[0].mask.dtype == bool


def test_thresholds_and_class_map(tiny_models) -> None:
    low = MaskRCNNDetector(tiny_models["maskrcnn"], score_threshold=0.1)
    assert [d.label for d in low.detect_image(bright_box_image())] == ["chair", "table"]
    assert MaskRCNNDetector(tiny_models["maskrcnn"], score_threshold=0.95).detect_image(bright_box_image()) == []
    assert MaskRCNNDetector(tiny_models["maskrcnn"], mask_threshold=1.0).detect_image(bright_box_image()) == []
    people_as_chairs = MaskRCNNDetector(tiny_models["maskrcnn"], class_map={1: "chair"})
    assert [(d.label, round(d.score, 2)) for d in people_as_chairs.detect_image(bright_box_image())] == [("chair", 0.95)]
    capped = MaskRCNNDetector(tiny_models["maskrcnn"], score_threshold=0.1, max_detections=2)
    assert [r.class_id for r in capped.detect_raw(bright_box_image())] == [1, 62]


def test_a_fixed_size_export_runs_on_a_resized_frame_and_scales_back(tiny_models) -> None:
    detector = MaskRCNNDetector(tiny_models["maskrcnn_fixed"])  # input [3, 48, 64]: half the frame
    assert detector.input_size_px == (48, 64)
    raw = detector.detect_raw(bright_box_image())
    chair = next(r for r in raw if r.class_id == 62)
    # The model's box (in its 48 x 64 input) is the frame's box, so scaled back it doubles, clipped.
    np.testing.assert_allclose(chair.box_px, [64.0, 48.0, 128.0, 96.0])
    assert chair.mask.shape == FRAME_SHAPE
    iou = (chair.mask & bright_box_mask()).sum() / (chair.mask | bright_box_mask()).sum()
    assert iou > 0.95


def test_a_yolo_model_does_not_fit_the_maskrcnn_adapter(tiny_models) -> None:
    expected_got = (
        "expected one input float32 \\[3, H, W\\].*got inputs: images tensor\\(float\\)\\[1,3,64,64\\]; outputs: output0"
    )
    with pytest.raises(ModelError, match=expected_got):
        MaskRCNNDetector(tiny_models["yolo"])
