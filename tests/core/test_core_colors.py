"""Voxel colours: each voxel's mean RGB over the pixels that back-project into it, fused as a mean weighted
by the occupancy weights, kept aligned with the keys through every merge, split and subset, and never
changing anything else."""

from __future__ import annotations

import dataclasses
from collections import defaultdict

import numpy as np
from handmade_frames import CHAIR_RGB, HEIGHT, INTRINSICS, TABLE_RGB, WIDTH, plane_frame, rect_mask, two_box_frame

from arcloud.core.boxes import refine
from arcloud.core.fusion import (
    fuse_detection,
    keep_voxels,
    merge_objects,
    new_object,
    resolve_conflicts,
    split_detection,
    union_voxels,
)
from arcloud.core.step import integrate_frame
from arcloud.core.types import CLASS_INDEX, N_CLASSES, Detection, Intrinsics, MapObject, Params, VoxelDetection
from arcloud.core.voxels import (
    back_project,
    mask_samples,
    mean_colors,
    pack_keys,
    points_to_keys,
    sampling_stride_px,
    voxelize_detections,
)
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05)


def block(lo, hi):
    grid = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
    return np.unique(pack_keys(grid))


def key_colors(keys: np.ndarray) -> np.ndarray:
    """A colour that names its voxel: what survives any merge, split or subset of voxels coloured so."""
    return np.stack((keys % 251, keys % 241, keys % 239), axis=1).astype(np.uint8)


def half_up(values: np.ndarray) -> np.ndarray:
    return np.floor(np.asarray(values, np.float64) + 0.5).astype(np.uint8)


# --- from pixels to voxels ---------------------------------------------------------------------------
def test_voxel_colours_are_the_mean_of_the_samples_in_each_voxel() -> None:
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, size=(HEIGHT, WIDTH, 3), dtype=np.uint8)
    depth = np.tile(np.linspace(1.0, 1.6, WIDTH, dtype=np.float32), (HEIGHT, 1))  # a slanted wall: voxels of many sizes
    frame = plane_frame(1.0, rgb=rgb)
    frame = dataclasses.replace(frame, depth_m=depth)
    mask = rect_mask(slice(5, 55), slice(8, 75))
    (det,) = voxelize_detections(frame, [Detection("couch", 0.9, mask)], PARAMS)  # a couch: no depth cleanup
    # The plain version: every sample the voxelization takes, summed per voxel in a dict.
    v_px, u_px, z_m = mask_samples(frame, mask, PARAMS, sampling_stride_px(frame, PARAMS))
    sample_keys = points_to_keys(back_project(frame, v_px, u_px, z_m), PARAMS.voxel_size_m)
    sums: dict[int, np.ndarray] = defaultdict(lambda: np.zeros(3))
    counts: dict[int, int] = defaultdict(int)
    for key, colour in zip(sample_keys.tolist(), rgb[v_px, u_px].astype(np.float64)):
        sums[key] += colour
        counts[key] += 1
    assert sorted(sums) == det.keys.tolist()
    expected = half_up([sums[k] / counts[k] for k in det.keys.tolist()])
    assert det.colors is not None and det.colors.dtype == np.uint8 and det.colors.shape == (det.keys.size, 3)
    np.testing.assert_array_equal(det.colors, expected)
    assert len({tuple(c) for c in det.colors}) > det.keys.size / 2  # not all alike: the test can fail


def test_a_red_patch_gives_red_voxels_and_the_same_voxels_as_a_black_frame() -> None:
    frame, detections = two_box_frame()
    chair, table = voxelize_detections(frame, detections, PARAMS)
    assert {tuple(c) for c in chair.colors} == {CHAIR_RGB}
    assert {tuple(c) for c in table.colors} == {TABLE_RGB}
    black = dataclasses.replace(frame, rgb=np.zeros_like(frame.rgb))
    for coloured, plain in zip((chair, table), voxelize_detections(black, detections, PARAMS), strict=True):
        np.testing.assert_array_equal(coloured.keys, plain.keys)
        assert {tuple(c) for c in plain.colors} == {(0, 0, 0)}


