"""A detector that replays a ScanNet-layout scene's 2D ground truth, to measure 3D association and fusion
alone (no detector errors).

For a frame named N it reads ``instance-filt/N.png`` (8-bit instance ids, 0 = none) and
``label-filt/N.png`` (16-bit label ids), resizes both to the frame by nearest neighbour, and returns one
``Detection`` (score 1.0) per instance of arcloud's classes. An instance's class is the most frequent
label id under its mask, mapped through the labels tsv (``label_ids="scannet"``: ScanNet label ids, as
ScanNet and ``render_scannet`` write for v1 scenes; ``"nyu40"``: nyu40 ids, as it writes for v2 scenes).
By default the scene says which: the ``label_ids`` of its ``render.json`` (a render), else ``"scannet"``
(real ScanNet exports are made from the v1 annotation). Without ``label-filt`` the class comes from the
scene's instances (instance id = ``object_id + 1``).

With ``faults`` (``arcloud.datasets.mask_faults.MaskFaults``) each instance comes out as a model's would:
borders off by a few pixels, some instances missed, some split, scores below 1, drawn per frame id and
instance from ``fault_seed`` (so a frame's detections do not depend on processing order).

Importing this module registers the detector spec ``gt-masks[:OPTIONS][:SCENE_DIR]`` with
``arcloud.detectors`` (``gt_masks_options`` reads OPTIONS).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from typing import Any, Literal

import numpy as np

from arcloud.core.types import Detection, Frame
from arcloud.datasets.files import read_label_png, resize_nearest
from arcloud.datasets.mask_faults import MaskFaults, faulty_detections, instance_rng, parse_mask_faults
from arcloud.datasets.scannet import ScanNetScene
from arcloud.errors import DatasetError, InvalidInput

logger = logging.getLogger(__name__)

LabelIds = Literal["scannet", "nyu40"]
LABEL_IDS = ("scannet", "nyu40")


class GroundTruthMaskDetector:
    """``arcloud.ports.Detector`` replaying the 2D ground-truth masks of ``scene``, keyed by frame id.

    Safe to call from many threads (it only reads files). Frames without 2D labels give no detections
    (logged once per frame id) unless ``strict``, which raises ``DatasetError``. ``label_ids``: what
    ``label-filt`` holds (None: ``scene_label_ids(scene)``). ``faults`` (None: exact masks, score 1) are
    drawn per frame id and instance id from ``fault_seed``."""

    def __init__(
        self,
        scene: ScanNetScene,
        *,
        label_ids: LabelIds | None = None,
        min_mask_px: int = 64,
        strict: bool = False,
        faults: MaskFaults | None = None,
        fault_seed: int = 0,
    ) -> None:
        if label_ids is None:
            label_ids = scene_label_ids(scene)
        elif label_ids not in LABEL_IDS:
            raise InvalidInput("label_ids", "'scannet', 'nyu40' or None", repr(label_ids))
        if faults is not None and not isinstance(faults, MaskFaults):
            raise InvalidInput("faults", "a MaskFaults or None", type(faults).__name__)
        if not scene.has_2d_labels:
            raise DatasetError(f"{scene.root}: expected an instance-filt/ folder of 2D ground truth, got none")
        if scene.labels is None and not scene.instances:
            raise DatasetError(f"{scene.root}: expected a labels tsv or an aggregation to name the 2D labels, got neither")
        self.scene = scene
        self.label_ids = label_ids
        self.min_mask_px = int(min_mask_px)
        self.strict = strict
        self.faults = faults
        self.fault_seed = int(fault_seed)
        self._class_of_object = {inst.object_id + 1: inst.label for inst in scene.instances}

    def _class_of_label(self, label_id: int) -> str | None:
        labels = self.scene.labels
        if labels is None:
            return None
        return labels.class_of_label_id(label_id) if self.label_ids == "scannet" else labels.class_of_nyu40(label_id)

    def detect(self, frame: Frame) -> list[Detection]:
        root = self.scene.root
        instance_path = root / "instance-filt" / f"{frame.frame_id}.png"
        if not instance_path.is_file():
            if self.strict:
                raise DatasetError(f"{instance_path}: expected the 2D instance image of frame {frame.frame_id}, got none")
            logger.warning("no 2D ground truth for frame %s of %s; no detections", frame.frame_id, self.scene.scene_id)
            return []
        instances = resize_nearest(read_label_png(instance_path), frame.shape)
        label_path = root / "label-filt" / f"{frame.frame_id}.png"
        labels = resize_nearest(read_label_png(label_path), frame.shape) if label_path.is_file() else None

        ids, counts = np.unique(instances, return_counts=True)
        detections = []
        for instance_id, count in zip(ids.tolist(), counts.tolist()):
            if instance_id == 0 or count < self.min_mask_px:
                continue
            mask = instances == instance_id
            label = None
            if labels is not None and self.scene.labels is not None:
                values, votes = np.unique(labels[mask], return_counts=True)
                label = self._class_of_label(int(values[np.argmax(votes)]))
            elif instance_id in self._class_of_object:
                label = self._class_of_object[instance_id]
            if label is None:
                continue
            if self.faults is None:
                detections.append(Detection(label, 1.0, mask))
            else:
                rng = instance_rng(self.fault_seed, frame.frame_id, instance_id)
                detections += faulty_detections(label, mask, self.faults, rng)
        return detections


def scene_label_ids(scene: ScanNetScene) -> LabelIds:
    """What the scene's ``label-filt`` images hold: the ``label_ids`` its ``render.json`` records (a
    ``render_scannet`` output), else ``"scannet"`` (ScanNet's own exports)."""
    record_path = scene.root / "render.json"
    if not record_path.is_file():
        return "scannet"
    try:
        record = json.loads(record_path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{record_path}: expected a JSON render record ({exc})") from exc
    label_ids = record.get("label_ids", "scannet") if isinstance(record, dict) else None
    if label_ids not in LABEL_IDS:
        raise DatasetError(f"{record_path}: expected label_ids 'scannet' or 'nyu40', got {label_ids!r}")
    return label_ids


#: What the ``gt-masks`` spec accepts, for messages.
GT_MASKS_SPEC = "gt-masks[:faults=NAME[,seed=N][,FIELD=VALUE...]][:SCENE_DIR]"


def gt_masks_options(argument: str) -> tuple[dict[str, Any], str]:
    """The text after ``gt-masks:`` -> (``GroundTruthMaskDetector`` options, scene folder or "").

    OPTIONS are comma-separated ``key=value`` items before the folder: ``faults=NAME`` (a preset of
    ``MASK_FAULT_PRESETS``: ``default``, ``none``), ``seed=N`` (``fault_seed``), and any field of
    ``MaskFaults`` (``drop_rate=0.2``, on ``default`` unless ``faults=`` names another). Examples:
    ``faults=default``, ``faults=default,seed=3:/data/scene0000_00``, ``/data/scene0000_00``."""
    head, _, rest = argument.partition(":")
    items = [item.partition("=") for item in head.split(",")] if head else []
    fields = {f.name for f in dataclasses.fields(MaskFaults)}
    if not items or not all(eq and key in fields | {"faults", "seed"} for key, eq, _ in items):
        return {}, argument  # no options: all of it is the folder
    values = {key: value for key, _, value in items}
    options: dict[str, object] = {}
    if "seed" in values:
        try:
            options["fault_seed"] = int(values.pop("seed"))
        except ValueError:
            raise InvalidInput("detector spec", f"{GT_MASKS_SPEC} with an integer seed", repr(argument)) from None
        if not values:
            raise InvalidInput("detector spec", f"{GT_MASKS_SPEC}: seed= with faults= or a fault field", repr(argument))
    if values:
        options["faults"] = parse_mask_faults(values.pop("faults", "default"), values)
    return options, rest


def gt_masks_detector(argument: str, **options: object) -> GroundTruthMaskDetector:
    """The ``gt-masks[:OPTIONS]:SCENE_DIR`` detector spec (``arcloud.detectors.make_detector``): replay
    the 2D ground truth of the ScanNet-layout scene in SCENE_DIR, with the faults OPTIONS name
    (``gt_masks_options``); ``options`` go to the detector too."""
    from arcloud.datasets.scannet import load_scannet_scene

    spec_options, scene_dir = gt_masks_options(argument)
    if not scene_dir:
        raise InvalidInput(
            "detector spec", f"{GT_MASKS_SPEC} with a ScanNet-layout scene folder", f"gt-masks:{argument} with no folder"
        )
    return GroundTruthMaskDetector(load_scannet_scene(scene_dir), **{**spec_options, **options})


def register_gt_masks_detector() -> None:
    """Make ``make_detector("gt-masks:...")`` build ``gt_masks_detector``."""
    from arcloud.detectors.factory import register_detector

    register_detector("gt-masks", gt_masks_detector, replace=True)


__all__ = [
    "GT_MASKS_SPEC",
    "LABEL_IDS",
    "GroundTruthMaskDetector",
    "gt_masks_detector",
    "gt_masks_options",
    "register_gt_masks_detector",
    "scene_label_ids",
]
