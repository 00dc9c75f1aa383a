import numpy as np
import pytest
from scipy import ndimage

from arcloud.core.boxes import (
    COMPONENT_GAP_VOXELS,
    box_voxel_mask,
    box_voxel_masks,
    fit_gravity_obb,
    label_side_by_side,
    refine,
    refine_all,
)
from arcloud.core.fusion import (
    VOTE_STEP,
    find_duplicates,
    fuse_detection,
    label_votes,
    merge_objects,
    new_object,
    object_label_index,
    resolve_conflicts,
    vote_of,
)
from arcloud.core.gravity import Gravity, up_rotation
from arcloud.core.types import CLASS_INDEX, Params, VoxelDetection, empty_object
from arcloud.core.voxels import pack_keys, unpack_keys


def block(lo, hi):
    grid = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
    return np.unique(pack_keys(grid))


def det(label, keys, score=0.9):
    return VoxelDetection(CLASS_INDEX[label], score, keys)


def test_fusion_adds_weights_and_votes_and_label_is_the_mode():
    keys = block((0, 0, 0), (4, 4, 4))
    obj = new_object(1, det("chair", keys), "a", 0.0)
    obj = fuse_detection(obj, det("chair", keys[:32]), "b")
    obj = fuse_detection(obj, det("couch", keys, 0.5), "b")
    assert obj.n_frames == 3 and obj.devices == {"a", "b"}
    assert obj.weights.max() == 3 and obj.weights.min() == 2
    assert object_label_index(obj) == CLASS_INDEX["chair"]
    assert obj.score_sum == pytest.approx(2.3)


def test_label_votes_sum_each_class_over_the_voxels_most_first_without_empty_classes():
    keys = block((0, 0, 0), (4, 4, 4))  # 64 voxels
    obj = new_object(1, det("couch", keys, 0.5), "a", 0.0)
    obj = fuse_detection(obj, det("chair", keys), "b")
    obj = fuse_detection(obj, det("chair", keys[:32]), "b")
    votes = label_votes(obj)
    assert list(votes) == ["chair", "couch"]  # most first, not in the order first voted
    assert votes == {"chair": 96 * float(vote_of(0.9)), "couch": 64 * float(vote_of(0.5))}
    assert label_votes(empty_object(2)) == {}  # no voxel, no vote


def test_votes_come_in_steps_so_their_sums_do_not_depend_on_the_order_of_frames():
    keys = block((0, 0, 0), (2, 2, 2))
    scores = np.random.default_rng(5).uniform(0.25, 1.0, 40)
    sums = []
    for order in (scores, scores[::-1]):
        obj = new_object(1, det("chair", keys, float(order[0])), "a", 0.0)
        for score in order[1:]:
            obj = fuse_detection(obj, det("chair", keys, float(score)), "a")
        sums.append(obj.votes[:, CLASS_INDEX["chair"]])
    np.testing.assert_array_equal(sums[0], sums[1])  # float32 sums of raw scores differ with their order
    assert sums[0][0] == sum(vote_of(float(s)) for s in scores) and sums[0][0] / VOTE_STEP == round(sums[0][0] / VOTE_STEP)
    assert abs(vote_of(0.7) - 0.7) <= VOTE_STEP / 2 and vote_of(0.0) == 0.0


def test_conflicts_leave_each_voxel_with_one_object():
    shared = block((0, 0, 0), (2, 2, 2))
    a = new_object(1, det("chair", np.union1d(shared, block((2, 0, 0), (4, 2, 2)))), "a", 0.0)
    b = new_object(2, det("table", np.union1d(shared, block((-2, 0, 0), (0, 2, 2)))), "a", 0.0)
    b = fuse_detection(b, det("table", shared), "a")  # b holds the shared voxels with more weight
    ra, rb = resolve_conflicts([a, b])
    assert np.intersect1d(ra.keys, rb.keys).size == 0
    assert np.isin(shared, rb.keys).all() and not np.isin(shared, ra.keys).any()
    assert ra.keys.size + rb.keys.size == np.union1d(a.keys, b.keys).size


def test_duplicates_of_same_label_merge_into_one():
    keys = block((0, 0, 0), (5, 5, 5))
    a = new_object(1, det("tv", keys), "a", 0.0)
    b = new_object(2, det("tv", keys[10:]), "b", 0.0)
    c = new_object(3, det("chair", keys), "c", 0.0)  # other label: stays apart
    far = new_object(4, det("tv", block((20, 0, 0), (25, 5, 5))), "d", 0.0)
    pairs = find_duplicates([a, b, c, far], Params())
    assert pairs == [(0, 1)]
    merged = merge_objects(a, b)
    assert merged.n_frames == 2 and merged.devices == {"a", "b"} and merged.keys.size == keys.size