def test_unregistered_colours_come_from_where_the_colour_camera_saw() -> None:
    # The depth camera at the origin sees a patch at 1.5 m before a wall at 3 m; the colour camera (longer
    # focal length, 10 cm to the right) sees the patch red where it projects. The colour image's pixels
    # at the patch's *depth* pixels are blue where they are not red: looked up there, colours would mix.
    patch = (slice(20, 40), slice(30, 50), 1.5)
    rgb_camera = Intrinsics(fx=120.0, fy=120.0, cx=42.0, cy=29.0)
    corners_px = np.array([[30, 20], [50, 40]], float)
    x = (corners_px[:, 0] - INTRINSICS.cx) * 1.5 / INTRINSICS.fx - 0.10
    y = (corners_px[:, 1] - INTRINSICS.cy) * 1.5 / INTRINSICS.fy
    u0, u1 = np.round(x * rgb_camera.fx / 1.5 + rgb_camera.cx).astype(int)
    v0, v1 = np.round(y * rgb_camera.fy / 1.5 + rgb_camera.cy).astype(int)
    rgb = np.full((HEIGHT, WIDTH, 3), 90, np.uint8)
    rgb[patch[0], patch[1]] = TABLE_RGB
    rgb[v0:v1, u0:u1] = CHAIR_RGB
    frame = plane_frame(3.0, patches=(patch,), rgb=rgb)
    depth2rgb = np.eye(4)
    depth2rgb[0, 3] = -0.10
    unregistered = dataclasses.replace(frame, rgb_intrinsics=rgb_camera, depth2rgb=depth2rgb)
    mask = [Detection("tv", 0.9, rect_mask(slice(v0 + 1, v1 - 1), slice(u0 + 1, u1 - 1)))]
    params = PARAMS.replace(layer_margin_m=None)
    (seen,) = voxelize_detections(unregistered, mask, params)
    assert {tuple(c) for c in seen.colors} == {CHAIR_RGB}
    assert (rgb[patch[0], patch[1]] == TABLE_RGB).all(axis=2).mean() > 0.1  # the mix a depth-pixel lookup would make


# --- fusion ------------------------------------------------------------------------------------------
def coloured(label: str, keys: np.ndarray, rgb: tuple[int, int, int], score: float = 0.9) -> VoxelDetection:
    return VoxelDetection(CLASS_INDEX[label], score, keys, np.tile(np.array(rgb, np.uint8), (keys.size, 1)))


def test_fusion_averages_colours_weighted_by_the_weights() -> None:
    keys = block((0, 0, 0), (3, 3, 3))
    obj = new_object(1, coloured("chair", keys, (10, 100, 200)), "a", 0.0)
    for _ in range(2):
        obj = fuse_detection(obj, coloured("chair", keys, (10, 100, 200)), "a")
    obj = fuse_detection(obj, coloured("chair", keys[:9], (12, 140, 0)), "b")  # weight 3 against 1
    assert obj.weights[:9].tolist() == [4] * 9 and obj.weights[9:].tolist() == [3] * 18
    np.testing.assert_array_equal(obj.colors[:9], np.tile(half_up([(3 * 10 + 12) / 4, (300 + 140) / 4, 600 / 4]), (9, 1)))
    assert obj.colors[0].tolist() == [11, 110, 150]  # 10.5 rounds up
    np.testing.assert_array_equal(obj.colors[9:], np.tile([10, 100, 200], (18, 1)))
    # The colours change nothing else: the same fusions without colours give the same arrays, bit for bit.
    plain = new_object(1, VoxelDetection(CLASS_INDEX["chair"], 0.9, keys), "a", 0.0)
    for _ in range(2):
        plain = fuse_detection(plain, VoxelDetection(CLASS_INDEX["chair"], 0.9, keys), "a")
    plain = fuse_detection(plain, VoxelDetection(CLASS_INDEX["chair"], 0.9, keys[:9]), "b")
    for name in ("keys", "weights", "seen", "votes"):
        assert getattr(obj, name).tobytes() == getattr(plain, name).tobytes(), name
    assert plain.colors is None


def test_a_merge_averages_each_shared_voxel_by_both_objects_weights() -> None:
    rng = np.random.default_rng(11)

    def random_object(object_id: int, keys: np.ndarray) -> MapObject:
        return MapObject(
            id=object_id,
            keys=keys,
            weights=rng.integers(1, 20, keys.size).astype(np.float32),
            votes=np.zeros((keys.size, N_CLASSES), np.float32),
            colors=rng.integers(0, 256, (keys.size, 3), dtype=np.uint8),
        )

    a = random_object(1, block((0, 0, 0), (6, 6, 6)))
    b = random_object(2, block((3, 3, 3), (9, 9, 9)))
    merged = merge_objects(a, b)
    evidence: dict[int, list[tuple[float, np.ndarray]]] = defaultdict(list)
    for obj in (a, b):
        for key, weight, colour in zip(obj.keys.tolist(), obj.weights.tolist(), obj.colors.astype(np.float64)):
            evidence[key].append((weight, colour))
    expected = half_up([sum(w * c for w, c in evidence[k]) / sum(w for w, _ in evidence[k]) for k in merged.keys.tolist()])
    np.testing.assert_array_equal(merged.colors, expected)
    assert not merged.colors.flags.writeable


