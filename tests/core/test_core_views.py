"""Decided across views, on hand-made frames: the label from every frame that saw an object, weighted by
how well each saw it (core.voxels.view_weights); boxes of what was seen (a chair pushed under a table
does not reach a floor no frame saw beside it: core.floor.floor_beside_seen); an object detected in
many frames at a low score is confirmed (core.confirm)."""

from __future__ import annotations

import numpy as np
import pytest
from handmade_frames import HEIGHT, WIDTH, look_down_pose, rect_mask, scene_frame

from arcloud.core.confirm import evidence
from arcloud.core.floor import frame_floor
from arcloud.core.step import integrate_frame
from arcloud.core.types import OBB, Detection, Params, empty_object
from arcloud.core.voxels import back_project, mask_extent, view_weights
from arcloud.stores.memory import MemoryStore

PARAMS = Params(voxel_size_m=0.05, floor_min_samples=5)
SCREEN = ((-0.4, 1.95, 1.0), (0.4, 2.0, 1.45))  # a TV on a wall at y = 2


def screen_views(first: int, n: int, *, yaw_deg: float):
    """Frames of the screen from 2 m, looking at it from ``yaw_deg`` off its normal."""
    for i in range(first, first + n):
        angle = np.radians(yaw_deg + 2.0 * (i % 3))
        eye = (2.0 * np.sin(angle), 2.0 - 2.0 * np.cos(angle), 1.2)
        frame, instance = scene_frame(look_down_pose(eye, (0.0, 2.0, 1.2)), [SCREEN], floor_z=None, frame_id=f"f{i}")
        yield frame, instance == 0


def mask_points(frame, mask):
    v, u = np.nonzero(mask & (frame.depth_m > 0))
    return back_project(frame, v, u, frame.depth_m[v, u])


def view_weight(frame, mask, points):
    return view_weights(frame, [mask_extent(mask)], [points], PARAMS)[0]


def test_view_weight_falls_for_cut_off_small_far_and_edge_on_views():
    frame, mask = next(screen_views(0, 1, yaw_deg=0.0))
    full = view_weight(frame, mask, mask_points(frame, mask))
    assert full == pytest.approx(1.0, abs=0.02)  # face on, whole, near
    (oblique, oblique_mask), *_ = screen_views(0, 1, yaw_deg=70.0)
    assert view_weight(oblique, oblique_mask, mask_points(oblique, oblique_mask)) < 0.6 * full
    cut = mask.copy()
    cut[: np.flatnonzero(mask.any(axis=1))[0] + 3] = False  # its top rows gone, then touching the border:
    cut[0] = mask[np.flatnonzero(mask.any(axis=1))[0] + 3]
    assert view_weight(frame, cut, mask_points(frame, cut)) == pytest.approx(PARAMS.view_truncated_weight, rel=0.05)
    tiny = rect_mask(slice(28, 30), slice(38, 40))  # 4 of 4800 pixels
    assert view_weight(frame, tiny, mask_points(frame, tiny)) == pytest.approx(4 / 4800 / 0.01, rel=0.05)
    far_points = mask_points(frame, mask) + np.array([0.0, 4.0, 0.0])  # 6 m away
    assert view_weight(frame, mask, far_points) < 0.6


def test_view_weights_of_a_frames_masks_together_are_each_masks_own():
    # One eigendecomposition serves every mask of a frame: the weights are those of one mask at a time.
    frame, mask = next(screen_views(0, 1, yaw_deg=35.0))
    cut = mask.copy()
    cut[: np.flatnonzero(mask.any(axis=1))[0] + 3] = False
    masks = [mask, rect_mask(slice(28, 30), slice(38, 40)), cut, rect_mask(slice(0, 30), slice(0, 60))]
    masks = [m & (frame.depth_m > 0) for m in masks]
    extents, points = [mask_extent(m) for m in masks], [mask_points(frame, m) for m in masks]
    together = view_weights(frame, extents, points, PARAMS)
    assert together == [view_weights(frame, [e], [p], PARAMS)[0] for e, p in zip(extents, points)]
    assert len(set(together)) == len(masks)  # four different views, four different weights


