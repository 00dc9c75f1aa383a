"""Ray-cast rendering of triangle meshes into colour, z-depth and instance images (Open3D Embree).

Generic: used for generated rooms and for real scanned meshes. Cameras follow OpenCV axes (x right,
y down, z forward) with pinhole intrinsics; pixel (u, v) looks through its centre at
((u - cx) / fx, (v - cy) / fy, 1) in the camera frame, so a hit's ray parameter is its z-depth.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from arcloud.core.checks import check_pose
from arcloud.core.types import Intrinsics
from arcloud.errors import InvalidInput

#: Lighting: an ambient share plus (weight, unit world direction) of fixed lights, so that the faces of
#: a box facing x, y and z get distinct brightness. Brightness is per triangle (flat shading).
AMBIENT = 0.45
LIGHTS = tuple(
    (w, np.asarray(d, np.float64) / np.linalg.norm(d)) for w, d in ((0.4, (0.3, 0.2, 0.93)), (0.25, (0.8, -0.55, 0.25)))
)


@dataclass(frozen=True, eq=False)
class RayHits:
    """Per-pixel first hits. depth_m: (H, W) float32 z-depth, 0 where no hit. triangle: (H, W) int32,
    -1 where no hit. uv: (H, W, 2) float32 barycentric (u, v) of the hit (the point is
    (1 - u - v) * a + u * b + v * c for triangle (a, b, c)). normal: (H, W, 3) float32 unit normals
    of the hit triangles in the world frame. uv and normal are None unless asked for (``surface``)."""

    depth_m: np.ndarray
    triangle: np.ndarray
    uv: np.ndarray | None
    normal: np.ndarray | None


@dataclass(frozen=True, eq=False)
class RenderResult:
    """rgb: (H, W, 3) uint8. depth_m: (H, W) float32 z-depth along the optical axis, 0 where no hit.
    instance: (H, W) int32, the hit triangle's instance id, 0 where background or no hit.
    triangle: (H, W) int32 hit triangle index, -1 where no hit."""

    rgb: np.ndarray
    depth_m: np.ndarray
    instance: np.ndarray
    triangle: np.ndarray


def _check_mesh(vertices: object, triangles: object) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise InvalidInput("vertices", "shape (V, 3) with V >= 1", f"shape {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0 or not np.issubdtype(t.dtype, np.integer):
        raise InvalidInput("triangles", "integer shape (T, 3) with T >= 1", f"shape {t.shape} dtype {t.dtype}")
    if not np.all(np.isfinite(v)):
        raise InvalidInput("vertices", "finite coordinates", "NaN or infinity")
    if t.min() < 0 or t.max() >= len(v):
        raise InvalidInput("triangles", f"vertex indices in [0, {len(v)})", f"[{t.min()}, {t.max()}]")
    return np.ascontiguousarray(v, dtype=np.float32), np.ascontiguousarray(t, dtype=np.uint32)


def _per_triangle(field: str, value: object, n: int, dtype: type, width: int | None) -> np.ndarray | None:
    if value is None:
        return None
    array = np.asarray(value)
    shape = (n,) if width is None else (n, width)
    if array.shape != shape:
        raise InvalidInput(field, f"shape {shape}", f"shape {array.shape}")
    return np.ascontiguousarray(array, dtype=dtype)


class MeshRenderer:
    """Renders one static triangle mesh from any pinhole camera.

    Colour comes from ``vertex_colors`` (interpolated with the hit's barycentric coordinates) or else
    ``triangle_colors`` (flat), else a uniform grey, shaded per triangle with an ambient term and two
    fixed lights (two-sided Lambertian on the triangle normals, see ``LIGHTS``). ``triangle_instance``
    gives the instance image (0 = background).

    Thread-safe: the Embree scene is built and committed once in ``__init__``; concurrent
    ``render``/``raycast`` calls are serialised around the ray cast itself and do the rest in
    parallel. The cast runs on Open3D's own threads while holding the GIL, so more Python threads do
    not speed rendering up; processes do (as ``arcloud.sim.sequence`` renders). A 640 x 480 frame of a
    generated room costs about 45 ms of CPU, mostly in the cast.
    """

    def __init__(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        *,
        triangle_colors: np.ndarray | None = None,
        vertex_colors: np.ndarray | None = None,
        triangle_instance: np.ndarray | None = None,
    ) -> None:
        import open3d as o3d  # heavy: only when a renderer is built

        self.vertices, self.triangles = _check_mesh(vertices, triangles)
        n_tri = len(self.triangles)
        self.triangle_colors = _per_triangle("triangle_colors", triangle_colors, n_tri, np.uint8, 3)
        self.vertex_colors = _per_triangle("vertex_colors", vertex_colors, len(self.vertices), np.uint8, 3)
        self.triangle_instance = _per_triangle("triangle_instance", triangle_instance, n_tri, np.int32, None)
        self._light = triangle_light(self.vertices, self.triangles)
        if self.vertex_colors is not None:
            self._vertex_colors_f = self.vertex_colors.astype(np.float32)
        albedo = (
            self.triangle_colors.astype(np.float32)
            if self.triangle_colors is not None
            else np.full((n_tri, 3), 180.0, np.float32)
        )
        # Lookup tables with a last row for pixels that hit nothing (triangle -1).
        self._color_table = np.zeros((n_tri + 1, 3), np.uint8)
        self._color_table[:n_tri] = np.clip(albedo * self._light[:, None], 0, 255).astype(np.uint8)
        self._instance_table = np.zeros(n_tri + 1, np.int32)
        if self.triangle_instance is not None:
            self._instance_table[:n_tri] = self.triangle_instance
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor.from_numpy(self.vertices), o3d.core.Tensor.from_numpy(self.triangles))
        self._tensor = o3d.core.Tensor.from_numpy
        self._o3d = o3d
        self._lock = threading.Lock()
        # Cast once so that Embree commits the scene now, not inside concurrent calls.
        ray = np.array([[0, 0, 0, 0, 0, 1]], np.float32)
        self._scene.cast_rays(o3d.core.Tensor(ray))  # type: ignore[call-overload]  # open3d's stubs want dtype and device: the array has them

    def raycast(
        self, cam2world: np.ndarray, intrinsics: Intrinsics, width: int, height: int, *, surface: bool = False, threads: int = 0
    ) -> RayHits:
        """First hits of the rays through every pixel centre of an (height, width) image; with
        ``surface``, also the hits' barycentric coordinates and normals (else None). ``threads``: Open3D's
        threads for the cast (0: one per core)."""
        pose = check_pose("cam2world", cam2world)
        if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer)) and width > 0 and height > 0):
            raise InvalidInput("width, height", "positive integers", f"{width!r}, {height!r}")
        # Open3D's rays go through (u + 0.5, v + 0.5); ours through pixel centres (u, v): shift c by 0.5.
        camera = np.array([[intrinsics.fx, 0.0, intrinsics.cx + 0.5], [0.0, intrinsics.fy, intrinsics.cy + 0.5], [0.0, 0.0, 1.0]])
        world2cam = np.eye(4)
        world2cam[:3, :3] = pose[:3, :3].T
        world2cam[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
        rays = self._o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            self._tensor(camera), self._tensor(world2cam), int(width), int(height)
        )  # (H, W, 6): origin, direction with z = 1 in the camera frame
        with self._lock:
            hits = self._scene.cast_rays(rays, nthreads=threads)
            t_hit = hits["t_hit"].numpy()
            primitive = hits["primitive_ids"].numpy()
            uv = hits["primitive_uvs"].numpy().copy() if surface else None
            normal = hits["primitive_normals"].numpy().copy() if surface else None
        triangle = primitive.view(np.int32).copy()  # Embree's invalid id 0xFFFFFFFF reads -1
        depth = np.where(triangle >= 0, t_hit, np.float32(0.0))
        return RayHits(depth, triangle, uv, normal)

    def render(self, cam2world: np.ndarray, intrinsics: Intrinsics, width: int, height: int, *, threads: int = 0) -> RenderResult:
        """Colour, z-depth and instance images of the mesh seen from ``cam2world`` (4, 4)."""
        hits = self.raycast(cam2world, intrinsics, width, height, surface=self.vertex_colors is not None, threads=threads)
        # Per-triangle tables have one more row, for "no hit" (index -1 takes the last row).
        instance = np.take(self._instance_table, hits.triangle)
        if self.vertex_colors is not None:
            hit = hits.triangle >= 0
            tri = np.where(hit, hits.triangle, 0)
            corners = self.triangles[tri]  # (H, W, 3)
            assert hits.uv is not None
            u, v = hits.uv[..., :1], hits.uv[..., 1:]
            colors = self._vertex_colors_f
            albedo = (1 - u - v) * colors[corners[..., 0]] + u * colors[corners[..., 1]] + v * colors[corners[..., 2]]
            rgb_f = albedo * self._light[tri][..., None]
            rgb_f[~hit] = 0.0
            rgb = np.clip(rgb_f, 0.0, 255.0).astype(np.uint8)
        else:
            rgb = np.take(self._color_table, hits.triangle, axis=0)
        return RenderResult(rgb, hits.depth_m, instance, hits.triangle)


def triangle_light(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) float32 brightness of each triangle under the fixed lights (two-sided Lambertian)."""
    a, b, c = (vertices[triangles[:, k]].astype(np.float64) for k in range(3))
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, norms, out=np.zeros_like(normals), where=norms > 0)
    light = AMBIENT + sum(w * np.abs(normals @ d) for w, d in LIGHTS)
    return light.astype(np.float32)
