"""A chair tucked under a table (core.boxes.reach_under): its box, a slab of the back seen above the top, reaches
under the table as deep as the chair is wide; hand-made boxes, and hand-made frames through the step."""

from __future__ import annotations

import numpy as np
import pytest
from handmade_frames import look_down_pose, scene_frame

from arcloud.core.boxes import reach_under
from arcloud.core.fusion import new_object
from arcloud.core.step import integrate_frame
from arcloud.core.types import AABB, CLASS_INDEX, OBB, Detection, MapObject, Params, VoxelDetection
from arcloud.core.voxels import pack_keys
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05, floor_min_samples=5)
TABLE = ((-0.5, 0.0, 0.0), (1.5, 0.9, 0.75))
BACK = ((0.0, -0.3, 0.0), (0.5, -0.1, 0.9))  # 0.5 wide, 0.2 deep, its face two voxels from the table's edge


def boxed(object_id: int, label: str, lo, hi, *, confirmed: bool = True) -> MapObject:
    """An object of ``label`` whose boxes are the axis-aligned box ``lo``-``hi`` (z up)."""
    obj = new_object(object_id, VoxelDetection(CLASS_INDEX[label], 0.9, pack_keys(np.zeros((1, 3), np.int64))), "d", 0.0)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return obj.replace(label=label, confirmed=confirmed, aabb=AABB(lo, hi), obb=OBB((lo + hi) / 2, hi - lo, np.eye(3), 0.0))


def reached(chair: MapObject, *around: MapObject, params: Params = PARAMS) -> MapObject:
    (out,) = reach_under([chair], [chair, *around], params)
    return out


def test_a_slab_beside_a_table_reaches_under_it_as_deep_as_it_is_wide():
    chair = reached(boxed(1, "chair", *BACK), boxed(2, "table", *TABLE))
    assert chair.aabb.min.tolist() == [0.0, -0.3, 0.0]
    assert chair.aabb.max.tolist() == pytest.approx([0.5, 0.2, 0.9])
    assert chair.obb.size.tolist() == pytest.approx([0.5, 0.5, 0.9])
    assert chair.obb.center.tolist() == pytest.approx([0.25, -0.05, 0.45])
    # The table on the other side: it reaches the other way, and no further than the table's far edge.
    lo, hi = TABLE
    mirrored = reached(
        boxed(1, "chair", (0.0, 0.1, 0.0), (0.5, 0.3, 0.9)), boxed(2, "table", (lo[0], -0.9, 0.0), (hi[0], 0.0, 0.75))
    )
    assert mirrored.aabb.min[1] == pytest.approx(-0.2) and mirrored.aabb.max[1] == pytest.approx(0.3)
    capped = reached(
        boxed(1, "chair", (0.0, -0.3, 0.0), (0.5, -0.1, 0.9)), boxed(2, "table", (-0.5, -0.05, 0.0), (1.5, 0.1, 0.75))
    )
    assert capped.aabb.max[1] == pytest.approx(0.1)
    capped = reached(
        boxed(1, "chair", (0.0, 0.1, 0.0), (0.5, 0.3, 0.9)), boxed(2, "table", (lo[0], -0.15, 0.0), (hi[0], 0.05, 0.75))
    )
    assert capped.aabb.min[1] == pytest.approx(-0.15)


@pytest.mark.parametrize(
    "chair, table, why",
    [
        (boxed(1, "chair", (0.0, -0.3, 0.0), (0.5, 0.0, 0.9)), boxed(2, "table", *TABLE), "deep enough: a seat seen"),
        (boxed(1, "chair", (0.0, -0.5, 0.0), (0.5, -0.3, 0.9)), boxed(2, "table", *TABLE), "pulled out: 0.3 m from it"),
        (boxed(1, "chair", *BACK), boxed(2, "table", *TABLE, confirmed=False), "a tentative table"),
        (boxed(1, "chair", *BACK), boxed(2, "table", (-0.5, 0.0, 0.0), (1.5, 0.9, 1.0)), "a counter above its back"),
        (boxed(1, "chair", *BACK), boxed(2, "table", (0.3, 0.0, 0.0), (1.5, 0.9, 0.75)), "beside a corner"),
        (boxed(1, "tv", *BACK), boxed(2, "table", *TABLE), "not a chair"),
        (boxed(1, "chair", (0.0, 0.2, 0.0), (0.5, 0.4, 0.9)), boxed(2, "table", *TABLE), "over the table"),
    ],
)
def test_a_box_stays_as_seen(chair: MapObject, table: MapObject, why: str):
    assert reached(chair, table).aabb is chair.aabb, why


def test_it_reaches_in_a_world_whose_up_is_y():
    # ARKit's world: y up, so the floor plan is (x, z); the same chair and table as above, turned.
    turned = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]])  # (x, y, z) z-up -> (x, z, -y) y-up

    def turn(lo, hi) -> tuple[np.ndarray, np.ndarray]:
        corners = np.array([lo, hi], float) @ turned.T
        return corners.min(axis=0), corners.max(axis=0)

    chair = reached(boxed(1, "chair", *turn(*BACK)), boxed(2, "table", *turn(*TABLE)), params=PARAMS.replace(up=(0.0, 1.0, 0.0)))
    lo, hi = turn(BACK[0], (0.5, 0.2, 0.9))
    assert chair.aabb.min.tolist() == pytest.approx(lo.tolist()) and chair.aabb.max.tolist() == pytest.approx(hi.tolist())


def test_the_step_boxes_the_back_of_a_tucked_chair_under_the_table():
    # A camera behind the chair sees its back above the table top; its seat is hidden (not in the scene at all).
    top, back = ((-0.5, 0.0, 0.70), (1.5, 0.9, 0.75)), ((0.0, -0.1, 0.45), (0.5, -0.05, 0.95))
    store = MemoryStore()
    for i in range(8):
        frame, instance = scene_frame(
            look_down_pose((-0.4 + 0.15 * i, -1.6, 1.5), (0.25, 0.3, 0.6)), [top, back], frame_id=f"f{i}"
        )
        integrate_frame(frame, [Detection("table", 0.9, instance == 0), Detection("chair", 0.9, instance == 1)], store, PARAMS)
    table, chair = sorted(store.list_objects("m"), key=lambda o: o.label == "chair")
    assert (table.label, chair.label) == ("table", "chair") and table.confirmed
    assert chair.aabb.size[0] == pytest.approx(0.45, abs=0.06)
    assert chair.aabb.size[1] == pytest.approx(chair.aabb.size[0])  # as deep as it is wide: 0.05 m of it seen
    assert chair.aabb.min[1] == pytest.approx(-0.125, abs=0.03) and chair.aabb.max[1] < table.aabb.max[1]
