"""The readers on the real data in ../shared (skipped when absent)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from arcloud.datasets.scannet import load_scannet_scene
from arcloud.datasets.sevenscenes import load_seven_scenes

pytestmark = pytest.mark.shared


def test_scannet_scene0000_ground_truth(shared: type) -> None:
    root = shared.path("data/scannet-scene0000_00")
    meta = json.loads((root / "real_frames" / "frames.json").read_text())
    scene = load_scannet_scene(root, scan2aligned=np.asarray(meta["axis_align_matrix"]))
    assert scene.scene_id == "scene0000_00" and len(scene.instances) == 55
    objects = {(o.raw_category, o.label) for o in scene.objects}
    assert objects == {("table", "table"), ("desk", "table"), ("couch", "couch"), ("tv", "tv")}
    assert sorted(o.label for o in scene.objects) == ["couch", "table", "table", "table", "tv"]
    for obj in scene.objects:
        assert np.all(obj.size > 0.05) and np.all(obj.size < 3.0), (obj.raw_category, obj.size)
        assert -0.2 < obj.aabb_min[2] < 1.0 and obj.aabb_max[2] < 2.0  # on the floor of the aligned frame (z up)
    # v1 boxes agree with the v2 annotation's boxes (mmdetection3d) where both name the object
    v2 = {(b["name"], tuple(np.round(b["center"], 1))): b for b in meta["gt_boxes_aligned"]}
    v2_sofa = next(b for (name, _), b in v2.items() if name == "sofa")
    couch = next(o for o in scene.objects if o.label == "couch")
    assert np.linalg.norm(couch.center[:2] - np.asarray(v2_sofa["center"])[:2]) < 0.15
    v2_desk = next(b for (name, _), b in v2.items() if name == "desk")
    desk = next(o for o in scene.objects if o.raw_category == "desk")
    assert np.linalg.norm(desk.center[:2] - np.asarray(v2_desk["center"])[:2]) < 0.15
    # the alignment is applied: the aligned room is centred near the origin
    floor = next(o for o in scene.instances if o.raw_category == "floor")
    assert np.all(np.abs(floor.center[:2]) < 0.5)


def _backproject(frame, step: int = 2) -> np.ndarray:
    depth = frame.depth_m[::step, ::step]
    v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]] * step
    valid = depth > 0
    k = frame.intrinsics
    z = depth[valid]
    points = np.stack([(u[valid] - k.cx) / k.fx * z, (v[valid] - k.cy) / k.fy * z, z], axis=1)
    return points @ frame.cam2world[:3, :3].T + frame.cam2world[:3, 3]


def test_seven_scenes_frames_back_project_consistently(shared: type) -> None:
    sequence = load_seven_scenes(shared.path("data/7scenes-redkitchen"))
    assert sequence.n_frames == 1000 and sequence.up_file is not None
    a, b = sequence.load_frame("000100"), sequence.load_frame("000110")
    points = _backproject(a)
    # project frame a's points into frame b and compare with b's depth there
    world2cam = np.linalg.inv(b.cam2world)
    cam = points @ world2cam[:3, :3].T + world2cam[:3, 3]
    k = b.intrinsics
    u = np.rint(cam[:, 0] / cam[:, 2] * k.fx + k.cx).astype(int)
    v = np.rint(cam[:, 1] / cam[:, 2] * k.fy + k.cy).astype(int)
    inside = (cam[:, 2] > 0.1) & (u >= 0) & (u < b.shape[1]) & (v >= 0) & (v < b.shape[0])
    depth_b = b.depth_m[v[inside], u[inside]]
    seen = depth_b > 0
    error = np.abs(depth_b[seen] - cam[inside, 2][seen])
    assert seen.sum() > 10_000
    assert np.median(error) < 0.02, np.median(error)


def test_seven_scenes_gravity_makes_floor_and_table_horizontal(shared: type) -> None:
    sequence = load_seven_scenes(shared.path("data/7scenes-redkitchen"), align_gravity=True)
    assert sequence.up == pytest.approx((0.0, 0.0, 1.0))
    heights = np.concatenate([_backproject(sequence.load_frame(n), step=8)[:, 2] for n in sequence.frame_names[::100]])
    counts, edges = np.histogram(heights, bins=np.arange(heights.min(), heights.max() + 0.02, 0.02))
    peak = edges[np.argmax(counts)]
    # a horizontal surface (the table top, about 0.7 m above the floor) makes a sharp peak in height
    assert counts.max() > 4 * np.median(counts)
    assert 0.5 < peak - np.percentile(heights, 1) < 0.9
