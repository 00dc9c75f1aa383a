"""Dataset readers and writers: ScanNet scenes (standard export layout), 7-Scenes sequences, a detector
replaying ScanNet 2D ground truth, and a renderer of annotated scanned meshes into ScanNet-layout scenes.

Each format is parsed once into typed dataclasses (``ScanNetScene``, ``SevenScenesSequence``); nothing
downstream sees file formats. Importing this package is light: modules load on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from arcloud.datasets.gt_masks import GroundTruthMaskDetector
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

#: Where each exported name lives; ``__getattr__`` imports the module on first use (PEP 562).
_MODULE_OF = {
    "GroundTruthMaskDetector": "gt_masks",
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
}

__all__ = [
    "DEFAULT_CLASS_MAPPING",
    "ClassMapping",
    "GroundTruthMaskDetector",
    "LabelTable",
    "ScanNetInstance",
    "ScanNetMesh",
    "ScanNetScene",
    "SevenScenesSequence",
    "find_scene_dirs",
    "load_axis_alignment",
    "load_scannet_scene",
    "load_seven_scenes",
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
