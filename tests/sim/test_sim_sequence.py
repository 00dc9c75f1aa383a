"""simulate_sequence: validated frames whose depth lies on the mesh, ids, timing, noise, workers."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from arcloud.core.checks import check_pose
from arcloud.core.types import Intrinsics
from arcloud.errors import InvalidInput
from arcloud.sim.detector import DetectorFaults, true_pose
from arcloud.sim.room import Room, generate_room, room_walk
from arcloud.sim.sequence import frame_id_of, gt_boxes, simulate_sequence

K = Intrinsics(262.5, 262.5, 159.5, 119.5)
W, H = 320, 240


@pytest.fixture(scope="module")
def room() -> Room:
    return generate_room(4)


@pytest.fixture(scope="module")
def poses(room: Room) -> list[np.ndarray]:
    return room_walk(room, 60, seed=4)[::10]


def backproject(depth_m: np.ndarray, intrinsics: Intrinsics, cam2world: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u].astype(np.float64)
    cam = np.column_stack([(u - intrinsics.cx) / intrinsics.fx * z, (v - intrinsics.cy) / intrinsics.fy * z, z])
    return cam @ cam2world[:3, :3].T + cam2world[:3, 3]


def test_noiseless_depth_back_projects_onto_the_mesh(room: Room, poses: list[np.ndarray]) -> None:
    frames = simulate_sequence(
        room, n_frames=len(poses), seed=4, width=W, height=H, intrinsics=K, faults=DetectorFaults.none(), poses=poses, workers=1
    )
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(room.vertices), o3d.core.Tensor(room.triangles.astype(np.uint32)))
    for frame, pose in zip(frames, poses):
        np.testing.assert_array_equal(frame.cam2world, pose)
        assert np.all(frame.depth_m > 0)  # a closed room: every ray hits something
        points = backproject(frame.depth_m, frame.intrinsics, frame.cam2world)[::7]
        distance = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
        # Open3D's closest-point query is a few millimetres off on sliver triangles (the baseboards' top
        # faces, 8 m x 1 cm), hence the looser bound on the worst point.
        assert np.percentile(distance, 99) < 1e-4 and distance.max() < 5e-3
        eye = pose[:3, 3]
        assert np.all(points[:, 2] > -1e-3) and np.all(points[:, 2] < room.size_m[2] + 1e-3)
        assert np.linalg.norm(points - eye, axis=1).min() > 0.05


def test_frames_have_ids_timestamps_and_reported_noisy_poses(room: Room, poses: list[np.ndarray]) -> None:
    faults = DetectorFaults()
    frames = simulate_sequence(
        room,
        n_frames=len(poses),
        seed=4,
        width=W,
        height=H,
        intrinsics=K,
        faults=faults,
        poses=poses,
        map_id="m1",
        device_id="dev-2",
        workers=1,
    )
    assert (
        [f.frame_id for f in frames]
        == [frame_id_of(i) for i in range(len(poses))]
        == ["f000000", "f000001", "f000002", "f000003", "f000004", "f000005"]
    )
    np.testing.assert_allclose([f.timestamp_s for f in frames], np.arange(len(poses)) / 30.0)
    assert {(f.map_id, f.device_id) for f in frames} == {("m1", "dev-2")}
    for frame, pose in zip(frames, poses):
        assert frame.rgb.shape == (H, W, 3) and frame.depth_m.shape == (H, W)
        reported = check_pose("cam2world", frame.cam2world)
        shift = np.linalg.norm(reported[:3, 3] - pose[:3, 3])
        assert 0 < shift < 0.08
        np.testing.assert_allclose(true_pose(reported, faults, 4, frame.frame_id), pose, atol=1e-9)
        invalid = np.mean(frame.depth_m == 0)
        assert 0.0005 < invalid < 0.2  # dropouts, not a blank frame


def test_same_arguments_same_frames_and_workers_do_not_matter(room: Room, poses: list[np.ndarray]) -> None:
    kwargs = dict(
        n_frames=4, seed=4, width=W // 2, height=H // 2, intrinsics=Intrinsics(131.25, 131.25, 79.5, 59.5), poses=poses[:4]
    )
    a = simulate_sequence(room, workers=1, **kwargs)
    b = simulate_sequence(room, workers=2, **kwargs)
    for fa, fb in zip(a, b):
        np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_array_equal(fa.depth_m, fb.depth_m)
        np.testing.assert_array_equal(fa.cam2world, fb.cam2world)
    c = simulate_sequence(room, workers=1, **{**kwargs, "seed": 5})
    assert not np.array_equal(a[0].depth_m, c[0].depth_m)


def test_gt_boxes_list_every_object(room: Room) -> None:
    boxes = gt_boxes(room)
    assert len(boxes) == len(room.objects)
    for (label, lo, hi), obj in zip(boxes, room.objects):
        assert label == obj.label and np.all(lo < hi)


def test_bad_arguments_raise_invalid_input(room: Room, poses: list[np.ndarray]) -> None:
    with pytest.raises(InvalidInput):
        simulate_sequence(room, n_frames=3, poses=poses[:2])
    with pytest.raises(InvalidInput):
        simulate_sequence(room, n_frames=2, poses=poses[:2], workers=0)
    with pytest.raises(InvalidInput):
        simulate_sequence(room, n_frames=1, poses=poses[:1], device_id="a/b", workers=1)
