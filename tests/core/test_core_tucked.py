"""A chair tucked under a table (core.boxes.reach_under): its box, a slab of the back seen above the top, reaches
under the table as deep as the chair is wide; hand-made boxes in worlds pointing up every way, and hand-made frames
through the step."""

from __future__ import annotations

import numpy as np
import pytest
from handmade_frames import look_down_pose, scene_frame

from arcloud.core.boxes import reach_under
from arcloud.core.fusion import new_object
from arcloud.core.step import find_visible, integrate_frame
from arcloud.core.types import AABB, CLASS_INDEX, OBB, Detection, MapObject, Params, VoxelDetection
from arcloud.core.voxels import pack_keys
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05, floor_min_samples=5)
TABLE = ((-0.5, 0.0, 0.0), (1.5, 0.9, 0.75))
BACK = ((0.0, -0.3, 0.0), (0.5, -0.1, 0.9))  # 0.5 wide, 0.2 deep, its face two voxels from the table's edge


def turn(axis: int, degrees: float) -> np.ndarray:
    """The rotation by ``degrees`` about world axis ``axis``."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    rotation = np.eye(3)
    rotation[i, i] = rotation[j, j] = c
    rotation[i, j], rotation[j, i] = -s, s
    return rotation


#: Worlds: (z-up coordinates -> world rotation, whether boxes are fitted in an aligned frame (world2aligned: the
#: rotation's inverse) rather than the world itself).
WORLDS = {
    "z up": (np.eye(3), False),
    "y up (ARKit)": (turn(0, -90), False),
    "y down (Kinect)": (turn(0, 90), False),
    "y up, aligned": (turn(0, -90), True),
    "z up turned 30 degrees, aligned": (turn(2, 30), True),
    "y down turned 30 degrees, aligned": (turn(0, 90) @ turn(2, 30), True),
}


def params_in(world: str) -> Params:
    rotation, aligned = WORLDS[world]
    world2aligned = None
    if aligned:
        matrix = np.eye(4)
        matrix[:3, :3] = rotation.T
        world2aligned = tuple(map(tuple, matrix.tolist()))
    return PARAMS.replace(up=tuple((rotation @ [0.0, 0.0, 1.0]).tolist()), world2aligned=world2aligned)


def boxed(object_id: int, label: str, lo, hi, *, world: str = "z up", yaw_deg: float = 0.0, confirmed: bool = True) -> MapObject:
    """An object of ``label`` whose boxes, in z-up coordinates, are the box ``lo``-``hi`` (its oriented box turned
    ``yaw_deg`` about its centre, its axis-aligned box that of the unturned box), placed in ``world``."""
    rotation, aligned = WORLDS[world]
    obj = new_object(object_id, VoxelDetection(CLASS_INDEX[label], 0.9, pack_keys(np.zeros((1, 3), np.int64))), "d", 0.0)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) @ rotation.T
    aabb = AABB(lo, hi) if aligned else AABB(corners.min(axis=0), corners.max(axis=0))
    obb = OBB(rotation @ ((lo + hi) / 2), hi - lo, rotation @ turn(2, yaw_deg), np.radians(yaw_deg))
    return obj.replace(label=label, confirmed=confirmed, aabb=aabb, obb=obb)


def reached(chair: MapObject, *around: MapObject, world: str = "z up") -> MapObject:
    (out,) = reach_under([chair], [chair, *around], params_in(world))
    return out


@pytest.mark.parametrize("world", WORLDS)
def test_a_slab_beside_a_table_reaches_under_it_as_deep_as_it_is_wide(world: str):
    chair = reached(boxed(1, "chair", *BACK, world=world), boxed(2, "table", *TABLE, world=world), world=world)
    want = boxed(1, "chair", (0.0, -0.3, 0.0), (0.5, 0.2, 0.9), world=world)
    assert chair.aabb.min.tolist() == pytest.approx(want.aabb.min.tolist())
    assert chair.aabb.max.tolist() == pytest.approx(want.aabb.max.tolist())
    assert chair.obb.center.tolist() == pytest.approx(want.obb.center.tolist())
    assert chair.obb.size.tolist() == pytest.approx([0.5, 0.5, 0.9])


def test_it_reaches_toward_the_table_and_no_further_than_its_far_edge():
    lo, hi = TABLE
    mirrored = reached(
        boxed(1, "chair", (0.0, 0.1, 0.0), (0.5, 0.3, 0.9)), boxed(2, "table", (lo[0], -0.9, 0.0), (hi[0], 0.0, 0.75))
    )
    assert mirrored.aabb.min[1] == pytest.approx(-0.2) and mirrored.aabb.max[1] == pytest.approx(0.3)
    narrow = boxed(2, "table", (-0.5, -0.05, 0.0), (1.5, 0.1, 0.75))
    assert reached(boxed(1, "chair", *BACK), narrow).aabb.max[1] == pytest.approx(0.1)
    narrow_below = boxed(2, "table", (lo[0], -0.15, 0.0), (hi[0], 0.05, 0.75))
    assert reached(boxed(1, "chair", (0.0, 0.1, 0.0), (0.5, 0.3, 0.9)), narrow_below).aabb.min[1] == pytest.approx(-0.15)
    # Two tables: the one spanning more of its width (a side table spanning half of it, at its other side).
    side = boxed(3, "table", (0.2, -0.9, 0.0), (1.0, -0.35, 0.7))
    for tables in [(side, boxed(2, "table", *TABLE)), (boxed(2, "table", *TABLE), side)]:
        both = reached(boxed(1, "chair", *BACK), *tables)
        assert both.aabb.min[1] == pytest.approx(-0.3) and both.aabb.max[1] == pytest.approx(0.2)


def test_a_turned_slab_grows_its_oriented_box_as_far_along_the_direction():
    # The oriented box turned 18 degrees: it grows along its nearer axis by the reach over the cosine between them.
    chair = reached(boxed(1, "chair", *BACK, yaw_deg=18.0), boxed(2, "table", *TABLE))
    assert chair.aabb.max[1] == pytest.approx(0.2)
    assert chair.obb.size[1] == pytest.approx(0.2 + 0.3 / np.cos(np.radians(18.0)))
    assert chair.obb.size[0] == pytest.approx(0.5)


@pytest.mark.parametrize(
    "chair, table, why",
    [
        (boxed(1, "chair", (0.0, -0.3, 0.0), (0.5, 0.0, 0.9)), boxed(2, "table", *TABLE), "deep enough: a seat seen"),
        (boxed(1, "chair", (0.0, -0.5, 0.0), (0.5, -0.3, 0.9)), boxed(2, "table", *TABLE), "pulled out: 0.3 m from it"),
        (boxed(1, "chair", *BACK), boxed(2, "table", *TABLE, confirmed=False), "a tentative table"),
        (boxed(1, "chair", *BACK), boxed(2, "table", (-0.5, 0.0, 0.0), (1.5, 0.9, 1.0)), "a counter above its back"),
        (boxed(1, "chair", *BACK), boxed(2, "table", (0.3, 0.0, 0.0), (1.5, 0.9, 0.75)), "beside a corner"),
        (boxed(1, "tv", *BACK), boxed(2, "table", *TABLE), "not a chair"),
        (boxed(1, "chair", *BACK), boxed(2, "couch", *TABLE), "not a table"),
        (boxed(1, "chair", (0.0, 0.2, 0.0), (0.5, 0.4, 0.9)), boxed(2, "table", *TABLE), "over the table"),
    ],
)
def test_a_box_stays_as_seen(chair: MapObject, table: MapObject, why: str):
    assert reached(chair, table).aabb is chair.aabb, why


def test_a_counter_above_the_back_keeps_it_in_a_world_whose_up_is_negative():
    # y down: the counter's top is the smaller y; it still rises above the chair's back, which stays a slab.
    world = "y down (Kinect)"
    chair = boxed(1, "chair", *BACK, world=world)
    assert reached(chair, boxed(2, "table", (-0.5, 0.0, 0.0), (1.5, 0.9, 1.0), world=world), world=world).aabb is chair.aabb
    assert reached(chair, boxed(2, "table", *TABLE, world=world), world=world).aabb is not chair.aabb


TOP, CHAIR_BACK = ((-0.5, 0.0, 0.70), (1.5, 0.9, 0.75)), ((0.0, -0.1, 0.45), (0.5, -0.05, 0.95))


def tucked_map() -> MemoryStore:
    """A camera behind a chair sees its back above a table's top (its seat is hidden: not in the scene at all)."""
    store = MemoryStore()
    for i in range(8):
        pose = look_down_pose((-0.4 + 0.15 * i, -1.6, 1.5), (0.25, 0.3, 0.6))
        frame, instance = scene_frame(pose, [TOP, CHAIR_BACK], frame_id=f"f{i}")
        integrate_frame(frame, [Detection("table", 0.9, instance == 0), Detection("chair", 0.9, instance == 1)], store, PARAMS)
    return store


