"""Fusion of detections into objects: occupancy weights, per-voxel label votes and mean colours, one
instance per voxel, merging of duplicates, and the object's label and confidence score."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from arcloud.core.associate import index_bounds_of_sets, overlap_matrix, stored_index_bounds_of
from arcloud.core.floor import add_votes
from arcloud.core.types import CLASS_INDEX, CLASSES, N_CLASSES, MapObject, Params, VoxelDetection, empty_object
from arcloud.core.voxels import (
    coarsen_keys,
    coarsen_keys_unsorted,
    in_sorted,
    keys_extent,
    mean_colors,
    sorted_unique,
    unpack_keys,
)
from arcloud.core.walls import add_wall_votes

_NO_VOXEL_COLORS = np.empty((0, 3), np.uint8)
_NO_VOXEL_COLORS.flags.writeable = False
_ZERO = np.float32(0.0)
_NO_CORNER = np.full(3, np.nan)  # the corner of a missing box (box_containment)
_NO_CORNER.flags.writeable = False

#: A detection votes its score rounded to this step: sums of such votes are exact in float32 (up to 2**18
#: per voxel), so the votes of a voxel do not depend on the order of its frames, and the store keeps them
#: as integers (``stores.codec``: 2 bytes a vote instead of 4). The label of a voxel is the mode of its
#: votes, which a step this fine (scores are 0.25-1) changes only in near ties.
VOTE_STEP = 2.0**-6


def vote_of(score: float) -> np.float32:
    """The vote a detection of ``score`` casts for its label: the score to the nearest ``VOTE_STEP``."""
    return np.float32(round(score / VOTE_STEP) * VOTE_STEP)


def union_voxels(
    a: MapObject,
    keys_b: np.ndarray,
    weights_b: np.ndarray,
    seen_b: np.ndarray,
    votes_b: np.ndarray,
    colors_b: np.ndarray | None = None,
) -> MapObject:
    """``a`` with a sparse voxel set added: weights, seen counts and votes of a voxel in both add up; its
    colours ((N_b, 3) uint8, None: unknown) average, weighted by the weights (``_union_colors``)."""
    keys, weights, seen, votes, colors, _, _ = _union_arrays(a, keys_b, weights_b, seen_b, votes_b, colors_b)
    return a.replace(keys=keys, weights=weights, seen=seen, votes=votes, colors=colors)


def _union_arrays(
    a: MapObject, keys_b: np.ndarray, weights_b: np.ndarray, seen_b: np.ndarray, votes_b: np.ndarray, colors_b: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """The new (writable) keys, weights, seen, votes and colours of ``union_voxels``, and where ``a``'s
    keys (N_a,) and ``keys_b`` (N_b,) sit in them."""
    keys = sorted_unique(np.concatenate((a.keys, keys_b)))
    weights = np.zeros(keys.size, np.float32)
    seen = np.zeros(keys.size, np.float32)
    votes = np.zeros((keys.size, N_CLASSES), np.float32)
    # a's keys are unique: each lands on a zero, and x + 0 is 0 + x bit for bit (-0.0 becomes +0.0
    # either way), so a's values are written, not gathered and added.
    at_a = np.searchsorted(keys, a.keys)
    weights[at_a] = a.weights + _ZERO
    seen[at_a] = a.seen_counts + _ZERO
    votes[at_a] = a.votes + _ZERO
    at_b = np.searchsorted(keys, keys_b)
    weights[at_b] += weights_b
    seen[at_b] += seen_b
    votes[at_b] += votes_b
    colors = _union_colors(a, weights_b, colors_b, at_a, at_b, weights)
    return keys, weights, seen, votes, colors, at_a, at_b


def _union_colors(
    a: MapObject, weights_b: np.ndarray, colors_b: np.ndarray | None, at_a: np.ndarray, at_b: np.ndarray, weights: np.ndarray
) -> np.ndarray | None:
    """The colours of a union whose summed ``weights`` hold ``a``'s voxels at ``at_a`` and the added ones
    at ``at_b``: each voxel's mean of both sides' colours weighted by their weights, rounded half up.
    Unknown (None) when a side with voxels has none: a mean over part of the evidence would pass for
    one over all of it."""
    colors_a = _NO_VOXEL_COLORS if at_a.size == 0 else a.colors  # an empty side knows all its colours
    colors_b = _NO_VOXEL_COLORS if at_b.size == 0 else colors_b
    if colors_a is None or colors_b is None:
        return None
    # Both sides' weighted colours, channel first, summed per voxel: one bincount for the three channels,
    # channel c's voxel k in bin c * N + k (each bin adds its terms in their order, as one bincount per
    # channel does).
    n = weights.size
    at = np.concatenate((at_a, at_b))
    weighted = np.concatenate(
        (np.multiply(colors_a.T, a.weights, dtype=np.float64), np.multiply(colors_b.T, weights_b, dtype=np.float64)), axis=1
    )
    sums = np.bincount(np.concatenate((at, at + n, at + 2 * n)), weights=weighted.reshape(-1), minlength=3 * n).reshape(3, n)
    return mean_colors(sums, np.where(weights > 0, weights, 1))


def fuse_detection(
    obj: MapObject, det: VoxelDetection, device_id: str, visible: np.ndarray | None = None, floor_vote: int | None = None
) -> MapObject:
    """The object with one more observation: each voxel the detection covers gains weight 1, a vote
    of the detection's score times its view weight (``vote_of``) for its label and the detection's colour into its mean; every voxel
    covered or ``visible`` ((N,) bool over the object's voxels: in view and not occluded in this frame)
    is counted as seen once more. Seen again, it has not been seen gone since (``n_gone`` 0).
    ``floor_vote``: the height bin of the floor this frame saw under the object (``core.floor``); the
    detection's ``wall_vote`` joins the object's (``core.walls``)."""
    det_votes = np.zeros((det.keys.size, N_CLASSES), np.float32)
    det_votes[:, det.label_index] = max(vote_of(det.score * det.view_weight), np.float32(VOTE_STEP))
    ones = np.ones(det.keys.size, np.float32)
    keys, weights, seen, votes, colors, at_obj, at_det = _union_arrays(obj, det.keys, ones, ones, det_votes, det.colors)
    if visible is not None and visible.any():
        # Visible voxels of the object that the detection did not cover: seen, not hit.
        covered = np.zeros(keys.size, bool)
        covered[at_det] = True
        seen[at_obj[visible & ~covered[at_obj]]] += 1
    return obj.replace(
        keys=keys,
        weights=weights,
        seen=seen,
        votes=votes,
        colors=colors,
        floor_votes=obj.floor_votes if floor_vote is None else add_votes(obj.floor_votes, {floor_vote: 1}),
        wall_votes=obj.wall_votes if det.wall_vote is None else add_wall_votes(obj.wall_votes, dict([det.wall_vote])),
        n_frames=obj.n_frames + 1,
        devices=obj.devices | {device_id},
        score_sum=obj.score_sum + det.score,
        n_gone=0,
    )


def split_detection(det: VoxelDetection, owners: Sequence[np.ndarray], factor: int) -> list[VoxelDetection]:
    """The detection's voxels shared out among objects (``owners``: their keys; the first is the one it
    was matched to): a voxel goes to a later owner when its coarse voxel (``factor`` times coarser) is
    that owner's and not the first's; a voxel in no owner's coarse voxels goes to the owner whose voxel
    bounds are nearest (the first on ties); the rest go to the first. One part per owner, in order
    (possibly empty); the first keeps the detection's wall vote."""
    coarse = coarsen_keys_unsorted(det.keys, factor)
    owner = np.zeros(det.keys.size, np.int64)
    taken = in_sorted(coarse, coarsen_keys(owners[0], factor))
    for i, keys in enumerate(owners[1:], start=1):
        mine = ~taken & in_sorted(coarse, coarsen_keys(keys, factor))
        owner[mine] = i
        taken |= mine
    if not taken.all():
        free = np.flatnonzero(~taken)
        ijk = unpack_keys(det.keys[free])
        gaps = []
        for keys in owners:
            if keys.size == 0:
                gaps.append(np.full(free.size, np.inf))
                continue
            lo, hi = keys_extent(keys)
            gaps.append(np.linalg.norm(np.maximum(lo - ijk, 0) + np.maximum(ijk - hi, 0), axis=1))
        owner[free] = np.argmin(np.stack(gaps), axis=0)
    parts = [owner == i for i in range(len(owners))]
    return [
        VoxelDetection(
            det.label_index, det.score, det.keys[p], None if det.colors is None else det.colors[p], det.view_weight, vote
        )
        for p, vote in zip(parts, [det.wall_vote] + [None] * (len(parts) - 1))
    ]


