"""MeshRenderer: exact z-depth and instance ids on hand-made scenes, colours, validation, threads."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from arcloud.core.types import Intrinsics
from arcloud.errors import InvalidInput
from arcloud.sim.room import generate_room, room_renderer
from arcloud.virtual_camera.render import MeshRenderer, triangle_light

K = Intrinsics(100.0, 100.0, 79.5, 59.5)
W, H = 160, 120


def quad(x0: float, x1: float, y0: float, y1: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float32)
    return vertices, np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def two_quads() -> MeshRenderer:
    """A wall at z = 2 (instance 7, red) and, nearer, a panel at z = 1 over x > 0 (instance 9, blue)."""
    v0, t0 = quad(-5, 5, -5, 5, 2.0)
    v1, t1 = quad(0, 5, -5, 5, 1.0)
    return MeshRenderer(
        np.concatenate([v0, v1]),
        np.concatenate([t0, t1 + 4]),
        triangle_colors=np.array([[200, 0, 0]] * 2 + [[0, 0, 200]] * 2, np.uint8),
        triangle_instance=np.array([7, 7, 9, 9], np.int32),
    )


def test_depth_and_instances_of_two_quads_are_exact() -> None:
    result = two_quads().render(np.eye(4), K, W, H)
    assert result.rgb.shape == (H, W, 3) and result.rgb.dtype == np.uint8
    assert result.depth_m.shape == (H, W) and result.depth_m.dtype == np.float32
    assert result.instance.shape == (H, W) and result.instance.dtype == np.int32
    right = np.arange(W) > K.cx  # pixel centres with x > 0 see the near panel
    np.testing.assert_allclose(result.depth_m[:, right], 1.0, atol=1e-6)
    np.testing.assert_allclose(result.depth_m[:, ~right], 2.0, atol=1e-6)
    assert np.all(result.instance[:, right] == 9) and np.all(result.instance[:, ~right] == 7)
    assert set(np.unique(result.triangle[:, right])) <= {2, 3} and set(np.unique(result.triangle[:, ~right])) <= {0, 1}
    # Flat colours, shaded the same over a flat quad.
    assert np.all(result.rgb[:, ~right, 0] > 0) and np.all(result.rgb[:, ~right, 1:] == 0)
    assert np.all(result.rgb[:, right, 2] > 0) and np.all(result.rgb[:, right, :2] == 0)
    assert len(np.unique(result.rgb[:, right].reshape(-1, 3), axis=0)) == 1


def test_depth_is_along_the_optical_axis_from_a_moved_camera() -> None:
    renderer = two_quads()
    cam2world = np.eye(4)
    cam2world[:3, 3] = [0.0, 0.0, -1.0]  # one metre back: every depth grows by one metre
    result = renderer.render(cam2world, K, W, H)
    right = np.arange(W) > K.cx
    np.testing.assert_allclose(result.depth_m[:, ~right], 3.0, atol=1e-5)
    np.testing.assert_allclose(result.depth_m[:, right], 2.0, atol=1e-5)
    # Turned 30 degrees about the camera's y axis, far to the left so that it sees only the wall at
    # z = 2: pixel u's ray (x, 0, 1) in the camera reaches the wall at z-depth 2 / (R (x, 0, 1))_z.
    angle = np.radians(30.0)
    turned = np.eye(4)
    turned[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    turned[:3, 3] = [-4.5, 0.0, 0.0]
    result = renderer.render(turned, K, W, H)
    x = (np.arange(W) - K.cx) / K.fx
    expected = 2.0 / (-np.sin(angle) * x + np.cos(angle))
    np.testing.assert_allclose(result.depth_m[int(K.cy)], expected, rtol=1e-5)
    assert np.all(result.instance == 7)


def test_rays_that_hit_nothing_give_zero() -> None:
    vertices, triangles = quad(0, 5, -5, 5, 2.0)
    result = MeshRenderer(vertices, triangles).render(np.eye(4), K, W, H)
    left = np.arange(W) < K.cx
    assert np.all(result.depth_m[:, left] == 0) and np.all(result.instance == 0)
    assert np.all(result.triangle[:, left] == -1) and np.all(result.rgb[:, left] == 0)
    assert np.all(result.rgb[:, ~left] > 0)  # no colours given: grey


def test_vertex_colours_are_interpolated_barycentrically() -> None:
    vertices = np.array([[-2, -2, 2], [2, -2, 2], [-2, 2, 2]], np.float32)
    colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
    renderer = MeshRenderer(vertices, np.array([[0, 1, 2]]), vertex_colors=colors)
    result = renderer.render(np.eye(4), K, W, H)
    light = float(triangle_light(vertices, np.array([[0, 1, 2]]))[0])
    # Pixel (u, v) sees the point x = 2 (u - cx) / fx, y = 2 (v - cy) / fy; barycentric weights follow.
    for u, v in ((40, 40), (70, 50), (50, 70)):
        x, y = 2 * (u - K.cx) / K.fx, 2 * (v - K.cy) / K.fy
        wb, wc = (x + 2) / 4, (y + 2) / 4
        expected = np.array([1 - wb - wc, wb, wc]) * 255 * light
        np.testing.assert_allclose(result.rgb[v, u], expected, atol=1.5)


def test_concurrent_renders_equal_sequential_ones() -> None:
    room = generate_room(1)
    renderer = room_renderer(room)
    poses = []
    for k in range(6):
        pose = np.eye(4)
        pose[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # looking along +y, image y down = world -z
        pose[:3, 3] = [1.0 + k, 0.5, 1.5]
        poses.append(pose)
    sequential = [renderer.render(p, K, W, H) for p in poses]
    with ThreadPoolExecutor(4) as pool:
        parallel = list(pool.map(lambda p: renderer.render(p, K, W, H), poses))
    for a, b in zip(sequential, parallel):
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
        np.testing.assert_array_equal(a.instance, b.instance)
        np.testing.assert_array_equal(a.rgb, b.rgb)
    # Looking at the far wall (y = 6 m) from y = 0.5 m: the centre pixel is at most 5.5 m away.
    assert 0 < sequential[0].depth_m[60, 80] <= 5.5 + 1e-4


@pytest.mark.parametrize(
    ("args", "kwargs", "field"),
    [
        ((np.zeros((4, 2)), np.array([[0, 1, 2]])), {}, "vertices"),
        ((np.zeros((3, 3)), np.array([[0, 1, 3]])), {}, "triangles"),
        ((np.zeros((3, 3)), np.array([[0.0, 1.0, 2.0]])), {}, "triangles"),
        ((np.full((3, 3), np.nan), np.array([[0, 1, 2]])), {}, "vertices"),
        ((np.zeros((3, 3)), np.array([[0, 1, 2]])), {"triangle_colors": np.zeros((2, 3))}, "triangle_colors"),
        ((np.zeros((3, 3)), np.array([[0, 1, 2]])), {"triangle_instance": np.zeros(3)}, "triangle_instance"),
    ],
)
def test_bad_meshes_raise_invalid_input(args: tuple, kwargs: dict, field: str) -> None:
    with pytest.raises(InvalidInput) as info:
        MeshRenderer(*args, **kwargs)
    assert info.value.field == field


def test_bad_pose_or_size_raise_invalid_input() -> None:
    renderer = two_quads()
    with pytest.raises(InvalidInput):
        renderer.render(np.eye(3), K, W, H)
    with pytest.raises(InvalidInput):
        renderer.render(np.diag([1.0, 1.0, -1.0, 1.0]), K, W, H)  # a reflection
    with pytest.raises(InvalidInput):
        renderer.render(np.eye(4), K, 0, H)
