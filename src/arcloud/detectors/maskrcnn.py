"""torchvision Mask R-CNN ONNX exports in onnxruntime, as an arcloud ``Detector``.

Model signature (``torch.onnx.export`` of ``torchvision.models.detection.maskrcnn_resnet50_fpn`` and
kin, NMS and mask pasting inside the graph):
- input (usually ``image``) float32 [3, H, W] RGB in 0..1, any size (or a fixed one: the frame is
  then resized to it and the results scaled back); [1, 3, H, W] is accepted too;
- outputs ``boxes`` [N, 4] (x1, y1, x2, y2 input px), ``labels`` [N] int64 (torchvision's 91-id
  COCO scheme: chair 62, couch 63, dining table 67, tv 72, laptop 73), ``scores`` [N] and ``masks``
  [N, 1, H, W] float probabilities over the whole input image.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping

import cv2
import numpy as np

from arcloud.core.checks import check_rgb
from arcloud.core.types import Detection, Frame
from arcloud.detectors.coco import COCO91, RawDetection, check_class_map, class_map_for, to_detections
from arcloud.detectors.onnx_yolo import check_count, check_fraction
from arcloud.detectors.session import input_specs, load_session, output_specs, signature_error
from arcloud.errors import ModelError

log = logging.getLogger(__name__)

#: Output names that identify a torchvision Mask R-CNN export.
MASKRCNN_OUTPUTS: tuple[str, ...] = ("boxes", "labels", "scores", "masks")
_ADAPTER = "Mask R-CNN"
_EXPECTED_SIGNATURE = (
    "one input float32 [3, H, W] (or [1, 3, H, W]) and outputs boxes [N, 4], labels [N], scores [N], masks [N, 1, H, W]"
)


def is_maskrcnn_export(output_names: list[str]) -> bool:
    """Whether a model's outputs name it a torchvision Mask R-CNN export."""
    return set(MASKRCNN_OUTPUTS) <= set(output_names)


