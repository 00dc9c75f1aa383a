"""Two objects of one class side by side stay two: a mask that spans both (a detector's merged
instance) is shared out between them instead of welding them (core.fusion.split_detection), and two
objects that frames detected apart are not merged (core.fusion.seen_apart, held_apart); one object seen in
parts, never two at once, becomes one."""

from __future__ import annotations

import numpy as np
import pytest
from handmade_frames import look_down_pose, scene_frame

from arcloud.core.boxes import refine
from arcloud.core.fusion import held_apart, new_object, spanned_frames
from arcloud.core.step import integrate_frame, joined_by_masks, seat_and_back
from arcloud.core.types import CLASS_INDEX, Detection, Params, VoxelDetection, empty_object
from arcloud.core.voxels import footprint_share, pack_keys
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05)
# Two TVs touching side by side, 0.7 m wide each, on a wall (the wall itself is not drawn).
TVS = [((-0.7, 1.95, 1.0), (0.0, 2.0, 1.4)), ((0.0, 1.95, 1.0), (0.7, 2.0, 1.4))]


def frames(n, first=0):
    for i in range(first, first + n):
        eye = (0.3 * np.sin(i), 0.0, 1.3)
        yield scene_frame(look_down_pose(eye, (0.0, 2.0, 1.2)), TVS, floor_z=None, frame_id=f"f{i}")


@pytest.mark.parametrize("split", [True, False])
def test_a_mask_spanning_two_tvs_does_not_weld_them(split):
    # Without the split rule (no rival is ever established) nor the apart rule: welded, as it once was.
    params = PARAMS if split else PARAMS.replace(split_min_frames=10**9, apart_min_frames=0)
    store = MemoryStore()
    for frame, instance in frames(4):  # seen apart first
        integrate_frame(frame, [Detection("tv", 0.9, instance == 0), Detection("tv", 0.9, instance == 1)], store, params)
    for frame, instance in frames(6, first=4):  # then as one instance
        integrate_frame(frame, [Detection("tv", 0.8, instance >= 0)], store, params)
    objects = sorted(store.list_objects("m"), key=lambda o: o.aabb.min[0])
    if not split:  # what happened before the split rule: one 1.4 m TV
        assert len(objects) == 1 and objects[0].aabb.size[0] > 1.2
        return
    assert len(objects) == 2
    for obj, (lo, hi) in zip(objects, TVS):
        assert obj.aabb.min[0] == pytest.approx(lo[0], abs=0.1) and obj.aabb.max[0] == pytest.approx(hi[0], abs=0.1)
        assert obj.n_frames == 10  # the merged masks counted as a view of each


def test_a_wide_tv_split_by_the_detector_in_two_frames_is_joined_by_whole_masks():
    # A wide TV's left part seen alone, then split into two masks in two frames (a second object, seen in two
    # frames), then whole: the whole masks go to the left object and the merge pass joins the right. Held
    # apart, the right one would take a share of each whole mask until seen in split_min_frames, and from then
    # on the split rule shares every mask out: two TVs for good.
    store = MemoryStore()
    for i, masks in enumerate([["left"]] * 3 + [["left", "right"]] * 2 + [["whole"]] * 4):
        frame, instance = next(frames(1, first=i))
        chosen = {"left": instance == 0, "right": instance == 1, "whole": instance >= 0}
        integrate_frame(frame, [Detection("tv", 0.9, chosen[m]) for m in masks], store, PARAMS)
    (tv,) = store.list_objects("m")
    assert tv.aabb.size[0] > 1.2


def couch_frame(i, halves):
    eye = (0.3 * np.sin(i), 0.0, 1.3)
    return scene_frame(look_down_pose(eye, (0.0, 2.0, 0.4)), halves, floor_z=None, frame_id=f"f{i}")


HALVES = [((-0.9, 1.6, 0.0), (0.0, 2.4, 0.8)), ((0.0, 1.6, 0.0), (0.9, 2.4, 0.8))]


