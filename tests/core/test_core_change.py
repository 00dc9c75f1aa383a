"""Change over time (core.step.count_misses, core.voxels.free_voxels): a frame that sees an object's
place empty (depth behind it) counts it *gone*, one that sees it there and detects nothing counts a
plain miss; an object seen gone in ``retire_min_gone_frames`` frames since it was last seen is retired
(event ``retired``, kept in the store's history); one missed in nearly every frame that saw it is deleted
as a phantom (event ``deleted``). Hand-made frames: exact boxes, exact depth."""

from __future__ import annotations

import numpy as np
import pytest
from handmade_frames import HEIGHT, INTRINSICS, WIDTH, look_down_pose, plane_frame, scene_frame

from arcloud.core.step import integrate_frame, stands_apart
from arcloud.core.types import AABB, Detection, MapObject, Params
from arcloud.core.voxels import center_rays, free_voxels, key_centers, min_pyramid, points_to_keys, visible_voxels
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05, floor_min_samples=5)
CHAIR = ((-0.25, -0.25, 0.0), (0.25, 0.25, 0.9))
SHIELD = ((-1.2, -1.2, 0.0), (1.2, 1.2, 2.0))  # a crate over the chair's place: nothing seen through it


def circle(n: int, first: int = 0, boxes: tuple = (CHAIR,)):
    """Frames walking round the origin at 2 m, looking down at the chair's place."""
    for i in range(first, first + n):
        angle = 0.4 * i
        eye = (2.0 * np.cos(angle), 2.0 * np.sin(angle), 1.5)
        yield scene_frame(look_down_pose(eye, (0.0, 0.0, 0.45)), list(boxes), frame_id=f"f{i}")


def mapped_chair(store: MemoryStore, n: int = 6) -> MapObject:
    for frame, instance in circle(n):
        integrate_frame(frame, [Detection("chair", 0.9, instance == 0)], store, PARAMS)
    (chair,) = store.list_objects("m")
    assert chair.confirmed and chair.n_gone == 0
    return chair


def test_a_voxel_is_free_when_every_ray_through_it_meets_depth_behind_it() -> None:
    frame = plane_frame(4.0)  # a wall 4 m ahead, filling the image
    keys = points_to_keys(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 4.0], [0.0, 0.0, 5.0], [10.0, 0.0, 2.0]]), 0.05)
    # in front of the wall (the rays pass through it), on the wall, behind the wall, out of view
    np.testing.assert_array_equal(free_voxels(frame, keys, PARAMS), [True, False, False, False])
    np.testing.assert_array_equal(visible_voxels(frame, keys, PARAMS), [False, True, False, False])


def test_a_thin_rail_off_the_voxel_centre_keeps_it_from_being_free() -> None:
    # A voxel 2 m ahead spans x in [0, 0.05] (columns 40 to 42.5); its centre projects to column 41. A
    # 1-pixel rail at 2.02 m in column 42 is inside the voxel, off its centre's ray.
    rail = plane_frame(4.0, patches=((slice(None), slice(42, 43), 2.02),))
    keys = points_to_keys(np.array([[0.025, 0.025, 2.025]]), 0.05)
    assert not free_voxels(rail, keys, PARAMS)[0] and not visible_voxels(rail, keys, PARAMS)[0]
    assert free_voxels(plane_frame(4.0), keys, PARAMS)[0]  # without the rail it is free
    hole = plane_frame(4.0, patches=((slice(None), slice(42, 43), 0.0),))
    assert free_voxels(hole, keys, PARAMS)[0]  # a pixel without depth says nothing...
    blind = plane_frame(4.0, patches=((slice(None), slice(41, 42), 0.0),))
    assert not free_voxels(blind, keys, PARAMS)[0]  # ...but the centre's ray must have depth


def test_the_min_pyramid_holds_block_minima() -> None:
    depth = np.random.default_rng(0).uniform(0.5, 5.0, (7, 10)).astype(np.float32)
    levels = min_pyramid(depth)
    assert [lv.shape for lv in levels] == [(7, 10), (4, 5), (2, 3), (1, 2), (1, 1)]
    for level, blocks in enumerate(levels):
        size = 2**level
        for i, j in np.ndindex(blocks.shape):
            assert blocks[i, j] == depth[i * size : (i + 1) * size, j * size : (j + 1) * size].min()