def new_object(object_id: int, det: VoxelDetection, device_id: str, now_s: float, floor_vote: int | None = None) -> MapObject:
    """A new object made of one detection."""
    fresh = empty_object(object_id).replace(created_at_s=now_s)
    return fuse_detection(fresh, det, device_id, floor_vote=floor_vote)


def keeper_rank(obj: MapObject) -> tuple[float, int]:
    """Which of objects that are one is kept when they merge: the most occupancy weight, then the older id."""
    return float(obj.weights.sum()), -obj.id


def merge_objects(keep: MapObject, absorbed: MapObject) -> MapObject:
    """``keep`` with ``absorbed``'s voxels and evidence added (two observations of one object). Misses are
    not added: pieces of one object are in view in the same frames, and a frame that detected one piece and
    missed the other did not miss the object; the merged object keeps the misses of the piece with the most
    occupancy weight (``keeper_rank``, as the merge pass picks its keeper; either order gives the same). Added, a
    fragment's misses sank the object it joined (a desk seen with its neighbour, then alone: office-00)."""
    merged = union_voxels(keep, absorbed.keys, absorbed.weights, absorbed.seen_counts, absorbed.votes, absorbed.colors)
    return merged.replace(
        floor_votes=add_votes(keep.floor_votes, absorbed.floor_votes),
        wall_votes=add_wall_votes(keep.wall_votes, absorbed.wall_votes),
        n_frames=keep.n_frames + absorbed.n_frames,
        n_missed=max((keep, absorbed), key=keeper_rank).n_missed,
        n_gone=min(keep.n_gone, absorbed.n_gone),  # seen gone since the later of their last sightings
        devices=keep.devices | absorbed.devices,
        score_sum=keep.score_sum + absorbed.score_sum,
        created_at_s=min(keep.created_at_s, absorbed.created_at_s),
        apart={i: n for i, n in add_votes(keep.apart, absorbed.apart).items() if i not in (keep.id, absorbed.id)},
        spanned={i: n for i, n in add_votes(keep.spanned, absorbed.spanned).items() if i not in (keep.id, absorbed.id)},
    )