def test_a_couch_seen_in_parts_is_joined_by_a_mask_that_spans_them():
    # A couch's two halves first seen in turn (two objects: never two masks in one frame), then whole:
    # the spanning mask is not shared out and the merge pass joins them.
    store = MemoryStore()
    for i in range(4):
        frame, instance = couch_frame(i, HALVES)
        integrate_frame(frame, [Detection("couch", 0.9, instance == i % 2)], store, PARAMS)
    assert len(store.list_objects("m")) == 2
    for i in range(4, 10):
        frame, instance = couch_frame(i, HALVES)
        integrate_frame(frame, [Detection("couch", 0.9, instance >= 0)], store, PARAMS)
    (couch,) = store.list_objects("m")
    assert couch.aabb.size[0] > 1.4  # both halves (each 0.9 m)


@pytest.mark.parametrize("frames_apart", [2, 3])
def test_two_couches_detected_apart_in_enough_frames_stay_two(frames_apart):
    # Two couches pushed together (no class the split rule covers) detected as two masks in one frame:
    # from apart_min_frames (3) such frames on, a mask spanning both is shared out and they are never merged.
    store = MemoryStore()
    for i in range(frames_apart):
        frame, instance = couch_frame(i, HALVES)
        integrate_frame(frame, [Detection("couch", 0.9, instance == 0), Detection("couch", 0.9, instance == 1)], store, PARAMS)
    for i in range(frames_apart, 10):
        frame, instance = couch_frame(i, HALVES)
        integrate_frame(frame, [Detection("couch", 0.9, instance >= 0)], store, PARAMS)
    objects = sorted(store.list_objects("m"), key=lambda o: o.aabb.min[0])
    if frames_apart < PARAMS.apart_min_frames:
        assert len(objects) == 1 and objects[0].aabb.size[0] > 1.4
        return
    assert len(objects) == 2
    for obj, (lo, hi) in zip(objects, HALVES):
        assert obj.aabb.min[0] == pytest.approx(lo[0], abs=0.15) and obj.aabb.max[0] == pytest.approx(hi[0], abs=0.15)
    left, right = objects
    assert left.apart.get(right.id, 0) >= frames_apart or right.apart.get(left.id, 0) >= frames_apart


def detect_desks(store, first, n, *, apart):
    """Frames of two desks pushed together (``HALVES``), detected as one mask spanning both or as two."""
    for i in range(first, first + n):
        frame, instance = couch_frame(i, HALVES)
        masks = [instance == 0, instance == 1] if apart else [instance >= 0]
        integrate_frame(frame, [Detection("table", 0.9, mask) for mask in masks], store, PARAMS)


@pytest.mark.parametrize("frames_apart", [1, 2, 8])
def test_an_object_grown_over_its_neighbour_is_carved_apart_by_frames_that_see_two(frames_apart):
    # Early frames see the two desks as one (one object over both); then frames see two masks: from
    # apart_min_frames such frames on, the object gives up, frame after frame, what the other's mask covers.
    store = MemoryStore()
    detect_desks(store, 0, 4, apart=False)
    (welded,) = store.list_objects("m")
    assert welded.aabb.size[0] > 1.4
    detect_desks(store, 4, frames_apart, apart=True)
    objects = sorted(store.list_objects("m"), key=lambda o: o.aabb.min[0])
    if frames_apart < PARAMS.apart_min_frames:  # on probation: the newer one keeps its voxels, nothing is carved
        assert len(objects) == 2 and max(o.aabb.size[0] for o in objects) > 1.4
        return
    assert len(objects) == 2
    for obj, (lo, hi) in zip(objects, HALVES):
        assert obj.aabb.min[0] == pytest.approx(lo[0], abs=0.15) and obj.aabb.max[0] == pytest.approx(hi[0], abs=0.15)
    detect_desks(store, 4 + frames_apart, 4, apart=False)  # a mask spanning both again is shared out
    assert len(store.list_objects("m")) == 2


