"""YOLO-seg adapter on tiny models with known outputs: letterbox geometry, NMS, mask sampling, decoding."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from tiny_onnx_models import BRIGHT_BOX_PX, FRAME_SHAPE, bright_box_image, bright_box_mask

from arcloud.core.checks import make_frame
from arcloud.core.types import Detection
from arcloud.detectors.onnx_yolo import PAD_VALUE, Letterbox, YoloSegDetector, instance_masks, letterbox_tensor, nms
from arcloud.errors import InvalidInput, ModelError
from arcloud.ports import Detector

# --- Letterbox --------------------------------------------------------------------------------------


def test_letterbox_geometry_matches_ultralytics_for_a_kinect_frame() -> None:
    box = Letterbox.fit((480, 640), 320)
    assert (box.scale, box.resized_width_px, box.resized_height_px) == (0.5, 320, 240)
    assert (box.pad_left_px, box.pad_top_px) == (0, 40)


def test_letterbox_puts_odd_padding_right_and_bottom() -> None:
    box = Letterbox.fit((101, 100), 64)  # resized 63 x 64: one pixel of padding to split
    assert (box.resized_width_px, box.resized_height_px) == (63, 64)
    assert box.pad_left_px == 0  # round(0.5 - 0.1): the extra column goes right, as in Ultralytics


def test_letterbox_round_trip_is_exact_for_a_known_box() -> None:
    box = Letterbox.fit((480, 640), 320)
    frame_box = np.array([[100.0, 50.0, 300.0, 250.0]])
    input_box = box.boxes_to_input(frame_box)
    np.testing.assert_array_equal(input_box, [[50.0, 65.0, 150.0, 165.0]])
    np.testing.assert_array_equal(box.boxes_to_frame(input_box), frame_box)


def test_letterbox_round_trip_with_a_non_dyadic_scale() -> None:
    box = Letterbox.fit((1080, 810), 640)  # bus.jpg: scale 0.5926, 80 px padding left and right
    assert (box.pad_left_px, box.pad_top_px, box.resized_width_px) == (80, 0, 480)
    frame_box = np.array([[20.0, 226.5, 797.0, 738.9], [0.0, 0.0, 810.0, 1080.0]])
    np.testing.assert_allclose(box.boxes_to_frame(box.boxes_to_input(frame_box)), frame_box, rtol=0, atol=1e-9)


def test_letterbox_boxes_to_frame_clips_to_the_frame_unless_asked_not_to() -> None:
    box = Letterbox.fit((480, 640), 320)
    outside = np.array([[-10.0, 0.0, 330.0, 320.0]])  # input px, partly in the padding
    np.testing.assert_array_equal(box.boxes_to_frame(outside), [[0.0, 0.0, 640.0, 480.0]])
    np.testing.assert_array_equal(box.boxes_to_frame(outside, clip=False), [[-20.0, -80.0, 660.0, 560.0]])


def test_letterbox_image_places_the_frame_where_the_geometry_says() -> None:
    rgb = bright_box_image()
    box = Letterbox.fit(FRAME_SHAPE, 64)
    image = box.image(rgb)
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    assert (image[: box.pad_top_px] == PAD_VALUE).all() and (image[box.pad_top_px + box.resized_height_px :] == PAD_VALUE).all()
    rows, cols = np.nonzero(image[..., 0] > 200)
    found = np.array([[cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]], dtype=np.float64)
    np.testing.assert_array_equal(found, box.boxes_to_input(np.array([BRIGHT_BOX_PX], dtype=np.float64)))
    tensor = letterbox_tensor(rgb, box)
    assert tensor.shape == (1, 3, 64, 64) and tensor.dtype == np.float32
    np.testing.assert_allclose(tensor[0].transpose(1, 2, 0), image / 255.0, atol=1e-6)
    assert tensor.flags.c_contiguous  # onnxruntime would copy a strided input


@pytest.mark.parametrize("frame_shape", [(48, 64), (64, 48), (30, 64), (64, 64), (17, 31)])
@pytest.mark.parametrize("size_px", [64, 96, 33])
def test_letterbox_tensor_is_the_letterboxed_image_times_a_255th_bit_for_bit(frame_shape: tuple[int, int], size_px: int) -> None:
    rgb = np.random.default_rng(7).integers(0, 256, (*frame_shape, 3), dtype=np.uint8)
    box = Letterbox.fit(frame_shape, size_px)
    plain = np.multiply(box.image(rgb).transpose(2, 0, 1)[None], np.float32(1 / 255), dtype=np.float32)
    assert letterbox_tensor(rgb, box).tobytes() == np.ascontiguousarray(plain).tobytes()


# --- NMS ----------------------------------------------------------------------------------------------


def test_nms_suppresses_overlaps_within_a_class_only() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [0, 0, 10, 10], [20, 20, 30, 30]], dtype=np.float64)
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    classes = np.array([0, 0, 1, 0])
    keep = nms(boxes, scores, classes, iou_threshold=0.5, max_keep=10)
    np.testing.assert_array_equal(keep, [0, 2, 3])  # box 1 overlaps box 0 (IoU 0.82); box 2 is another class


def test_nms_keeps_a_box_whose_iou_equals_the_threshold_and_caps_the_count() -> None:
    boxes = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [40, 0, 50, 10]], dtype=np.float64)  # IoU(0, 1) = 1/3
    scores = np.array([0.9, 0.8, 0.7])
    classes = np.zeros(3, dtype=np.int64)
    np.testing.assert_array_equal(nms(boxes, scores, classes, 1 / 3, 10), [0, 1, 2])
    np.testing.assert_array_equal(nms(boxes, scores, classes, 0.3, 10), [0, 2])
    np.testing.assert_array_equal(nms(boxes, scores, classes, 1 / 3, 2), [0, 1])
    assert nms(np.empty((0, 4)), np.empty(0), np.empty(0, np.int64), 0.5, 10).size == 0


# --- Masks ------------------------------------------------------------------------------------------


def test_instance_masks_match_bilinear_sampling_of_the_prototypes() -> None:
    rng = np.random.default_rng(7)
    box = Letterbox.fit((480, 640), 320)  # scale 0.5, 40 px padding, 80 x 80 prototypes (stride 4)
    # Smooth random prototypes: a coarse random field, so masks have extended shapes.
    prototypes = np.kron(rng.normal(size=(4, 10, 10)), np.ones((8, 8))).astype(np.float32)
    coefficients = rng.normal(size=(3, 4)).astype(np.float32)
    boxes_px = np.array([[10.3, 20.7, 300.2, 400.9], [0.0, 0.0, 640.0, 480.0], [500.5, 100.0, 501.5, 101.0]])
    masks = instance_masks(coefficients, prototypes, boxes_px, box, mask_threshold=0.5)

    # Reference: every frame pixel's centre mapped to prototype coordinates, sampled bilinearly.
    stride = 320 / 80
    v, u = np.mgrid[0:480, 0:640]
    px = ((u + 0.5) * box.scale + box.pad_left_px) / stride - 0.5
    py = ((v + 0.5) * box.scale + box.pad_top_px) / stride - 0.5
    for coeffs, (x1, y1, x2, y2), mask in zip(coefficients, boxes_px, masks):
        cell_probability = 1 / (1 + np.exp(-np.tensordot(coeffs, prototypes, axes=1)))
        probability = map_coordinates(cell_probability, [py, px], order=1, mode="nearest")
        inside = (u >= x1) & (u < x2) & (v >= y1) & (v < y2)
        expected = (probability > 0.5) & inside
        assert mask.shape == (480, 640) and mask.dtype == bool
        assert not (mask & ~inside).any()
        assert (mask != expected).sum() <= max(1, 0.0005 * inside.sum())  # fixed-point interpolation rounding only
    assert masks[2].sum() <= 1  # a one-pixel box gives at most its pixel


def test_instance_masks_of_an_empty_box_are_empty() -> None:
    box = Letterbox.fit((48, 64), 64)
    zero_width_box = np.array([[5.0, 5.0, 5.0, 9.0]])
    masks = instance_masks(np.ones((1, 1), np.float32), np.full((1, 16, 16), 10, np.float32), zero_width_box, box, 0.5)
    assert masks[0].shape == (48, 64) and not masks[0].any()


# --- The adapter on a tiny model ----------------------------------------------------------------------


def test_detect_finds_the_chair_with_its_mask_and_drops_the_duplicate(tiny_models) -> None:
    detector = YoloSegDetector(tiny_models["yolo"])
    assert isinstance(detector, Detector)
    assert detector.input_size_px == 64
    assert detector.class_map == {0: "chair", 1: "table"}  # from the names metadata
    frame = make_frame(
        bright_box_image(), np.ones(FRAME_SHAPE, np.float32), (100.0, 100.0, 64.0, 48.0), np.eye(4),
        timestamp_s=0.0, map_id="m", device_id="d", frame_id="f",
    )  # fmt: skip
    detections = detector.detect(frame)
    assert len(detections) == 1
    chair = detections[0]
    assert isinstance(chair, Detection) and chair.label == "chair"
    assert chair.score == pytest.approx(0.9)
    # The mask is the bright box but for its corners, where bilinear sampling of the 4 px prototype
    # cells mixes in three dark cells (as Ultralytics' upsampling does).
    expected = bright_box_mask()
    assert not (chair.mask & ~expected).any()
    x1, y1, x2, y2 = BRIGHT_BOX_PX
    corners = np.zeros_like(expected)
    for y, x in ((y1, x1), (y1, x2 - 3), (y2 - 3, x1), (y2 - 3, x2 - 3)):
        corners[y : y + 3, x : x + 3] = True
    np.testing.assert_array_equal(chair.mask | corners, expected)
    assert set(detector.last_timing) == {"preprocess_s", "session_s", "postprocess_s"}
    assert all(t >= 0 for t in detector.last_timing.values())


def test_detect_raw_returns_every_class_with_boxes_in_frame_pixels(tiny_models) -> None:
    detector = YoloSegDetector(tiny_models["yolo"])
    raw = detector.detect_raw(bright_box_image())
    assert [(r.class_id, r.class_name) for r in raw] == [(0, "chair"), (2, "person")]
    assert [r.score for r in raw] == pytest.approx([0.9, 0.7])
    np.testing.assert_allclose(raw[0].box_px, BRIGHT_BOX_PX)  # input px (16, 20, 48, 44) un-letterboxed
    np.testing.assert_allclose(raw[1].box_px, [8.0, 72.0, 32.0, 96.0])  # clipped at the frame's bottom
    assert not raw[1].mask.any()  # a dark region: the mask is empty
    assert detector.detect_raw(bright_box_image(), with_masks=False)[0].mask is None


def test_thresholds_and_class_map_options(tiny_models) -> None:
    low = YoloSegDetector(tiny_models["yolo"], score_threshold=0.05, iou_threshold=0.95)
    labels = sorted((d.label, round(d.score, 2)) for d in low.detect_image(bright_box_image()))
    assert labels == [("chair", 0.8), ("chair", 0.9), ("table", 0.1)]  # no suppression, low scores kept
    high = YoloSegDetector(tiny_models["yolo"], score_threshold=0.95)
    assert high.detect_image(bright_box_image()) == []
    people = YoloSegDetector(tiny_models["yolo"], class_map={2: "chair"})
    assert [(d.label, round(d.score, 2)) for d in people.detect_image(bright_box_image())] == []  # empty mask dropped
    strict_masks = YoloSegDetector(tiny_models["yolo"], mask_threshold=1.0)
    assert strict_masks.detect_image(bright_box_image()) == []
    one = YoloSegDetector(tiny_models["yolo"], score_threshold=0.05, iou_threshold=0.95, max_detections=1)
    assert [d.score for d in one.detect_image(bright_box_image())] == [pytest.approx(0.9)]


def test_bad_options_are_refused(tiny_models) -> None:
    with pytest.raises(InvalidInput, match="score_threshold: expected a number in \\[0, 1\\], got 1.5"):
        YoloSegDetector(tiny_models["yolo"], score_threshold=1.5)
    with pytest.raises(InvalidInput, match="max_detections: expected an int >= 1, got 0"):
        YoloSegDetector(tiny_models["yolo"], max_detections=0)
    with pytest.raises(InvalidInput, match="class_map\\[0\\]: expected one of .*got 'sofa'"):
        YoloSegDetector(tiny_models["yolo"], class_map={0: "sofa"})
    with pytest.raises(InvalidInput, match="class ids of the model, in \\[0, 3\\), got 5"):
        YoloSegDetector(tiny_models["yolo"], class_map={5: "chair"})
    detector = YoloSegDetector(tiny_models["yolo"])
    with pytest.raises(InvalidInput, match="rgb: expected dtype uint8"):
        detector.detect_image(bright_box_image().astype(np.float32))


def test_a_model_without_names_for_its_non_coco_classes_is_refused(tiny_models) -> None:
    with pytest.raises(ModelError, match="expected class names in its 'names' metadata for its 3 classes"):
        YoloSegDetector(tiny_models["yolo_no_names"])