def test_the_arms_of_a_couch_that_meet_merge_while_chairs_that_touch_stay_two():
    # An L-shaped couch first seen as its two arms (two users starting at either end): they meet at the
    # corner, share few voxels (within one voxel of each other) and their boxes overlap by half.
    arm_x = block((0, 0, 0), (40, 12, 8))  # 2.0 x 0.6 m
    arm_y = block((28, 6, 0), (40, 50, 8))  # the other arm, 2.2 m along y, over arm_x's end
    arms = [new_object(1, det("couch", arm_x), "a", 0.0), new_object(2, det("couch", arm_y), "b", 0.0)]
    params = Params()
    assert find_duplicates(arms, params) == [(1, 0)]  # one couch seen in parts, kept as the larger arm
    # With the threshold of the classes that stand side by side (chairs, TVs, laptops) they stay two.
    assert find_duplicates(arms, params.replace(merge_min_overlap_parts=params.merge_min_overlap)) == []
    # Two chairs touching the same way stay two.
    chairs = [new_object(1, det("chair", arm_x), "a", 0.0), new_object(2, det("chair", arm_y), "b", 0.0)]
    assert find_duplicates(chairs, params) == []


def test_refine_drops_stray_voxels_and_fits_tight_boxes():
    body = block((0, 0, 0), (10, 6, 4))  # 0.5 x 0.3 x 0.2 m at 5 cm
    stray = pack_keys(np.array([[40, 40, 40]]))
    obj = new_object(1, det("table", np.union1d(body, stray)), "a", 0.0)
    for _ in range(4):
        obj = fuse_detection(obj, det("table", body), "a")
    params = Params(voxel_size_m=0.05)
    refined = refine(obj, params)
    assert refined.label == "table"
    # Centre to centre (box_pad_voxels = 0): voxel centres 0.025 .. 0.475 etc.
    assert np.allclose(refined.aabb.min, [0.025, 0.025, 0.025]) and np.allclose(refined.aabb.max, [0.475, 0.275, 0.175])
    assert np.allclose(sorted(refined.obb.size), [0.15, 0.25, 0.45])
    padded = refine(obj, params.replace(box_pad_voxels=0.5))
    assert np.allclose(padded.aabb.min, [0, 0, 0]) and np.allclose(padded.aabb.max, [0.5, 0.3, 0.2])
    assert 0 < refined.score < 0.9
    assert refined.bounds.max[0] > 2.0  # the index bounds still cover every voxel kept


def test_background_seen_often_but_rarely_covered_is_pruned_and_kept_out_of_the_box():
    body = block((0, 0, 0), (6, 6, 6))
    wall = block((0, 6, 0), (6, 7, 6))  # one layer behind the object that masks bled onto once
    obj = new_object(1, det("tv", np.union1d(body, wall)), "a", 0.0)
    visible = np.ones(np.union1d(body, wall).size, bool)
    for _ in range(4):  # the wall is visible but not covered: occupancy 1/5
        obj = fuse_detection(obj, det("tv", body), "a", visible)
    assert set(box_voxel_mask(obj, Params()).nonzero()[0]) == set(np.flatnonzero(np.isin(obj.keys, body)))
    assert refine(obj, Params()).n_voxels == obj.n_voxels  # not seen often enough to prune yet
    for _ in range(8):
        obj = fuse_detection(obj, det("tv", body), "a", np.ones(obj.keys.size, bool))
    pruned = refine(obj, Params(prune_min_seen=10, prune_max_occupancy=0.1))
    assert np.array_equal(pruned.keys, body)
    # Rarely visible parts (legs) keep their voxels however strong the rest is.
    legs = block((0, 0, -6), (1, 1, 0))
    table = new_object(2, det("table", np.union1d(body, legs)), "a", 0.0)
    for i in range(50):  # the legs are in view (and covered) in 5 frames of 51
        seen_legs = i % 10 == 0
        covered = np.union1d(body, legs) if seen_legs else body
        table = fuse_detection(table, det("table", covered), "a", np.isin(table.keys, covered))
    assert np.isin(legs, refine(table, Params()).keys).all()
    assert box_voxel_mask(table, Params())[np.isin(table.keys, legs)].all()


def test_small_disconnected_part_is_not_in_the_box():
    body = block((0, 0, 0), (10, 10, 10))
    island = block((30, 0, 0), (31, 2, 2))  # 4 voxels, well observed but tiny
    obj = new_object(1, det("couch", np.union1d(body, island)), "a", 0.0)
    mask = box_voxel_mask(obj, Params())
    assert mask.sum() == body.size


