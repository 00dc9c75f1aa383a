"""Dataset readers and writers: ScanNet scenes (standard export layout), 7-Scenes sequences, TUM RGB-D
recordings, ground-truth boxes of any of them, a detector replaying ScanNet 2D ground truth, and a
renderer of annotated scanned meshes into ScanNet-layout scenes.

Each format is parsed once into typed dataclasses (``ScanNetScene``, ``SevenScenesSequence``,
``TumSequence``, ``GroundTruthBoxes``); ``load_recording`` gives any layout to an evaluation as one
``Recording``; nothing downstream sees file formats. Importing this package is light: modules load on
first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from arcloud.datasets.gt_boxes import GroundTruthBoxes, load_ground_truth
    from arcloud.datasets.gt_masks import GroundTruthMaskDetector
    from arcloud.datasets.recording import Recording, load_recording
    from arcloud.datasets.scannet import (
        DEFAULT_CLASS_MAPPING,
        ClassMapping,
        LabelTable,
        ScanNetInstance,
        ScanNetMesh,
        ScanNetScene,
        find_scene_dirs,
        load_axis_alignment,
        load_scannet_scene,
        read_label_table,
    )
    from arcloud.datasets.sevenscenes import SevenScenesSequence, load_seven_scenes
    from arcloud.datasets.tum import TumSequence, load_tum

#: Where each exported name lives; ``__getattr__`` imports the module on first use (PEP 562).
_MODULE_OF = {
    "GroundTruthBoxes": "gt_boxes",
    "load_ground_truth": "gt_boxes",
    "GroundTruthMaskDetector": "gt_masks",
    "Recording": "recording",
    "load_recording": "recording",
    **dict.fromkeys(
        (
            "DEFAULT_CLASS_MAPPING",
            "ClassMapping",
            "LabelTable",
            "ScanNetInstance",
            "ScanNetMesh",
            "ScanNetScene",
            "find_scene_dirs",
            "load_axis_alignment",
            "load_scannet_scene",
            "read_label_table",
        ),
        "scannet",
    ),
    "SevenScenesSequence": "sevenscenes",
    "load_seven_scenes": "sevenscenes",
    "TumSequence": "tum",
    "load_tum": "tum",
}

__all__ = [
    "DEFAULT_CLASS_MAPPING",
    "ClassMapping",
    "GroundTruthBoxes",
    "GroundTruthMaskDetector",
    "LabelTable",
    "Recording",
    "ScanNetInstance",
    "ScanNetMesh",
    "ScanNetScene",
    "SevenScenesSequence",
    "TumSequence",
    "find_scene_dirs",
    "load_axis_alignment",
    "load_ground_truth",
    "load_recording",
    "load_scannet_scene",
    "load_seven_scenes",
    "load_tum",
    "read_label_table",
]


def __getattr__(name: str) -> Any:
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
