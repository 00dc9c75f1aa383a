"""Each fast path of the core agrees exactly with its plain version, on many seeded random inputs."""

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import ConvexHull

from arcloud.core.associate import (
    index_bounds,
    index_bounds_of_sets,
    overlap_coefficient,
    overlap_matrix,
)
from arcloud.core.boxes import (
    at_least,
    at_least_floats,
    convex_hull_2d,
    fit_aabb,
    fit_gravity_obb,
    fit_voxels_aabb,
    fit_voxels_obb,
    footprint_outline,
    footprint_outline_plain,
    min_area_yaw,
    min_area_yaw_plain,
    voxels_outline,
)
from arcloud.core.checks import make_frame
from arcloud.core.fusion import box_containment
from arcloud.core.gravity import Gravity
from arcloud.core.types import AABB, Detection, Params, empty_object
from arcloud.core.voxels import (
    KEY_OFFSET,
    coarsen_keys,
    coarsen_keys_plain,
    erode,
    erode_sampled,
    ijk_bounds,
    ijk_centers,
    ijk_extent,
    key_centers,
    keys_bounds,
    keys_extent,
    pack_keys,
    points_extent,
    sampling_stride_px,
    sorted_unique,
    unpack_keys,
    visible_voxels,
    visible_voxels_of_sets,
    voxelize_detections,
)

CASES = 300


def random_ijk(rng, n):
    """Voxel indices near the origin, far out, and at the very edge of the key range."""
    scale = rng.choice([3, 50, 10**4, KEY_OFFSET - 1])
    return rng.integers(-scale, scale + 1, (n, 3))


def random_mask(rng, height, width):
    mask = np.zeros((height, width), bool)
    for _ in range(int(rng.integers(0, 4))):
        r0, c0 = rng.integers(0, height), rng.integers(0, width)
        mask[r0 : r0 + rng.integers(1, height + 1), c0 : c0 + rng.integers(1, width + 1)] = True
    mask |= rng.random((height, width)) < rng.choice([0.0, 0.002, 0.3])
    return mask


def test_sorted_unique_is_np_unique():
    rng = np.random.default_rng(0)
    for _ in range(CASES):
        values = rng.integers(-20, 20, int(rng.integers(0, 60))) * int(rng.choice([1, 10**12]))
        assert np.array_equal(sorted_unique(values), np.unique(values))


