"""Dataset readers and writers: ScanNet scenes (standard export layout), 7-Scenes sequences, a detector
replaying ScanNet 2D ground truth, and a renderer of annotated scanned meshes into ScanNet-layout scenes.

Each format is parsed once into typed dataclasses (``ScanNetScene``, ``SevenScenesSequence``); nothing
downstream sees file formats. Importing this package is light: modules load on first use.
"""

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
