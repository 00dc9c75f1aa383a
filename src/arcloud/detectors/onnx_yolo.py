"""Ultralytics YOLO-seg (v8/v11 export signature) in onnxruntime, as an arcloud ``Detector``.

Model signature (any Ultralytics ``*-seg`` ONNX export without NMS in the graph):
- input ``images`` float32 [1, 3, S, S]: RGB in 0..1, letterboxed (aspect kept, centred, pad 114);
- ``output0`` [1, 4 + nc + nm, A]: per anchor a box (cx, cy, w, h in input px), nc class scores
  (sigmoid applied, no objectness) and nm mask coefficients;
- ``output1`` [1, nm, P, P]: mask prototypes; an instance mask is sigmoid(coefficients . prototypes),
  cropped to its box, upsampled and un-letterboxed to the frame, thresholded.

Post-processing is done the "native" way (upsample, then crop at the exact box, as Ultralytics does
with ``retina_masks``), but only over each box's region: the prototype crop under the box is warped
straight to frame pixels with one affine map, so no full-size float mask is ever made.
"""

from __future__ import annotations

import ast
import logging
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from arcloud.core.checks import check_finite_number, check_rgb, describe
from arcloud.core.types import CLASSES, Detection, Frame
from arcloud.detectors.coco import (
    COCO80,
    RawDetection,
    check_class_map,
    class_map_for,
    parse_names_metadata,
    to_detections,
)
from arcloud.detectors.session import input_specs, load_session, metadata, output_specs, signature_error
from arcloud.errors import InvalidInput, ModelError

log = logging.getLogger(__name__)

PAD_VALUE = 114
_ADAPTER = "YOLO-seg"
#: Per-class score thresholds by default (arcloud class -> threshold; the others take ``score_threshold``).
#: YOLO11n-seg scores screens low: on the 7-Scenes TVs, whole and lit, 0.10 where YOLOv8n-seg gives 0.87
#: and 0.52; at 0.25 it reports a TV in 28 of the frames that see the nearer one, at 0.1 in 85. The map's
#: evidence (detection rate, frames, plausible box: core.confirm) keeps the low-scored phantoms out.
DEFAULT_CLASS_SCORE_THRESHOLDS: dict[str, float] = {"tv": 0.1}
_EXPECTED_SIGNATURE = (
    "one input float32 [1, 3, S, S] (S fixed, or given by the 'imgsz' metadata) and outputs "
    "[1, 4 + nc + nm, A] and [1, nm, P, P] (e.g. output0 [1, 116, 8400], output1 [1, 32, 160, 160])"
)


# --- Letterbox geometry ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Letterbox:
    """Where a frame of (frame_height_px, frame_width_px) sits in the square model input of size_px.

    input = frame * scale + pad (per axis); the resized frame covers
    [pad_left_px, pad_left_px + resized_width_px) x [pad_top_px, pad_top_px + resized_height_px).
    """

    frame_height_px: int
    frame_width_px: int
    size_px: int
    scale: float
    resized_width_px: int
    resized_height_px: int
    pad_left_px: int
    pad_top_px: int

    @classmethod
    def fit(cls, frame_shape: tuple[int, int], size_px: int) -> Letterbox:
        """The Ultralytics letterbox (scale up or down, centred; odd padding puts the extra pixel
        right/bottom) of a frame of shape (H, W) into size_px x size_px."""
        height, width = int(frame_shape[0]), int(frame_shape[1])
        scale = min(size_px / height, size_px / width)
        resized_w, resized_h = int(round(width * scale)), int(round(height * scale))
        pad_left = int(round((size_px - resized_w) / 2 - 0.1))
        pad_top = int(round((size_px - resized_h) / 2 - 0.1))
        return cls(height, width, size_px, scale, resized_w, resized_h, pad_left, pad_top)

    def boxes_to_input(self, boxes_px: np.ndarray) -> np.ndarray:
        """(N, 4) x1, y1, x2, y2 frame px -> model input px."""
        boxes = np.asarray(boxes_px, dtype=np.float64)
        return boxes * self.scale + np.array([self.pad_left_px, self.pad_top_px] * 2, dtype=np.float64)

    def boxes_to_frame(self, boxes_px: np.ndarray, *, clip: bool = True) -> np.ndarray:
        """(N, 4) x1, y1, x2, y2 model input px -> frame px, clipped to the frame unless ``clip=False``."""
        boxes = (np.asarray(boxes_px, dtype=np.float64) - [self.pad_left_px, self.pad_top_px] * 2) / self.scale
        if clip:
            boxes[:, 0::2] = boxes[:, 0::2].clip(0, self.frame_width_px)
            boxes[:, 1::2] = boxes[:, 1::2].clip(0, self.frame_height_px)
        return boxes

    def image(self, rgb: np.ndarray) -> np.ndarray:
        """(size_px, size_px, 3) uint8: ``rgb`` (H, W, 3) resized (bilinear) and padded with 114."""
        out = np.full((self.size_px, self.size_px, 3), PAD_VALUE, dtype=np.uint8)
        resized = rgb
        if (self.resized_width_px, self.resized_height_px) != (self.frame_width_px, self.frame_height_px):
            resized = cv2.resize(rgb, (self.resized_width_px, self.resized_height_px), interpolation=cv2.INTER_LINEAR)
        top, left = self.pad_top_px, self.pad_left_px
        out[top : top + self.resized_height_px, left : left + self.resized_width_px] = resized
        return out