def test_one_frame_that_splits_an_object_into_two_masks_does_not_split_it():
    # A detector's one-off split (two masks for one object) makes a second object on probation; the next
    # frame that sees the object whole merges it back (an object seen in that frame only is not held apart).
    store = MemoryStore()
    detect_desks(store, 0, 4, apart=False)
    detect_desks(store, 4, 1, apart=True)
    assert len(store.list_objects("m")) == 2
    detect_desks(store, 5, 1, apart=False)
    (table,) = store.list_objects("m")
    assert table.aabb.size[0] > 1.4 and table.apart == {}


@pytest.mark.parametrize(("frames_apart", "masks_over_both", "n_objects"), [(1, 1, 2), (1, 2, 1), (2, 2, 2), (2, 3, 1)])
def test_desks_seen_apart_stay_two_under_masks_over_both_while_fewer_of_those(frames_apart, masks_over_both, n_objects):
    # Two desks pushed together, each seen alone, then seen apart in fewer frames than apart_min_frames (an order
    # of a 10-user walk), then under masks spanning both: each such mask is shared out and counts a span
    # (MapObject.spanned) while the spans are fewer than the frames apart; the next mask over both welds them.
    store = MemoryStore()
    for i, desk in enumerate((0, 1)):
        frame, instance = couch_frame(20 + i, HALVES)
        integrate_frame(frame, [Detection("table", 0.9, instance == desk)], store, PARAMS)
    detect_desks(store, 0, frames_apart, apart=True)
    detect_desks(store, frames_apart, masks_over_both, apart=False)
    objects = sorted(store.list_objects("m"), key=lambda o: o.aabb.min[0])
    assert len(objects) == n_objects
    if n_objects == 1:
        assert objects[0].aabb.size[0] > 1.4 and objects[0].spanned == {} and objects[0].apart == {}
        return
    left, right = objects
    assert spanned_frames(left, right) == masks_over_both
    for obj, (lo, hi) in zip(objects, HALVES):
        assert obj.aabb.min[0] == pytest.approx(lo[0], abs=0.15) and obj.aabb.max[0] == pytest.approx(hi[0], abs=0.15)
    # One more frame that sees them apart reaches apart_min_frames (3) when added up with what came before:
    # from then on they stay two under any number of masks over both.
    detect_desks(store, frames_apart + masks_over_both, PARAMS.apart_min_frames - frames_apart, apart=True)
    detect_desks(store, 10, 4, apart=False)
    assert len(store.list_objects("m")) == 2


def test_a_piece_split_off_an_object_in_one_frame_and_not_seen_again_is_merged_back():
    # One frame's masks split a desk's end off (a detector's one-off split); later masks cover the rest of the
    # desk only (its end hidden). The piece, seen in that one frame only, is not held apart: it merges back.
    end, rest = ((-0.9, 1.6, 0.0), (-0.65, 2.4, 0.8)), ((-0.65, 1.6, 0.0), (0.9, 2.4, 0.8))
    store = MemoryStore()
    for i, masks in enumerate([["whole"]] * 4 + [["end", "rest"]] + [["rest"]] * 3):
        frame, instance = couch_frame(i, [end, rest])
        chosen = {"whole": instance >= 0, "end": instance == 0, "rest": instance == 1}
        integrate_frame(frame, [Detection("table", 0.9, chosen[m]) for m in masks], store, PARAMS)
        if i == 4:
            assert len(store.list_objects("m")) == 2
    (desk,) = store.list_objects("m")
    assert desk.aabb.size[0] > 1.4  # the rest, 1.55 m (the end, seen and left out of 3 masks, fades)


