"""Masks cleaned with depth before fusing (core.voxels): what shows through a mask's gaps or past its
border lies behind the object and stays out; colour masks of unregistered frames land where the
colour camera saw them."""

from __future__ import annotations

import dataclasses

import numpy as np
from handmade_frames import INTRINSICS, look_down_pose, plane_frame, rect_mask, scene_frame

from arcloud.core.step import integrate_frame
from arcloud.core.types import Detection, Intrinsics, Params
from arcloud.core.voxels import key_centers, voxelize_detections
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05, erode_px=0, floor_min_samples=5)  # tiny frames: few floor samples


def depths_of(keys: np.ndarray) -> np.ndarray:
    return key_centers(keys, PARAMS.voxel_size_m)[:, 2]  # camera at the origin looking along +z


def test_a_mask_over_slats_keeps_the_slats_not_the_wall_behind_them():
    # A chair back of four slats at 1.5 m; between them the wall at 3 m shows through.
    slats = tuple((slice(r, r + 3), slice(20, 50), 1.5) for r in (10, 16, 22, 28))
    frame = plane_frame(3.0, patches=slats)
    mask = rect_mask(slice(10, 31), slice(20, 50))  # the whole back, gaps included
    (observation,) = voxelize_detections(frame, [Detection("chair", 0.9, mask)], PARAMS)
    assert depths_of(observation.keys).max() < 1.6
    without = voxelize_detections(frame, [Detection("chair", 0.9, mask)], PARAMS.replace(layer_margin_m=None))[0]
    assert depths_of(without.keys).max() > 2.9  # the cleanup is what removed the wall


def test_a_mask_bleeding_past_the_border_keeps_only_the_object():
    frame = plane_frame(3.0, patches=((slice(20, 40), slice(30, 50), 1.5),))
    mask = rect_mask(slice(16, 44), slice(26, 54))  # 4 px of wall on every side
    (observation,) = voxelize_detections(frame, [Detection("chair", 0.9, mask)], PARAMS)
    assert np.all(np.abs(depths_of(observation.keys) - 1.5) < 0.06)
    (untouched,) = voxelize_detections(frame, [Detection("couch", 0.9, mask)], PARAMS)  # couches are not cleaned
    assert depths_of(untouched.keys).max() > 2.9


def test_a_mask_bleeding_onto_the_floor_boxes_the_object_above_it():
    store = MemoryStore()
    for i, angle in enumerate(np.linspace(0, 2 * np.pi, 8, endpoint=False)):
        eye = (2.0 * np.cos(angle), 2.0 * np.sin(angle), 1.5)
        frame, instance = scene_frame(
            look_down_pose(eye, (0.0, 0.0, 0.3)), [((-0.25, -0.25, 0.0), (0.25, 0.25, 0.5))], frame_id=f"f{i}"
        )
        rows, cols = np.nonzero(instance == 0)
        mask = rect_mask(slice(rows.min(), rows.max() + 6), slice(cols.min() - 3, cols.max() + 4))  # and the floor around
        integrate_frame(frame, [Detection("tv", 0.9, mask)], store, PARAMS)  # a TV: no reaching for the floor
    (obj,) = store.list_objects("m")
    assert obj.aabb.min[2] > PARAMS.floor_clearance_m - PARAMS.voxel_size_m / 2  # the floor layer is not boxed
    assert np.all(np.abs(obj.aabb.min[:2]) <= 0.3) and np.all(np.abs(obj.aabb.max[:2]) <= 0.3)