def test_an_undetected_object_still_there_is_missed_never_retired() -> None:
    store = MemoryStore()
    mapped_chair(store)
    events = []
    for frame, _ in circle(30, first=6):  # the chair is there; the detector misses it
        events += integrate_frame(frame, [], store, PARAMS).events
    (chair,) = store.list_objects("m")
    assert chair.n_missed >= 25 and chair.n_gone == 0
    assert not any(e.kind == "retired" for e in events) and store.retired_objects("m") == []


def test_an_object_missed_in_nearly_every_frame_that_sees_it_is_deleted_as_a_phantom() -> None:
    store = MemoryStore()
    chair = mapped_chair(store, n=4)  # detected in 4 frames, then seen and not detected
    params = PARAMS.replace(discard_min_sightings=40, discard_max_detection_rate=0.1)
    misses, last = [], None
    for frame, _ in circle(60, first=4):
        (before,) = store.list_objects("m")
        last = integrate_frame(frame, [], store, params)
        if not store.list_objects("m"):
            break
        misses.append(store.list_objects("m")[0].n_missed)
    # Kept at 40 sightings (4 detected, 36 missed: a rate of 0.1); the 37th miss (4 / 41 < 0.1) deletes it.
    assert before.n_missed == 36 and misses[-1] == 36 and len(misses) >= 36
    assert last is not None and last.left == [chair.id] and last.retired == []
    (event,) = last.events
    assert (event.kind, event.object_id, event.was_confirmed) == ("deleted", chair.id, before.confirmed)
    assert store.retired_objects("m") == []  # not kept in the history of things taken away
    never = MemoryStore()  # discard_max_detection_rate 0: never deleted
    mapped_chair(never, n=4)
    for frame, _ in circle(60, first=4):
        integrate_frame(frame, [], never, params.replace(discard_max_detection_rate=0.0))
    (kept,) = never.list_objects("m")
    assert kept.n_missed > 36