@pytest.mark.parametrize("factor", [1, 2, 3, 4, 5, 8, 16])
def test_coarsen_keys_is_its_plain_version(factor):
    rng = np.random.default_rng(factor)
    for _ in range(CASES // 3):
        keys = sorted_unique(pack_keys(random_ijk(rng, int(rng.integers(1, 200)))))
        assert np.array_equal(coarsen_keys(keys, factor), coarsen_keys_plain(keys, factor))


def test_voxel_centres_and_bounds_from_indices_are_those_from_keys():
    rng = np.random.default_rng(1)
    for _ in range(CASES):
        keys = pack_keys(random_ijk(rng, int(rng.integers(1, 50))))
        size = float(rng.choice([0.01, 0.05, 0.1]))
        ijk = unpack_keys(keys)
        assert np.array_equal(ijk_centers(ijk, size), key_centers(keys, size))
        assert all(np.array_equal(a, b) for a, b in zip(ijk_bounds(ijk, size), keys_bounds(keys, size)))


def test_index_extents_are_axis_reductions_of_the_unpacked_keys():
    rng = np.random.default_rng(7)
    for _ in range(CASES):
        ijk = random_ijk(rng, int(rng.integers(1, 300)))
        keys = pack_keys(ijk)  # unsorted, with repeats: the extents take any keys
        assert np.array_equal(unpack_keys(keys), ijk)
        plain = (ijk.min(axis=0), ijk.max(axis=0))
        for extent in (ijk_extent(ijk), keys_extent(keys), index_bounds(keys)):
            assert all(np.array_equal(a, b) and a.dtype == b.dtype for a, b in zip(extent, plain))


def test_points_extent_is_the_axis_reductions_signed_zeros_and_nan_included():
    rng = np.random.default_rng(8)
    for _ in range(CASES):
        points = rng.normal(0, 10, (int(rng.integers(1, 300)), int(rng.integers(1, 4))))
        points *= rng.choice([-1, 1], points.shape[1])[None] if rng.random() < 0.5 else np.sign(points)  # zeros at an end too
        if rng.random() < 0.2:  # columns of +0.0 and -0.0 alone: the order of comparisons picks the sign
            points = np.where(rng.random(points.shape) < 0.5, 0.0, -0.0)
        for special in rng.choice([0.0, -0.0, np.nan, np.inf], int(rng.integers(0, 3))):
            points[rng.integers(0, points.shape[0]), rng.integers(0, points.shape[1])] = special
        plain = (points.min(axis=0), points.max(axis=0))
        for a, b in zip(points_extent(points), plain):
            assert a.tobytes() == b.tobytes()  # bit for bit: the sign of a zero too


def test_erode_is_binary_erosion_with_background_outside():
    rng = np.random.default_rng(2)
    for _ in range(CASES):
        mask = random_mask(rng, int(rng.integers(1, 40)), int(rng.integers(1, 40)))
        radius = int(rng.integers(0, 4))
        plain = ndimage.binary_erosion(mask, np.ones((2 * radius + 1,) * 2, bool), border_value=0) if radius else mask
        assert np.array_equal(erode(mask, radius), plain)


def test_erode_sampled_is_erode_then_sampled():
    rng = np.random.default_rng(3)
    for _ in range(CASES):
        mask = random_mask(rng, int(rng.integers(1, 50)), int(rng.integers(1, 50)))
        radius, stride = int(rng.integers(0, 4)), int(rng.integers(1, 5))
        assert np.array_equal(erode_sampled(mask, radius, stride), erode(mask, radius)[::stride, ::stride])


def test_footprint_outline_is_its_plain_version():
    rng = np.random.default_rng(5)
    for _ in range(CASES):
        xy = rng.normal(0, rng.choice([0.05, 0.5, 3.0]), (int(rng.integers(1, 400)), 2)) + rng.uniform(-10, 10, 2)
        size = float(rng.choice([0.02, 0.05, 0.1]))
        assert np.array_equal(footprint_outline(xy, size), footprint_outline_plain(xy, size))


def sorted_voxels(rng, n):
    """Unique voxel indices (N, 3) sorted as their keys sort, of a few shapes and places."""
    ijk = random_ijk(rng, n) if rng.random() < 0.3 else rng.integers(-25, 25, (n, 3)) + rng.integers(-(10**5), 10**5, 3)
    return unpack_keys(sorted_unique(pack_keys(ijk)))


def test_voxels_outline_is_the_footprint_outline_of_their_centres():
    rng = np.random.default_rng(10)
    for _ in range(CASES):
        size = float(rng.choice([0.01, 0.02, 0.05, 0.1, 0.3]))
        ijk = sorted_voxels(rng, int(rng.integers(1, 400)))
        assert np.array_equal(voxels_outline(ijk, size), footprint_outline(ijk_centers(ijk, size)[:, :2], size))


def test_min_area_yaw_is_its_plain_version():
    rng = np.random.default_rng(11)
    for _ in range(CASES):
        points = (rng.integers(-30, 30, (int(rng.integers(3, 40)), 2)) + 0.5) * float(rng.choice([0.05, 0.1]))
        if rng.random() < 0.3:
            points = rng.normal(0, 2.0, points.shape)
        hull = convex_hull_2d(points)
        if len(hull) >= 3:
            assert min_area_yaw(hull) == min_area_yaw_plain(hull)
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])  # ties: the first angle
    assert min_area_yaw(square) == min_area_yaw_plain(square) == 0.0


def test_at_least_floats_is_at_least():
    rng = np.random.default_rng(12)
    for _ in range(CASES):
        lo = rng.normal(0, 1, 3) * rng.choice([0.0, 1.0], 3)
        hi = lo + rng.choice([0.0, 0.01, 0.5], 3) * rng.random(3)
        min_size = float(rng.choice([0.0, 0.05, 0.2]))
        floats = at_least_floats(lo.tolist(), hi.tolist(), min_size)
        arrays = at_least(lo, hi, min_size)
        assert all(np.array(f).tobytes() == a.tobytes() for f, a in zip(floats, arrays))  # signed zeros too


def test_voxels_aabb_is_the_aabb_of_their_centres():
    rng = np.random.default_rng(14)
    for _ in range(CASES):
        size, pad = float(rng.choice([0.02, 0.05, 0.1])), float(rng.choice([0.0, 0.05]))
        ijk = random_ijk(rng, int(rng.integers(1, 300)))
        lo, hi = (corner.tolist() for corner in ijk_extent(ijk))
        fast, plain = fit_voxels_aabb(lo, hi, size, pad), fit_aabb(ijk_centers(ijk, size), pad, size)
        assert fast.min.tobytes() == plain.min.tobytes() and fast.max.tobytes() == plain.max.tobytes()


