import numpy as np
import pytest
from handmade_frames import INTRINSICS, plane_frame, rect_mask
from scipy import ndimage

from arcloud.core.camera import boxes_in_frustum, frame_frustum, view_frustum
from arcloud.core.types import Detection, Params
from arcloud.core.voxels import (
    coarsen_keys,
    erode,
    erode_sampled,
    footprint_share,
    in_sorted,
    key_centers,
    mask_extent,
    mask_points,
    near_mask,
    pack_keys,
    sorted_unique,
    summed_area,
    unpack_keys,
    voxelize_detections,
)


def test_pack_unpack_round_trip_and_order():
    rng = np.random.default_rng(1)
    ijk = rng.integers(-(2**20), 2**20, size=(1000, 3))
    keys = pack_keys(ijk)
    assert np.array_equal(unpack_keys(keys), ijk)
    order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
    assert np.array_equal(np.argsort(keys, kind="stable"), order)
    with pytest.raises(ValueError, match="outside"):
        pack_keys(np.array([[2**20, 0, 0]]))


def test_erode_matches_definition():
    rng = np.random.default_rng(2)
    mask = rng.random((20, 30)) > 0.3
    eroded = erode(mask, 1)
    padded = np.pad(mask, 1)
    expected = np.ones_like(mask)
    for dr in range(3):
        for dc in range(3):
            expected &= padded[dr : dr + 20, dc : dc + 30]
    assert np.array_equal(eroded, expected)


def test_mask_points_back_project_exactly():
    frame = plane_frame(2.0)
    params = Params(erode_px=0)
    points = mask_points(frame, rect_mask(slice(30, 31), slice(40, 42)), params)
    # Pixels (u=40, v=30) and (u=41, v=30) at 2 m with f=100, c=(40, 30).
    assert np.allclose(points, [[0.0, 0.0, 2.0], [0.02, 0.0, 2.0]])


def test_voxelize_plane_patch_gives_expected_voxels_and_erosion_shrinks_it():
    pose = np.eye(4)
    pose[:3, 3] = [0.013, -0.021, 0.0]  # off-grid, so voxel edges do not line up with pixels
    frame = plane_frame(1.0, cam2world=pose)
    mask = rect_mask(slice(10, 50), slice(20, 60))  # 40x40 px at 1 m, f=100 -> 0.4 x 0.4 m
    no_erosion = voxelize_detections(frame, [Detection("table", 0.7, mask)], Params(erode_px=0, voxel_size_m=0.1))[0]
    centers = key_centers(no_erosion.keys, 0.1)
    assert np.allclose(centers[:, 2], 1.05)  # all on the plane z = 1 m -> voxel layer [1.0, 1.1)
    xs, ys = np.unique(np.round(centers[:, 0], 3)), np.unique(np.round(centers[:, 1], 3))
    # x spans [-0.2 + 0.013, 0.19 + 0.013] -> voxel columns -0.2..0.1 (4 voxels, plus the partial one)
    assert xs.size in (4, 5) and ys.size in (4, 5)
    assert no_erosion.keys.size == xs.size * ys.size
    assert no_erosion.label_index == 1 and no_erosion.score == pytest.approx(0.7)
    eroded = voxelize_detections(frame, [Detection("table", 0.7, mask)], Params(erode_px=6, voxel_size_m=0.1))[0]
    assert eroded.keys.size < no_erosion.keys.size
    assert np.isin(eroded.keys, no_erosion.keys).all()


def test_voxelize_respects_depth_range_and_drops_tiny_detections():
    frame = plane_frame(6.0)  # beyond the default 5 m
    mask = rect_mask(slice(0, 60), slice(0, 80))
    assert voxelize_detections(frame, [Detection("tv", 0.9, mask)], Params()) == []
    near = plane_frame(2.0)
    tiny = rect_mask(slice(30, 32), slice(40, 42))
    assert voxelize_detections(near, [Detection("tv", 0.9, tiny)], Params(erode_px=0)) == []


