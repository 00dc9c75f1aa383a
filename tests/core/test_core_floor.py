"""The floor (core.floor) and floor-standing objects reaching it (core.boxes.reach_floor), on hand-made
frames ray cast from boxes on a floor plane."""

from __future__ import annotations

import numpy as np
import pytest
from handmade_frames import look_down_pose, scene_frame

from arcloud.core.floor import floor_height, frame_floor, height_bin
from arcloud.core.step import integrate_frame
from arcloud.core.types import Detection, Params
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05, floor_min_samples=5)  # tiny frames: few floor samples per cell


def test_a_frame_finds_the_floor_below_the_camera_and_not_a_table_top():
    pose = look_down_pose((0.0, -2.0, 1.5), (0.0, 0.0, 0.3))
    frame, _ = scene_frame(pose, [((-0.3, -0.3, 0.0), (0.3, 0.3, 0.45))], floor_z=-0.2)
    assert frame_floor(frame, PARAMS).height_m == pytest.approx(-0.2, abs=PARAMS.floor_bin_m)
    # A camera 0.6 m above a table top that fills its view: no floor (a device is held well above it).
    over_table = look_down_pose((0.0, 0.0, 1.35), (0.0, 0.3, 0.75))
    frame, _ = scene_frame(over_table, [((-3.0, -3.0, 0.0), (3.0, 3.0, 0.75))], floor_z=None)
    assert frame_floor(frame, PARAMS).height_m is None


def test_floor_votes_take_the_lowest_well_supported_height():
    floor, table = height_bin(0.0, PARAMS), height_bin(0.75, PARAMS)
    assert floor_height({table: 30, floor: 12}, PARAMS) == pytest.approx((floor + 0.5) * PARAMS.floor_bin_m)
    assert floor_height({table: 30, floor: 3}, PARAMS) == pytest.approx((table + 0.5) * PARAMS.floor_bin_m)  # too few
    assert floor_height({}, PARAMS) is None


def walk_around(boxes, label_masks, n=8, radius=2.0, height=1.5, floor_z=0.0):
    """Frames of a camera circling the origin, with detections from ``label_masks`` (label, box index,
    rows kept: a function of the instance image giving the mask)."""
    for i in range(n):
        angle = 2 * np.pi * i / n
        eye = (radius * np.cos(angle), radius * np.sin(angle), height)
        frame, instance = scene_frame(look_down_pose(eye, (0.0, 0.0, 0.45)), boxes, floor_z=floor_z, frame_id=f"f{i}")
        yield frame, [Detection(label, 0.9, mask_of(instance)) for label, mask_of in label_masks]


@pytest.mark.parametrize("label, reaches", [("chair", True), ("tv", False)])
def test_floor_standing_objects_reach_the_floor_their_frames_saw(label, reaches):
    # Only the upper part of the object is in view and detected (its legs are hidden): it floats at 0.45 m.
    seat_and_back = ((-0.23, -0.23, 0.46), (0.23, 0.23, 0.93))
    store = MemoryStore()
    for frame, detections in walk_around([seat_and_back], [(label, lambda inst: inst == 0)]):
        integrate_frame(frame, detections, store, PARAMS)
    (obj,) = store.list_objects("m")
    assert obj.aabb.max[2] == pytest.approx(0.925, abs=0.03)
    if reaches:
        assert obj.aabb.min[2] == pytest.approx(0.0, abs=PARAMS.floor_bin_m)
        assert obj.obb.center[2] - obj.obb.size[2] / 2 == pytest.approx(0.0, abs=PARAMS.floor_bin_m)
    else:
        assert obj.aabb.min[2] >= 0.45  # a TV does not stand on the floor: it stays where it was seen