def test_held_apart_reads_the_two_objects_alike():
    # Either order of the pair gives one answer: the split classes' exception looks at both labels, and the
    # spans count each frame once, on whichever object the mask matched.
    a = empty_object(1).replace(label="table", n_frames=5, apart={2: 2})
    b = empty_object(2).replace(label="tv", n_frames=5, apart={1: 2})
    assert not held_apart(a, b, PARAMS) and not held_apart(b, a, PARAMS)
    b = b.replace(label="table")
    assert held_apart(a, b, PARAMS) and held_apart(b, a, PARAMS)
    assert not held_apart(a.replace(n_frames=1), b, PARAMS) and not held_apart(b, a.replace(n_frames=1), PARAMS)
    a, b = a.replace(spanned={2: 1}), b.replace(spanned={1: 1})  # two frames, one matched to each
    assert not held_apart(a, b, PARAMS) and not held_apart(b, a, PARAMS)


# A chair in two boxes: its seat, and its back standing on the seat's rear edge.
SEAT = ((-0.25, 2.0, 0.4), (0.25, 2.5, 0.5))
BACK = ((-0.25, 2.4, 0.5), (0.25, 2.5, 0.9))
BEHIND, FRONT = ((0.0, 4.0, 1.4), (0.0, 2.45, 0.7)), ((0.0, 0.8, 1.3), (0.0, 2.2, 0.5))


def detect_chair(store, first, n, view, part, params=PARAMS, label="chair", pieces=(SEAT, BACK)):
    """Frames of the chair (``pieces``: its seat and back) from ``view`` (eye, target), detected as ``part``:
    "back", "seat" or "whole"."""
    (eye_x, eye_y, eye_z), target = view
    for i in range(first, first + n):
        eye = (eye_x + 0.3 * np.sin(i), eye_y, eye_z)
        frame, instance = scene_frame(look_down_pose(eye, target), list(pieces), floor_z=None, frame_id=f"f{i}")
        mask = {"seat": instance == 0, "back": instance == 1, "whole": instance >= 0}[part]
        integrate_frame(frame, [Detection(label, 0.9, mask)], store, params)


@pytest.mark.parametrize(("label", "join"), [("chair", True), ("chair", False), ("tv", False)])
def test_a_chair_seen_in_pieces_is_joined_by_a_mask_that_spans_them(label, join):
    # Its back first, from behind, then its seat from the front: two objects (they share no voxel), neither
    # ever detected apart from the other in one frame. Masks of the whole chair then join them: pieces
    # standing on one footprint. (Without the rule, a share of 1 wanted: the masks are shared out. Not for
    # a class that does not stand on the floor: a screen over a shelf stands on the shelf's footprint.)
    # (The rule off: no footprint share joins them, nor do the three masks over both, fewer than apart_min_frames.)
    params = PARAMS if join or label != "chair" else PARAMS.replace(merge_spanned_min_footprint=1.0, apart_min_frames=4)
    store = MemoryStore()
    detect_chair(store, 0, 4, BEHIND, "back", params, label)
    detect_chair(store, 4, 4, FRONT, "seat", params, label)
    back, seat = sorted(store.list_objects("m"), key=lambda o: -o.aabb.max[2])
    assert back.aabb.min[1] > 2.35 and seat.aabb.max[2] < 0.55 and not back.apart and not seat.apart
    detect_chair(store, 8, 3, FRONT, "whole", params, label)
    objects = store.list_objects("m")
    if not join:
        assert len(objects) == 2 and {o.label for o in objects} == {label}
        return
    (chair,) = objects
    assert chair.n_frames >= 11  # (the frame that joined them counts in both)
    assert chair.aabb.min == pytest.approx([-0.25, 2.0, 0.4], abs=0.08) and chair.aabb.max == pytest.approx(
        [0.25, 2.5, 0.9], abs=0.08
    )


def chair_piece(object_id, lo, hi):
    """A refined chair object of the voxels from index ``lo`` to ``hi`` (exclusive), seen in 5 frames."""
    grid = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
    piece = new_object(object_id, VoxelDetection(CLASS_INDEX["chair"], 0.9, np.unique(pack_keys(grid))), "a", 0.0)
    return refine(piece.replace(n_frames=5, score_sum=4.5), PARAMS)