def test_the_step_boxes_the_back_of_a_tucked_chair_under_the_table():
    table, chair = sorted(tucked_map().list_objects("m"), key=lambda o: o.label == "chair")
    assert (table.label, chair.label) == ("table", "chair") and table.confirmed
    assert chair.aabb.size[0] == pytest.approx(0.45, abs=0.06)
    assert chair.aabb.size[1] == pytest.approx(chair.aabb.size[0])  # as deep as it is wide: 0.05 m of it seen
    assert chair.aabb.min[1] == pytest.approx(-0.125, abs=0.03) and chair.aabb.max[1] < table.aabb.max[1]


def test_a_view_of_the_chair_without_its_table_keeps_the_box_under_the_table():
    store = tucked_map()
    (before,) = [o for o in store.list_objects("m") if o.label == "chair"]
    frame, instance = scene_frame(look_down_pose((-0.8, -1.2, 0.9), (0.25, -0.3, 0.2)), [TOP, CHAIR_BACK], frame_id="g")
    assert find_visible(store, frame, PARAMS) == [before.id] and (instance == 1).sum() > 50  # the table out of view
    integrate_frame(frame, [Detection("chair", 0.9, instance == 1)], store, PARAMS)
    (after,) = [o for o in store.list_objects("m") if o.label == "chair"]
    assert after.n_frames == before.n_frames + 1
    assert after.aabb.max[1] == pytest.approx(before.aabb.max[1]) and after.aabb.size[1] > 0.3
