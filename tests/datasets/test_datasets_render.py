"""Rendering an annotated mesh into a ScanNet-layout scene (default and random walks, v1 and v2
annotations), reading it back, and evaluating on it."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from datasets_builders import ALIGNMENT, ROOM_PARTS, SCENE_ID, build_room_scene, circle_walk

from arcloud.core.types import Intrinsics, Params
from arcloud.datasets.files import read_label_png
from arcloud.datasets.gt_masks import GroundTruthMaskDetector
from arcloud.datasets.render_scannet import (
    label_lookup,
    random_user_walk,
    render_scannet,
    room_layout,
    scaled_intrinsics,
    shake,
    triangle_instances,
)
from arcloud.datasets.scannet import load_scannet_scene
from arcloud.errors import InvalidInput

SMALL = Intrinsics(120.0, 120.0, 79.5, 59.5)


def test_room_layout_from_the_annotation(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path))
    layout = room_layout(scene)
    np.testing.assert_allclose(layout.floor_min_xy, [-3.0, -3.0], atol=0.15)
    np.testing.assert_allclose(layout.floor_max_xy, [3.0, 3.0], atol=0.15)
    assert layout.floor_z_m == pytest.approx(0.0, abs=0.05)
    obstacles = {tuple(np.round(np.r_[lo, hi], 2)) for lo, hi in layout.obstacles_xy}
    assert obstacles == {(-3.0, 3.0, 3.0, 3.1), (0.8, 0.8, 1.3, 1.3), (-1.6, -0.9, -0.4, -0.1)}  # wall, chair, table
    np.testing.assert_allclose(layout.targets, [[1.05, 1.05, 0.45], [-1.0, -0.5, 0.375]])  # our classes only


def test_triangle_instances_and_labels(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path))
    per_triangle = triangle_instances(scene)
    assert per_triangle.shape == (len(scene.mesh.triangles),)
    assert np.bincount(per_triangle).tolist() == [36, 12, 12, 12, 12]  # 3 unannotated walls, 4 instances
    # ScanNet label ids (the tsv's id) of instance ids 1..4: floor 11, wall 0 (not in the tsv), chair 2, table 4
    assert label_lookup(scene).tolist() == [0, 11, 0, 2, 4]


def test_scaled_intrinsics() -> None:
    k = scaled_intrinsics(Intrinsics(577.87, 577.87, 319.5, 239.5), (640, 480), (320, 240))
    assert k == pytest.approx(Intrinsics(288.935, 288.935, 159.5, 119.5))


def test_render_read_back_and_evaluate(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh"))
    out = tmp_path / "render"
    scene_dir = render_scannet(
        scene, out, users=2, frames_per_user=6, seed=3, width=160, height=120, intrinsics=SMALL, walk=circle_walk
    )
    record = json.loads((scene_dir / "render.json").read_text())
    assert record["frames"] == 12 and record["user_frames"] == [[0, 6], [6, 12]] and record["dropped"] == 0
    assert record["annotation"] == "v1" and record["label_ids"] == "scannet" and record["eye_height_m"] == 1.5
    assert (out / "scannetv2-labels.combined.tsv").is_file() and not (scene_dir / "labels_v2").exists()

    rendered = load_scannet_scene(scene_dir)
    assert rendered.annotation == "v1" and len(rendered.instances) == len(ROOM_PARTS)
    np.testing.assert_allclose(rendered.scan2aligned, ALIGNMENT, atol=1e-6)
    assert rendered.n_frames == 12 and rendered.depth_intrinsics == pytest.approx(SMALL)
    # poses on disk are in the scan frame; the reader brings them back to the walk (aligned frame)
    layout = room_layout(scene)
    walk1 = circle_walk(
        layout.floor_min_xy, layout.floor_max_xy, layout.targets, 6, 3 * 1000 + 1, eye_height_m=1.5, floor_z_m=layout.floor_z_m
    )
    np.testing.assert_allclose(rendered.pose("7"), walk1[1], atol=1e-6)
    frame = rendered.load_frame("7")
    assert frame.rgb.shape == (120, 160, 3) and frame.depth_m.dtype == np.float32
    # every pixel sees the closed room; depths are those of a 6 m room seen from inside
    assert np.all(frame.depth_m > 0) and frame.depth_m.max() < 6.5

    # the 2D ground truth replays as detections that back-project onto the annotated boxes
    detector = GroundTruthMaskDetector(rendered)
    labels_seen = set()
    for name in rendered.frame_names:
        frame = rendered.load_frame(name)
        for det in detector.detect(frame):
            labels_seen.add(det.label)
            v, u = np.nonzero(det.mask)
            z = frame.depth_m[v, u]
            k = frame.intrinsics
            cam = np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], axis=1)
            world = cam @ frame.cam2world[:3, :3].T + frame.cam2world[:3, 3]
            lo, hi = ROOM_PARTS[det.label]
            assert np.all(world >= lo - 0.02) and np.all(world <= hi + 0.02), det.label
    assert labels_seen == {"chair", "table"}


def test_v2_scene_labels(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path, v2=True))
    assert scene.annotation == "v2"
    # label-filt ids of instance ids 0..301: the nyu40 ids, floor 2 (instance 3 -> 4), chair 5 (9 -> 10), desk 14 (300 -> 301)
    lookup = label_lookup(scene)
    assert len(lookup) == 302 and {i: int(v) for i, v in enumerate(lookup) if v} == {4: 2, 10: 5, 301: 14}
    assert np.bincount(triangle_instances(scene))[[0, 4, 10, 301]].tolist() == [48, 12, 12, 12]  # walls unannotated in v2
    layout = room_layout(scene)
    np.testing.assert_allclose(layout.targets, [[1.05, 1.05, 0.45], [-1.0, -0.5, 0.375]])  # chair, desk


def test_render_of_a_v2_scene_reads_back_as_v2(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh", v2=True))
    scene_dir = render_scannet(
        scene, tmp_path / "render", users=2, frames_per_user=6, seed=3, width=160, height=120, intrinsics=SMALL, walk=circle_walk
    )
    record = json.loads((scene_dir / "render.json").read_text())
    assert record["annotation"] == "v2" and record["label_ids"] == "nyu40"
    assert sorted(p.name for p in (scene_dir / "labels_v2").iterdir()) == [
        f"{SCENE_ID}_ins_label_all.npy",
        f"{SCENE_ID}_sem_label_all.npy",
    ]
    assert not (scene_dir / f"{SCENE_ID}.aggregation.json").exists()  # its objectIds are not what the images hold

    rendered = load_scannet_scene(scene_dir)
    assert rendered.annotation == "v2"
    assert [(i.object_id, i.nyu40_id, i.label) for i in rendered.instances] == [(3, 2, None), (9, 5, "chair"), (300, 14, "table")]
    for a, b in zip(rendered.instances, scene.instances):
        np.testing.assert_allclose(a.aabb_min, b.aabb_min, atol=1e-6)
        np.testing.assert_allclose(a.aabb_max, b.aabb_max, atol=1e-6)
    # the images hold v2 instance ids + 1 (16-bit: beyond 255) and nyu40 ids
    instance_ids = np.unique(
        np.concatenate([read_label_png(scene_dir / "instance-filt" / f"{n}.png").ravel() for n in rendered.frame_names])
    )
    label_ids = np.unique(
        np.concatenate([read_label_png(scene_dir / "label-filt" / f"{n}.png").ravel() for n in rendered.frame_names])
    )
    assert set(instance_ids.tolist()) <= {0, 4, 10, 301} and 301 in instance_ids
    assert set(label_ids.tolist()) <= {0, 2, 5, 14} and 14 in label_ids

    # the detector reads render.json and takes the ids as nyu40 ids: 14 is a desk (table), 5 a chair
    detector = GroundTruthMaskDetector(rendered)
    assert detector.label_ids == "nyu40"
    seen = {d.label for n in rendered.frame_names for d in detector.detect(rendered.load_frame(n))}
    assert seen == {"chair", "table"}
    # an explicit value wins; read as ScanNet label ids the floor's 2 is a chair and 5 and 14 are nothing
    as_scannet = GroundTruthMaskDetector(rendered, label_ids="scannet")
    by_mask_size = [(d.label, d.mask.sum()) for n in rendered.frame_names for d in as_scannet.detect(rendered.load_frame(n))]
    assert {label for label, _ in by_mask_size} == {"chair"} and max(size for _, size in by_mask_size) > 0.3 * 160 * 120
    chair, desk = rendered.gt_boxes()
    assert (chair.label, desk.label) == ("chair", "table")
    np.testing.assert_allclose(desk.min, ROOM_PARTS["table"][0], atol=1e-6)
    np.testing.assert_allclose(desk.max, ROOM_PARTS["table"][1], atol=1e-6)


def test_eval_on_a_rendered_scene_finds_the_ground_truth(tmp_path: Path) -> None:
    from arcloud.accuracy.dataset_runs import evaluate_scenes
    from arcloud.datasets.frames import LazyFrames

    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh"))
    scene_dir = render_scannet(
        scene, tmp_path / "render", users=2, frames_per_user=8, seed=0, width=160, height=120, intrinsics=SMALL, walk=circle_walk
    )
    rendered = load_scannet_scene(scene_dir)
    frames = LazyFrames(rendered.frame_names, rendered.load_frame, cache=True)
    exported: list[tuple[str, int, int]] = []
    result = evaluate_scenes(
        [(SCENE_ID, frames, GroundTruthMaskDetector(rendered), rendered.gt_boxes())],
        Params(),
        users=(1, 2),
        runs=2,
        on_run=lambda scene, k, run, objects: exported.append((scene, k, run)),
    )
    rows = {row["users"]: row for row in result["table1"]}
    assert rows[1]["approach"] == "centralized" and rows[1]["runs"] == 1
    assert rows[2]["approach"] == "distributed" and rows[2]["runs"] == 2
    assert rows[1]["map25_mean"] == pytest.approx(1.0)
    assert rows[2]["map25_mean"] == pytest.approx(1.0)
    assert exported == [(SCENE_ID, 1, 0), (SCENE_ID, 2, 0), (SCENE_ID, 2, 1)]


def test_render_with_the_simulator_walk(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh"))
    scene_dir = render_scannet(scene, tmp_path / "render", users=2, frames_per_user=30, seed=1, width=80, height=60)
    rendered = load_scannet_scene(scene_dir)
    record = json.loads((scene_dir / "render.json").read_text())
    assert rendered.n_frames == record["frames"] == 60 - record["dropped"] >= 50
    eyes = rendered.cam2world[:, :3, 3]
    assert np.all(np.abs(eyes[:, :2]) < 3.0) and np.all((eyes[:, 2] > 1.2) & (eyes[:, 2] < 1.8))  # inside, at eye height
    assert not np.allclose(rendered.cam2world[0], rendered.cam2world[30])  # two users, two walks
    detector = GroundTruthMaskDetector(rendered, min_mask_px=10)
    seen = {d.label for name in rendered.frame_names for d in detector.detect(rendered.load_frame(name))}
    assert seen == {"chair", "table"}


def test_random_user_walks_are_drawn_per_seed_and_user() -> None:
    walks = [random_user_walk(seed, user) for seed in range(5) for user in range(10)]
    assert random_user_walk(3, 4) == random_user_walk(3, 4) and len(set(walks)) == len(walks)
    heights = np.array([w.eye_height_m for w in walks])
    assert np.all((heights >= 1.1) & (heights <= 1.9)) and heights.min() < 1.3 and heights.max() > 1.7
    assert all(0.03 <= w.step_m <= 0.1 and 6 <= w.fixation_frames <= 30 and 0.5 <= w.coverage <= 1.5 for w in walks)
    assert all(0.2 <= w.shake_deg <= 1.5 and 0.002 <= w.shake_m <= 0.01 for w in walks)


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_shake_moves_poses_like_a_hand_held_camera() -> None:
    from arcloud.virtual_camera.gaze import look_at

    poses = [look_at(np.array([0.1 * i, 0.0, 1.5]), np.array([0.1 * i, 3.0, 1.0])) for i in range(2000)]
    assert all(np.array_equal(a, b) for a, b in zip(shake(poses, 0.0, 0.0, np.random.default_rng(0)), poses))
    shaken = shake(poses, 1.0, 0.005, np.random.default_rng(0))
    turned = np.array([_rotation_deg(p, s) for p, s in zip(poses, shaken)])
    moved = np.array([np.linalg.norm(s[:3, 3] - p[:3, 3]) for p, s in zip(poses, shaken)])
    # per axis about 1 degree and 5 mm: the norm of three such is about 1.6 degrees and 8 mm
    assert 1.2 < np.sqrt(np.mean(turned**2)) < 2.1 and 0.006 < np.sqrt(np.mean(moved**2)) < 0.011
    # smooth over a few frames: neighbours differ much less than the shake itself
    steps = np.array([_rotation_deg(a, b) for a, b in zip(shaken[:-1], shaken[1:])])
    assert np.sqrt(np.mean(steps**2)) < 0.7 * np.sqrt(np.mean(turned**2))
    for s in shaken[:5]:
        np.testing.assert_allclose(s[:3, :3] @ s[:3, :3].T, np.eye(3), atol=1e-9)  # still rigid


def test_render_with_random_walks(tmp_path: Path) -> None:
    scene = load_scannet_scene(build_room_scene(tmp_path / "mesh"))
    asked: list[dict] = []

    def recording_walk(floor_min_xy, floor_max_xy, targets, n_frames, seed, **options):
        asked.append({"seed": seed, **options})
        return circle_walk(
            floor_min_xy,
            floor_max_xy,
            targets,
            n_frames,
            seed,
            eye_height_m=options["eye_height_m"],
            floor_z_m=options["floor_z_m"],
        )

    scene_dir = render_scannet(
        scene, tmp_path / "render", users=3, frames_per_user=4, seed=2, width=80, height=60, walk=recording_walk, style="random"
    )
    record = json.loads((scene_dir / "render.json").read_text())
    drawn = [random_user_walk(2, user) for user in range(3)]
    assert record["style"] == "random" and record["walk_styles"] == [dataclasses.asdict(w) for w in drawn]
    assert [a["seed"] for a in asked] == [2000, 2001, 2002]
    assert [a["eye_height_m"] for a in asked] == [w.eye_height_m for w in drawn]
    assert all(a["eye_height_jitter_m"] == 0.0 and a["step_m"] == w.step_m for a, w in zip(asked, drawn))
    # the poses on disk are the planned walk shaken by a few degrees at most
    rendered = load_scannet_scene(scene_dir)
    layout = room_layout(scene)
    planned = circle_walk(
        layout.floor_min_xy,
        layout.floor_max_xy,
        layout.targets,
        4,
        2001,
        eye_height_m=drawn[1].eye_height_m,
        floor_z_m=layout.floor_z_m,
    )
    for i, pose in enumerate(planned):
        shaken = rendered.pose(str(4 + i))
        assert 0.0 < _rotation_deg(pose, shaken) < 6.0 and np.linalg.norm(shaken[:3, 3] - pose[:3, 3]) < 0.05
    with pytest.raises(InvalidInput, match="style"):
        render_scannet(scene, tmp_path / "other", users=1, frames_per_user=2, style="wobbly")