_TO_UNIT = np.float32(1 / 255)


def letterbox_tensor(rgb: np.ndarray, box: Letterbox) -> np.ndarray:
    """(1, 3, S, S) float32 in 0..1, C-contiguous: the letterboxed RGB image ``box.image(rgb)``, NCHW, times
    float32(1 / 255) (the same values; a test holds them equal). Written channel-first at once: a transposed
    view of the image would reach onnxruntime strided, and it copies such an input before every run
    (0.6-1.5 ms of ``session.run`` on a VGA frame, more than this function takes)."""
    size, top, left = box.size_px, box.pad_top_px, box.pad_left_px
    height, width = box.resized_height_px, box.resized_width_px
    resized = rgb
    if (width, height) != (box.frame_width_px, box.frame_height_px):
        resized = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_LINEAR)
    tensor = np.empty((1, 3, size, size), np.float32)
    pad = np.float32(PAD_VALUE) * _TO_UNIT
    tensor[0, :, :top] = pad
    tensor[0, :, top + height :] = pad
    tensor[0, :, top : top + height, :left] = pad
    tensor[0, :, top : top + height, left + width :] = pad
    tensor[0, :, top : top + height, left : left + width] = np.multiply(resized, _TO_UNIT, dtype=np.float32).transpose(2, 0, 1)
    return tensor


# --- Post-processing -------------------------------------------------------------------------------


def nms(boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, iou_threshold: float, max_keep: int) -> np.ndarray:
    """Class-aware greedy non-maximum suppression.

    boxes: (N, 4) x1, y1, x2, y2; scores: (N,); class_ids: (N,) int. Returns the indices kept, by
    falling score: a box is dropped when its IoU with a kept box of the same class exceeds the threshold.
    """
    if boxes.shape[0] == 0:
        return np.empty(0, dtype=np.intp)
    # Shift each class to its own region so that boxes of different classes never overlap.
    span = float(np.abs(boxes).max()) * 2 + 1
    shifted = boxes + (class_ids.astype(np.float64) * span)[:, None]
    x1, y1, x2, y2 = shifted.T
    areas = (x2 - x1).clip(0) * (y2 - y1).clip(0)
    order = np.argsort(-scores, kind="stable")
    keep: list[np.intp] = []
    while order.size and len(keep) < max_keep:
        i, rest = order[0], order[1:]
        keep.append(i)
        w = (np.minimum(x2[i], x2[rest]) - np.maximum(x1[i], x1[rest])).clip(0)
        h = (np.minimum(y2[i], y2[rest]) - np.maximum(y1[i], y1[rest])).clip(0)
        inter = w * h
        iou = inter / np.maximum(areas[i] + areas[rest] - inter, 1e-12)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.intp)


