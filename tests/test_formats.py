"""The export encoders on hand-made input, read back by standard readers (Open3D, trimesh)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from arcloud.core.types import LabelledBox
from arcloud.core.voxels import points_to_keys
from arcloud.errors import InvalidInput
from arcloud.formats.gltf import Box, boxes_glb
from arcloud.formats.ply import points_ply
from arcloud.formats.scannet import Prediction, read_boxes, scannet_files


def test_ply_round_trips_through_open3d(tmp_path: Path) -> None:
    import open3d as o3d

    rng = np.random.default_rng(0)
    points = rng.uniform(-3, 3, (50, 3))
    colors = rng.integers(0, 256, (50, 3))
    path = tmp_path / "p.ply"
    path.write_bytes(points_ply(points, colors, np.arange(50), comment="two\nlines"))
    cloud = o3d.io.read_point_cloud(path)
    np.testing.assert_allclose(np.asarray(cloud.points), points, atol=1e-5)  # float32
    np.testing.assert_array_equal(np.round(np.asarray(cloud.colors) * 255), colors)
    with pytest.raises(InvalidInput):
        points_ply(points, colors[:3], np.arange(50))
    with pytest.raises(InvalidInput):
        points_ply(np.full((1, 3), np.nan), colors[:1], np.arange(1))


def test_glb_nodes_and_an_empty_scene_load() -> None:
    import trimesh

    boxes = [Box(7, "chair", 0.9, (1.0, 2.0, 0.5), (0.5, 0.6, 1.0), 0.3), Box(8, "tv", 0.4, (0.0, 0.0, 1.0), (1.0, 0.1, 0.6))]
    scene = trimesh.load(io.BytesIO(boxes_glb(boxes)), file_type="glb", force="scene")
    assert sorted(scene.graph.nodes_geometry) == ["chair 7", "tv 8"]
    empty = trimesh.load(io.BytesIO(boxes_glb([])), file_type="glb", force="scene")
    assert len(empty.graph.nodes_geometry) == 0
    with pytest.raises(InvalidInput):
        boxes_glb([Box(1, "chair", 1.0, (np.inf, 0.0, 0.0), (1.0, 1.0, 1.0))])


def test_scannet_masks_boxes_and_the_reader() -> None:
    size = 0.05
    inside = np.array([[1.01, 1.01, 1.01], [1.06, 1.01, 1.01]])
    vertices = np.vstack([inside, [[5.0, 5.0, 5.0]]])
    chair = Prediction("chair", 0.8, np.array([1.0, 1.0, 1.0]), np.array([1.1, 1.05, 1.05]), points_to_keys(inside, size))
    laptop = Prediction("laptop", 0.5, np.zeros(3), np.ones(3), points_to_keys(vertices[2:], size))
    files = scannet_files("scene0000_00", [chair, laptop], vertices_m=vertices, voxel_size_m=size)
    assert files["scene0000_00.txt"].decode().splitlines() == [
        "pred_mask/scene0000_00_000.txt 5 0.800000",
        "pred_mask/scene0000_00_001.txt 40 0.500000",
    ]
    assert files["pred_mask/scene0000_00_000.txt"].decode().split() == ["1", "1", "0"]
    assert files["pred_mask/scene0000_00_001.txt"].decode().split() == ["0", "0", "1"]
    boxes = read_boxes(files["scene0000_00_boxes.txt"].decode())
    assert [(b.label, b.score) for b in boxes] == [("chair", 0.8), ("laptop", 0.5)]
    assert isinstance(boxes[0], LabelledBox) and np.allclose(boxes[0].max, [1.1, 1.05, 1.05])
    for bad in ("5 0.5 1 2 3", "99 0.5 0 0 0 1 1 1", "x y"):
        with pytest.raises(InvalidInput, match="line 1"):
            read_boxes(bad)
    with pytest.raises(InvalidInput):
        scannet_files("a/b", [])
