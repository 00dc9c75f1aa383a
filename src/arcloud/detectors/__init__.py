"""Detector adapters: ONNX models (Ultralytics YOLO-seg, torchvision Mask R-CNN exports) in onnxruntime,
and a registry of detectors by spec string (``make_detector("onnx:PATH")``).

Importing this package is light: onnxruntime loads with the first model.
"""

from arcloud.detectors.coco import COCO80, COCO80_TO_CLASS, COCO91, COCO91_TO_CLASS, RawDetection
from arcloud.detectors.factory import DETECTOR_FACTORIES, MODEL_ENV_VAR, make_detector, register_detector
from arcloud.detectors.maskrcnn import MaskRCNNDetector
from arcloud.detectors.onnx_yolo import Letterbox, YoloSegDetector

__all__ = [
    "COCO80",
    "COCO80_TO_CLASS",
    "COCO91",
    "COCO91_TO_CLASS",
    "DETECTOR_FACTORIES",
    "Letterbox",
    "MODEL_ENV_VAR",
    "MaskRCNNDetector",
    "RawDetection",
    "YoloSegDetector",
    "make_detector",
    "register_detector",
]