def test_thin_legs_are_kept_in_the_box():
    # A table: a 4 cm top at 0.72 m on four 5 cm legs, seen from around; floor reaching turned off, so
    # only the legs' own voxels can take the box down to the floor. (These 80 x 60 frames see a leg 2 px
    # wide, as a VGA frame sees it 10 px wide: no erosion, which would take all of it here.)
    top = ((-0.58, -0.38, 0.72), (0.58, 0.38, 0.76))
    legs = [((x - 0.025, y - 0.025, 0.0), (x + 0.025, y + 0.025, 0.72)) for x in (-0.53, 0.53) for y in (-0.33, 0.33)]
    store = MemoryStore()
    params = PARAMS.replace(floor_standing=(), erode_px=0)
    for frame, detections in walk_around([top, *legs], [("table", lambda inst: inst >= 0)], n=12, radius=2.2, height=1.4):
        integrate_frame(frame, detections, store, params)
    (table,) = store.list_objects("m")
    assert table.aabb.min[2] <= 0.1 and table.aabb.max[2] == pytest.approx(0.75, abs=0.05)
    assert table.aabb.size[0] == pytest.approx(1.15, abs=0.1)


@pytest.mark.parametrize(
    ("up", "to_world", "shift"),
    [
        ((0.0, -1.0, 0.0), ((1, 0, 0), (0, 0, -1), (0, 1, 0)), (0, -1, 0)),  # a Kinect's y-down world: height h at y -h-1
        ((0.0, 1.0, 0.0), ((1, 0, 0), (0, 0, 1), (0, -1, 0)), (0, 0, 0)),  # ARKit's y-up world
        ((-1.0, 0.0, 0.0), ((0, 0, -1), (0, 1, 0), (1, 0, 0)), (-1, 0, 0)),
    ],
)
def test_the_floor_clearance_leaves_out_the_same_layers_whichever_way_the_world_points_up(
    up: tuple[float, float, float], to_world: tuple[tuple[int, ...], ...], shift: tuple[int, int, int]
) -> None:
    from arcloud.core.boxes import box_voxel_masks
    from arcloud.core.fusion import new_object
    from arcloud.core.types import CLASS_INDEX, VoxelDetection
    from arcloud.core.voxels import pack_keys, unpack_keys

    def kept_layers(params: Params, rotation: np.ndarray, offset: np.ndarray) -> list[int]:
        column = np.mgrid[0:4, 0:4, 0:8].reshape(3, -1).T  # 4 x 4 voxels, 8 layers above a floor at 1 cm (z up)
        keys = np.sort(pack_keys(column @ rotation.T + offset))
        obj = new_object(1, VoxelDetection(CLASS_INDEX["chair"], 0.9, keys), "d", 0.0)
        obj = obj.replace(floor_votes={height_bin(0.01, params): 5})
        ijk = unpack_keys(obj.keys)
        keep = box_voxel_masks([obj], params, [ijk], [floor_height(obj.floor_votes, params)], [None])[0]
        return sorted({int(h) for h in ((ijk[keep] - offset) @ rotation)[:, 2]})

    z_up = kept_layers(Params(), np.eye(3, dtype=int), np.zeros(3, int))
    assert z_up[0] >= 1  # the layer on the floor is left out
    assert kept_layers(Params(up=up), np.array(to_world), np.array(shift)) == z_up


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)])
def test_the_axis_aligned_box_reaches_the_floor_whichever_way_the_world_points_up(up: tuple[float, float, float]) -> None:
    from arcloud.core.boxes import reach_floor
    from arcloud.core.types import AABB, OBB

    params = Params(up=up)
    up_v = np.asarray(up)
    axes = np.stack([np.cross(up_v, np.roll(up_v, 1)), np.roll(up_v, 1), up_v], axis=1)  # box axes, the last up
    seat = 0.69 * up_v  # a chair's seat and back, 0.45-0.93 m above a floor at height 0
    corners = np.array(
        [seat - 0.23 * axes[:, 0] - 0.23 * axes[:, 1] - 0.24 * up_v, seat + 0.23 * axes[:, 0] + 0.23 * axes[:, 1] + 0.24 * up_v]
    )
    aabb = AABB(corners.min(axis=0), corners.max(axis=0))
    obb = OBB(seat, np.array([0.46, 0.46, 0.48]), axes, 0.0)
    aabb, obb = reach_floor(aabb, obb, 0.0, params)
    axis = int(np.argmax(np.abs(up_v)))
    bottom = aabb.min[axis] if up_v[axis] > 0 else -aabb.max[axis]
    top = aabb.max[axis] if up_v[axis] > 0 else -aabb.min[axis]
    assert bottom == pytest.approx(0.0) and top == pytest.approx(0.93)
    assert obb.size[2] == pytest.approx(0.93) and float(up_v @ obb.center) == pytest.approx(0.465)