def box_pixel_ranges(boxes_px: np.ndarray) -> np.ndarray:
    """(N, 4) int: the pixel columns [u0, u1) and rows [v0, v1) whose index lies in each box
    (x1 <= u < x2), as u0, v0, u1, v1."""
    return np.ceil(boxes_px).astype(np.int64)


def instance_masks(
    coefficients: np.ndarray,
    prototypes: np.ndarray,
    boxes_px: np.ndarray,
    box: Letterbox,
    mask_threshold: float,
) -> list[np.ndarray]:
    """(H, W) bool masks: sigmoid(coefficients . prototypes) sampled bilinearly at each frame pixel
    inside its box, thresholded.

    coefficients: (N, nm); prototypes: (nm, P, P) over the model input; boxes_px: (N, 4) frame px.
    Only the prototype cells under each box are evaluated; one affine warp takes them to frame pixels.
    """
    _, proto_h, proto_w = prototypes.shape
    stride = box.size_px / proto_w
    # Frame pixel u (centre u + 0.5) -> input x = (u + 0.5) * scale + pad -> prototype cell coordinate
    # x / stride - 0.5 (cell centres at (i + 0.5) * stride): an affine map a * u + b per axis.
    a = box.scale / stride
    b_x = (0.5 * box.scale + box.pad_left_px) / stride - 0.5
    b_y = (0.5 * box.scale + box.pad_top_px) / stride - 0.5
    ranges = box_pixel_ranges(boxes_px)
    height, width = box.frame_height_px, box.frame_width_px
    masks = []
    for coeffs, (u0, v0, u1, v1) in zip(coefficients, ranges):
        mask = np.zeros((height, width), dtype=bool)
        if u1 <= u0 or v1 <= v0:
            masks.append(mask)
            continue
        # Prototype cells that bilinear sampling touches for pixels u0..u1-1, v0..v1-1.
        px0 = max(int(math.floor(a * u0 + b_x)), 0)
        px1 = min(int(math.floor(a * (u1 - 1) + b_x)) + 2, proto_w)
        py0 = max(int(math.floor(a * v0 + b_y)), 0)
        py1 = min(int(math.floor(a * (v1 - 1) + b_y)) + 2, proto_h)
        logits = np.tensordot(coeffs, prototypes[:, py0:py1, px0:px1], axes=1)
        crop = 1.0 / (1.0 + np.exp(-logits, dtype=np.float32))
        to_crop = np.array([[a, 0.0, a * u0 + b_x - px0], [0.0, a, a * v0 + b_y - py0]])
        sampled = cv2.warpAffine(
            crop,
            to_crop,
            (int(u1 - u0), int(v1 - v0)),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
        mask[v0:v1, u0:u1] = sampled > mask_threshold
        masks.append(mask)
    return masks


# --- The adapter -----------------------------------------------------------------------------------


class YoloSegDetector:
    """Ultralytics YOLO-seg ONNX model -> arcloud ``Detection``s (implements ``arcloud.ports.Detector``).

    ``class_map``: model class id -> arcloud class (default: by COCO name, i.e. chair 56, couch 57,
    dining table 60, tv 62, laptop 63). ``class_score_thresholds``: arcloud class -> its score threshold
    (default ``DEFAULT_CLASS_SCORE_THRESHOLDS``; ``{}``: ``score_threshold`` for all). ``last_timing`` holds the split of the latest call:
    ``preprocess_s``, ``session_s``, ``postprocess_s`` (for benchmarks; per instance, not per thread).
    Safe to call from several threads (onnxruntime sessions are).
    """

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        score_threshold: float = 0.25,
        class_score_thresholds: Mapping[str, float] | None = None,
        iou_threshold: float = 0.5,
        mask_threshold: float = 0.5,
        class_map: Mapping[int, str] | None = None,
        intra_op_threads: int | None = None,
        execution_provider: str = "cpu",
        max_detections: int = 100,
    ) -> None:
        self.model_path = str(model_path)
        self.score_threshold = check_fraction("score_threshold", score_threshold)
        chosen = DEFAULT_CLASS_SCORE_THRESHOLDS if class_score_thresholds is None else class_score_thresholds
        unknown = sorted(set(chosen) - set(CLASSES))
        if unknown:
            raise InvalidInput("class_score_thresholds", f"classes from {CLASSES}", repr(unknown))
        self.class_score_thresholds = {str(k): check_fraction(f"class_score_thresholds[{k!r}]", v) for k, v in chosen.items()}
        self.iou_threshold = check_fraction("iou_threshold", iou_threshold)
        self.mask_threshold = check_fraction("mask_threshold", mask_threshold)
        self.max_detections = check_count("max_detections", max_detections)
        self._session = load_session(model_path, intra_op_threads=intra_op_threads, execution_provider=execution_provider)
        self.input_name, self.input_size_px, self._output_names, n_classes = self._check_signature()
        self.class_names = self._class_names(n_classes)
        self.class_map = (
            class_map_for(self.class_names) if class_map is None else check_class_map(class_map, len(self.class_names))
        )
        self._mapped_ids = np.array(sorted(self.class_map), dtype=np.intp)
        # Each model class's threshold: its arcloud class's in class_score_thresholds, else score_threshold.
        self._row_thresholds = np.array(
            [
                self.class_score_thresholds.get(self.class_map.get(i, ""), self.score_threshold)
                for i in range(len(self.class_names))
            ],
            np.float32,
        )
        self.last_timing: dict[str, float] = {}

    def __repr__(self) -> str:
        return f"YoloSegDetector({self.model_path!r}, input_size_px={self.input_size_px})"

    def _check_signature(self) -> tuple[str, int, tuple[str, str], int | None]:
        inputs, outputs = input_specs(self._session), output_specs(self._session)
        if len(inputs) != 1 or len(inputs[0].shape) != 4 or inputs[0].type != "tensor(float)":
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        _, channels, height, width = inputs[0].shape
        if channels not in (3, None) and not isinstance(channels, str):
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        size = height if isinstance(height, int) else _imgsz_metadata(metadata(self._session))
        if not isinstance(size, int) or (isinstance(width, int) and width != size):
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        by_rank = {len(o.shape): o for o in outputs}
        if len(outputs) != 2 or set(by_rank) != {3, 4}:
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        detections, prototypes = by_rank[3], by_rank[4]
        n_channels, n_coeffs = detections.shape[1], prototypes.shape[1]
        n_classes = None
        if isinstance(n_channels, int) and isinstance(n_coeffs, int):
            n_classes = n_channels - 4 - n_coeffs
            if n_classes < 1:
                raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        return inputs[0].name, size, (detections.name, prototypes.name), n_classes

    def _class_names(self, n_classes: int | None) -> tuple[str, ...]:
        names = parse_names_metadata(metadata(self._session).get("names"))
        if names is not None and (n_classes is None or len(names) == n_classes) and sorted(names) == list(range(len(names))):
            return tuple(names[i] for i in range(len(names)))
        if n_classes in (None, len(COCO80)):
            if names is not None:
                log.warning("model %s: unusable 'names' metadata; using the COCO names", self.model_path)
            return COCO80
        raise ModelError(
            f"model {self.model_path}: expected class names in its 'names' metadata for its {n_classes} classes, "
            "got none usable (pass a model exported with its names)"
        )

    # Public API

    def detect(self, frame: Frame) -> list[Detection]:
        """Detections of arcloud's classes in the frame's RGB image."""
        return self.detect_image(frame.rgb)

    def detect_image(self, rgb: np.ndarray) -> list[Detection]:
        """Detections of arcloud's classes in an (H, W, 3) uint8 RGB image; masks (H, W) bool."""
        if self._mapped_ids.size == 0:
            return []
        raw = self._detect(rgb, self._mapped_ids)
        return [d for d in to_detections(raw, self.class_map) if d.mask.any()]

    def detect_raw(self, rgb: np.ndarray, *, with_masks: bool = True) -> list[RawDetection]:
        """Detections of every model class (COCO ids and names), boxes in frame px, by falling score."""
        return self._detect(rgb, None, with_masks=with_masks)

    # Steps

    def _detect(self, rgb: np.ndarray, class_ids: np.ndarray | None, *, with_masks: bool = True) -> list[RawDetection]:
        rgb = check_rgb(rgb)
        t0 = time.perf_counter()
        box = Letterbox.fit(rgb.shape[:2], self.input_size_px)
        tensor = letterbox_tensor(rgb, box)
        t1 = time.perf_counter()
        detections, prototypes = self._session.run(self._output_names, {self.input_name: tensor})
        t2 = time.perf_counter()
        raw = self.decode(detections, prototypes, box, class_ids, with_masks=with_masks)
        t3 = time.perf_counter()
        self.last_timing = {"preprocess_s": t1 - t0, "session_s": t2 - t1, "postprocess_s": t3 - t2}
        return raw

    def decode(
        self,
        detections: np.ndarray,
        prototypes: np.ndarray,
        box: Letterbox,
        class_ids: np.ndarray | None = None,
        *,
        with_masks: bool = True,
    ) -> list[RawDetection]:
        """Raw detections from the model outputs.

        detections: (1, 4 + nc + nm, A); prototypes: (1, nm, P, P); class_ids: the model class ids to
        keep (None: all). Each anchor takes its best class among ``class_ids``.
        """
        preds, protos = detections[0], prototypes[0]
        n_coeffs = protos.shape[0]
        n_classes = preds.shape[0] - 4 - n_coeffs
        if n_classes != len(self.class_names):
            raise ModelError(
                f"model {self.model_path}: expected output0 with 4 + {len(self.class_names)} + {n_coeffs} rows, "
                f"got {preds.shape[0]}"
            )
        # Decide early on the few rows that matter: best class score per anchor, then threshold.
        scores_rows = preds[4 : 4 + n_classes] if class_ids is None else preds[4 + class_ids]
        thresholds = (self._row_thresholds if class_ids is None else self._row_thresholds[class_ids])[:, None]
        anchors = np.flatnonzero((scores_rows > thresholds).any(axis=0))
        if anchors.size == 0:
            return []
        candidate_scores = np.where(scores_rows[:, anchors] > thresholds, scores_rows[:, anchors], -1.0)
        best_row = candidate_scores.argmax(axis=0)
        scores = candidate_scores[best_row, np.arange(anchors.size)].astype(np.float64)
        ids = best_row if class_ids is None else class_ids[best_row]
        cx, cy, w, h = preds[:4, anchors].astype(np.float64)
        boxes_input = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
        keep = nms(boxes_input, scores, ids, self.iou_threshold, self.max_detections)
        boxes_px = box.boxes_to_frame(boxes_input[keep])
        masks: list[np.ndarray | None] = [None] * keep.size
        if with_masks:
            coefficients = preds[4 + n_classes :, anchors[keep]].T
            masks = list(instance_masks(coefficients, protos, boxes_px, box, self.mask_threshold))
        return [
            RawDetection(int(c), self.class_names[int(c)], float(s), b, m)
            for c, s, b, m in zip(ids[keep], scores[keep], boxes_px, masks)
        ]


def _imgsz_metadata(meta: Mapping[str, str]) -> int | None:
    """The square input size from Ultralytics' ``imgsz`` metadata ("[640, 640]"), or None."""
    try:
        value = ast.literal_eval(meta.get("imgsz", ""))
    except (ValueError, SyntaxError):
        return None
    sizes = set(value) if isinstance(value, (list, tuple)) else {value}
    size = sizes.pop() if len(sizes) == 1 else None
    return size if isinstance(size, int) and size > 0 else None


def check_fraction(field: str, value: object) -> float:
    """A number in [0, 1] (thresholds), else ``InvalidInput``."""
    number = check_finite_number(field, value)
    if not 0.0 <= number <= 1.0:
        raise InvalidInput(field, "a number in [0, 1]", describe(value))
    return number


def check_count(field: str, value: object) -> int:
    """An int >= 1, else ``InvalidInput``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InvalidInput(field, "an int >= 1", describe(value))
    return int(value)