def keep_voxels(obj: MapObject, keep: np.ndarray) -> MapObject:
    """The object with only the voxels where ``keep`` (N,) is True."""
    seen = None if obj.seen is None else obj.seen[keep]
    colors = None if obj.colors is None else obj.colors[keep]
    return obj.replace(keys=obj.keys[keep], weights=obj.weights[keep], votes=obj.votes[keep], seen=seen, colors=colors)


def object_label_index(obj: MapObject, voxel_labels: np.ndarray | None = None) -> int:
    """The mode of the voxels' labels (each voxel's label is the mode of its votes: ``voxel_labels``
    (N,) when the caller has them), weighted by occupancy; -1 for an object without voxels."""
    if obj.keys.size == 0:
        return -1
    if voxel_labels is None:
        voxel_labels = obj.votes.argmax(axis=1)
    return int(np.bincount(voxel_labels, weights=obj.weights, minlength=N_CLASSES).argmax())


def label_votes(obj: MapObject) -> dict[str, float]:
    """The object's label votes summed over its voxels, by class name, most first (ties in ``CLASSES`` order);
    classes without a vote left out. Each detection voted its score (times how well its view saw the object) in
    every voxel it covered. The label is the class most of the object's occupancy votes for, voxel by voxel
    (``object_label_index``): usually, not always, the first class here."""
    totals = obj.votes.sum(axis=0, dtype=np.float64)
    order = sorted(range(N_CLASSES), key=lambda i: -totals[i])
    return {CLASSES[i]: float(totals[i]) for i in order if totals[i] > 0}