def test_voxels_obb_is_the_obb_of_their_centres():
    rng = np.random.default_rng(13)
    up, tilted = Gravity.of((0.0, 0.0, 1.0)), Gravity.of((0.1, -0.2, 1.0))
    for case in range(CASES):
        size = float(rng.choice([0.02, 0.05, 0.1]))
        ijk = sorted_voxels(rng, int(rng.integers(1, 300)))
        gravity, pad = (up, tilted)[case % 2], [None, 0.0, size][case % 3]
        k_range = (int(ijk[:, 2].min()), int(ijk[:, 2].max())) if rng.random() < 0.5 else None
        fast = fit_voxels_obb(ijk, size, gravity, pad, k_range)
        plain = fit_gravity_obb(ijk_centers(ijk, size), size, gravity, pad)
        for a, b in ((fast.center, plain.center), (fast.size, plain.size), (fast.rotation, plain.rotation)):
            assert a.tobytes() == b.tobytes()
        assert fast.yaw_rad == plain.yaw_rad


def test_overlap_of_sets_with_themselves_is_that_of_a_copy_and_pair_by_pair():
    """The merge pass's call (one list on both sides, each pair once) against the general path, each pair's
    overlap coefficient on its own and the overlap's definition; with empty sets, wanted pairs and known bounds."""
    rng = np.random.default_rng(15)
    for _ in range(CASES // 3):
        n = int(rng.integers(1, 8))
        sets = [
            sorted_unique(pack_keys(rng.integers(-6, 6, (int(rng.integers(0, 3)) * int(rng.integers(1, 40)), 3)) + c))
            for c in rng.integers(-12, 12, (n, 3))
        ]
        wanted = rng.random((n, n)) < 0.7 if rng.random() < 0.7 else None
        bounds = [index_bounds(s) if s.size and rng.random() < 0.5 else None for s in sets]
        tolerance = int(rng.integers(0, 3))
        same = overlap_matrix(sets, sets, tolerance, bounds_a=bounds, bounds_b=bounds, pairs_wanted=wanted)
        copy = overlap_matrix(sets, list(sets), tolerance, bounds_a=bounds, bounds_b=bounds, pairs_wanted=wanted)
        assert same.tobytes() == copy.tobytes()
        for i, j in np.ndindex(n, n):
            if not sets[i].size or not sets[j].size or (wanted is not None and not wanted[i, j]):
                assert same[i, j] == 0.0
                continue
            assert (
                same[i, j]
                == overlap_coefficient(sets[i], sets[j], tolerance)
                == overlap_by_definition(sets[i], sets[j], tolerance)
            )


def overlap_by_definition(keys_a, keys_b, tolerance):
    """What the association's docstring says: of the smaller set (of sets of one size, whichever reads more), each
    voxel on the other counts 1 and each within ``tolerance`` along every axis a half."""

    def covered(x, y):
        distance = np.abs(unpack_keys(x)[:, None, :] - unpack_keys(y)[None, :, :]).max(axis=2).min(axis=1)
        return (np.count_nonzero(distance == 0) + np.count_nonzero((distance > 0) & (distance <= tolerance)) / 2) / x.size

    if keys_a.size != keys_b.size:
        return covered(*sorted((keys_a, keys_b), key=len))
    return max(covered(keys_a, keys_b), covered(keys_b, keys_a))


def box_containment_plain(objects):
    """``box_containment`` through numpy's wrappers (np.clip, np.prod, np.nan_to_num)."""
    n = len(objects)
    lo = np.array([o.aabb.min if o.aabb is not None else np.full(3, np.nan) for o in objects])
    hi = np.array([o.aabb.max if o.aabb is not None else np.full(3, np.nan) for o in objects])
    inter = np.prod(np.clip(np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None]), 0, None), axis=2)
    volume = np.prod(hi - lo, axis=1)
    smaller = np.minimum(volume[:, None], volume[None])
    out = np.divide(inter, smaller, out=np.zeros((n, n)), where=np.isfinite(smaller) & (smaller > 0))
    return np.nan_to_num(out)


def test_box_containment_is_its_plain_version():
    rng = np.random.default_rng(16)
    for _ in range(CASES):
        objects = []
        for i in range(int(rng.integers(1, 12))):
            lo = rng.normal(0, 1, 3).round(int(rng.integers(0, 3)))
            hi = lo + rng.choice([0.0, 0.1, 1.0, 1e-200], 3) * rng.random(3)  # flat, thin and tiny boxes too
            box = None if rng.random() < 0.2 else AABB(lo, hi)
            objects.append(empty_object(i).replace(aabb=box))
        assert box_containment(objects).tobytes() == box_containment_plain(objects).tobytes()


