import itertools

import numpy as np
import pytest

from arcloud.core.associate import (
    GATED_COST,
    UNMATCHED_COST,
    associate,
    association_cost,
    hungarian_match,
    overlap_matrix,
)
from arcloud.core.types import Params
from arcloud.core.voxels import KEY_MASK, KEY_OFFSET, NEARNESS_GRID_CELLS, nearness, pack_keys, shared_count


def random_sets(rng, n, universe=400, size=(0, 60)):
    return [np.unique(rng.integers(0, universe, rng.integers(*size))).astype(np.int64) for _ in range(n)]


def test_nearness_is_two_on_the_other_set_one_within_reach_else_zero():
    rng = np.random.default_rng(3)
    for _ in range(30):
        a, b = (np.unique(rng.integers(-6, 6, (int(rng.integers(1, 60)), 3)), axis=0) for _ in range(2))
        reach = int(rng.integers(0, 3))
        # Chebyshev distance of every voxel of a to its nearest in b.
        nearest = np.abs(a[:, None, :] - b[None, :, :]).max(axis=2).min(axis=1)
        order = np.argsort(pack_keys(a))
        got = nearness(pack_keys(a)[order], np.sort(pack_keys(b)), reach)
        expected = np.where(nearest == 0, 2, np.where(nearest <= reach, 1, 0))[order]
        assert np.array_equal(got, expected)
        assert shared_count(pack_keys(a)[order], np.sort(pack_keys(b)), reach) == expected.sum() / 2


def test_nearness_of_sets_with_stray_voxels_far_off_is_found_without_a_grid_of_their_extent():
    # Two small sets, each with a voxel 150 voxels off: their extents span a grid past NEARNESS_GRID_CELLS.
    rng = np.random.default_rng(8)
    a = np.vstack([np.unique(rng.integers(0, 8, (60, 3)), axis=0), [[150, 150, 150]]])
    b = np.vstack([np.unique(rng.integers(0, 8, (60, 3)), axis=0) + (0, 1, 0), [[-150, 149, 151]], [[149, 151, 150]]])
    assert np.prod(np.ptp(np.vstack([a, b]), axis=0) + 1) > NEARNESS_GRID_CELLS
    nearest = np.abs(a[:, None, :] - b[None, :, :]).max(axis=2).min(axis=1)
    order = np.argsort(pack_keys(a))
    expected = np.where(nearest == 0, 2, np.where(nearest <= 1, 1, 0))[order]
    assert np.array_equal(nearness(pack_keys(a)[order], np.sort(pack_keys(b)), 1), expected)
    assert expected[-1] == 1  # a's stray voxel (the last key), beside one of b's


def test_nearness_at_the_edges_of_the_packable_range():
    top, bottom = KEY_MASK - KEY_OFFSET, -KEY_OFFSET
    for a, b in (([top - 1, 0, 0], [top, 0, 1]), ([bottom + 1, 0, 0], [bottom, 0, 1]), ([0, top, 0], [1, top - 1, 0])):
        assert nearness(pack_keys(np.array([a])), pack_keys(np.array([b])), 1).tolist() == [1]
        assert nearness(pack_keys(np.array([b])), pack_keys(np.array([b])), 1).tolist() == [2]


def sheet(y: int, size: int = 8) -> np.ndarray:
    """A wall one voxel thick at y, ``size`` x ``size`` voxels."""
    i, k = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    return np.sort(pack_keys(np.column_stack([i.ravel(), np.full(i.size, y), k.ravel()])))


def test_sheets_one_voxel_apart_overlap_wherever_the_grid_falls():
    # Coarsened by 2, sheets at y 30 / 31 shared every coarse voxel and at 31 / 32 none: now half, at every y.
    for y in (30, 31, -7):
        assert overlap_matrix([sheet(y)], [sheet(y + 1)], 1)[0, 0] == 0.5
        assert overlap_matrix([sheet(y)], [sheet(y)], 1)[0, 0] == 1.0
        assert overlap_matrix([sheet(y)], [sheet(y + 2)], 1)[0, 0] == 0.0
        assert overlap_matrix([sheet(y)], [sheet(y + 1)], 0)[0, 0] == 0.0


def test_the_overlap_does_not_depend_on_where_the_grid_falls():
    rng = np.random.default_rng(11)
    a, b = (
        [np.unique(rng.integers(0, 6, (int(rng.integers(5, 80)), 3)) + rng.integers(-8, 8, 3), axis=0) for _ in range(n)]
        for n in (6, 4)
    )
    reference = overlap_matrix([np.sort(pack_keys(x)) for x in a], [np.sort(pack_keys(x)) for x in b], 1)
    assert reference.any() and not reference.all()
    for shift in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [-3, 5, 2]):
        moved = overlap_matrix([np.sort(pack_keys(x + shift)) for x in a], [np.sort(pack_keys(x + shift)) for x in b], 1)
        assert np.array_equal(moved, reference)