def current_label_index(obj: MapObject, changed: bool = True) -> int:
    """The object's label index: recomputed from its votes when it changed since its last refinement,
    else the one refinement stored."""
    if not changed and obj.label in CLASS_INDEX:
        return CLASS_INDEX[obj.label]
    return object_label_index(obj)


def seen_apart(a: MapObject, b: MapObject, params: Params) -> bool:
    """Whether frames detected ``a`` and ``b`` as two instances in one view (``core.step.mark_apart``)
    often enough (``apart_min_frames``; 0: never) to keep them two."""
    frames = max(a.apart.get(b.id, 0), b.apart.get(a.id, 0))
    return params.apart_min_frames > 0 and frames >= params.apart_min_frames


def held_apart(a: MapObject, b: MapObject, params: Params) -> bool:
    """Whether ``a`` and ``b`` are kept two for now: seen apart (``seen_apart``), or seen apart in fewer frames
    than that but in more than the frames whose one mask covered both (``spanned_frames``). Two desks pushed
    together, seen apart twice and then under one mask, stay two (the mask is shared out and counts a span) until
    masks have spanned them as often as frames parted them. An object seen in one frame only (the split that
    made it: a table's leg cut off its mask by the detector) is not held: nothing but that split speaks for it.
    Nor are ``split_classes``: a mask over two of them seen in ``split_min_frames`` is always shared out
    (``core.associate.Association``), so masks over both could never join a detector's split of one TV."""
    if params.apart_min_frames == 0:
        return False
    frames = max(a.apart.get(b.id, 0), b.apart.get(a.id, 0))
    if frames == 0 or frames >= params.apart_min_frames:
        return frames > 0
    if a.label in params.split_classes or b.label in params.split_classes or min(a.n_frames, b.n_frames) < 2:
        return False
    return spanned_frames(a, b) < frames


def spanned_frames(a: MapObject, b: MapObject) -> int:
    """Frames whose one mask covered ``a`` and ``b``: each is counted once, on the object the mask matched."""
    return a.spanned.get(b.id, 0) + b.spanned.get(a.id, 0)


