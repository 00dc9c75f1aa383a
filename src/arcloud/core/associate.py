"""Association of a frame's detections with the visible objects: the Hungarian method on common voxels.

The cost of pairing detection d with object o is ``1 - overlap(d, o)`` where

    overlap = (|voxels of the smaller set on the other's| + |those only beside it| / 2) / |the smaller set|

"beside": within ``association_tolerance_voxels`` along every axis (two observations of one surface a few
centimetres apart still meet; ``core.voxels.shared_count``). Coarsened keys once gave the tolerance, and
gave it only where two voxels fell in one aligned pair of the grid (sheets one voxel apart shared all or
nothing), so the map depended on where the world's grid fell; a voxel beside counts a half, what it shared
on average over the grid's phases. Counted whole, a fragment of a few voxels read 1.0 against any detection
around it, and a laptop's detections went to a 5-voxel laptop piece rather than the larger object they
covered (simulated office-01). Dividing by the smaller set (the overlap coefficient)
rather than the union (IoU) is deliberate: one frame sees only part of an object, so a correct detection
of a large fused object has a small IoU but nearly all of its voxels inside the object. Pairs with an
overlap below ``association_min_overlap`` are gated (never matched). A class mismatch adds
``class_mismatch_penalty``; with ``class_aware`` (the default) a mismatched pair is also gated unless
its overlap reaches ``class_mismatch_min_overlap`` — the overlap coefficient of a small object resting on
a large one (a laptop on a table) is high, so without this the laptop's detections feed the table;
label confusion on one physical object, by contrast, overlaps it almost entirely.
Every entry of the cost matrix is finite: empty sets give overlap 0.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from arcloud.core.types import CLASS_INDEX, MapObject, Params
from arcloud.core.voxels import keys_extent, shared_count, unpack_keys

GATED_COST = 1e3  # finite stand-in for "impossible", so linear_sum_assignment never sees inf or NaN
#: A detection left without an object costs what a pair sharing nothing would: every pair the gates let through
#: costs less (overlap >= ``association_min_overlap``), so a pair is made where it shares something, and the
#: matching maximises the overlap shared, never the number of pairs.
UNMATCHED_COST = 1.0


def index_bounds(keys: np.ndarray) -> np.ndarray:
    """(2, 3) min and max voxel indices of non-empty keys."""
    return np.array(keys_extent(keys))


def index_bounds_of_sets(sets: Sequence[np.ndarray]) -> np.ndarray:
    """(S, 2, 3) ``index_bounds`` of each of S >= 1 non-empty key sets, for all at once: the keys
    concatenated and unpacked, each index reduced set by set (``reduceat``)."""
    starts = list(itertools.accumulate((s.size for s in sets[:-1]), initial=0))  # a few ints: no numpy call
    indices = np.ascontiguousarray(unpack_keys(np.concatenate(sets)).T)  # (3, N): rows reduce fastest
    return np.stack((np.minimum.reduceat(indices, starts, axis=1).T, np.maximum.reduceat(indices, starts, axis=1).T), axis=1)


def stored_index_bounds_of(objects: Sequence[MapObject], voxel_size_m: float) -> list[np.ndarray | None]:
    """``stored_index_bounds`` of each object."""
    return [stored_index_bounds(o, voxel_size_m) for o in objects]


def stored_index_bounds(obj: MapObject, voxel_size_m: float) -> np.ndarray | None:
    """(2, 3) voxel-index bounds from the bounds refinement stored with the object (exact while its
    voxels are unchanged), or None when it has none."""
    if obj.bounds is None:
        return None
    lo = np.floor(obj.bounds.min / voxel_size_m + 1e-6).astype(np.int64)
    hi = np.floor(obj.bounds.max / voxel_size_m - 1e-6).astype(np.int64)
    return np.array((lo, hi))


def known_or_computed_bounds(
    sets: Sequence[np.ndarray], live: Sequence[int], known: Sequence[np.ndarray | None] | None
) -> np.ndarray:
    """(len(live), 2, 3) voxel-index bounds of ``sets[live]`` (non-empty): the known ones where given."""
    missing = [i for i in live if known is None or known[i] is None]
    if not missing:
        return np.array([known[i] for i in live])  # type: ignore[index]  # known holds every live one
    computed = dict(zip(missing, index_bounds_of_sets([sets[i] for i in missing])))
    return np.array([computed[i] if i in computed else known[i] for i in live])  # type: ignore[index]  # known when not computed


def overlap_matrix(
    sets_a: Sequence[np.ndarray],
    sets_b: Sequence[np.ndarray],
    tolerance_voxels: int,
    *,
    bounds_a: Sequence[np.ndarray | None] | None = None,
    bounds_b: Sequence[np.ndarray | None] | None = None,
    pairs_wanted: np.ndarray | None = None,
) -> np.ndarray:
    """(A, B) overlap coefficient in [0, 1] of key sets within ``tolerance_voxels`` (see the module docstring).

    Pairs whose voxel bounds are apart are 0 without looking at their keys: in a frame, most
    detection/object pairs are far apart. ``bounds_a`` and ``bounds_b`` may give known (2, 3) voxel-index
    bounds of the sets (None entries are computed); ``pairs_wanted`` (A, B) bool limits the pairs computed."""
    overlap = np.zeros((len(sets_a), len(sets_b)))
    live_a = [i for i, s in enumerate(sets_a) if s.size]
    live_b = [j for j, s in enumerate(sets_b) if s.size]
    if not live_a or not live_b:
        return overlap
    bounds_a_arr = known_or_computed_bounds(sets_a, live_a, bounds_a)
    bounds_b_arr = known_or_computed_bounds(sets_b, live_b, bounds_b)
    reach = tolerance_voxels
    touching = np.all(
        (bounds_a_arr[:, None, 0] <= bounds_b_arr[None, :, 1] + reach)
        & (bounds_b_arr[None, :, 0] <= bounds_a_arr[:, None, 1] + reach),
        axis=2,
    )
    if pairs_wanted is not None:
        touching &= pairs_wanted[np.ix_(live_a, live_b)]
    symmetric = sets_b is sets_a  # one list against itself (the merge pass): each pair once
    for i, j in zip(*np.nonzero(touching)):
        a, b = live_a[i], live_b[j]
        if symmetric and b < a and touching[j, i]:
            overlap[a, b] = overlap[b, a]
            continue
        overlap[a, b] = overlap_coefficient(sets_a[a], sets_b[b], reach, bounds_a_arr[i], bounds_b_arr[j])
    return overlap


def overlap_coefficient(
    keys_a: np.ndarray, keys_b: np.ndarray, reach: int, bounds_a: np.ndarray | None = None, bounds_b: np.ndarray | None = None
) -> float:
    """The share of the smaller of two non-empty key sets that the other covers (``shared_count``; of sets of one
    size, the larger share: the same whichever is given first). ``bounds_a``, ``bounds_b``: their known
    (2, 3) voxel-index bounds."""
    lo_a, hi_a = keys_extent(keys_a) if bounds_a is None else bounds_a
    lo_b, hi_b = keys_extent(keys_b) if bounds_b is None else bounds_b
    if keys_a.size < keys_b.size:
        return shared_count(keys_a, keys_b, reach, (lo_a, hi_a, lo_b, hi_b)) / keys_a.size
    if keys_b.size < keys_a.size:
        return shared_count(keys_b, keys_a, reach, (lo_b, hi_b, lo_a, hi_a)) / keys_b.size
    return (
        max(
            shared_count(keys_a, keys_b, reach, (lo_a, hi_a, lo_b, hi_b)),
            shared_count(keys_b, keys_a, reach, (lo_b, hi_b, lo_a, hi_a)),
        )
        / keys_a.size
    )


def association_cost(overlap: np.ndarray, labels_a: Sequence[int], labels_b: Sequence[int], params: Params) -> np.ndarray:
    """(A, B) finite cost: 1 - overlap, plus the class term; gated pairs get ``GATED_COST``."""
    mismatch = np.asarray(labels_a)[:, None] != np.asarray(labels_b)[None, :]
    cost = 1.0 - overlap + params.class_mismatch_penalty * mismatch
    gated = overlap < params.association_min_overlap
    if params.class_aware:
        gated |= mismatch & (overlap < params.class_mismatch_min_overlap)
    return np.where(gated, GATED_COST, cost)


def hungarian_match(cost: np.ndarray) -> list[tuple[int, int]]:
    """Minimum-cost pairs (row, col) from ``linear_sum_assignment``, where each row may instead stay unpaired at
    ``UNMATCHED_COST``; gated pairs are never made. Without that choice the assignment pairs as many rows as it
    can first: a detection of one desk that touches a neighbour's object would push the detection of that object
    onto a weaker pair (two monitors side by side welded, the third never made)."""
    if cost.size == 0:
        return []
    n_rows, n_cols = cost.shape
    padded = np.full((n_rows, n_cols + n_rows), GATED_COST)
    padded[:, :n_cols] = cost
    padded[np.arange(n_rows), n_cols + np.arange(n_rows)] = UNMATCHED_COST  # row r's own "unpaired"
    rows, cols = linear_sum_assignment(padded)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if c < n_cols and cost[r, c] < GATED_COST]


@dataclass(frozen=True, slots=True)
class Association:
    """pairs: (detection index, object index). unmatched: detection indices without an object, in
    order. rivals: matched detection index -> other objects of its label that it also covers (a mask
    spanning two TVs side by side): fusing all of it into its match would weld them together. For
    ``split_classes`` (chairs, TVs and laptops stand side by side in rooms, while a table or a couch
    that a detection spans with another of its kind is more often one object first seen in parts), and
    for any class when the two are held apart (``core.fusion.held_apart``: two desks pushed together)."""

    pairs: list[tuple[int, int]]
    unmatched: list[int]
    rivals: dict[int, list[int]]


def associate(
    detection_keys: Sequence[np.ndarray],
    detection_labels: Sequence[int],
    object_keys: Sequence[np.ndarray],
    object_labels: Sequence[int],
    params: Params,
    *,
    object_bounds: Sequence[np.ndarray | None] | None = None,
    object_frames: Sequence[int] | None = None,
    held_apart: np.ndarray | None = None,
) -> Association:
    """Match detections to objects. ``object_bounds``: known (2, 3) voxel-index bounds (see
    overlap_matrix). ``object_frames``: how many frames each object was seen in; only objects seen in
    at least ``split_min_frames`` are rivals (a younger one is more likely a fragment to merge).
    ``held_apart``: (O, O) bool, pairs of objects held apart: rivals whatever their class."""
    overlap = overlap_matrix(detection_keys, object_keys, params.association_tolerance_voxels, bounds_b=object_bounds)
    pairs = hungarian_match(association_cost(overlap, detection_labels, object_labels, params))
    matched = {d for d, _ in pairs}
    established = (
        np.ones(len(object_keys), bool) if object_frames is None else np.asarray(object_frames) >= params.split_min_frames
    )
    labels = np.asarray(object_labels)
    rivals: dict[int, list[int]] = {}
    splittable = {CLASS_INDEX[name] for name in params.split_classes}
    for d, o in pairs:
        apart = None if held_apart is None or not held_apart[o].any() else held_apart[o]
        if detection_labels[d] not in splittable and apart is None:
            continue
        rival = established if detection_labels[d] in splittable else np.zeros(len(object_keys), bool)
        if apart is not None:
            rival = rival | apart
        covered = np.flatnonzero((overlap[d] >= params.association_min_overlap) & (labels == detection_labels[d]) & rival)
        others = [int(j) for j in covered if j != o]
        if others:
            rivals[d] = others
    return Association(pairs, [d for d in range(len(detection_keys)) if d not in matched], rivals)
