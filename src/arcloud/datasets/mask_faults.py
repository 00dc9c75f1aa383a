"""Faults of a 2D instance-segmentation model, applied to exact ground-truth masks.

Exact masks (rendered, or ScanNet's ``instance-filt``) measure 3D association and fusion without the
detector's errors; ``MaskFaults`` puts the errors of a COCO instance-segmentation model on VGA frames
back, one instance at a time: borders grown or shrunk by a few pixels and ragged along their length,
instances missed in some frames (small ones more often), an instance cut in two detections, and
scores below 1.

Determinism: every draw for an instance of a frame comes from ``instance_rng(seed, frame_id,
instance_id)``, so a frame's detections do not depend on which user sends it, in which order, or on
the other instances of the frame.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from arcloud.core.types import Detection
from arcloud.errors import InvalidInput

#: Fields of ``MaskFaults`` that are probabilities.
_PROBABILITIES = ("drop_rate", "small_drop_rate", "split_rate")


@dataclass(frozen=True)
class MaskFaults:
    """What an instance-segmentation model gets wrong, per instance and frame. The defaults are about
    what a COCO model's masks look like on 640x480 indoor frames: borders 1-6 px off, one instance in
    ten missed (small ones up to about half the time), one in twenty split, scores 0.7-1.0;
    ``MaskFaults.none()`` changes nothing.

    Borders (pixels): the border moves by an offset drawn uniformly in ``[-shrink_px, grow_px]``
    (grown: it bleeds onto what lies behind; shrunk: thin parts vanish), plus a smooth ragged jitter of
    standard deviation ``ragged_px`` whose bumps are about ``ragged_period_px`` long.
    Misses: an instance is dropped with probability ``drop_rate``, and small ones (fewer than
    ``small_area_px`` pixels) also with up to ``small_drop_rate`` more, rising as their area falls to 0.
    Splits: an instance of at least ``split_min_area_px`` pixels is cut in two detections by a random
    line through its centre with probability ``split_rate`` (the smaller part scores lower).
    Scores: ``1 - score_jitter * |N(0, 1)|``, at least ``min_score``.
    """

    grow_px: float = 4.0
    shrink_px: float = 3.0
    ragged_px: float = 1.5
    ragged_period_px: float = 24.0
    drop_rate: float = 0.1
    small_area_px: int = 2500
    small_drop_rate: float = 0.4
    split_rate: float = 0.05
    split_min_area_px: int = 4000
    score_jitter: float = 0.15
    min_score: float = 0.05

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise InvalidInput(f"MaskFaults.{f.name}", "a finite number >= 0", repr(value))
        for name in (*_PROBABILITIES, "min_score"):
            if getattr(self, name) > 1:
                raise InvalidInput(f"MaskFaults.{name}", "a number in [0, 1]", repr(getattr(self, name)))
        if self.ragged_period_px < 2:
            raise InvalidInput("MaskFaults.ragged_period_px", "at least 2 px", repr(self.ragged_period_px))

    @classmethod
    def none(cls) -> MaskFaults:
        """Exact masks, every instance, score 1."""
        return cls(
            grow_px=0.0, shrink_px=0.0, ragged_px=0.0, drop_rate=0.0, small_drop_rate=0.0, split_rate=0.0, score_jitter=0.0
        )

    def replace(self, **changes: Any) -> MaskFaults:
        return dataclasses.replace(self, **changes)


#: Named fault sets (``parse_mask_faults``).
MASK_FAULT_PRESETS: dict[str, MaskFaults] = {"default": MaskFaults(), "none": MaskFaults.none()}


def parse_mask_faults(name: str, overrides: dict[str, str] | None = None) -> MaskFaults:
    """A preset of ``MASK_FAULT_PRESETS`` by name, with fields replaced by ``overrides`` (field -> text)."""
    if name not in MASK_FAULT_PRESETS:
        raise InvalidInput("faults", f"one of {sorted(MASK_FAULT_PRESETS)}", repr(name))
    faults = MASK_FAULT_PRESETS[name]
    fields = {f.name: f.type for f in dataclasses.fields(MaskFaults)}
    changes: dict[str, object] = {}
    for key, text in (overrides or {}).items():
        if key not in fields:
            raise InvalidInput("faults field", f"one of {sorted(fields)}", repr(key))
        try:
            changes[key] = int(text) if fields[key] == "int" else float(text)
        except ValueError:
            raise InvalidInput(f"MaskFaults.{key}", "a number", repr(text)) from None
    return faults.replace(**changes) if changes else faults


def instance_rng(seed: int, frame_id: str, instance_id: int) -> np.random.Generator:
    """The generator of one instance of one frame: the same in any process, thread and call order."""
    return np.random.default_rng([int(seed), zlib.crc32(frame_id.encode("utf-8")), int(instance_id)])


def faulty_detections(label: str, mask: np.ndarray, faults: MaskFaults, rng: np.random.Generator) -> list[Detection]:
    """What a model with ``faults`` reports for an instance whose exact (H, W) bool mask is ``mask``:
    nothing (missed), one detection, or two (split)."""
    area_px = int(np.count_nonzero(mask))
    if area_px == 0:
        return []
    # Every number is drawn up front, so that turning one fault off leaves the others' draws alone.
    u_drop, u_split, u_offset, split_angle, split_share = rng.random(5)
    score_noise = abs(rng.normal())
    small = max(0.0, 1.0 - area_px / faults.small_area_px) if faults.small_area_px > 0 else 0.0
    p_keep = (1.0 - faults.drop_rate) * (1.0 - faults.small_drop_rate * small)
    if u_drop >= p_keep:
        return []
    offset_px = -faults.shrink_px + u_offset * (faults.grow_px + faults.shrink_px)
    moved = move_border(mask, offset_px, faults.ragged_px, faults.ragged_period_px, rng)
    score = float(np.clip(1.0 - faults.score_jitter * score_noise, faults.min_score, 1.0))
    if u_split < faults.split_rate and area_px >= faults.split_min_area_px:
        first, second = split_mask(moved, math.pi * split_angle)
        if first.any() and second.any():
            if np.count_nonzero(first) < np.count_nonzero(second):
                first, second = second, first
            weaker = max(faults.min_score, score * (0.6 + 0.35 * split_share))
            return [Detection(label, score, first), Detection(label, float(weaker), second)]
    return [Detection(label, score, moved)] if moved.any() else []


def move_border(mask: np.ndarray, offset_px: float, ragged_px: float, period_px: float, rng: np.random.Generator) -> np.ndarray:
    """The (H, W) bool ``mask`` with its border moved out by ``offset_px`` (in when negative) plus a
    smooth random jitter of standard deviation ``ragged_px`` with bumps about ``period_px`` long.
    Zero offset and jitter give the mask back unchanged."""
    import cv2

    if offset_px == 0 and ragged_px == 0:
        return mask.copy()
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    margin = int(math.ceil(max(offset_px, 0.0) + 3 * ragged_px)) + 2
    r0, r1 = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + margin + 1, h)
    c0, c1 = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + margin + 1, w)
    crop = np.ascontiguousarray(mask[r0:r1, c0:c1], dtype=np.uint8)
    inside = cv2.distanceTransform(crop, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - crop, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # Signed distance of each pixel centre from the border (half a pixel beyond the nearest pixel
    # centre on the other side): > 0 outside, < 0 inside.
    signed_px = outside - inside
    signed_px -= np.float32(0.5) * np.sign(signed_px)
    threshold = np.full(crop.shape, offset_px, np.float32)
    if ragged_px > 0:
        ch, cw = crop.shape
        coarse = rng.normal(0.0, ragged_px, (int(ch / period_px) + 2, int(cw / period_px) + 2)).astype(np.float32)
        threshold += cv2.resize(coarse, (cw, ch), interpolation=cv2.INTER_CUBIC)
    out = np.zeros_like(mask, dtype=bool)
    out[r0:r1, c0:c1] = signed_px < threshold
    return out


def split_mask(mask: np.ndarray, angle_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """The (H, W) bool ``mask`` cut in two by the line through its centroid at ``angle_rad`` from the
    image's x axis: (pixels on one side, pixels on the other)."""
    rows, cols = np.nonzero(mask)
    normal = (-math.sin(angle_rad), math.cos(angle_rad))  # (x, y) across the line
    side = (cols - cols.mean()) * normal[0] + (rows - rows.mean()) * normal[1]
    first = np.zeros_like(mask, dtype=bool)
    second = np.zeros_like(mask, dtype=bool)
    first[rows[side >= 0], cols[side >= 0]] = True
    second[rows[side < 0], cols[side < 0]] = True
    return first, second


__all__ = [
    "MASK_FAULT_PRESETS",
    "MaskFaults",
    "faulty_detections",
    "instance_rng",
    "move_border",
    "parse_mask_faults",
    "split_mask",
]