def test_monotone_chain_hull_is_qhulls_polygon():
    """Every qhull vertex, in the same counter-clockwise order; where rounding makes a point on an edge
    look convex to the chain's cross product (qhull leaves it out), the chain keeps it on that edge."""
    rng = np.random.default_rng(6)
    for _ in range(CASES):
        n = int(rng.integers(3, 65))
        points = (rng.integers(-30, 30, (n, 2)) + 0.5) * 0.05  # cell centres, as the box fit gives them
        if np.linalg.matrix_rank(points - points[0]) < 2:
            continue  # qhull refuses collinear points
        fast, plain = convex_hull_2d(points), points[ConvexHull(points).vertices]
        on_plain = [int(np.flatnonzero((plain == p).all(axis=1))[0]) if (plain == p).all(axis=1).any() else -1 for p in fast]
        kept = [i for i in on_plain if i >= 0]
        assert sorted(kept) == list(range(len(plain)))  # all of qhull's vertices
        assert np.array_equal(np.roll(kept, -kept.index(0)), np.arange(len(plain)))  # in its order
        for at, p in zip(on_plain, fast):
            if at < 0:  # an extra point: on the segment between its neighbours on qhull's polygon
                a, b = plain - p, np.roll(plain, -1, axis=0) - p
                distance = np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) / np.linalg.norm(b - a, axis=1)
                assert distance.min() < 1e-12


def test_a_z_up_box_skips_the_rotation_by_the_identity():
    rng = np.random.default_rng(7)
    identity = Gravity.of((0.0, 0.0, 1.0))
    rotating = Gravity(identity.world2gravity.copy(), False)  # the same rotation, applied
    for _ in range(CASES // 3):
        centers = (rng.integers(-40, 40, (int(rng.integers(1, 300)), 3)) + 0.5) * 0.05
        a, b = fit_gravity_obb(centers, 0.05, identity), fit_gravity_obb(centers, 0.05, rotating)
        assert np.array_equal(a.center, b.center) and np.array_equal(a.size, b.size) and a.yaw_rad == b.yaw_rad


def test_pixel_stride_is_capped_by_params_and_one_samples_every_pixel():
    rng = np.random.default_rng(8)
    depth = np.full((120, 160), 0.8, np.float32)  # near: a pixel spans 4 mm, a voxel 12 pixels
    frame = make_frame(
        np.zeros((120, 160, 3), np.uint8),
        depth,
        (200.0, 200.0, 80.0, 60.0),
        np.eye(4),
        timestamp_s=0.0,
        map_id="m",
        device_id="d",
        frame_id="f",
    )
    assert sampling_stride_px(frame, Params()) == 4
    assert sampling_stride_px(frame, Params(pixel_stride_max_px=2)) == 2
    assert sampling_stride_px(frame, Params(pixel_stride_max_px=1)) == 1
    mask = random_mask(rng, 120, 160)
    every, sampled = (
        voxelize_detections(frame, [Detection("tv", 0.9, mask)], Params(pixel_stride_max_px=n, erode_px=0)) for n in (1, 4)
    )
    assert np.isin(sampled[0].keys, every[0].keys).all()  # a sample of the same pixels


def test_visibility_of_several_sets_at_once_is_that_of_each_set():
    rng = np.random.default_rng(9)
    params = Params()
    for _ in range(CASES // 3):
        depth = rng.uniform(0.5, 4.0, (48, 64)).astype(np.float32)
        depth[rng.random(depth.shape) < 0.2] = 0.0
        pose = np.eye(4)
        pose[:3, 3] = rng.normal(0, 0.2, 3)
        frame = make_frame(
            np.zeros((48, 64, 3), np.uint8),
            depth,
            (50.0, 50.0, 31.5, 23.5),
            pose,
            timestamp_s=0.0,
            map_id="m",
            device_id="d",
            frame_id="f",
        )
        sets = [
            sorted_unique(pack_keys(rng.integers(-30, 30, (int(rng.integers(0, 80)), 3)) + [0, 0, 40]))
            for _ in range(int(rng.integers(1, 6)))
        ]
        together = visible_voxels_of_sets(frame, sets, params)
        assert len(together) == len(sets)
        for keys, visible in zip(sets, together):
            assert np.array_equal(visible, visible_voxels(frame, keys, params))


def test_bounds_of_several_sets_at_once_are_those_of_each():
    rng = np.random.default_rng(10)
    for _ in range(CASES // 3):
        sets = [pack_keys(random_ijk(rng, int(rng.integers(1, 60)))) for _ in range(int(rng.integers(1, 8)))]
        together = index_bounds_of_sets(sets)
        assert together.shape == (len(sets), 2, 3) and together.dtype == np.int64
        assert all(np.array_equal(b, index_bounds(keys)) for b, keys in zip(together, sets))