def test_splits_subsets_and_conflicts_keep_colours_with_their_keys() -> None:
    keys = block((0, 0, 0), (8, 4, 4))
    det = VoxelDetection(CLASS_INDEX["chair"], 0.9, keys, key_colors(keys))
    parts = split_detection(det, [block((0, 0, 0), (3, 4, 4)), block((5, 0, 0), (8, 4, 4))], 1)
    assert sum(p.keys.size for p in parts) == keys.size and all(p.keys.size for p in parts)
    for part in parts:
        np.testing.assert_array_equal(part.colors, key_colors(part.keys))
    a = new_object(1, VoxelDetection(CLASS_INDEX["chair"], 0.9, keys, key_colors(keys)), "a", 0.0)
    other = block((6, 0, 0), (12, 4, 4))
    b = new_object(2, VoxelDetection(CLASS_INDEX["table"], 0.9, other, key_colors(other)), "a", 0.0)
    b = fuse_detection(b, VoxelDetection(CLASS_INDEX["table"], 0.9, other, key_colors(other)), "a")  # b wins shared voxels
    resolved = resolve_conflicts([a, b])
    assert resolved[0].keys.size < a.keys.size
    subset = keep_voxels(a, np.arange(a.keys.size) % 3 == 0)
    stray = new_object(
        3, VoxelDetection(CLASS_INDEX["chair"], 0.9, np.union1d(keys, pack_keys(np.array([[40, 40, 40]])))), "a", 0.0
    )
    for obj in (*resolved, subset, merge_objects(a, b), refine(a, PARAMS)):
        np.testing.assert_array_equal(obj.colors, key_colors(obj.keys))
    assert refine(stray, PARAMS).colors is None  # refined without colours: still none


def test_unknown_colours_stay_unknown_and_an_empty_object_takes_a_detections() -> None:
    keys = block((0, 0, 0), (3, 3, 3))
    known = new_object(1, coloured("tv", keys, (1, 2, 3)), "a", 0.0)
    assert known.colors is not None  # an empty object has no voxel of unknown colour
    unknown = known.replace(colors=None)  # as read from a blob of codec version 2
    assert fuse_detection(unknown, coloured("tv", keys[:5], (9, 9, 9)), "a").colors is None
    assert merge_objects(known, unknown).colors is None and merge_objects(unknown, known).colors is None
    assert fuse_detection(known, VoxelDetection(CLASS_INDEX["tv"], 0.9, keys[:5]), "a").colors is None
    assert keep_voxels(unknown, np.ones(keys.size, bool)).colors is None
    empty_unknown = unknown.replace(keys=keys[:0], weights=known.weights[:0], votes=known.votes[:0], seen=None)
    np.testing.assert_array_equal(fuse_detection(empty_unknown, coloured("tv", keys, (4, 5, 6)), "a").colors[0], [4, 5, 6])


def test_mean_colors_round_half_up() -> None:
    sums = np.array([[5.0, 2.0, 0.0], [7.0, 3.0, 0.0], [510.0, 4.0, 0.0]])  # channel first: 3 voxels
    np.testing.assert_array_equal(mean_colors(sums, np.array([2, 4, 1], np.float32)), [[3, 4, 255], [1, 1, 1], [0, 0, 0]])


def test_a_union_with_voxels_of_no_weight_gives_them_colour_0_without_a_warning() -> None:
    keys = block((0, 0, 0), (2, 1, 1))
    obj = new_object(1, coloured("tv", keys, (9, 9, 9)), "a", 0.0)
    got = union_voxels(obj, block((5, 0, 0), (7, 1, 1)), np.zeros(2, np.float32), np.zeros(2, np.float32), obj.votes, obj.colors)
    assert got.colors.tolist() == [[9, 9, 9]] * 2 + [[0, 0, 0]] * 2


# --- the step ----------------------------------------------------------------------------------------
def test_the_step_colours_the_objects_and_changes_nothing_else() -> None:
    coloured_store, black_store = MemoryStore(), MemoryStore()
    for i in range(4):
        frame, detections = two_box_frame(f"f{i}", shift_m=0.01 * i)
        integrate_frame(frame, detections, coloured_store, PARAMS, now_s=1.0)
        integrate_frame(dataclasses.replace(frame, rgb=np.zeros_like(frame.rgb)), detections, black_store, PARAMS, now_s=1.0)
    objects, plain = coloured_store.list_objects("m"), black_store.list_objects("m")
    assert [o.label for o in objects] == [o.label for o in plain] and len(objects) == 2
    for obj, other in zip(objects, plain):
        assert {tuple(c) for c in obj.colors} == {CHAIR_RGB if obj.label == "chair" else TABLE_RGB}
        for name in ("keys", "weights", "seen", "votes"):
            assert getattr(obj, name).tobytes() == getattr(other, name).tobytes(), name
        assert (obj.score, obj.n_frames, obj.version, obj.confirmed) == (
            other.score,
            other.n_frames,
            other.version,
            other.confirmed,
        )
        np.testing.assert_array_equal(obj.aabb.min, other.aabb.min)
        np.testing.assert_array_equal(obj.obb.center, other.obb.center)