def test_parts_joined_by_the_objects_own_weak_voxels_stay_in_the_box_and_empty_space_splits():
    # A screen's body and its back, one layer of the object's voxels between them that the occupancy rule
    # leaves out (seen 5 times, covered once: which voxels fall short is up to the frames' order): one part.
    body = block((0, 0, 0), (10, 10, 4))
    layer = block((0, 0, 4), (10, 10, 5))
    back = block((0, 0, 5), (10, 10, 6))  # a quarter of the body's voxels
    everything = np.union1d(np.union1d(body, layer), back)
    obj = new_object(1, det("tv", everything), "a", 0.0)
    for _ in range(4):
        obj = fuse_detection(obj, det("tv", np.union1d(body, back)), "a", np.ones(obj.keys.size, bool))
    params = Params(min_component_fraction=0.5)
    mask = box_voxel_mask(obj, params)
    assert set(obj.keys[mask]) == set(np.union1d(body, back))  # the weak layer joins, and stays out itself
    # A back beside the body with empty layers between them (never the object's): up to COMPONENT_GAP_VOXELS of
    # them, the back is what a camera below it saw thinly and stays; one more, it is a small part of its own.
    for gap in (1, COMPONENT_GAP_VOXELS, COMPONENT_GAP_VOXELS + 1):
        far_back = block((10 + gap, 0, 0), (11 + gap, 10, 4))  # ``gap`` empty layers behind the body (x 0-9)
        apart = new_object(2, det("tv", np.union1d(body, far_back)), "a", 0.0)
        kept = np.union1d(body, far_back) if gap <= COMPONENT_GAP_VOXELS else body
        assert set(apart.keys[box_voxel_mask(apart, params)]) == set(kept), gap


def test_a_part_a_gap_away_stays_only_within_the_gap_above_or_below_the_large_parts():
    # A screen (z 0-5) and, one empty layer below it, a piece the masks bled onto: reaching no further below the
    # screen than COMPONENT_GAP_VOXELS, it is the screen's lower edge and stays; reaching further, it is the shelf
    # under the screen and goes.
    screen = block((0, 0, 0), (12, 2, 6))
    params = Params(min_component_fraction=0.9)  # the piece is under 0.9 of the screen however deep
    for depth in (COMPONENT_GAP_VOXELS - 1, COMPONENT_GAP_VOXELS, 5):
        below = block((0, 0, -1 - depth), (12, 2, -1))  # the gap at z -1, the piece at z -1 - depth .. -2
        tv = new_object(1, det("tv", np.union1d(screen, below)), "a", 0.0)
        kept = np.union1d(screen, below) if 1 + depth <= COMPONENT_GAP_VOXELS else screen
        assert set(tv.keys[box_voxel_mask(tv, params)]) == set(kept), depth


def test_small_parts_chained_a_gap_apart_stay_but_not_through_a_part_that_goes():
    # A screen's back seen in two pieces behind it (x), each two empty voxels from the last: both stay. Below
    # the screen, a shelf too deep to stay, and a piece two empty voxels past the shelf's end: it reaches the
    # screen only through the shelf, so it goes with it.
    screen = block((0, 0, 0), (12, 2, 6))
    near_piece, far_piece = block((0, 4, 0), (12, 5, 6)), block((0, 7, 0), (12, 8, 6))
    params = Params(min_component_fraction=0.9)
    tv = new_object(1, det("tv", np.union1d(screen, np.union1d(near_piece, far_piece))), "a", 0.0)
    assert box_voxel_mask(tv, params).all()
    shelf, past_shelf = block((0, 0, -5), (16, 2, -1)), block((19, 0, -2), (21, 2, -1))
    tv = new_object(2, det("tv", np.union1d(screen, np.union1d(shelf, past_shelf))), "a", 0.0)
    assert set(tv.keys[box_voxel_mask(tv, params)]) == set(screen)


def test_a_chain_carries_only_through_parts_with_voxels_kept():
    # In front of a screen (y 0-1), single voxels every third voxel along y: the masks covered them once in five
    # views, so the occupancy rule leaves them out. At the chain's end, a stray voxel the masks covered in every view.
    # Each is within the gap of the next, but only kept voxels carry a chain: the stray goes. With the weak voxels
    # covered as often as the screen, they are a TV's back seen in pieces, and the chain and its end stay.
    screen = block((0, 0, 0), (12, 2, 6))
    hops = [block((5, y, 3), (6, y + 1, 4)) for y in (4, 7, 10)]
    stray = block((5, 13, 3), (6, 14, 4))
    chain = np.unique(np.concatenate(hops))
    params = Params(min_component_fraction=0.9)
    for chain_covered in (False, True):
        tv = new_object(1, det("tv", np.unique(np.concatenate([screen, chain, stray]))), "a", 0.0)
        again = np.unique(np.concatenate([screen, stray] + ([chain] if chain_covered else [])))
        for _ in range(4):
            tv = fuse_detection(tv, det("tv", again), "a", np.ones(tv.keys.size, bool))
        mask = box_voxel_mask(tv, params)
        expected = np.unique(np.concatenate([screen, chain, stray])) if chain_covered else screen
        assert set(tv.keys[mask]) == set(expected), chain_covered


