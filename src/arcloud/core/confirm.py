"""An object's confidence score, and when it is *confirmed*: served to clients by default.

The evidence, all kept with the object and summed over frames (so it does not depend on the order in
which frames arrive):
- ``n_frames``: frames whose detection fused into it, and the mean of their scores;
- ``label_purity``: the share of its voxels' occupancy whose voxel label is its label;
- ``n_missed``: frames that had it in view, mostly unoccluded, and detected nothing there. A detector
  that calls a magazine a laptop does so from a few angles only: real objects are detected in most of
  the frames that see them (0.8-0.95 on 7-Scenes), such phantoms in few (0.01-0.2);
- its geometry: a box the size of its class (``plausible``).

score = mean detection score x purity x (1 - exp(-n_frames / score_support_frames)) x detection rate,
times ``implausible_score_factor`` for a box no object of its class has. It ranks objects for AP.

Confirmed: at least ``confirm_min_frames`` frames, a detection rate of at least
``confirm_min_detection_rate``, a plausible box and a score of at least ``confirm_min_score`` — or, in
place of the score, detections in at least ``confirm_evidence_frames`` frames: a model may score a class
low (a desk seen in parts, a dark screen) and still find it in most of the frames that see it, which a
phantom never does for long. The rule
is evaluated at every refinement and whenever a frame misses the object, so a confirmed object whose
evidence weakens (it was carried out of the room, or it was a phantom seen long enough) becomes
tentative again. The number of devices is not evidence: in the multi-user protocol it reflects how the
walk was cut.

A *phantom* is forgotten: an object that at least ``discard_min_sightings`` frames saw, detected in fewer
than ``discard_max_detection_rate`` of them, cannot be confirmed without far more detections than a
real object gets; it is deleted (``core.step.count_misses``) rather than stored for ever, unless other
objects lie within its bounds (``core.step.stands_apart``). Should the detector call the place that
class again, a new object starts from that detection.
"""

from __future__ import annotations

import math

import numpy as np

from arcloud.core.floor import floor_height
from arcloud.core.types import MapObject, Params

#: Lengths are compared to the micrometre (rounded to this many decimals of a metre): heights worked out from
#: coordinates carry rounding that falls with the world's grid (a chair 0.3 m tall measured 0.30000000000000004
#: or 0.29999999999999993 m), so a rule must not turn on it.
EXACT_DIGITS = 6

#: Plausible sizes per class, metres: (longest footprint side min, max), (height min, max), thickness max
#: (the shorter footprint side; None: any). Generous: noisy voxel boxes of real objects must pass.
CLASS_SIZES_M: dict[str, tuple[tuple[float, float], tuple[float, float], float | None]] = {
    "chair": ((0.25, 1.4), (0.3, 1.6), None),
    "table": ((0.4, 4.5), (0.25, 1.4), None),
    "couch": ((0.7, 4.5), (0.3, 1.5), None),
    "tv": ((0.3, 3.0), (0.15, 2.0), 0.8),  # thickness: a screen on its stand
    "laptop": ((0.2, 0.55), (0.0, 0.5), 0.5),
}


def detection_rate(obj: MapObject, n_missed: int | None = None) -> float:
    """The share of the frames that saw the object in which it was detected (with ``n_missed`` misses
    instead of its own, when given)."""
    seen = obj.n_frames + (obj.n_missed if n_missed is None else n_missed)
    return obj.n_frames / seen if seen else 0.0


def is_phantom(obj: MapObject, params: Params, *, n_missed: int | None = None) -> bool:
    """Whether the object is a phantom to forget (see the module docstring), with ``n_missed`` misses
    instead of its own when given."""
    sightings = obj.n_frames + (obj.n_missed if n_missed is None else n_missed)
    return sightings >= params.discard_min_sightings and detection_rate(obj, n_missed) < params.discard_max_detection_rate


def plausible(obj: MapObject, params: Params) -> bool:
    """Whether the object's gravity-aligned box has a size its class can have; a floor-standing object
    whose floor is known must also not float far above it (its top is its height then)."""
    sizes = CLASS_SIZES_M.get(obj.label)
    if sizes is None or obj.obb is None:
        return obj.obb is not None
    (long_min, long_max), (height_min, height_max), thickness_max = sizes
    # To the micrometre (``EXACT_DIGITS``); Python floats: max and min of numpy scalars cost more.
    width, depth, height = (round(v, EXACT_DIGITS) for v in obj.obb.size.tolist())
    longest, shortest = max(width, depth), min(width, depth)
    if obj.label == "tv":  # a screen stands upright: its longest side may be its height
        longest = max(longest, height)
    if obj.label in params.floor_standing:
        floor_m = floor_height(obj.floor_votes, params)
        if floor_m is not None:
            top_m = float(params.gravity.up @ obj.obb.center) + height / 2
            height = round(top_m - floor_m, EXACT_DIGITS)
    return (
        long_min <= longest <= long_max
        and height_min <= height <= height_max
        and (thickness_max is None or shortest <= thickness_max)
    )


def evidence(obj: MapObject, params: Params, *, n_missed: int | None = None) -> tuple[float, bool]:
    """The object's (score, confirmed) from its evidence (see the module docstring); ``n_missed``
    replaces its own miss count (what one more miss would do)."""
    if obj.n_frames == 0:
        return 0.0, False
    is_plausible = plausible(obj, params)
    rate = detection_rate(obj, n_missed)
    support = 1.0 - math.exp(-obj.n_frames / params.score_support_frames)
    score = obj.score_sum / obj.n_frames * obj.label_purity * support * rate
    score = float(score if is_plausible else score * params.implausible_score_factor)
    confirmed = (
        obj.n_frames >= params.confirm_min_frames
        and rate >= params.confirm_min_detection_rate
        and is_plausible
        and (score >= params.confirm_min_score or obj.n_frames >= params.confirm_evidence_frames > 0)
    )
    return score, confirmed


def with_evidence(obj: MapObject, params: Params) -> MapObject:
    """The object with its score and confirmation brought up to date with its evidence."""
    score, confirmed = evidence(obj, params)
    return obj.replace(score=score, confirmed=confirmed)


def label_purity(weights: np.ndarray, voxel_labels: np.ndarray, label_index: int) -> float:
    """The share of the voxels' occupancy ``weights`` (N,) whose label (``voxel_labels`` (N,): the
    mode of each voxel's votes, ``votes.argmax(axis=1)``) is ``label_index``."""
    total = float(weights.sum())
    return float(weights[voxel_labels == label_index].sum() / total) if total > 0 else 0.0