def test_unregistered_colour_masks_are_looked_up_where_the_colour_camera_saw():
    # Depth camera at the origin; the colour camera has a longer focal length and sits 10 cm to the right.
    patch = (slice(20, 40), slice(30, 50), 1.5)
    frame = plane_frame(3.0, patches=(patch,))
    rgb = Intrinsics(fx=120.0, fy=120.0, cx=42.0, cy=29.0)
    depth2rgb = np.eye(4)
    depth2rgb[0, 3] = -0.10
    unregistered = dataclasses.replace(frame, rgb_intrinsics=rgb, depth2rgb=depth2rgb)
    # Where the colour camera sees the patch's corners at 1.5 m.
    corners_px = np.array([[30, 20], [50, 40]], float)
    x = (corners_px[:, 0] - INTRINSICS.cx) * 1.5 / INTRINSICS.fx - 0.10
    y = (corners_px[:, 1] - INTRINSICS.cy) * 1.5 / INTRINSICS.fy
    u0, u1 = np.round(x * rgb.fx / 1.5 + rgb.cx).astype(int)
    v0, v1 = np.round(y * rgb.fy / 1.5 + rgb.cy).astype(int)
    colour_mask = rect_mask(slice(v0 + 1, v1 - 1), slice(u0 + 1, u1 - 1))
    params = PARAMS.replace(layer_margin_m=None)  # registration alone
    on_patch = lambda detection: np.mean(np.abs(depths_of(detection.keys) - 1.5) < 0.06)  # noqa: E731 - a one-line predicate
    (registered,) = voxelize_detections(unregistered, [Detection("tv", 0.9, colour_mask)], params)
    (naive,) = voxelize_detections(frame, [Detection("tv", 0.9, colour_mask)], params)  # as if registered
    assert on_patch(registered) == 1.0  # the wall beside the patch, hidden from the colour camera, stays out
    assert on_patch(naive) < 0.75
    (cleaned,) = voxelize_detections(unregistered, [Detection("chair", 0.9, colour_mask)], PARAMS)
    assert on_patch(cleaned) == 1.0


# Screens on walls (core.voxels.off_wall_samples): the hand-made wall at z = 3 m faces the camera, so it is
# vertical when up is -y (image rows run down).
UPRIGHT = PARAMS.replace(up=(0.0, -1.0, 0.0))


def tv_depths(frame, mask, params=UPRIGHT) -> np.ndarray:
    observations = voxelize_detections(frame, [Detection("tv", 0.9, mask)], params)
    return np.concatenate([depths_of(o.keys) for o in observations]) if observations else np.empty(0)


def test_a_screen_mask_that_takes_in_the_wall_past_its_edge_keeps_the_screen():
    frame = plane_frame(3.0, patches=((slice(20, 40), slice(30, 50), 2.82),))  # 18 cm off the wall
    mask = rect_mask(slice(17, 43), slice(27, 53))  # 3 px of wall on every side
    assert tv_depths(frame, mask).max() < 2.9
    assert tv_depths(frame, mask, UPRIGHT.replace(wall_margin_m=None)).max() > 2.9  # the rule is what removed it
    assert tv_depths(frame, mask, PARAMS).max() > 2.9  # with z up that plane is a floor, not a wall


def test_a_dark_screen_whose_mask_sees_only_the_wall_adds_nothing():
    frame = plane_frame(3.0, patches=((slice(10, 50), slice(15, 65), 0.0),))  # no depth back from the screen
    mask = rect_mask(slice(8, 52), slice(13, 67))
    assert tv_depths(frame, mask).size == 0
    assert np.all(np.abs(tv_depths(frame, mask, UPRIGHT.replace(wall_margin_m=None)) - 3.0) < 0.06)


def test_a_mask_inside_its_screen_keeps_the_screen_its_surroundings_lie_on():
    # The mask falls short of the monitor's edge: the ring around it is the monitor's own face.
    frame = plane_frame(3.0, patches=((slice(10, 50), slice(10, 70), 2.0),))
    depths = tv_depths(frame, rect_mask(slice(15, 45), slice(15, 65)))
    assert depths.size and np.all(np.abs(depths - 2.0) < 0.06)


def test_a_monitor_far_from_the_wall_keeps_its_stand():
    stand = (slice(35, 42), slice(36, 44), 2.2)  # 20 cm behind the screen, 80 cm off the wall
    frame = plane_frame(3.0, patches=((slice(15, 35), slice(25, 55), 2.0), stand))
    depths = tv_depths(frame, rect_mask(slice(12, 45), slice(22, 58)))
    assert depths.max() < 2.9 and np.any(np.abs(depths - 2.2) < 0.06)
