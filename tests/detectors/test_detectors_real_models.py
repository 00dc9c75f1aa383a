"""The real YOLOv8n-seg models on real pictures (../shared; skipped with a reason when absent)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from arcloud.core.checks import make_frame
from arcloud.core.types import Frame
from arcloud.detectors.coco import RawDetection
from arcloud.detectors.onnx_yolo import YoloSegDetector

pytestmark = pytest.mark.shared

MODEL_640 = "models/yolov8n-seg-fp32-640.onnx"
MODEL_320 = "models/yolov8n-seg-int8-320.onnx"
SEVEN_SCENES = "data/7scenes-redkitchen"
# Frames where the dining table and chairs are in view (240: two chairs by the table and a tv;
# 560: two chairs and the table, seen from the other side).
TABLE_AND_CHAIR_FRAMES = (240, 560)


def read_rgb(path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, f"cannot read {path}"
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def seven_scenes_frame(shared, index: int) -> Frame:
    folder = shared.path(SEVEN_SCENES)
    stem = folder / f"frame-{index:06d}"
    return make_frame(
        read_rgb(f"{stem}.color.jpg"),
        cv2.imread(f"{stem}.depth.png", cv2.IMREAD_UNCHANGED),
        (585.0, 585.0, 320.0, 240.0),
        np.loadtxt(f"{stem}.pose.txt"),
        timestamp_s=float(index),
        map_id="redkitchen",
        device_id="kinect",
        frame_id=f"{index:06d}",
        depth_scale=1000.0,
    )


@pytest.fixture
def detector_640(shared) -> YoloSegDetector:
    return YoloSegDetector(shared.path(MODEL_640))  # cheap after the first: the session is cached


def assert_masks_inside_boxes(raw: list[RawDetection], shape: tuple[int, int]) -> None:
    for r in raw:
        assert r.mask.shape == shape and r.mask.dtype == bool
        x1, y1, x2, y2 = r.box_px
        assert 0 <= x1 < x2 <= shape[1] and 0 <= y1 < y2 <= shape[0]
        rows, cols = np.nonzero(r.mask)
        assert rows.size > 0, f"empty mask for {r.class_name} {r.score:.2f}"
        assert cols.min() >= x1 - 1e-9 and cols.max() < x2 and rows.min() >= y1 - 1e-9 and rows.max() < y2
        # A mask fills a fair part of its box (objects are not slivers inside their boxes).
        assert r.mask.sum() > 0.2 * (x2 - x1) * (y2 - y1), f"{r.class_name}: mask {r.mask.sum()} px in its box"


def test_bus_jpg_gives_a_bus_and_people(detector_640, shared) -> None:
    rgb = read_rgb(shared.path("data/images/bus.jpg"))
    raw = detector_640.detect_raw(rgb)
    buses = [r for r in raw if r.class_name == "bus"]
    people = [r for r in raw if r.class_name == "person" and r.score > 0.5]
    assert len(buses) == 1 and buses[0].score > 0.7
    x1, y1, x2, y2 = buses[0].box_px
    assert x2 - x1 > 0.9 * rgb.shape[1] and 0.2 * rgb.shape[0] < y1 < y2 < 0.8 * rgb.shape[0]
    assert len(people) >= 3  # three pedestrians stand in front of the bus
    for person in people:
        x1, y1, x2, y2 = person.box_px
        assert 1.5 < (y2 - y1) / (x2 - x1) < 5  # upright
        assert y2 > 0.75 * rgb.shape[0]  # feet near the bottom of the picture
    assert_masks_inside_boxes(raw, rgb.shape[:2])
    assert not any(r.class_id in detector_640.class_map for r in raw)  # no furniture in the street
    assert detector_640.last_timing["session_s"] > 0


@pytest.mark.parametrize("index", TABLE_AND_CHAIR_FRAMES)
def test_seven_scenes_frames_give_chairs_and_the_dining_table(detector_640, shared, index) -> None:
    frame = seven_scenes_frame(shared, index)
    height, width = frame.shape
    detections = detector_640.detect(frame)
    labels = [d.label for d in detections]
    assert labels.count("chair") >= 2 and labels.count("table") == 1, labels
    for d in detections:
        assert d.mask.shape == frame.shape and d.mask.dtype == bool and 0.25 < d.score <= 1
    table = next(d for d in detections if d.label == "table")
    assert 0.15 < table.mask.sum() / (height * width) < 0.7  # the table fills much of these views
    for chair in (d for d in detections if d.label == "chair"):
        assert 0.01 < chair.mask.sum() / (height * width) < 0.15
        assert not (chair.mask & table.mask).all()
    # The table is below the horizon in these views: most of its mask lies in the image's lower half.
    rows = np.nonzero(table.mask)[0]
    assert np.median(rows) > height / 2
    mapped = [r for r in detector_640.detect_raw(frame.rgb) if r.class_id in detector_640.class_map]
    assert_masks_inside_boxes(mapped, frame.shape)


def test_int8_320_model_runs_with_its_own_input_size(shared) -> None:
    detector = YoloSegDetector(shared.path(MODEL_320))
    assert detector.input_size_px == 320
    rgb = read_rgb(shared.path("data/images/bus.jpg"))
    raw = detector.detect_raw(rgb)
    names = [r.class_name for r in raw]
    assert "bus" in names and names.count("person") >= 2
    assert_masks_inside_boxes(raw, rgb.shape[:2])
    frame = seven_scenes_frame(shared, TABLE_AND_CHAIR_FRAMES[0])
    labels = [d.label for d in detector.detect(frame)]
    assert "chair" in labels and "table" in labels, labels
