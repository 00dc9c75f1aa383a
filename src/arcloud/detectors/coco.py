"""COCO class names, the maps from COCO ids to arcloud's classes, and the COCO-labelled raw detection.

Two id schemes are in use:
- the 80 contiguous ids of Ultralytics YOLO models (``COCO80``, 0 = person);
- torchvision's 91-id scheme of the original COCO category ids (``COCO91``, 0 = background, with
  "N/A" gaps), which Mask R-CNN exports emit.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from arcloud.core.checks import describe
from arcloud.core.types import CLASSES, Detection
from arcloud.errors import InvalidInput

#: The 80 COCO class names in Ultralytics' contiguous order (id = index).
COCO80: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange",
    "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch", "potted plant",
    "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard", "cell phone",
    "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
    "teddy bear", "hair drier", "toothbrush",
)  # fmt: skip

#: COCO category ids that the 2014/2017 annotations never use (gaps in the 91-id scheme).
_COCO91_UNUSED_IDS = frozenset({12, 26, 29, 30, 45, 66, 68, 69, 71, 83})


def _coco91_names() -> tuple[str, ...]:
    names = iter(COCO80)
    return tuple("__background__" if i == 0 else "N/A" if i in _COCO91_UNUSED_IDS else next(names) for i in range(91))


#: torchvision's 91 category names (id = index; 0 = background, "N/A" = unused id).
COCO91: tuple[str, ...] = _coco91_names()

#: Which COCO class names become which arcloud class.
COCO_NAME_TO_CLASS: dict[str, str] = {
    "chair": "chair",
    "dining table": "table",
    "laptop": "laptop",
    "couch": "couch",
    "tv": "tv",
}


def class_map_for(names: Mapping[int, str] | tuple[str, ...]) -> dict[int, str]:
    """Model class id -> arcloud class, for a model whose class names are ``names``."""
    items = names.items() if isinstance(names, Mapping) else enumerate(names)
    return {int(i): COCO_NAME_TO_CLASS[name] for i, name in items if name in COCO_NAME_TO_CLASS}


#: Default maps: YOLO 80-id (chair 56, couch 57, dining table 60, tv 62, laptop 63) and
#: torchvision 91-id (chair 62, couch 63, dining table 67, tv 72, laptop 73).
COCO80_TO_CLASS: dict[int, str] = class_map_for(COCO80)
COCO91_TO_CLASS: dict[int, str] = class_map_for(COCO91)


def check_class_map(class_map: Mapping[int, str], n_model_classes: int | None) -> dict[int, str]:
    """A class map {model class id: arcloud class}; ids must be in [0, n_model_classes) when that is
    known. Raises ``InvalidInput`` naming the wrong entry."""
    checked = {}
    for class_id, label in class_map.items():
        field = f"class_map[{class_id!r}]"
        if label not in CLASSES:
            raise InvalidInput(field, f"one of {CLASSES}", describe(label))
        in_range = isinstance(class_id, (int, np.integer)) and not isinstance(class_id, bool) and class_id >= 0
        if not in_range or (n_model_classes is not None and class_id >= n_model_classes):
            expected = "class ids >= 0" if n_model_classes is None else f"class ids of the model, in [0, {n_model_classes})"
            raise InvalidInput("class_map", expected, describe(class_id))
        checked[int(class_id)] = label
    return checked


def parse_names_metadata(text: str | None) -> dict[int, str] | None:
    """Class names from an Ultralytics ``names`` metadata string ("{0: 'person', ...}"), or None."""
    if not text:
        return None
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return None
    if isinstance(value, dict) and all(isinstance(k, int) and isinstance(v, str) for k, v in value.items()):
        return dict(value)
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return dict(enumerate(value))
    return None


@dataclass(frozen=True, eq=False, slots=True)
class RawDetection:
    """A detection in the model's own class scheme, before mapping to arcloud's classes.

    box_px: (4,) float64 x1, y1, x2, y2 in frame pixels. mask: (H, W) bool, or None when not computed.
    """

    class_id: int
    class_name: str
    score: float
    box_px: np.ndarray
    mask: np.ndarray | None


def to_detections(raw: list[RawDetection], class_map: Mapping[int, str]) -> list[Detection]:
    """The raw detections whose class is mapped, as arcloud ``Detection``s (mask required)."""
    return [Detection(class_map[r.class_id], r.score, r.mask) for r in raw if r.class_id in class_map and r.mask is not None]