def test_a_phantom_is_deleted_only_when_it_stands_apart_from_other_objects() -> None:
    def boxed(object_id: int, lo: tuple[float, float, float], hi: tuple[float, float, float] | None) -> MapObject:
        empty = np.empty(0, np.int64)
        bounds = None if hi is None else AABB(np.array(lo), np.array(hi))
        return MapObject(
            id=object_id, keys=empty, weights=np.empty(0, np.float32), votes=np.empty((0, 5), np.float32), bounds=bounds
        )

    phantom = boxed(1, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    assert stands_apart(phantom, [phantom, boxed(2, (1.2, 0.0, 0.0), (2.0, 1.0, 1.0))])
    assert not stands_apart(phantom, [phantom, boxed(2, (1.0, 0.5, 0.5), (2.0, 1.0, 1.0))])  # touching
    assert not stands_apart(phantom, [boxed(2, (0.2, 0.2, -1.0), (0.4, 0.4, 3.0)), phantom])  # through it
    assert stands_apart(phantom, [phantom, boxed(2, (0.2, 0.2, 0.2), None)])  # no bounds: nowhere
    assert not stands_apart(boxed(3, (0.0, 0.0, 0.0), None), [phantom])


def test_an_object_seen_gone_is_retired_after_the_stated_frames() -> None:
    store = MemoryStore()
    chair = mapped_chair(store)
    gone_counts, last = [], chair
    for k, (frame, _) in enumerate(circle(PARAMS.retire_min_gone_frames, first=6, boxes=())):  # carried away
        last = store.list_objects("m")[0]
        result = integrate_frame(frame, [], store, PARAMS, now_s=100.0 + k)
        gone_counts.append([o.n_gone for o in store.list_objects("m")])
    assert gone_counts == [[1], [2], []]  # one more each frame; the third retires it
    assert last.n_missed == 2 and last.score < chair.score  # seen gone counts as missed: it lost support on the way
    assert result.retired == [chair.id] and result.left == [chair.id]
    (event,) = result.events
    assert event.kind == "retired" and event.object_id == chair.id and event.object is None
    assert event.was_confirmed == last.confirmed
    (record,) = store.retired_objects("m")
    assert record.meta.id == chair.id and record.meta.label == "chair" and record.meta.version == last.version


def test_seeing_the_object_again_resets_its_gone_count() -> None:
    store = MemoryStore()
    mapped_chair(store)
    frames = list(circle(2, first=6, boxes=())) + list(circle(1, first=8)) + list(circle(2, first=9, boxes=()))
    counts = []
    for frame, _ in frames:  # gone, gone, there (not detected), gone, gone
        integrate_frame(frame, [], store, PARAMS)
        counts.append(store.list_objects("m")[0].n_gone)
    assert counts == [1, 2, 0, 1, 2]
    frame, instance = next(circle(1, first=11))  # detected: gone count back to 0 too
    integrate_frame(frame, [Detection("chair", 0.9, instance == 0)], store, PARAMS)
    assert store.list_objects("m")[0].n_gone == 0


def test_an_occluded_place_is_no_evidence() -> None:
    store = MemoryStore()
    mapped_chair(store)
    for frame, _ in circle(10, first=6, boxes=(SHIELD,)):  # the chair may be gone; a crate hides its place
        integrate_frame(frame, [], store, PARAMS)
    (chair,) = store.list_objects("m")
    assert chair.n_gone == 0 and chair.n_missed == 0 and chair.confirmed


@pytest.mark.parametrize("retire_after", [0, 5])
def test_retirement_follows_its_parameter(retire_after: int) -> None:
    params = PARAMS.replace(retire_min_gone_frames=retire_after)
    store = MemoryStore()
    for frame, instance in circle(6):
        integrate_frame(frame, [Detection("chair", 0.9, instance == 0)], store, params)
    retired_at = None
    for k, (frame, _) in enumerate(circle(8, first=6, boxes=())):
        if integrate_frame(frame, [], store, params).retired:
            retired_at = k + 1
    assert retired_at == (retire_after or None)  # 0: never retired


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_free_voxels_err_towards_not_free(seed: int) -> None:
    """Against the plain test (every pixel of the voxel's square read): a voxel ``free_voxels`` calls
    free is free pixel by pixel, and free along its centre ray (``center_rays``)."""
    rng = np.random.default_rng(seed)
    blocks = rng.uniform(1.0, 4.0, (HEIGHT // 6 + 1, WIDTH // 6 + 1))
    depth = np.kron(blocks, np.ones((6, 6)))[:HEIGHT, :WIDTH].astype(np.float32)  # surfaces of 6 x 6 pixels
    depth[rng.random((HEIGHT, WIDTH)) < 0.005] = 0.0  # holes
    frame = plane_frame(4.0, patches=((slice(None), slice(None), depth),))
    keys = points_to_keys(rng.uniform((-0.8, -0.6, 0.5), (0.8, 0.6, 2.5), (2000, 3)), PARAMS.voxel_size_m)
    free = free_voxels(frame, keys, PARAMS)
    assert free.any() and not free.all()
    assert not (free & ~center_rays(frame, keys, PARAMS)[1]).any()
    assert not (free & ~plain_free(frame, keys)).any()
    flat = plane_frame(4.0)  # one depth everywhere: the pyramid's blocks hold nothing else, the two agree
    np.testing.assert_array_equal(free_voxels(flat, keys, PARAMS), plain_free(flat, keys))


def plain_free(frame, keys: np.ndarray) -> np.ndarray:
    """The centre's pixel and every pixel with depth of each voxel's square (``free_voxels``' definition),
    read one by one."""
    centers = key_centers(keys, PARAMS.voxel_size_m)
    radius = PARAMS.voxel_size_m * np.sqrt(3) / 2
    out = np.zeros(keys.size, bool)
    for n, (x, y, z) in enumerate(centers):  # cam2world is the identity
        u, v = np.floor(x * INTRINSICS.fx / z + INTRINSICS.cx + 0.5), np.floor(y * INTRINSICS.fy / z + INTRINSICS.cy + 0.5)
        half = np.ceil(radius * INTRINSICS.fx / max(z - radius, PARAMS.depth_min_m))
        if u - half < 0 or u + half >= WIDTH or v - half < 0 or v + half >= HEIGHT:
            continue
        square = frame.depth_m[int(v - half) : int(v + half) + 1, int(u - half) : int(u + half) + 1]
        beyond = z + PARAMS.visibility_tolerance_m + PARAMS.voxel_size_m / 2
        out[n] = frame.depth_m[int(v), int(u)] > beyond and square[square > 0].min() > beyond
    return out