def find_duplicates(
    objects: Sequence[MapObject],
    params: Params,
    changed: Sequence[bool] | None = None,
    apart_now: Sequence[tuple[int, int]] = (),
    joined: Sequence[tuple[int, int]] = (),
) -> list[tuple[int, int]]:
    """Pairs (keep, absorb) of indices of objects that are one physical object: same label and an
    overlap >= ``merge_min_overlap``, or pieces of one object that a mask spanned (``joined``: id pairs,
    ``core.step.joined_by_masks``), unless they are held apart (``held_apart``: frames saw them apart) or
    the current frame saw them apart (``apart_now``: id pairs, smaller first). Chains resolve to one keeper
    per group (the most observed), and a chain never joins two objects held apart.
    With ``changed``, only pairs with at least one changed object are considered (the others were
    checked when they last changed)."""
    if len(objects) < 2:
        return []
    flags = np.ones(len(objects), bool) if changed is None else np.asarray(changed, bool)
    labels = np.array([current_label_index(o, bool(c)) for o, c in zip(objects, flags)])
    wanted = (labels[:, None] == labels[None, :]) & (flags[:, None] | flags[None, :])
    np.fill_diagonal(wanted, False)
    if not wanted.any():
        return []
    keys = [o.keys for o in objects]
    # Unchanged objects' stored bounds are exact; only changed ones need their keys unpacked (once,
    # here, rather than once for each side of the matrix).
    bounds = stored_index_bounds_of([o for o, c in zip(objects, flags) if not c], params.voxel_size_m)
    unchanged = iter(bounds)
    bounds = [next(unchanged) if not c else None for c in flags]
    unknown = [i for i, (o, b) in enumerate(zip(objects, bounds)) if b is None and o.keys.size]
    if unknown:
        for i, b in zip(unknown, index_bounds_of_sets([objects[i].keys for i in unknown])):
            bounds[i] = b
    overlap = overlap_matrix(
        keys, keys, params.association_tolerance_voxels, bounds_a=bounds, bounds_b=bounds, pairs_wanted=wanted
    )
    split = {CLASS_INDEX[name] for name in params.split_classes}  # tables, couches: seen in parts
    parts = np.array([label not in split for label in labels.tolist()], bool)
    min_overlap = np.where(parts[:, None], params.merge_min_overlap_parts, params.merge_min_overlap)
    same = wanted & ((overlap >= min_overlap) | (box_containment(objects) >= params.merge_min_box_containment))
    if joined:
        index = {o.id: i for i, o in enumerate(objects)}
        for a, b in joined:
            if a in index and b in index:
                i, j = index[a], index[b]
                same[i, j] = same[j, i] = wanted[i, j]
    np.fill_diagonal(same, False)
    parent = list(range(len(objects)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    members_of = {i: [i] for i in range(len(objects))}
    now = set(apart_now)
    for i, j in zip(*np.nonzero(np.triu(same))):
        ri, rj = root(int(i)), root(int(j))
        if ri == rj or any(
            held_apart(objects[a], objects[b], params) or id_pair(objects[a].id, objects[b].id) in now
            for a in members_of[ri]
            for b in members_of[rj]
        ):
            continue
        parent[ri] = rj
        members_of[rj] += members_of.pop(ri)
    groups: dict[int, list[int]] = {}
    for i in range(len(objects)):
        groups.setdefault(root(i), []).append(i)
    pairs: list[tuple[int, int]] = []
    for members in groups.values():
        if len(members) > 1:
            keeper = max(members, key=lambda i: keeper_rank(objects[i]))
            pairs.extend((keeper, m) for m in members if m != keeper)
    return pairs


def id_pair(a: int, b: int) -> tuple[int, int]:
    """Two object ids as a pair, the smaller first (how pairs of objects are keyed: apart, spanned, joined)."""
    return (a, b) if a < b else (b, a)


def box_containment(objects: Sequence[MapObject]) -> np.ndarray:
    """(N, N): the share of the smaller object's box volume inside the other's box (0 without boxes).

    Parts of one object seen from different sides (a chair's back from behind, its seat from the front)
    share few voxels but sit in one box."""
    n = len(objects)
    lo = np.concatenate([o.aabb.min if o.aabb is not None else _NO_CORNER for o in objects]).reshape(n, 3)
    hi = np.concatenate([o.aabb.max if o.aabb is not None else _NO_CORNER for o in objects]).reshape(n, 3)
    # np.clip(x, 0, None) is np.maximum(x, 0) and np.prod np.multiply.reduce, called without their wrappers.
    inter = np.multiply.reduce(np.maximum(np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None]), 0), axis=2)
    volume = np.multiply.reduce(hi - lo, axis=1)
    smaller = np.minimum(volume[:, None], volume[None])
    out = np.divide(inter, smaller, out=np.zeros((n, n)), where=np.isfinite(smaller) & (smaller > 0))
    return out if np.isfinite(out).all() else np.nan_to_num(out)  # nan_to_num leaves finite values as they are


def resolve_conflicts(objects: Sequence[MapObject]) -> list[MapObject]:
    """One instance per voxel: a voxel held by several objects stays with the one that holds it with
    the highest weight (ties: the lower id) and leaves the others."""
    if len(objects) < 2:
        return list(objects)
    keys = np.concatenate([o.keys for o in objects])
    ordered = np.sort(keys)
    if not (ordered[1:] == ordered[:-1]).any():
        return list(objects)  # no voxel is held twice (the common case): skip the three-key sort
    weights = np.concatenate([o.weights for o in objects])
    owner = np.repeat(np.arange(len(objects)), [o.keys.size for o in objects])
    ids = np.array([o.id for o in objects])[owner]
    order = np.lexsort((ids, -weights, keys))
    sorted_keys = keys[order]
    loser = np.zeros(keys.size, bool)
    loser[order[1:]] = sorted_keys[1:] == sorted_keys[:-1]
    if not loser.any():
        return list(objects)
    resolved = []
    start = 0
    for obj in objects:
        drop = loser[start : start + obj.keys.size]
        start += obj.keys.size
        resolved.append(obj if not drop.any() else keep_voxels(obj, ~drop))
    return resolved