def brute_force(cost):
    """The minimum total cost over every matching of rows to distinct columns, each row paired by a pair the gates
    let through or left unpaired at ``UNMATCHED_COST``, and the matchings (sorted pairs) that reach it: more than
    one where costs tie."""
    d, o = cost.shape
    matchings = []
    for choice in itertools.product([None, *range(o)], repeat=d):  # each row's column, or None: unpaired
        taken = [c for c in choice if c is not None]
        if len(taken) == len(set(taken)) and all(c is None or cost[r, c] < GATED_COST for r, c in enumerate(choice)):
            matchings.append([(r, c) for r, c in enumerate(choice) if c is not None])
    totals = [sum(cost[r, c] for r, c in pairs) + UNMATCHED_COST * (d - len(pairs)) for pairs in matchings]
    best = min(totals)
    return best, {tuple(sorted(pairs)) for pairs, total in zip(matchings, totals) if total <= best + 1e-9}


@pytest.mark.parametrize("seed", range(25))
def test_hungarian_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    dets, objs = random_sets(rng, int(rng.integers(1, 5)), 120), random_sets(rng, int(rng.integers(1, 5)), 120)
    labels_d, labels_o = rng.integers(0, 3, len(dets)), rng.integers(0, 3, len(objs))
    params = Params(association_min_overlap=0.2, association_tolerance_voxels=0, class_aware=bool(seed % 2))
    cost = association_cost(overlap_matrix(dets, objs, 0), labels_d, labels_o, params)
    assert np.isfinite(cost).all()
    pairs = hungarian_match(cost)
    best, optimal = brute_force(cost)
    total = sum(cost[r, c] for r, c in pairs) + UNMATCHED_COST * (cost.shape[0] - len(pairs))
    assert total == pytest.approx(best)
    assert tuple(sorted(pairs)) in optimal  # one of the optimal matchings, gated pairs left out
    assert all(cost[r, c] < GATED_COST for r, c in pairs)


def test_a_weak_pair_never_displaces_a_strong_one_to_pair_more():
    # desks D, A, C in a row: A mapped whole, D in part, C new. A's detection covers A and touches D; C's touches A.
    overlap = np.array([[1.0, 0.333], [0.2, 0.0]])  # rows: the detections of A and C; columns: objects A and D
    cost = association_cost(overlap, [0, 0], [0, 0], Params())
    assert hungarian_match(cost) == [(0, 0)]  # A's detection to A; C's left to become a new object, not welded to A
    assert hungarian_match(cost[1:]) == [(0, 0)]  # alone, C's detection still joins A (shares 0.2)


def test_gating_keeps_weak_pairs_unmatched_and_class_aware_option():
    obj = np.arange(100, dtype=np.int64)
    strong = np.arange(50, dtype=np.int64)  # all inside the object
    weak = np.arange(95, 195, dtype=np.int64)  # 5 of 100 inside
    params = Params(association_min_overlap=0.2, association_tolerance_voxels=0)
    found = associate([strong, weak], [0, 0], [obj], [0], params)
    pairs, unmatched = found.pairs, found.unmatched
    assert pairs == [(0, 0)] and unmatched == [1]
    # Class-aware (default): a label mismatch is gated unless the overlap reaches class_mismatch_min_overlap.
    partly = np.arange(50, 150, dtype=np.int64)  # 50 of 100 inside
    assert params.class_mismatch_min_overlap > 0.5
    found = associate([partly], [1], [obj], [0], params)
    pairs, unmatched = found.pairs, found.unmatched
    assert pairs == [] and unmatched == [0]
    pairs = associate([strong], [1], [obj], [0], params).pairs
    assert pairs == [(0, 0)]  # all inside: label confusion on one object
    pairs = associate([partly], [1], [obj], [0], params.replace(class_aware=False)).pairs
    assert pairs == [(0, 0)]  # not class-aware: only a penalty
    # With a same-label candidate as good, the penalty makes the matching choose it.
    pairs = associate([strong], [1], [obj, obj], [0, 1], params).pairs
    assert pairs == [(0, 1)]


def test_overlap_normalised_by_smaller_set_and_empty_sets_are_zero():
    big = np.arange(1000, dtype=np.int64)
    part = np.arange(10, dtype=np.int64)
    empty = np.empty(0, np.int64)
    overlap = overlap_matrix([part, empty], [big, empty], 0)
    assert overlap.tolist() == [[1.0, 0.0], [0.0, 0.0]]
    assert not np.isnan(overlap).any()


def test_each_object_takes_at_most_one_detection():
    obj = np.arange(100, dtype=np.int64)
    a, b = np.arange(0, 60, dtype=np.int64), np.arange(40, 100, dtype=np.int64)
    found = associate([a, b], [0, 0], [obj], [0], Params(association_tolerance_voxels=0))
    pairs, unmatched = found.pairs, found.unmatched
    assert len(pairs) == 1 and len(unmatched) == 1