def test_floor_clearance_does_not_turn_on_where_the_grid_falls():
    # Voxels whose bottoms lie exactly floor_clearance_m above the floor are on the line (floor, not object),
    # however the floor height and the voxels' corners round: the world moved by whole voxels keeps the verdict.
    params = Params(voxel_size_m=0.05, min_component_fraction=0.0)
    kept_rows = set()
    for shift in range(-30, 30, 7):
        keys = block((0, 0, shift), (4, 4, shift + 8))
        obj = new_object(1, det("chair", keys), "a", 0.0)
        # the floor 0.8 voxels (floor_clearance_m) below the lowest row's bottom: that row's bottom on the line
        floor_m = (shift - params.floor_clearance_m / params.voxel_size_m) * params.voxel_size_m
        (mask,) = box_voxel_masks([obj], params, [unpack_keys(obj.keys)], [floor_m], [None])
        kept_rows.add(int(np.count_nonzero(mask)) // 16)
    assert kept_rows == {7}  # the row on the line out, every other row in, at every shift


def test_a_part_a_gap_away_is_not_joined_where_it_would_make_the_box_one_the_class_cannot_have():
    # A laptop 0.30 m long (7 voxels at 5 cm, between outer centres) and, two empty voxels past its end, 4 voxels of
    # the keyboard beside it that masks bled onto: joined, the laptop would be 0.60 m long (a laptop is at most
    # 0.55 m), so the piece stays a small part of its own and out of the box. The same shapes as a TV's are a size
    # a TV can have, and join.
    body, beside = block((0, 0, 0), (7, 5, 1)), block((9, 0, 0), (13, 5, 1))
    params = Params(voxel_size_m=0.05, min_component_fraction=0.7, box_pad_voxels=0)
    laptop = new_object(1, det("laptop", np.union1d(body, beside)), "a", 0.0)
    assert set(laptop.keys[box_voxel_mask(laptop, params)]) == set(body)
    screen, back = block((0, 0, 0), (7, 1, 6)), block((9, 0, 0), (13, 1, 6))
    tv = new_object(2, det("tv", np.union1d(screen, back)), "a", 0.0)
    assert box_voxel_mask(tv, params).all()


def test_small_parts_a_gap_apart_are_not_counted_as_one_larger_part():
    # A part of 100 voxels, and far from it two of 75 one empty layer apart: each of the two is small beside the
    # first (under 0.8 of it) and stays small, though together they would be the largest.
    a = block((0, 0, 0), (10, 10, 1))
    b, c = block((30, 0, 0), (45, 5, 1)), block((30, 6, 0), (45, 11, 1))
    params = Params(min_component_fraction=0.8)
    obj = new_object(1, det("table", np.union1d(np.union1d(a, b), c)), "a", 0.0)
    assert set(obj.keys[box_voxel_mask(obj, params)]) == set(a)


def same_parts(a, b):
    """Whether two labellings of one grid make the same parts (label numbers aside)."""
    pairs = np.unique(np.stack((a.ravel(), b.ravel())), axis=1)
    return len(set(pairs[0])) == len(set(pairs[1])) == pairs.shape[1] and bool(((a == 0) == (b == 0)).all())


@pytest.mark.parametrize("widths", [(6, 5, 7), (3, 40, 2)])  # side by side, and too unlike to share an array
def test_grids_labelled_side_by_side_have_the_parts_each_has_alone(widths):
    rng = np.random.default_rng(sum(widths))
    grids = [rng.random((int(rng.integers(2, 9)), w, int(rng.integers(2, 6)))) < 0.3 for w in widths]
    labelled = label_side_by_side([(list(g.shape), np.argwhere(g)) for g in grids])
    structure = np.ones((3, 3, 3), bool)
    for grid, parts in zip(grids, labelled):
        assert parts.shape == grid.shape and same_parts(parts, ndimage.label(grid, structure=structure)[0])
    # Two cells of one grid on its last layer, and a next grid whose first layer would join them: still two parts.
    ends, bridge = np.zeros((2, 1, 5), bool), np.ones((1, 1, 5), bool)
    ends[1, 0, [0, 4]] = True
    first, _ = label_side_by_side([(list(ends.shape), np.argwhere(ends)), (list(bridge.shape), np.argwhere(bridge))])
    assert first[1, 0, 0] != first[1, 0, 4]


def test_box_voxels_and_refined_objects_together_are_each_ones_own():
    body = block((0, 0, 0), (10, 10, 10))
    with_island = new_object(1, det("couch", np.union1d(body, block((30, 0, 0), (31, 2, 2)))), "a", 0.0)
    screen = new_object(
        2, det("tv", np.union1d(block((0, 0, 0), (10, 10, 4)), block((0, 0, 7), (10, 10, 8)))), "a", 0.0
    )  # 3 empty layers
    small = new_object(3, det("chair", block((5, 5, 5), (6, 6, 7))), "a", 0.0)
    objects, params = [with_island, screen, small], Params(min_component_fraction=0.5)
    masks = box_voxel_masks(objects, params, [unpack_keys(o.keys) for o in objects], [None] * 3, [None] * 3)
    assert [m.tolist() for m in masks] == [box_voxel_mask(o, params).tolist() for o in objects]
    assert masks[0].sum() == body.size and masks[1].sum() == 400  # each lost its small part
    for together, alone in zip(refine_all(objects, params), [refine(o, params) for o in objects]):
        assert np.array_equal(together.keys, alone.keys) and together.label == alone.label
        assert np.array_equal(together.aabb.min, alone.aabb.min) and np.array_equal(together.aabb.max, alone.aabb.max)
        assert np.array_equal(together.obb.center, alone.obb.center) and np.array_equal(together.obb.size, alone.obb.size)


def test_gravity_obb_recovers_a_rotated_box():
    rng = np.random.default_rng(4)
    yaw = 0.4
    local = rng.uniform([-1.0, -0.4, 0.0], [1.0, 0.4, 0.7], (4000, 3))
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    obb = fit_gravity_obb(local @ rot.T + [3.0, 1.0, 0.0], 0.0, Gravity.of((0.0, 0.0, 1.0)))
    assert np.allclose(sorted(obb.size), [0.7, 0.8, 2.0], atol=0.03)
    assert np.allclose(obb.center, [3.0, 1.0, 0.35], atol=0.03)
    assert np.allclose(up_rotation(np.array([0.0, -1.0, 0.0])) @ [0, -1, 0], [0, 0, 1])


def test_one_layer_of_voxels_gives_a_box_one_voxel_thick():
    flat = new_object(1, det("table", block((0, 0, 0), (8, 6, 1))), "a", 0.0)
    refined = refine(flat, Params(voxel_size_m=0.05))
    assert np.allclose(refined.aabb.size, [0.35, 0.25, 0.05])
    assert np.allclose(sorted(refined.obb.size), [0.05, 0.25, 0.35])


def test_objects_on_one_line_get_a_box_along_it():
    # qhull refuses collinear footprints (more than 64 outline points go to it): a long thin row of voxels.
    line = np.stack([np.arange(100) * 0.05 + 0.025, np.arange(100) * 0.05 + 0.025, np.full(100, 0.5)], axis=1)
    obb = fit_gravity_obb(line, 0.05, Gravity.of((0.0, 0.0, 1.0)), 0.0)
    assert sorted(obb.size[:2].round(2)) == [0.05, pytest.approx(np.hypot(4.95, 4.95), abs=0.01)]
    straight = line * np.array([1.0, 0.0, 1.0]) + np.array([0.0, 0.025, 0.0])
    assert fit_gravity_obb(straight, 0.05, Gravity.of((0.0, 0.0, 1.0)), 0.0).size[:2].round(2).tolist() == [4.95, 0.05]


def test_a_merged_object_keeps_the_misses_of_its_larger_piece_not_their_sum():
    # A desk detected in 8 frames and missed in 3, and a fragment of it detected once and then missed in 27
    # frames that detected the desk instead: merged, the desk was missed in 3 frames, not 30.
    desk = new_object(1, det("table", block((0, 0, 0), (10, 6, 2))), "a", 0.0)
    for _ in range(7):
        desk = fuse_detection(desk, det("table", desk.keys), "a")
    desk = desk.replace(n_missed=3)
    fragment = new_object(2, det("table", block((8, 4, 0), (12, 8, 2))), "a", 0.0).replace(n_missed=27)
    for merged in (merge_objects(desk, fragment), merge_objects(fragment, desk)):
        assert (merged.n_frames, merged.n_missed) == (9, 3)
