"""Geometry invariants of the core, as hypothesis properties (derandomized: the same examples every run).

- a refined object's AABB contains the centres of the voxels it is fitted to (``core.boxes``), and so does its
  gravity-aligned OBB where up is +z; where up is another direction the OBB's footprint is fitted to a
  re-gridded outline, and a centre may stand out of it by up to sqrt(2) / 2 voxel on the ground axes;
- merging two objects gives the same voxels, weights, seen counts, votes, colours and evidence in either
  order (``core.fusion.merge_objects``); only what the kept object's identity carries (id, version) differs;
- association: the overlap of two sets does not depend on which side each is on, and a detection tied
  between two identical objects is matched to one of them with the other as its rival, in either order of
  the objects (``core.associate``).
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from arcloud.core.associate import associate, overlap_matrix
from arcloud.core.boxes import box_voxel_mask, prune_voxels, refine
from arcloud.core.fusion import merge_objects
from arcloud.core.types import CLASS_INDEX, N_CLASSES, MapObject, Params
from arcloud.core.voxels import ijk_centers, pack_keys, unpack_keys

PROPERTY = settings(derandomize=True, max_examples=50, deadline=None)
EPS_M = 1e-9


@st.composite
def key_sets(draw: st.DrawFn, min_size: int = 1, max_size: int = 40, span: int = 8) -> np.ndarray:
    """Sorted unique packed keys of voxels in a ``span``-wide cube about a drawn corner (negative indices too)."""
    corner = draw(st.tuples(*[st.integers(-50, 50)] * 3))
    ijk = draw(st.lists(st.tuples(*[st.integers(0, span - 1)] * 3), min_size=min_size, max_size=max_size, unique=True))
    return np.unique(pack_keys(np.array(ijk, np.int64).reshape(-1, 3) + np.array(corner)))


@st.composite
def map_objects(draw: st.DrawFn, object_id: int = 1) -> MapObject:
    """An object with voxels, weights (whole detections), seen counts at least the weights (or unknown), votes and
    colours (or unknown), and evidence counters."""
    keys = draw(key_sets())
    n = keys.size
    weights = np.array(draw(st.lists(st.integers(1, 30), min_size=n, max_size=n)), np.float32)
    extra_seen = np.array(draw(st.lists(st.integers(0, 30), min_size=n, max_size=n)), np.float32)
    votes = draw(arrays(np.float32, (n, N_CLASSES), elements=st.sampled_from([0.0, 0.25, 0.5, 1.5, 3.0])))
    colors = draw(st.none() | arrays(np.uint8, (n, 3)))
    return MapObject(
        id=object_id,
        keys=keys,
        weights=weights,
        votes=votes,
        seen=draw(st.sampled_from([None, weights + extra_seen])),
        colors=colors,
        n_frames=int(weights.max()),
        devices=frozenset(draw(st.sets(st.sampled_from("abc")))),
        score_sum=draw(st.floats(0, 30, width=32)),
        created_at_s=draw(st.floats(0, 1e6)),
        n_missed=draw(st.integers(0, 5)),
        n_gone=draw(st.integers(0, 5)),
        floor_votes=draw(st.dictionaries(st.integers(-3, 3), st.integers(1, 4), max_size=3)),
        wall_votes=draw(st.dictionaries(st.integers(0, 359), st.tuples(st.integers(1, 4), st.integers(-5000, 5000)), max_size=3)),
        apart=draw(st.dictionaries(st.integers(1, 6), st.integers(1, 4), max_size=3)),
        spanned=draw(st.dictionaries(st.integers(1, 6), st.integers(1, 4), max_size=3)),
    )


ups = st.sampled_from([(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.3, 0.2, 1.0), (1.0, 1.0, 0.2)])


@PROPERTY
@given(obj=map_objects(), up=ups, voxel_size_m=st.sampled_from([0.02, 0.05, 0.1]), pad=st.sampled_from([0.0, 0.5]))
def test_a_refined_objects_boxes_contain_the_voxels_they_are_fitted_to(
    obj: MapObject, up: tuple[float, float, float], voxel_size_m: float, pad: float
) -> None:
    params = Params(voxel_size_m=voxel_size_m, up=up, box_pad_voxels=pad)
    # no floor or wall: with them, voxels just above the floor or behind the wall are left out of the boxes on purpose
    obj = obj.replace(floor_votes={}, wall_votes={})
    refined = refine(obj, params)
    pruned = prune_voxels(obj, params)
    if pruned.keys.size == 0:
        assert refined.aabb is None and refined.obb is None
        return
    fitted = box_voxel_mask(pruned, params)
    if not fitted.any():  # refine boxes every voxel then
        fitted[:] = True
    centers = ijk_centers(unpack_keys(pruned.keys[fitted]), voxel_size_m)
    assert refined.aabb is not None and refined.obb is not None
    assert np.all(centers >= refined.aabb.min - EPS_M) and np.all(centers <= refined.aabb.max + EPS_M)
    box = refined.obb
    assert np.allclose(box.rotation.T @ box.rotation, np.eye(3))
    local = (centers - box.center) @ box.rotation  # world -> box: the rotation's columns are the box's axes
    # Up +z: the footprint is the voxels' own cells, so the box holds every centre. Up otherwise: the footprint
    # is fitted to the centres of the cells of a grid in the gravity frame that the centres fall in, each at
    # most half a cell away on either ground axis, so a centre may stand out by up to sqrt(2) / 2 voxel there.
    slack = 0.0 if up == (0.0, 0.0, 1.0) else voxel_size_m * np.sqrt(2) / 2
    assert np.all(np.abs(local) <= box.size / 2 + [slack, slack, 0.0] + 1e-7)
    assert np.allclose(box.rotation[:, 2], params.gravity.up)  # gravity-aligned: the box's third axis is up


@PROPERTY
@given(a=map_objects(object_id=1), b=map_objects(object_id=2))
def test_merging_two_objects_does_not_depend_on_their_order(a: MapObject, b: MapObject) -> None:
    ab, ba = merge_objects(a, b), merge_objects(b, a)
    assert np.array_equal(ab.keys, ba.keys) and np.array_equal(ab.keys, np.union1d(a.keys, b.keys))
    for name in ("weights", "votes", "seen_counts"):
        assert np.array_equal(getattr(ab, name), getattr(ba, name)), name
    assert (ab.colors is None) == (ba.colors is None) and (ab.colors is None or np.array_equal(ab.colors, ba.colors))
    for name in (
        "n_frames",
        "n_missed",
        "n_gone",
        "devices",
        "score_sum",
        "created_at_s",
        "floor_votes",
        "wall_votes",
        "apart",
        "spanned",
    ):
        assert getattr(ab, name) == getattr(ba, name), name
    assert float(ab.weights.sum()) == float(a.weights.sum()) + float(b.weights.sum())  # nothing lost (whole numbers)
    assert (ab.id, ba.id) == (a.id, b.id)  # the kept object's identity


@PROPERTY
@given(
    sets_a=st.lists(key_sets(min_size=0), max_size=4),
    sets_b=st.lists(key_sets(min_size=0), max_size=4),
    tolerance=st.integers(0, 2),
)
def test_overlap_does_not_depend_on_which_side_a_set_is(
    sets_a: list[np.ndarray], sets_b: list[np.ndarray], tolerance: int
) -> None:
    overlap = overlap_matrix(sets_a, sets_b, tolerance)
    assert np.array_equal(overlap, overlap_matrix(sets_b, sets_a, tolerance).T)
    assert np.all((overlap >= 0) & (overlap <= 1))


@PROPERTY
@given(
    twin=key_sets(min_size=4),
    step=st.integers(1, 3),
    label=st.sampled_from(("chair", "laptop", "tv")),  # split classes: an established twin is a rival
    others=st.lists(key_sets(min_size=4), max_size=2),
)
def test_a_detection_tied_between_twins_takes_one_and_names_the_other_in_either_order(
    twin: np.ndarray, step: int, label: str, others: list[np.ndarray]
) -> None:
    """The detection lies inside both twins (cost 0 to each: the least there is); objects of another class
    cost more (their class penalty)."""
    params = Params(association_tolerance_voxels=0)
    index = CLASS_INDEX[label]
    objects = [twin, twin.copy(), *others]
    labels = [index, index] + [CLASS_INDEX["table"]] * len(others)
    for order in ([0, 1, *range(2, len(objects))], [1, 0, *range(2, len(objects))]):
        found = associate([twin[::step]], [index], [objects[i] for i in order], [labels[i] for i in order], params)
        ((d, o),) = found.pairs
        matched = order[o]
        assert d == 0 and matched in (0, 1) and found.unmatched == []
        assert [order[i] for i in found.rivals[0]] == [1 - matched]
