"""Exported maps: the served and tentative objects of a map as JSON, in a declared frame.

Every exported map declares its frame: ``"world_from_export"`` (4x4, row-major) maps its coordinates to
the dataset's pose frame, and ``"frame"`` says which frame that is in words.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from arcloud.core.types import MapObject, Params

if TYPE_CHECKING:
    from arcloud.datasets.gt_boxes import GroundTruthBoxes
    from arcloud.datasets.scannet import ScanNetScene
    from arcloud.datasets.sevenscenes import SevenScenesSequence
    from arcloud.datasets.tum import TumSequence


def objects_json(objects: Sequence[MapObject]) -> list[dict[str, Any]]:
    """The reportable objects (label and box) as JSON-friendly dicts, highest score first."""
    boxed = sorted((o for o in objects if o.aabb is not None and o.label), key=lambda o: -o.score)
    return [
        {
            "label": o.label,
            "score": round(float(o.score), 6),
            "aabb_min": [round(float(v), 4) for v in o.aabb.min],  # type: ignore[union-attr]  # boxed objects have an aabb
            "aabb_max": [round(float(v), 4) for v in o.aabb.max],  # type: ignore[union-attr]  # boxed objects have an aabb
        }
        for o in boxed
    ]


@dataclass(frozen=True, eq=False)
class ExportFrame:
    """The frame a dataset's maps are boxed and exported in.

    description: the frame in words. world2export: (4, 4) maps the map's world to it, for
    ``Params.world2aligned`` (None: the map's world itself). export2pose: (4, 4) maps it to the
    dataset's pose frame (the frame of its pose files), written as ``world_from_export``."""

    description: str
    export2pose: np.ndarray
    world2export: np.ndarray | None = None

    def params(self, params: Params) -> Params:
        """``params`` fitting boxes in this frame."""
        if self.world2export is None:
            return params
        return params.replace(world2aligned=tuple(tuple(float(v) for v in row) for row in self.world2export))


def ground_truth_export_frame(ground_truth: GroundTruthBoxes, world2file: np.ndarray) -> ExportFrame:
    """The ground truth's aligned frame (the recording's declared evaluation frame, as ScanNet's
    axisAlignment is); ``world2file`` (4, 4) maps the map's world to the ground truth's (pose) world."""
    return ExportFrame(
        f"{ground_truth.path.name} aligned frame (gravity_aligned.world_to_aligned: z up, floor at z = 0, x along the walls)",
        np.linalg.inv(ground_truth.file2aligned),
        ground_truth.file2aligned @ world2file,
    )


def scannet_export_frame(scene: ScanNetScene, ground_truth: GroundTruthBoxes | None = None) -> ExportFrame:
    """ScanNet maps are built in the scene's aligned frame (the reader aligns the poses); with a
    ground-truth file (its world the scan frame of the poses), they are boxed in its aligned frame."""
    if ground_truth is not None:
        return ground_truth_export_frame(ground_truth, np.linalg.inv(scene.scan2aligned))
    return ExportFrame("ScanNet axis-aligned frame (axisAlignment applied to the scan frame)", np.linalg.inv(scene.scan2aligned))


def gravity_export_frame(sequence: SevenScenesSequence | TumSequence, pose_frame: str) -> ExportFrame:
    """With ground truth, its aligned frame; without, the sequence's (gravity-aligned) world, or its
    pose frame (``pose_frame`` in words) when it is not aligned."""
    if sequence.ground_truth is not None:
        return ground_truth_export_frame(sequence.ground_truth, sequence.world2file)
    if np.allclose(sequence.world2file, np.eye(4)):
        return ExportFrame(pose_frame, sequence.world2file)
    return ExportFrame(
        "gravity-aligned world (the pose frame turned by the smallest rotation that takes up to +z)", sequence.world2file
    )


def seven_scenes_export_frame(sequence: SevenScenesSequence) -> ExportFrame:
    return gravity_export_frame(sequence, "7-Scenes pose frame")


def tum_export_frame(sequence: TumSequence) -> ExportFrame:
    return gravity_export_frame(sequence, "TUM groundtruth.txt frame")


def export_payload(objects: Sequence[MapObject], frame: ExportFrame, **facts: object) -> dict[str, object]:
    """An exported map: ``facts`` (scene, users, run...), the frame (``frame`` in words,
    ``world_from_export``), the served objects (``MapObject.confirmed``) under ``objects`` and the
    tentative ones under ``tentative`` (both as ``objects_json``)."""
    return {
        **facts,
        "frame": frame.description,
        "world_from_export": [[float(v) for v in row] for row in frame.export2pose],
        "objects": objects_json([o for o in objects if o.confirmed]),
        "tentative": objects_json([o for o in objects if not o.confirmed]),
    }
