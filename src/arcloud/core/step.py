"""The per-frame step (the paper's Algorithm 1), over the ports.

detect -> voxelize (masks cleaned with depth) -> find visible objects -> lock -> associate -> fuse (and
judge each visible object nothing was detected on by the depth at its voxels: a miss when its surface is
there, *seen gone* when the rays pass through where it was; one seen gone in enough frames is retired:
event ``retired``; one missed in nearly all the frames that saw it is a phantom: deleted) ->
create -> refine (boxes reach the floor the frames saw; score and confirmation from the evidence) ->
commit what changed as one ``MapChange``, which unlocks in the same atomic write (a lock is held no longer
than the write: ``MapStore.commit``). The change's events go to the map's change log in that write too;
whoever announces them (server-sent events, Zenoh) reads the log (``core.change``), so no event is lost to a
worker that dies after its commit.

Creation is where two workers that see the same new object at the same moment would make it twice
(locks only protect objects that exist). So new objects are created under a *space claim* on the index
cells they cover: while holding it, the step looks again for objects that appeared there since its
frustum query, tries their locks without waiting (waiting could deadlock with a worker that holds them
and waits for our cells) and fuses into them. Whatever still slips through (a lock that could not be
taken) is caught by the *merge pass*: every frame merges the same-label objects it holds whose voxels
overlap, so a duplicate lives only until some frame sees both copies. A claim takes at most
``MAX_CELLS_PER_CALL`` index cells: a frame whose new objects would span more is refused
(``TooManyCells``, before anything is claimed), as it always would be.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from arcloud.core.associate import associate, overlap_matrix, stored_index_bounds_of
from arcloud.core.boxes import COMPONENT_GAP_VOXELS, reach_under, refine_all, tucked_slab
from arcloud.core.camera import boxes_in_frustum, frame_frustum
from arcloud.core.change import MapChange
from arcloud.core.checks import check_detections
from arcloud.core.confirm import evidence, is_phantom
from arcloud.core.errors import LockTimeout, TooManyCells
from arcloud.core.floor import FrameFloor, add_votes, frame_floor
from arcloud.core.fusion import (
    current_label_index,
    find_duplicates,
    fuse_detection,
    held_apart,
    id_pair,
    keep_voxels,
    merge_objects,
    new_object,
    resolve_conflicts,
    seen_apart,
    spanned_frames,
    split_detection,
)
from arcloud.core.ports import MAX_CELLS_PER_CALL, Detector, Lease, MapStore
from arcloud.core.types import Detection, Frame, MapObject, ObjectEvent, Params, VoxelDetection
from arcloud.core.voxels import (
    center_rays,
    coarsen_keys,
    coarsen_keys_unsorted,
    footprint_share,
    free_voxels,
    in_sorted,
    key_centers,
    keys_bounds,
    keys_extent,
    visible_voxels_of_sets,
    voxelize_detections,
)

log = logging.getLogger(__name__)

MISS_SAMPLE_VOXELS = 256  # a miss looks at this many of an object's voxels, spread over it


@dataclass(slots=True)
class StepResult:
    """What one frame did to the map."""

    frame_key: str
    skipped: bool = False  # the frame had been processed before (idempotent re-delivery)
    n_detections: int = 0
    n_visible: int = 0
    matched: int = 0
    created: list[int] = field(default_factory=list)
    updated: list[int] = field(default_factory=list)
    left: list[int] = field(default_factory=list)  # ids that left the map: merged, deleted or retired
    retired: list[int] = field(default_factory=list)  # seen gone: left the map, kept in its history
    events: list[ObjectEvent] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)


def process_frame(
    frame: Frame,
    detector: Detector,
    store: MapStore,
    params: Params,
) -> StepResult:
    """Detect (holding no lock), then integrate the detections into the map."""
    if store.is_frame_done(frame.map_id, frame.key):
        return StepResult(frame.key, skipped=True)
    started = time.perf_counter()
    detections = detector.detect(frame)
    result = integrate_frame(frame, detections, store, params)
    result.timings_s["detect"] = time.perf_counter() - started - sum(result.timings_s.values())
    return result


def integrate_frame(
    frame: Frame,
    detections: Sequence[Detection],
    store: MapStore,
    params: Params,
    *,
    now_s: float | None = None,
) -> StepResult:
    """Everything after detection: voxelize, find visible objects, lock, associate, fuse, create,
    refine, commit (the map's change log with it, and the unlock)."""
    now_s = time.time() if now_s is None else now_s
    result = StepResult(frame.key)
    clock = _Clock(result.timings_s)

    observations = voxelize_detections(frame, check_detections(detections, frame.shape), params)
    result.n_detections = len(observations)
    clock.lap("voxelize")
    visible_ids = find_visible(store, frame, params)
    result.n_visible = len(visible_ids)
    clock.lap("query")
    if not observations and not visible_ids:  # nothing to fuse, nothing to miss: only record the frame
        result.skipped = not store.commit(frame.map_id, [], MapChange(), frame_key=frame.key)
        return result

    floor = frame_floor(frame, params) if observations else None  # only fused objects take its vote
    clock.lap("floor")
    with store.lock(frame.map_id, visible_ids, ttl_s=params.lock_ttl_s, timeout_s=params.lock_timeout_s) as lease:
        clock.lap("lock")
        # What changed is tracked by id: ``voxels_changed`` objects are refined before they are written,
        # ``rescored`` ones (a miss moved their score) are written as they are, the rest are left alone.
        stored = {o.id: o for o in store.get(frame.map_id, visible_ids)}
        objects, unmatched, voxels_changed, taken, joined = fuse_matches(
            list(stored.values()), observations, params, frame, floor
        )
        misses = count_misses(objects, voxels_changed, frame, params)
        objects, rescored = misses.objects, misses.rescored
        result.matched = len(observations) - len(unmatched)
        clock.lap("associate_fuse")
        leases: list[Lease] = [lease]
        try:
            if unmatched:
                claims, late, late_and_new, late_changed, late_taken = create_under_claim(
                    store, frame, unmatched, visible_ids, params, now_s, floor
                )
                leases += claims
                stored.update({o.id: o for o in late})
                objects += late_and_new
                voxels_changed |= late_changed
                taken += late_taken
            apart = apart_in_frame(taken, params) if params.apart_min_frames else []
            objects = mark_apart(objects, apart, params)
            objects, carved, probation = carve_apart(objects, taken, apart, params)
            voxels_changed |= carved
            objects, absorbed_into = merge_duplicates(objects, voxels_changed, params, apart, joined)
            objects, trimmed = resolve_shared_voxels(objects, probation)
            voxels_changed |= set(absorbed_into.values()) | trimmed
            to_write = refine_changed(objects, voxels_changed, rescored, params)
            to_write = reach_under_tables(store, frame.map_id, to_write, objects, voxels_changed, params)
            upserts, removed, events = diff_with_stored(to_write, stored, absorbed_into, frame.map_id, now_s)
            events += [ObjectEvent("retired", frame.map_id, o.id, was_confirmed=o.confirmed) for o in misses.retired]
            events += [ObjectEvent("deleted", frame.map_id, o.id, was_confirmed=o.confirmed) for o in misses.phantoms]
            removed += misses.phantoms
            written = {o.id for o in upserts} | {o.id for o in removed}
            change = MapChange(
                upserts=tuple(upserts),
                deletes=tuple(removed),
                retired=tuple(misses.retired),
                misses={i: n for i, n in misses.n_missed.items() if i not in written},
                gone={i: n for i, n in misses.n_gone.items() if i not in written},
                events=tuple(events),
            )
            clock.lap("create_refine")
            if not store.commit(frame.map_id, leases, change, frame_key=frame.key):
                return StepResult(frame.key, skipped=True, timings_s=result.timings_s)
            clock.lap("write")
        finally:  # a commit that wrote released every lease: these releases (and the with's) then do nothing
            for extra in leases[1:]:
                extra.release()

    result.created = [e.object_id for e in events if e.kind == "created"]
    result.updated = [e.object_id for e in events if e.kind == "updated"]
    result.left = [e.object_id for e in events if e.kind in ("merged", "deleted", "retired")]
    result.retired = [e.object_id for e in events if e.kind == "retired"]
    result.events = events
    log.debug(
        "frame %s/%s: %d detections, %d visible, %d matched, %d created, %d left (%d retired)",
        frame.map_id,
        frame.key,
        result.n_detections,
        result.n_visible,
        result.matched,
        len(result.created),
        len(result.left),
        len(result.retired),
    )
    return result


def find_visible(store: MapStore, frame: Frame, params: Params) -> list[int]:
    """Ids of the objects whose bounds intersect the frame's view frustum (sorted)."""
    frustum = frame_frustum(frame, params)
    if frustum is None:
        return []
    lo, hi = frustum.bounds()
    candidates = store.query_region(frame.map_id, lo, hi)
    if not candidates:
        return []
    ids = list(candidates)
    mins = np.array([candidates[i][0] for i in ids])
    maxs = np.array([candidates[i][1] for i in ids])
    return sorted(int(ids[k]) for k in np.flatnonzero(boxes_in_frustum(frustum, mins, maxs)))


def fuse_matches(
    objects: list[MapObject],
    observations: Sequence[VoxelDetection],
    params: Params,
    frame: Frame,
    floor: FrameFloor | None = None,
) -> tuple[list[MapObject], list[VoxelDetection], set[int], list[tuple[VoxelDetection, int]], list[tuple[int, int]]]:
    """Associate observations with objects (Hungarian) and fuse the pairs, counting which voxels of a
    matched object the frame saw; returns the objects (fused ones replaced), the observations left
    unmatched, the ids of the fused objects, the matched pairs (observation, object id) and the pieces
    of one object that a mask spanned (``joined_by_masks``)."""
    if not observations:
        return objects, [], set(), [], []
    association = associate(
        [o.keys for o in observations],
        [o.label_index for o in observations],
        [o.keys for o in objects],
        [current_label_index(o, changed=False) for o in objects],  # as read: refined
        params,
        object_bounds=stored_index_bounds_of(objects, params.voxel_size_m),
        object_frames=[o.n_frames for o in objects],
        held_apart=apart_matrix(objects, params),
    )
    matched = {o for _, o in association.pairs}
    views: dict[int, VoxelDetection] = {}
    for d, o in association.pairs:
        rivals = association.rivals.get(d, [])
        if not rivals:
            views[o] = observations[d]
            continue
        parts = split_detection(observations[d], [objects[i].keys for i in (o, *rivals)], 1 + params.association_tolerance_voxels)
        views[o] = parts[0]
        # A rival's share is a view of it when nothing else in this frame matched it.
        for rival, part in zip(rivals, parts[1:]):
            if rival not in matched and rival not in views and part.keys.size >= params.min_voxels_per_detection:
                views[rival] = part
    fused = list(objects)
    fused_ids = set()
    viewed = [(o, view) for o, view in views.items() if view.keys.size]
    # Which voxels of each object the frame saw, as it was read (each object takes one view).
    visible = visible_voxels_of_sets(frame, [objects[o].keys for o, _ in viewed], params)
    for (o, view), visible_of_o in zip(viewed, visible):
        fused[o] = fuse_detection(objects[o], view, frame.device_id, visible_of_o, floor_vote(floor, view, params))
        fused_ids.add(fused[o].id)
    # A mask over its match and a rival held apart for now, or over a seat and a back ``joined_by_masks`` may join:
    # one more frame that spanned the pair, counted once a frame on the match (``core.fusion.spanned_frames`` reads
    # both sides). Pairs held for good need no count.
    counted: set[tuple[int, int]] = set()
    for d, o in association.pairs:
        counting = []
        for r in association.rivals.get(d, ()):
            a, b = objects[o], objects[r]
            pair = id_pair(a.id, b.id)
            if pair not in counted and (
                (held_apart(a, b, params) and not seen_apart(a, b, params))
                or (may_be_pieces(a, b, params) and seat_and_back(a, b, params))
            ):
                counted.add(pair)
                counting.append(r)
        if counting:
            fused[o] = fused[o].replace(spanned=add_votes(fused[o].spanned, {objects[r].id: 1 for r in counting}))
            fused_ids.add(fused[o].id)
    taken = [(observations[d], objects[o].id) for d, o in association.pairs]
    joined = joined_by_masks(objects, association.pairs, association.rivals, params)
    return fused, [observations[d] for d in association.unmatched], fused_ids, taken, joined


def joined_by_masks(
    objects: Sequence[MapObject], pairs: Sequence[tuple[int, int]], rivals: Mapping[int, Sequence[int]], params: Params
) -> list[tuple[int, int]]:
    """Object id pairs (a, b), a < b, that are pieces of one object: one mask of this frame spanned both
    (``rivals`` of a matched detection, ``core.associate.Association``), no frame ever saw them apart
    (``may_be_pieces``), and they stand on one footprint (``footprint_share`` at least
    ``merge_spanned_min_footprint``). A chair's back first seen from behind and its seat from the front are two
    objects until a mask covers the whole chair; two chairs side by side, or two screens, stand on two
    footprints, and a spanning mask is shared out between them as before. A seat and a back whose footprints
    only meet along an edge (``seat_and_back``; 7-Scenes' chair, in K = 10 orders) are joined once masks have
    spanned them in ``apart_min_frames`` frames, as many as would part them for good. The merge pass joins the
    pairs (``merge_duplicates``)."""
    joined: list[tuple[int, int]] = []
    for d, o in pairs:
        for r in rivals.get(d, ()):
            a, b = objects[o], objects[r]
            if not may_be_pieces(a, b, params):
                continue
            spans = spanned_frames(a, b) + 1  # this frame's mask too
            spanned = 0 < params.apart_min_frames <= spans and seat_and_back(a, b, params)
            if spanned or footprint_share(a.keys, b.keys, params) >= params.merge_spanned_min_footprint:
                joined.append(id_pair(a.id, b.id))
    return joined


#: A chair's back: the shorter side of its footprint at most this (metres)...
BACK_MAX_DEPTH_M = 0.2
#: ...and a seat beside it: its top at most this share of the back's height above their common base (a seat at
#: 0.48 m against its back at 0.83 m reads 0.58).
SEAT_TOP_SHARE = 0.7


def seat_and_back(a: MapObject, b: MapObject, params: Params) -> bool:
    """Whether two boxed objects are a chair's back and its seat: the taller is thin (``BACK_MAX_DEPTH_M``), the
    other stands much lower (``SEAT_TOP_SHARE``; heights along gravity, from their gravity-aligned boxes), and
    their footprints meet, ``COMPONENT_GAP_VOXELS`` empty voxels between them at most (as a box's parts do). A
    stool beside a chair, or a chair whose back was never seen beside a whole one, are no seat and back: the
    taller one is no thin slab."""
    if a.obb is None or b.obb is None:
        return False
    boxes = (a.obb, b.obb)
    bottoms = [float(params.gravity.up @ box.center) - float(box.size[2]) / 2 for box in boxes]
    base = min(bottoms)
    (low, _), (tall, back) = sorted(
        ((bottom + float(box.size[2]) - base, box) for bottom, box in zip(bottoms, boxes)), key=lambda top: top[0]
    )
    return (
        min(float(back.size[0]), float(back.size[1])) <= BACK_MAX_DEPTH_M
        and low <= SEAT_TOP_SHARE * tall
        and footprint_share(a.keys, b.keys, params, COMPONENT_GAP_VOXELS + 1) > 0
    )


def may_be_pieces(a: MapObject, b: MapObject, params: Params) -> bool:
    """Whether masks over both of ``a`` and ``b`` may join them (``joined_by_masks``): no frame ever saw them
    apart (not once: ``MapObject.apart``), and their class stands on the floor (``Params.floor_standing``): a
    screen over the shelf below it stands on the shelf's footprint, and a tentative twin there must not take
    the screen."""
    return a.label in params.floor_standing and b.id not in a.apart and a.id not in b.apart


def apart_matrix(objects: Sequence[MapObject], params: Params) -> np.ndarray | None:
    """(O, O) bool: the pairs of ``objects`` held apart (``held_apart``); None when there is none."""
    if not any(o.apart for o in objects):
        return None
    index = {o.id: i for i, o in enumerate(objects)}
    out = np.zeros((len(objects), len(objects)), bool)
    for i, obj in enumerate(objects):
        for other in obj.apart:
            j = index.get(other)
            if j is not None and held_apart(obj, objects[j], params):
                out[i, j] = out[j, i] = True
    return out


def apart_in_frame(taken: Sequence[tuple[VoxelDetection, int]], params: Params) -> list[tuple[int, int]]:
    """Object id pairs (a, b), a < b, that this frame saw apart: two detections of one class that share few
    voxels (overlap below ``association_min_overlap``) went to them (``taken``: (observation, object
    id) of every observation fused into an object or made one)."""
    by_label: dict[int, list[tuple[VoxelDetection, int]]] = {}
    for observation, object_id in taken:
        by_label.setdefault(observation.label_index, []).append((observation, object_id))
    pairs: dict[tuple[int, int], None] = {}
    margin = params.association_tolerance_voxels + 1
    for group in by_label.values():
        if len({object_id for _, object_id in group}) < 2:
            continue
        keys = [observation.keys for observation, _ in group]
        extents = [keys_extent(k) for k in keys]
        overlap = None
        for a, (_, id_a) in enumerate(group):
            for b in range(a + 1, len(group)):
                id_b = group[b][1]
                if id_a == id_b:
                    continue
                (lo_a, hi_a), (lo_b, hi_b) = extents[a], extents[b]
                if not bool(np.any(lo_a > hi_b + margin) or np.any(lo_b > hi_a + margin)):  # near in space: measure
                    if overlap is None:
                        overlap = overlap_matrix(keys, keys, params.association_tolerance_voxels)
                    if overlap[a, b] >= params.association_min_overlap:
                        continue
                pairs[id_pair(id_a, id_b)] = None
    return list(pairs)


def mark_apart(objects: list[MapObject], apart: Sequence[tuple[int, int]], params: Params) -> list[MapObject]:
    """The objects of each pair this frame saw apart (``apart_in_frame``) count one more frame apart from each
    other (``MapObject.apart``; ``core.fusion.held_apart`` keeps them from being merged, and a later mask
    spanning both is shared out between them)."""
    if params.apart_min_frames == 0 or not apart:
        return objects
    seen_with: dict[int, dict[int, int]] = {}
    for a, b in apart:
        seen_with.setdefault(a, {})[b] = 1
        seen_with.setdefault(b, {})[a] = 1
    return [o.replace(apart=add_votes(o.apart, seen_with[o.id])) if o.id in seen_with else o for o in objects]


def carve_apart(
    objects: list[MapObject], taken: Sequence[tuple[VoxelDetection, int]], apart: Sequence[tuple[int, int]], params: Params
) -> tuple[list[MapObject], set[int], set[int]]:
    """Objects that this frame saw apart (``apart``, ``mark_apart`` applied) but the map holds as overlapping:
    an object that early frames grew over its neighbour (two monitors side by side welded, a desk's object
    grown over the desk pushed against it) while another object took the neighbour's detections.

    Seen apart in ``apart_min_frames`` frames (``seen_apart``), each gives up its voxels in the coarse cells
    that the other's detections in this frame cover and its own do not (frame after frame: what one frame
    does not show stays). Seen apart in fewer, the younger of the two (fewer frames) is *on probation*: it
    keeps every voxel (the step leaves it out of ``resolve_shared_voxels``) and the merge pass does not join
    the pair in this frame; a later frame that does not see them apart merges it back when it was seen in that
    frame only (a detector's one-off split of one object into two masks; objects seen in more frames are
    ``core.fusion.held_apart`` until masks over both catch up), one that does counts another frame apart.
    Returns the objects, the ids of those that gave up voxels, and the ids on probation."""
    index = {o.id: i for i, o in enumerate(objects)}
    factor = 1 + params.association_tolerance_voxels
    carved: set[int] = set()
    probation: set[int] = set()
    # An object is in several pairs: its detections this frame and the extents are worked out once each. An
    # object's extent is read before it gives anything up, so it can only be larger than its voxels' now,
    # which keeps the early-out below safe.
    seen_now: dict[int, np.ndarray] = {}
    seen_extent: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    object_extent: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for id_a, id_b in apart:
        a, b = objects[index[id_a]], objects[index[id_b]]
        if not seen_apart(a, b, params):
            probation.add(min((a, b), key=lambda o: (o.n_frames, -o.id)).id)
            continue
        for obj in (a, b):
            if obj.id not in seen_now:
                seen_now[obj.id] = np.concatenate([obs.keys for obs, owner in taken if owner == obj.id])
                seen_extent[obj.id] = keys_extent(seen_now[obj.id])
                if obj.keys.size:
                    object_extent[obj.id] = keys_extent(obj.keys)
        for owner, other in ((id_a, id_b), (id_b, id_a)):
            obj = objects[index[owner]]
            if not obj.keys.size:
                continue
            (lo, hi), (lo_other, hi_other) = object_extent[owner], seen_extent[other]
            if np.any(lo > hi_other + factor) or np.any(lo_other > hi + factor):  # no coarse cell near both: none to give
                continue
            obj_cells = coarsen_keys_unsorted(obj.keys, factor)
            give = in_sorted(obj_cells, coarsen_keys(seen_now[other], factor)) & ~in_sorted(
                obj_cells, coarsen_keys(seen_now[owner], factor)
            )
            if give.any():
                objects[index[owner]] = keep_voxels(obj, ~give)
                carved.add(owner)
    return objects, carved, probation


@dataclass(slots=True)
class Misses:
    """What a frame's depth says of the visible objects it detected nothing on (``count_misses``)."""

    objects: list[MapObject]  # every object given, those rescored replaced, those retired or phantoms left out
    n_missed: dict[int, int] = field(default_factory=dict)  # new miss counts of objects not rewritten
    n_gone: dict[int, int] = field(default_factory=dict)  # new gone counts of objects not rewritten (changed ones)
    rescored: set[int] = field(default_factory=set)  # ids whose score or status moved: rewritten, not refined
    retired: list[MapObject] = field(default_factory=list)  # seen gone long enough: removed, as read
    phantoms: list[MapObject] = field(default_factory=list)  # missed too often (core.confirm.is_phantom): deleted, as read


def count_misses(objects: list[MapObject], fused_ids: set[int], frame: Frame, params: Params) -> Misses:
    """Judge the objects the frame had in view whose detection did not come (not in ``fused_ids``) by
    the frame's depth at a sample of their voxels (``MISS_SAMPLE_VOXELS`` spread over each, all
    objects' at once):

    - *seen gone*: ``gone_min_free`` of the sample's upper part (more than ``gone_above_base_m`` above
      its base, the 10th percentile of its heights) is seen empty (``free_voxels``: the rays through
      each voxel meet nothing until well behind it). One more miss (``core.confirm``) and one more
      frame seen gone (``n_gone``); at ``retire_min_gone_frames`` frames seen gone since it was last seen there
      (detected, or its surface measured), it is *retired*: removed from the map. Its base is left
      out because there the surface it stood on (floor, table top) is measured whether it is there or
      not: a laptop taken off a table leaves the table top in its lowest voxels;
    - *seen, not detected*: else, when ``miss_min_visible`` of the sample shows its surface (it is there
      and mostly unoccluded): one more miss; it is not gone (``n_gone`` back to 0);
    - anything else (out of view, occluded, no depth there, or a mix) is no evidence.

    A missed detection of an object still there shows depth *at* its voxels, not behind them, so it
    does not count towards retiring it. An object that one more miss makes a phantom
    (``core.confirm.is_phantom``) is deleted (``phantoms``) when it stands apart from the other objects
    the frame has in view (``stands_apart``). A miss rewrites an object when its score or status moves enough
    (``rescored``); otherwise its counters are written alone (``n_missed``, ``n_gone``: no new version)."""
    out = Misses(list(objects))
    undetected = [i for i, obj in enumerate(objects) if obj.id not in fused_ids and obj.keys.size]
    if not undetected:
        return out
    samples = [objects[i].keys[:: max(1, objects[i].keys.size // MISS_SAMPLE_VOXELS)] for i in undetected]
    all_samples = np.concatenate(samples)
    starts = list(itertools.accumulate((s.size for s in samples[:-1]), initial=0))
    segments = [slice(start, start + s.size) for start, s in zip(starts, samples)]
    visible, free_centres = center_rays(frame, all_samples, params)
    surface_shares = np.add.reduceat(visible, starts) / [s.size for s in samples]
    heights = key_centers(all_samples, params.voxel_size_m) @ params.gravity.up

    def gone_in(free: np.ndarray, ks: Sequence[int]) -> set[int]:
        return {k for k in ks if gone_share(free[segments[k]], heights[segments[k]], params) >= params.gone_min_free}

    # An object seen gone along every ray through its voxels is seen gone along their centres' rays
    # (center_rays, cheap): the exact test (free_voxels, which reads a pyramid of the depth image)
    # runs on the samples of those objects alone.
    some_free = np.flatnonzero(np.add.reduceat(free_centres, starts))
    maybe = sorted(gone_in(free_centres, some_free.tolist()))
    gone: set[int] = set()
    if maybe:
        at = np.concatenate([np.arange(all_samples.size)[segments[k]] for k in maybe])
        free = np.zeros(all_samples.size, bool)
        free[at] = free_voxels(frame, all_samples[at], params)
        gone = gone_in(free, maybe)
    removed_ids: set[int] = set()  # retired and phantoms
    for k, (i, surface) in enumerate(zip(undetected, surface_shares)):
        obj = objects[i]
        if k in gone:
            n_gone = obj.n_gone + 1
            if 0 < params.retire_min_gone_frames <= n_gone:
                out.retired.append(obj)
                removed_ids.add(obj.id)
                continue
        elif surface >= params.miss_min_visible:
            n_gone = 0
        else:
            continue
        if is_phantom(obj, params, n_missed=obj.n_missed + 1) and stands_apart(obj, objects):
            out.phantoms.append(obj)
            removed_ids.add(obj.id)
            continue
        score, confirmed = evidence(obj, params, n_missed=obj.n_missed + 1)
        if confirmed != obj.confirmed or abs(score - obj.score) > params.rescore_write_delta:
            out.objects[i] = obj.replace(n_missed=obj.n_missed + 1, n_gone=n_gone, score=score, confirmed=confirmed)
            out.rescored.add(obj.id)
        else:
            out.n_missed[obj.id] = obj.n_missed + 1
            if n_gone != obj.n_gone:
                out.n_gone[obj.id] = n_gone
    if removed_ids:
        out.objects = [o for o in out.objects if o.id not in removed_ids]
    return out


def stands_apart(obj: MapObject, objects: Sequence[MapObject]) -> bool:
    """Whether the bounds of ``obj`` (all its voxels) meet those of none of the other ``objects``. A
    phantom among other objects is kept: it holds voxels that would otherwise go to them (one object a
    voxel), so deleting it would reshape its neighbours (on 7-Scenes, a phantom chair under two TVs let
    them grow into each other and merge)."""
    if obj.bounds is None:
        return False
    return not any(
        other.id != obj.id
        and other.bounds is not None
        and bool(np.all(other.bounds.min <= obj.bounds.max) and np.all(obj.bounds.min <= other.bounds.max))
        for other in objects
    )


def gone_share(free: np.ndarray, heights: np.ndarray, params: Params) -> float:
    """The share of an object's sampled voxels (whether each is seen empty, ``free_voxels`` (N,) bool,
    and their heights (N,) along up) above its base (more than ``gone_above_base_m`` above the 10th
    percentile height) that the frame sees empty. 0 when none lies above its base (a flat object)."""
    k = (heights.size - 1) // 10
    base_m = np.partition(heights, k)[k]
    upper = heights > base_m + params.gone_above_base_m
    n_upper = int(np.count_nonzero(upper))
    return float(np.count_nonzero(free[upper])) / n_upper if n_upper else 0.0


def floor_vote(floor: FrameFloor | None, observation: VoxelDetection, params: Params) -> int | None:
    """The frame's vote for the floor under an observed object (``core.floor``)."""
    return None if floor is None else floor.vote_for(key_centers(observation.keys, params.voxel_size_m), params)


def claim_cells(
    observations: Sequence[VoxelDetection], params: Params
) -> tuple[list[tuple[int, int, int]], np.ndarray, np.ndarray]:
    """Index cells covered by the observations' bounds, and the overall (lo, hi). ``TooManyCells`` when
    they are more than one claim takes (``MAX_CELLS_PER_CALL``; a box is counted before its cells are listed)."""
    bounds = [keys_bounds(o.keys, params.voxel_size_m) for o in observations]
    lo = np.min([b[0] for b in bounds], axis=0)
    hi = np.max([b[1] for b in bounds], axis=0)
    cells: set[tuple[int, int, int]] = set()
    for b_lo, b_hi in bounds:
        c_lo = np.floor(b_lo / params.index_cell_m).astype(int)
        c_hi = np.floor(b_hi / params.index_cell_m).astype(int)
        n_box = math.prod(int(b) - int(a) + 1 for a, b in zip(c_lo, c_hi))
        if n_box > MAX_CELLS_PER_CALL:
            raise TooManyCells("detections", n_box, MAX_CELLS_PER_CALL)
        for i in range(c_lo[0], c_hi[0] + 1):
            for j in range(c_lo[1], c_hi[1] + 1):
                for k in range(c_lo[2], c_hi[2] + 1):
                    cells.add((i, j, k))
        if len(cells) > MAX_CELLS_PER_CALL:  # at least this many: the boxes left are not counted
            raise TooManyCells("detections", len(cells), MAX_CELLS_PER_CALL)
    return sorted(cells), lo, hi


def create_under_claim(
    store: MapStore,
    frame: Frame,
    unmatched: Sequence[VoxelDetection],
    held_ids: Sequence[int],
    params: Params,
    now_s: float,
    floor: FrameFloor | None = None,
) -> tuple[list[Lease], list[MapObject], list[MapObject], set[int], list[tuple[VoxelDetection, int]]]:
    """Claim the space of the unmatched observations; fuse them into objects that appeared there since
    the frustum query (when their locks are free), create objects for the rest. Returns the claim and
    the leases on the late objects, the late objects as read, the late (fused) plus new objects, and
    the ids of those whose voxels changed (fused or new), and which object took each observation
    (observation, object id)."""
    cells, lo, hi = claim_cells(unmatched, params)
    claim = store.claim(frame.map_id, cells, ttl_s=params.lock_ttl_s, timeout_s=params.lock_timeout_s)
    late_leases: list[Lease] = []
    try:
        late_ids = sorted(set(store.query_region(frame.map_id, lo, hi)) - set(held_ids))
        late_leases = try_lock(store, frame.map_id, late_ids, params)
        late = store.get(frame.map_id, [lease.ids[0] for lease in late_leases])
        # (Pieces of one object that a mask spans are joined when a later frame's mask spans them again.)
        fused_late, still_unmatched, fused_ids, taken, _ = fuse_matches(late, unmatched, params, frame, floor)
        new_ids = store.new_ids(frame.map_id, len(still_unmatched)) if still_unmatched else []
        taken += list(zip(still_unmatched, new_ids))
        created = [
            new_object(i, o, frame.device_id, now_s, floor_vote(floor, o, params)) for i, o in zip(new_ids, still_unmatched)
        ]
    except BaseException:
        for lease in [claim, *late_leases]:
            lease.release()
        raise
    return [claim, *late_leases], late, fused_late + created, fused_ids | set(new_ids), taken


def try_lock(store: MapStore, map_id: str, ids: Sequence[int], params: Params) -> list[Lease]:
    """Locks on whichever of ``ids`` are free now, one lease each, without waiting."""
    leases = []
    for object_id in ids:
        try:
            leases.append(store.lock(map_id, [object_id], ttl_s=params.lock_ttl_s, timeout_s=0))
        except LockTimeout:
            log.debug("map %s: object %d busy; a later merge pass resolves any duplicate", map_id, object_id)
    return leases


def merge_duplicates(
    objects: Sequence[MapObject],
    voxels_changed: set[int],
    params: Params,
    apart: Sequence[tuple[int, int]] = (),
    joined: Sequence[tuple[int, int]] = (),
) -> tuple[list[MapObject], dict[int, int]]:
    """The merge pass: objects that are one physical object (``find_duplicates``; only pairs with an
    object whose voxels changed are looked at, never a pair this frame saw ``apart``, and the pieces a mask
    ``joined``) merged into one keeper each. Returns the objects left and ``absorbed_into``: absorbed id ->
    keeper id."""
    objects = list(objects)
    absorbed_into: dict[int, int] = {}
    changed = [o.id in voxels_changed for o in objects]
    for keep, absorb in find_duplicates(objects, params, changed, apart, joined):
        objects[keep] = merge_objects(objects[keep], objects[absorb])
        absorbed_into[objects[absorb].id] = objects[keep].id
    return [o for o in objects if o.id not in absorbed_into], absorbed_into


def resolve_shared_voxels(objects: Sequence[MapObject], probation: Collection[int] = ()) -> tuple[list[MapObject], set[int]]:
    """One instance per voxel (``resolve_conflicts``) among the objects not on ``probation``
    (``carve_apart``); returns the objects and the ids of those that gave up voxels (resolving only
    removes voxels, so they are the ones with fewer)."""
    subject = [o for o in objects if o.id not in probation]
    resolved = iter(resolve_conflicts(subject))
    out = [o if o.id in probation else next(resolved) for o in objects]
    return out, {new.id for old, new in zip(objects, out) if new.keys.size != old.keys.size}


def refine_changed(objects: Sequence[MapObject], voxels_changed: set[int], rescored: set[int], params: Params) -> list[MapObject]:
    """The objects to write, in order: those whose voxels changed, refined (an object refined to no
    voxels comes back empty), and those only rescored, as they are."""
    written = [o for o in objects if o.id in voxels_changed or o.id in rescored]
    refined = iter(refine_all([o for o in written if o.id in voxels_changed], params))
    return [next(refined) if o.id in voxels_changed else o for o in written]


def reach_under_tables(
    store: MapStore, map_id: str, to_write: Sequence[MapObject], objects: Sequence[MapObject], refined: set[int], params: Params
) -> list[MapObject]:
    """``to_write`` with the ``refined`` chairs whose boxes are slabs reaching under their tables
    (``core.boxes.reach_under``): a table among ``objects`` (the frame's, locked), else one the store holds around
    the slab, read unlocked (only its box is used): a view that sees the chair but not its table changes nothing."""
    now = {o.id: o for o in objects} | {o.id: o for o in to_write}
    reached = {o.id: o for o in reach_under([o for o in to_write if o.id in refined], list(now.values()), params)}
    alone = [o for o in reached.values() if o.aabb is now[o.id].aabb and tucked_slab(o, params)]  # no table in view
    if alone:
        margin = max(float(o.aabb.size.max()) for o in alone if o.aabb is not None)
        lo = np.min([o.bounds.min for o in alone if o.bounds is not None], axis=0) - margin
        hi = np.max([o.bounds.max for o in alone if o.bounds is not None], axis=0) + margin
        around = store.get(map_id, [i for i in store.query_region(map_id, lo, hi) if i not in now])
        reached |= {o.id: o for o in reach_under(alone, around, params)}
    return [reached.get(o.id, o) for o in to_write]


def diff_with_stored(
    to_write: Sequence[MapObject], stored: Mapping[int, MapObject], absorbed_into: Mapping[int, int], map_id: str, now_s: float
) -> tuple[list[MapObject], list[MapObject], list[ObjectEvent]]:
    """What the commit writes, against the objects as read (``stored``): each object of ``to_write``
    with its version bumped (created or updated; one left without voxels is deleted), and the stored
    objects absorbed by a merge deleted. Returns (upserts, deletes as stored, events)."""
    upserts, removed, events = [], [], []
    for obj in to_write:
        old = stored.get(obj.id)
        if obj.keys.size == 0:
            if old is not None:
                removed.append(old)
                events.append(ObjectEvent("deleted", map_id, obj.id, was_confirmed=old.confirmed))
            continue
        version = (old.version if old is not None else 0) + 1
        final = obj.replace(version=version, updated_at_s=now_s, created_at_s=obj.created_at_s or now_s)
        upserts.append(final)
        events.append(
            ObjectEvent(
                "created" if old is None else "updated", map_id, obj.id, final, was_confirmed=old is not None and old.confirmed
            )
        )
    for absorbed_id, keeper_id in absorbed_into.items():
        if absorbed_id in stored:
            removed.append(stored[absorbed_id])
            events.append(
                ObjectEvent("merged", map_id, absorbed_id, merged_into=keeper_id, was_confirmed=stored[absorbed_id].confirmed)
            )
    return upserts, removed, events


class _Clock:
    """Accumulates the time between laps into named entries."""

    def __init__(self, timings: dict[str, float]) -> None:
        self.timings = timings
        self.last = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + now - self.last
        self.last = now