class MaskRCNNDetector:
    """torchvision Mask R-CNN ONNX export -> arcloud ``Detection``s (implements ``arcloud.ports.Detector``).

    Same options as ``YoloSegDetector``: ``iou_threshold`` is accepted for a uniform interface but
    unused (the export runs NMS inside the graph). ``class_map``: label id -> arcloud class (default:
    torchvision's 91-id COCO scheme). ``last_timing``: ``preprocess_s``, ``session_s``, ``postprocess_s``.
    """

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        score_threshold: float = 0.25,
        iou_threshold: float = 0.5,
        mask_threshold: float = 0.5,
        class_map: Mapping[int, str] | None = None,
        intra_op_threads: int | None = None,
        execution_provider: str = "cpu",
        max_detections: int = 100,
    ) -> None:
        self.model_path = str(model_path)
        self.score_threshold = check_fraction("score_threshold", score_threshold)
        self.iou_threshold = check_fraction("iou_threshold", iou_threshold)
        self.mask_threshold = check_fraction("mask_threshold", mask_threshold)
        self.max_detections = check_count("max_detections", max_detections)
        self._session = load_session(model_path, intra_op_threads=intra_op_threads, execution_provider=execution_provider)
        self.input_name, self._batched, self.input_size_px = self._check_signature()
        self.class_names = COCO91
        self.class_map = class_map_for(COCO91) if class_map is None else check_class_map(class_map, None)
        self.last_timing: dict[str, float] = {}

    def __repr__(self) -> str:
        return f"MaskRCNNDetector({self.model_path!r})"

    def _check_signature(self) -> tuple[str, bool, tuple[int, int] | None]:
        inputs, outputs = input_specs(self._session), output_specs(self._session)
        if len(inputs) != 1 or inputs[0].type != "tensor(float)" or len(inputs[0].shape) not in (3, 4):
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        shape = inputs[0].shape
        batched = len(shape) == 4
        if batched and isinstance(shape[0], int) and shape[0] != 1:
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        channels, height, width = shape[-3:]
        if isinstance(channels, int) and channels != 3:
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        if not is_maskrcnn_export([o.name for o in outputs]):
            raise signature_error(self.model_path, _ADAPTER, _EXPECTED_SIGNATURE, self._session)
        fixed = (height, width) if isinstance(height, int) and isinstance(width, int) else None
        return inputs[0].name, batched, fixed

    # Public API

    def detect(self, frame: Frame) -> list[Detection]:
        """Detections of arcloud's classes in the frame's RGB image."""
        return self.detect_image(frame.rgb)

    def detect_image(self, rgb: np.ndarray) -> list[Detection]:
        """Detections of arcloud's classes in an (H, W, 3) uint8 RGB image; masks (H, W) bool."""
        raw = self._detect(rgb, mapped_only=True)
        return [d for d in to_detections(raw, self.class_map) if d.mask.any()]

    def detect_raw(self, rgb: np.ndarray) -> list[RawDetection]:
        """Detections of every label (torchvision COCO ids and names), boxes in frame px, by falling score."""
        return self._detect(rgb, mapped_only=False)

    # Steps

    def _detect(self, rgb: np.ndarray, *, mapped_only: bool) -> list[RawDetection]:
        rgb = check_rgb(rgb)
        height, width = rgb.shape[:2]
        t0 = time.perf_counter()
        image = rgb
        if self.input_size_px is not None and self.input_size_px != (height, width):
            image = cv2.resize(rgb, self.input_size_px[::-1], interpolation=cv2.INTER_LINEAR)
        tensor = np.multiply(image.transpose(2, 0, 1), np.float32(1 / 255), dtype=np.float32)
        if self._batched:
            tensor = tensor[None]
        t1 = time.perf_counter()
        boxes, labels, scores, masks = self._session.run(list(MASKRCNN_OUTPUTS), {self.input_name: tensor})
        t2 = time.perf_counter()
        raw = self.decode(boxes, labels, scores, masks, (height, width), mapped_only=mapped_only)
        t3 = time.perf_counter()
        self.last_timing = {"preprocess_s": t1 - t0, "session_s": t2 - t1, "postprocess_s": t3 - t2}
        return raw

    def decode(
        self,
        boxes: np.ndarray,
        labels: np.ndarray,
        scores: np.ndarray,
        masks: np.ndarray,
        frame_shape: tuple[int, int],
        *,
        mapped_only: bool = False,
    ) -> list[RawDetection]:
        """Raw detections from the export's outputs (see the module docstring for shapes), boxes and
        masks scaled to ``frame_shape`` (H, W) when the model ran at another size."""
        boxes, labels, scores, masks = (np.asarray(x) for x in (boxes, labels, scores, masks))
        if boxes.ndim == 3:  # a batched export: [1, N, ...]
            boxes, labels, scores, masks = boxes[0], labels[0], scores[0], masks[0]
        n = boxes.shape[0]
        fits = boxes.shape == (n, 4) and labels.shape == (n,) and scores.shape == (n,)
        if not fits or masks.ndim != 4 or masks.shape[:2] != (n, 1):
            got = ", ".join(f"{k} {list(v.shape)}" for k, v in zip(MASKRCNN_OUTPUTS, (boxes, labels, scores, masks)))
            raise ModelError(
                f"model {self.model_path}: expected boxes [N, 4], labels [N], scores [N], masks [N, 1, H, W], got {got}"
            )
        height, width = frame_shape
        keep = scores > self.score_threshold
        if mapped_only:
            keep &= np.isin(labels, list(self.class_map))
        order = np.flatnonzero(keep)
        order = order[np.argsort(-scores[order], kind="stable")][: self.max_detections]
        mask_h, mask_w = masks.shape[2:]
        scale = np.array([width / mask_w, height / mask_h] * 2)
        result = []
        for i in order:
            box_px = (boxes[i].astype(np.float64) * scale).clip(0, [width, height, width, height])
            probabilities = masks[i, 0]
            if (mask_h, mask_w) != (height, width):
                probabilities = cv2.resize(probabilities.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
            label = int(labels[i])
            name = self.class_names[label] if 0 <= label < len(self.class_names) else f"class_{label}"
            result.append(RawDetection(label, name, float(scores[i]), box_px, probabilities > self.mask_threshold))
        return result