def test_frustum_contains_what_the_camera_sees():
    pose = np.eye(4)
    pose[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # camera looking along world +x, z up
    pose[:3, 3] = [1.0, 2.0, 1.5]
    frustum = view_frustum(INTRINSICS, 80, 60, pose, 0.5, 4.0)
    ahead = np.array([3.0, 2.0, 1.5])
    behind = np.array([-1.0, 2.0, 1.5])
    beside = np.array([3.0, 6.0, 1.5])
    inside = boxes_in_frustum(frustum, np.array([ahead, behind, beside]) - 0.1, np.array([ahead, behind, beside]) + 0.1)
    assert inside.tolist() == [True, False, False]
    big = boxes_in_frustum(frustum, np.array([[-5.0, -5.0, -5.0]]), np.array([[5.0, 5.0, 5.0]]))
    assert big.tolist() == [True]


def test_frame_frustum_near_far_from_depth():
    frame = plane_frame(2.0, patches=((slice(0, 5), slice(0, 5), 1.0),))
    frustum = frame_frustum(frame, Params())
    depths = frustum.corners[:, 2]
    assert depths.min() == pytest.approx(0.9) and depths.max() == pytest.approx(2.1)
    assert frame_frustum(plane_frame(0.0), Params()) is None


@pytest.mark.parametrize("factor", [2, 3, 4, 8])
def test_coarsen_keys_matches_unpack_divide_pack(factor):
    rng = np.random.default_rng(factor)
    ijk = rng.integers(-300, 300, (4000, 3))
    ijk[:2] = [[-(2**20), -(2**20), -(2**20)], [2**20 - 1, 2**20 - 1, 2**20 - 1]]  # the extreme indices
    keys = np.unique(pack_keys(ijk))
    expected = np.unique(pack_keys(np.floor_divide(unpack_keys(keys), factor)))
    got = coarsen_keys(keys, factor)
    assert got.dtype == expected.dtype and np.array_equal(got, expected)


def test_sorted_unique_matches_np_unique():
    rng = np.random.default_rng(0)
    for values in (rng.integers(-50, 50, 1000), rng.integers(0, 3, 1), np.empty(0, np.int64), rng.random(200).round(1)):
        got, expected = sorted_unique(values), np.unique(values)
        assert got.dtype == expected.dtype and np.array_equal(got, expected)


@pytest.mark.parametrize("radius_px, stride_px", [(0, 3), (1, 1), (2, 4), (3, 2)])
def test_erode_sampled_is_erode_then_sample(radius_px, stride_px):
    mask = np.random.default_rng(radius_px).random((37, 53)) < 0.9
    assert np.array_equal(erode_sampled(mask, radius_px, stride_px), erode(mask, radius_px)[::stride_px, ::stride_px])


def test_in_sorted_is_isin():
    rng = np.random.default_rng(5)
    for n_values, n_ordered in ((1000, 300), (50, 1), (20, 0), (0, 10)):
        values = rng.integers(-40, 40, n_values)
        ordered = sorted_unique(rng.integers(-30, 30, n_ordered))
        assert np.array_equal(in_sorted(values, ordered), np.isin(values, ordered))
    assert in_sorted(np.array([7, 9]), np.array([9])).tolist() == [False, True]  # past the last: not found


@pytest.mark.parametrize("radius_px", [1, 3, 8])
def test_near_mask_is_a_square_maximum_filter(radius_px):
    rng = np.random.default_rng(radius_px)
    mask = np.zeros((31, 47), bool)
    mask[tuple(rng.integers(0, (31, 47), (6, 2)).T)] = True  # a few pixels, some near the border
    mask[0, 5] = mask[12, 46] = True
    v, u = np.arange(31)[:, None], np.arange(47)[None, :]
    expected = ndimage.maximum_filter(mask.view(np.uint8), size=2 * radius_px + 1) > 0
    assert np.array_equal(near_mask(summed_area(mask), v, u, radius_px), expected)
    rows, cols = rng.integers(0, 31, 100), rng.integers(0, 47, 100)  # read at scattered pixels
    assert np.array_equal(near_mask(summed_area(mask), rows, cols, radius_px), expected[rows, cols])


@pytest.mark.parametrize("width", [64, 61])  # read as 64-bit words, and not
def test_mask_extent_is_the_bounding_box_of_the_pixels(width):
    rng = np.random.default_rng(width)
    for _ in range(50):
        mask = np.zeros((23, width), bool)
        mask[tuple(rng.integers(0, (23, width), (int(rng.integers(1, 6)), 2)).T)] = True
        rows, cols = np.nonzero(mask)
        assert mask_extent(mask) == (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)
    assert mask_extent(np.zeros((23, width), bool)) is None


def _box_keys(lo, hi):
    grid = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
    return sorted_unique(pack_keys(grid))


def test_footprint_share_tells_pieces_of_one_object_from_neighbours():
    params = Params()  # 5 cm voxels, one voxel of tolerance
    seat = _box_keys((0, 0, 8), (10, 10, 10))  # 0.5 x 0.5 m, 0.4-0.5 m up
    back = _box_keys((0, 8, 10), (10, 12, 18))  # above the seat's rear edge, reaching 0.1 m behind it
    # Of the back's 4 rows of ground cells: 2 on the seat's, 1 within a voxel of it, 1 beyond; either way round.
    assert footprint_share(back, seat, params) == footprint_share(seat, back, params) == 0.75
    beside = _box_keys((10, 0, 0), (20, 10, 18))  # a neighbour touching along x
    assert footprint_share(seat, beside, params) == pytest.approx(0.1)  # its edge column only
    apart = _box_keys((13, 0, 0), (23, 10, 18))
    assert footprint_share(seat, apart, params) == 0.0
    up_y = Params(up=(0.0, 1.0, 0.0))  # the same shapes with y up: the footprint is x-z
    assert footprint_share(seat, _box_keys((0, 20, 0), (10, 30, 10)), up_y) == 1.0
    assert footprint_share(seat, _box_keys((0, 20, 11), (10, 30, 20)), up_y) == 0.0