def test_a_seat_and_back_on_footprints_that_meet_along_an_edge_join_after_apart_min_frames_masks_over_both():
    # A seat (z 0.4-0.5 m) and a thin back (0.1 m deep, up to 0.9 m) behind it, two empty voxel rows between their
    # footprints: no footprint share joins them (7-Scenes' chair in K = 10 orders). Masks over both join them once
    # there have been apart_min_frames of them (this frame's included). A stool beside a whole chair, as near, is
    # no seat and back: the taller is no thin slab.
    seat, back = chair_piece(1, (0, 0, 8), (10, 8, 10)), chair_piece(2, (0, 10, 8), (10, 12, 18))
    stool, chair = chair_piece(3, (12, 0, 0), (20, 10, 9)), chair_piece(4, (0, 0, 0), (10, 10, 18))
    assert footprint_share(seat.keys, back.keys, PARAMS) == 0 and seat_and_back(seat, back, PARAMS)
    assert not seat_and_back(stool, chair, PARAMS)
    assert not seat_and_back(seat, chair_piece(5, (0, 11, 8), (10, 13, 18)), PARAMS)  # three empty rows: too far
    assert not seat_and_back(back, chair_piece(6, (0, 13, 8), (10, 15, 18)), PARAMS)  # two backs, as high
    for spans in range(PARAMS.apart_min_frames + 1):
        for pair in ((seat, back), (stool, chair)):
            a, b = pair[0].replace(spanned={pair[1].id: spans} if spans else {}), pair[1]
            joined = joined_by_masks([a, b], [(0, 0)], {0: [1]}, PARAMS)
            expected = pair[0] is seat and spans + 1 >= PARAMS.apart_min_frames
            assert joined == ([(a.id, b.id)] if expected else []), (pair[0].id, spans)
    # Never once seen apart, or not at all.
    assert joined_by_masks([seat.replace(spanned={2: 5}, apart={2: 1}), back], [(0, 0)], {0: [1]}, PARAMS) == []


def test_two_masks_over_a_seat_and_back_in_one_frame_count_one_span():
    store = MemoryStore()
    pieces = (SEAT, ((-0.25, 2.5, 0.4), (0.25, 2.6, 0.9)))
    detect_chair(store, 0, 4, BEHIND, "back", pieces=pieces)
    detect_chair(store, 4, 4, FRONT, "seat", pieces=pieces)
    a, b = store.list_objects("m")
    assert seat_and_back(a, b, PARAMS)
    frame, instance = scene_frame(look_down_pose(*FRONT), list(pieces), floor_z=None, frame_id="f9")
    integrate_frame(frame, [Detection("chair", 0.9, instance >= 0), Detection("chair", 0.8, instance >= 0)], store, PARAMS)
    a, b = store.list_objects("m")
    assert spanned_frames(a, b) == 1


# Two chairs side by side, touching.
CHAIRS = [((-0.5, 2.0, 0.0), (0.0, 2.5, 0.9)), ((0.0, 2.0, 0.0), (0.5, 2.5, 0.9))]


def test_two_chairs_side_by_side_seen_one_at_a_time_stay_two_under_a_mask_that_spans_them():
    # Never detected apart in one frame either (one at a time), but they stand on two footprints: a mask
    # spanning both is shared out between them, as between two screens.
    store = MemoryStore()
    for i in range(10):
        eye = (0.3 * np.sin(i), 0.5, 1.4)
        frame, instance = scene_frame(look_down_pose(eye, (0.0, 2.2, 0.5)), CHAIRS, floor_z=None, frame_id=f"f{i}")
        mask = instance == i % 2 if i < 6 else instance >= 0
        integrate_frame(frame, [Detection("chair", 0.9, mask)], store, PARAMS)
    objects = sorted(store.list_objects("m"), key=lambda o: o.aabb.min[0])
    assert len(objects) == 2 and not any(o.apart for o in objects)
    for obj, (lo, hi) in zip(objects, CHAIRS):
        assert obj.aabb.min[0] == pytest.approx(lo[0], abs=0.1) and obj.aabb.max[0] == pytest.approx(hi[0], abs=0.1)
