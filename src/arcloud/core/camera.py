"""Camera view frustums and the test of object bounds against them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from arcloud.core.types import Frame, Intrinsics, Params


@dataclass(frozen=True, eq=False, slots=True)
class Frustum:
    """A camera's view volume in world coordinates.

    planes: (6, 4) rows (n, d) with inward unit normals: a point x is inside when n . x + d >= 0 for all.
    corners: (8, 3) near then far corners."""

    planes: np.ndarray
    corners: np.ndarray

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) of the frustum's axis-aligned bounding box."""
        return self.corners.min(axis=0), self.corners.max(axis=0)


def view_frustum(intrinsics: Intrinsics, width: int, height: int, cam2world: np.ndarray, near_m: float, far_m: float) -> Frustum:
    """The frustum of a pinhole camera between the planes z = near_m and z = far_m (camera frame)."""
    x0, x1 = -intrinsics.cx / intrinsics.fx, (width - intrinsics.cx) / intrinsics.fx
    y0, y1 = -intrinsics.cy / intrinsics.fy, (height - intrinsics.cy) / intrinsics.fy
    rays = np.array([[x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1]])
    corners_cam = np.concatenate([rays * near_m, rays * far_m])
    rotation, origin = cam2world[:3, :3], cam2world[:3, 3]
    corners = corners_cam @ rotation.T + origin
    # Inward normals in the camera frame: near, far, then the four sides (cross products of edge rays).
    normals_cam = [np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])]
    sides = np.cross(rays, rays[[1, 2, 3, 0]])  # of each edge ray and the next: one call, the same products
    for n in sides:
        normals_cam.append(n / np.linalg.norm(n))
    normals = np.array(normals_cam) @ rotation.T
    points_on = np.array([corners[0], corners[4], origin, origin, origin, origin])
    d = -np.einsum("ij,ij->i", normals, points_on)
    return Frustum(planes=np.column_stack([normals, d]), corners=corners)


def frame_frustum(frame: Frame, params: Params) -> Frustum | None:
    """The frame's frustum, near/far from its valid depth (within the params' depth range), padded by
    two voxels; None when the frame has no valid depth."""
    # Every 4th pixel bounds the depth range to within the padding (copied: strided reads cost more;
    # every other row first, whole, which streams a depth image not yet in cache faster: ~15%).
    sample = np.ascontiguousarray(frame.depth_m[::2].copy()[:, ::2])
    valid = sample[(sample >= params.depth_min_m) & (sample <= params.depth_max_m)]
    if valid.size == 0:
        return None
    pad_m = 2 * params.voxel_size_m
    near_m = max(params.depth_min_m, float(valid.min()) - pad_m)
    far_m = min(params.depth_max_m, float(valid.max())) + pad_m
    height, width = frame.depth_m.shape
    return view_frustum(frame.intrinsics, width, height, frame.cam2world, near_m, far_m)


def boxes_in_frustum(frustum: Frustum, mins: np.ndarray, maxs: np.ndarray) -> np.ndarray:
    """(N,) bool: which boxes [mins, maxs] (N, 3) may intersect the frustum.

    A box is out when its corner furthest along a plane's inward normal is still outside that plane
    (conservative: a few boxes near the frustum's edges pass without intersecting it)."""
    mins = np.asarray(mins, dtype=np.float64).reshape(-1, 3)
    maxs = np.asarray(maxs, dtype=np.float64).reshape(-1, 3)
    normals, d = frustum.planes[:, :3], frustum.planes[:, 3]
    # (N, 6, 3): per box and plane, the corner furthest along the normal.
    positive = np.where(normals[None] >= 0, maxs[:, None], mins[:, None])
    return np.all(np.einsum("npk,pk->np", positive, normals) + d >= 0, axis=1)
