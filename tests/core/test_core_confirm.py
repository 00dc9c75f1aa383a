"""Confirmation (core.confirm): served objects need frames, a detection rate, a plausible box and a
score; frames that see an object and detect nothing count misses, and a confirmed object whose
evidence weakens becomes tentative again."""

from __future__ import annotations

import numpy as np
import pytest
from handmade_frames import look_down_pose, scene_frame

from arcloud.core.boxes import refine
from arcloud.core.confirm import detection_rate, evidence, plausible
from arcloud.core.fusion import new_object
from arcloud.core.step import integrate_frame
from arcloud.core.types import CLASS_INDEX, OBB, Detection, MapObject, Params, VoxelDetection, empty_object
from arcloud.core.voxels import pack_keys
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05, floor_min_samples=5)
CHAIR = ((-0.25, -0.25, 0.0), (0.25, 0.25, 0.9))


def boxed(label: str, size: tuple[float, float, float], **evidence: object) -> MapObject:
    obb = OBB(center=np.array([0.0, 0.0, size[2] / 2]), size=np.array(size), rotation=np.eye(3), yaw_rad=0.0)
    return empty_object(1).replace(label=label, obb=obb, **evidence)


@pytest.mark.parametrize(
    "label, size, expected",
    [
        ("chair", (0.5, 0.5, 0.9), True),
        ("chair", (0.3, 0.25, 0.1), False),  # 10 cm tall: something on the floor, not a chair
        ("table", (1.6, 0.9, 0.75), True),
        ("tv", (1.0, 0.1, 0.6), True),
        ("tv", (0.16, 0.26, 0.25), False),  # a 26 cm "TV": a toy or a picture
        ("laptop", (0.35, 0.25, 0.2), True),
        ("laptop", (0.6, 0.58, 0.34), False),  # a keyboard and what lies around it
    ],
)
def test_plausible_boxes_by_class(label, size, expected):
    assert plausible(boxed(label, size), PARAMS) is expected


def test_the_rule_needs_frames_rate_geometry_and_score():
    good = boxed("chair", (0.5, 0.5, 0.9), n_frames=10, n_missed=2, score_sum=8.0, label_purity=0.9)
    assert evidence(good, PARAMS)[1] and detection_rate(good) == pytest.approx(10 / 12)
    assert not evidence(good.replace(n_frames=2, score_sum=1.6), PARAMS)[1]
    assert not evidence(good.replace(n_missed=40), PARAMS)[1]  # detected in 10 of 50 frames that saw it
    assert not evidence(good.replace(score_sum=1.5), PARAMS)[1]  # mean detection score 0.15
    assert not evidence(good.replace(label_purity=0.2), PARAMS)[1]  # its voxels mostly vote for other labels
    assert not evidence(boxed("chair", (0.3, 0.25, 0.1), n_frames=10, score_sum=8.0, label_purity=0.9), PARAMS)[1]


def circle(n, first=0, boxes=(CHAIR,)):
    for i in range(first, first + n):
        angle = 0.4 * i
        eye = (2.0 * np.cos(angle), 2.0 * np.sin(angle), 1.5)
        yield scene_frame(look_down_pose(eye, (0.0, 0.0, 0.45)), list(boxes), frame_id=f"f{i}")


def test_objects_are_confirmed_by_evidence_and_turn_tentative_when_seen_missing():
    store = MemoryStore()
    statuses = []
    for frame, instance in circle(6):
        result = integrate_frame(frame, [Detection("chair", 0.9, instance == 0)], store, PARAMS)
        statuses.append(store.list_objects("m")[0].confirmed)
    assert statuses[0] is False and statuses[-1] is True  # one frame is not enough; six are
    (chair,) = store.list_objects("m")
    assert chair.n_missed == 0 and chair.version == 6
    events = []
    for frame, _ in circle(20, first=6):  # in view, nothing detected: the chair was carried away
        result = integrate_frame(frame, [], store, PARAMS)
        events += result.events
    (chair,) = store.list_objects("m")
    assert chair.n_missed >= 15 and not chair.confirmed  # (a view that sees less than 30 % of it is no miss)
    assert any(e.kind == "updated" and e.object is not None and not e.object.confirmed for e in events)
    assert chair.version < 6 + 20  # most misses only counted, not rewritten


def test_an_occluded_object_is_not_missed():
    store = MemoryStore()
    for frame, instance in circle(6):
        integrate_frame(frame, [Detection("chair", 0.9, instance == 0)], store, PARAMS)
    shield = ((-1.2, -1.2, 0.0), (1.2, 1.2, 2.0))  # a crate around the chair
    for frame, _ in circle(10, first=6, boxes=(CHAIR, shield)):
        integrate_frame(frame, [], store, PARAMS)
    (chair,) = store.list_objects("m")
    assert chair.n_missed == 0 and chair.confirmed


def test_a_box_as_tall_as_its_class_can_be_is_plausible_wherever_the_grid_falls():
    # A chair 0.30 m (the least a chair can be) between its outer voxels' centres: its height, a difference of
    # coordinates, measured 0.30000000000000004 m or 0.29999999999999993 m by where the world's grid fell.
    i, j, k = np.meshgrid(np.arange(8), np.arange(8), np.arange(7), indexing="ij")
    block = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    heights, verdicts = set(), set()
    for shift in range(-40, 40, 3):
        obj = refine(
            new_object(1, VoxelDetection(CLASS_INDEX["chair"], 0.9, np.sort(pack_keys(block + (0, 0, shift)))), "a", 0.0), PARAMS
        )
        heights.add(float(obj.obb.size[2]))
        verdicts.add(plausible(obj, PARAMS))
    assert len(heights) > 1  # the float differs with the grid's phase ...
    assert verdicts == {True}  # ... and the verdict does not


def test_a_floor_standing_box_as_tall_as_its_class_can_be_above_its_floor_is_plausible_wherever_the_grid_falls():
    # The same chair with its floor at its lowest voxels' centres: its height is then its top less the floor's
    # height, 0.30 m between the two in exact arithmetic, and its verdict must not turn on that difference's rounding.
    params = Params(voxel_size_m=0.05, floor_bin_m=0.05, floor_min_samples=5)
    i, j, k = np.meshgrid(np.arange(8), np.arange(8), np.arange(7), indexing="ij")
    block = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    verdicts = set()
    for shift in range(-40, 40, 3):
        obj = refine(
            new_object(1, VoxelDetection(CLASS_INDEX["chair"], 0.9, np.sort(pack_keys(block + (0, 0, shift)))), "a", 0.0), params
        )
        obj = obj.replace(floor_votes={shift: 100})  # the floor at (shift + 0.5) voxels: the lowest voxels' centres
        verdicts.add(plausible(obj, params))
    assert verdicts == {True}