@pytest.mark.parametrize("weighted", [True, False])
def test_oblique_views_do_not_rename_a_screen(weighted):
    # Three face-on views call it a TV; four edge-on views call it a laptop (a screen seen obliquely).
    params = PARAMS if weighted else PARAMS.replace(view_oblique_min=1.0)
    store = MemoryStore()
    for frame, mask in screen_views(0, 3, yaw_deg=0.0):
        integrate_frame(frame, [Detection("tv", 0.8, mask)], store, params)
    for frame, mask in screen_views(3, 4, yaw_deg=65.0):
        integrate_frame(frame, [Detection("laptop", 0.8, mask)], store, params)
    (screen,) = store.list_objects("m")
    assert screen.n_frames == 7
    assert screen.label == ("tv" if weighted else "laptop")


COUNTER = ((-1.5, -0.5, 0.0), (1.5, 0.5, 0.9))  # a long solid counter (a desk with a front panel)
CHAIR_BEHIND = ((-0.25, 0.6, 0.45), (0.25, 1.0, 1.1))  # a chair behind it: only its back shows above it


def front_views(boxes, n=8):
    """Frames from the counter's front side, -60 to 60 degrees around it, with their instance images."""
    for i in range(n):
        angle = np.radians(-60 + 120 * i / (n - 1))
        eye = (3.0 * np.sin(angle), -3.0 * np.cos(angle), 1.6)
        yield scene_frame(look_down_pose(eye, (0.0, 0.0, 0.6)), boxes, frame_id=f"f{i}")


def test_the_floor_is_voted_under_an_object_only_where_a_frame_sees_it_beside_the_object():
    open_chair = ((0.9, -1.3, 0.45), (1.3, -0.9, 0.95))
    frame, _ = scene_frame(look_down_pose((0.0, -3.5, 1.8), (0.0, 0.0, 0.5)), [COUNTER, CHAIR_BEHIND, open_chair])
    floor = frame_floor(frame, PARAMS)
    assert floor.height_m == pytest.approx(0.0, abs=PARAMS.floor_bin_m)
    behind = np.array([[-0.25, 0.6, 0.9], [0.25, 1.0, 1.1]])  # what shows of the chair behind
    beside = np.array([[0.9, -1.3, 0.45], [1.3, -0.9, 0.95]])
    assert floor.vote_for(beside, PARAMS) is not None
    assert floor.vote_for(behind, PARAMS) is None  # the counter and the chair hide the floor all around it
    assert floor.vote_for(behind, PARAMS.replace(floor_ring_min_seen=0)) is not None


def test_a_chair_behind_a_counter_keeps_the_box_that_was_seen():
    store = MemoryStore()
    for frame, instance in front_views([COUNTER, CHAIR_BEHIND]):
        integrate_frame(frame, [Detection("chair", 0.9, instance == 1), Detection("table", 0.9, instance == 0)], store, PARAMS)
    chair = next(o for o in store.list_objects("m") if o.label == "chair")
    assert chair.aabb.min[2] >= 0.8  # seen above the counter only: no frame saw the floor beside it
    unchecked = MemoryStore()
    for frame, instance in front_views([COUNTER, CHAIR_BEHIND]):
        detections = [Detection("chair", 0.9, instance == 1), Detection("table", 0.9, instance == 0)]
        integrate_frame(frame, detections, unchecked, PARAMS.replace(floor_ring_min_seen=0))
    chair = next(o for o in unchecked.list_objects("m") if o.label == "chair")
    assert chair.aabb.min[2] == pytest.approx(0.0, abs=PARAMS.floor_bin_m)  # what the rule was before: amodal


def test_detections_in_many_frames_confirm_an_object_whatever_its_score():
    obb = OBB(center=np.array([0.0, 0.0, 0.375]), size=np.array([1.6, 0.9, 0.75]), rotation=np.eye(3), yaw_rad=0.0)
    desk = empty_object(1).replace(label="table", obb=obb, label_purity=1.0, n_missed=10)
    few = desk.replace(n_frames=10, score_sum=10 * 0.3)  # mean score 0.3: the score is below confirm_min_score
    many = desk.replace(n_frames=PARAMS.confirm_evidence_frames, score_sum=PARAMS.confirm_evidence_frames * 0.3)
    assert not evidence(few, PARAMS)[1]
    assert evidence(many, PARAMS)[1]
    assert not evidence(many, PARAMS.replace(confirm_evidence_frames=0))[1]
    assert not evidence(many.replace(n_missed=10 * PARAMS.confirm_evidence_frames), PARAMS)[1]  # a rate too low


def test_frames_are_the_size_the_tests_assume():
    assert (HEIGHT, WIDTH) == (60, 80)
