"""Hand-made frames for core tests: flat depth planes and rectangular masks, exact geometry."""

from __future__ import annotations

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.types import Detection, Frame, Intrinsics

INTRINSICS = Intrinsics(fx=100.0, fy=100.0, cx=40.0, cy=30.0)
HEIGHT, WIDTH = 60, 80


def plane_frame(
    depth_m: float = 2.0,
    *,
    cam2world: np.ndarray | None = None,
    frame_id: str = "f0",
    device_id: str = "dev",
    map_id: str = "m",
    patches: tuple = (),
    rgb: np.ndarray | None = None,
) -> Frame:
    """A frame looking at a wall at ``depth_m``; ``patches`` are (rows, cols, depth) rectangles in front;
    ``rgb`` (H, W, 3) uint8 its colour image (default black)."""
    depth = np.full((HEIGHT, WIDTH), depth_m, np.float32)
    for rows, cols, patch_depth in patches:
        depth[rows, cols] = patch_depth
    return make_frame(
        np.zeros((HEIGHT, WIDTH, 3), np.uint8) if rgb is None else rgb,
        depth,
        INTRINSICS,
        np.eye(4) if cam2world is None else cam2world,
        timestamp_s=0.0,
        map_id=map_id,
        device_id=device_id,
        frame_id=frame_id,
    )


def rect_mask(rows: slice, cols: slice) -> np.ndarray:
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[rows, cols] = True
    return mask


CHAIR_RGB, TABLE_RGB, WALL_RGB = (200, 60, 40), (40, 90, 210), (90, 90, 90)


def two_box_frame(frame_id: str = "f0", device_id: str = "dev", map_id: str = "m", shift_m: float = 0.0):
    """A chair-like patch at 1.5 m and a table-like patch at 2.5 m in front of a wall at 4 m, coloured
    ``CHAIR_RGB``, ``TABLE_RGB`` and ``WALL_RGB``."""
    pose = np.eye(4)
    pose[0, 3] = shift_m
    chair = (slice(10, 30), slice(10, 30), 1.5)
    table = (slice(30, 55), slice(45, 75), 2.5)
    rgb = np.empty((HEIGHT, WIDTH, 3), np.uint8)
    rgb[:] = WALL_RGB
    rgb[chair[0], chair[1]] = CHAIR_RGB
    rgb[table[0], table[1]] = TABLE_RGB
    frame = plane_frame(
        4.0, cam2world=pose, frame_id=frame_id, device_id=device_id, map_id=map_id, patches=(chair, table), rgb=rgb
    )
    detections = [
        Detection("chair", 0.9, rect_mask(chair[0], chair[1])),
        Detection("table", 0.8, rect_mask(table[0], table[1])),
    ]
    return frame, detections


def look_down_pose(eye: tuple[float, float, float], target: tuple[float, float, float]) -> np.ndarray:
    """cam2world of a camera at ``eye`` looking at ``target`` in a z-up world (image y down)."""
    eye_v, forward = np.asarray(eye, float), np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(forward, right), forward, eye_v
    return pose


#: Four walls of a 4 x 4 m room, 2.5 m high, a table and a cabinet.
BOX_ROOM = [
    ((-0.1, -0.1, 0.0), (0.0, 4.1, 2.5)),
    ((4.0, -0.1, 0.0), (4.1, 4.1, 2.5)),
    ((-0.1, -0.1, 0.0), (4.1, 0.0, 2.5)),
    ((-0.1, 4.0, 0.0), (4.1, 4.1, 2.5)),
    ((1.0, 2.6, 0.0), (2.0, 3.3, 0.75)),
    ((3.0, 0.5, 0.0), (3.6, 1.5, 1.2)),
]


def turning_poses(n: int = 12, step_deg: float = 12.0, *, pitching: bool = True) -> np.ndarray:
    """Poses (N, 4, 4) at the middle of ``BOX_ROOM``, stepping 5 cm and turning ``step_deg`` a frame, looking down and up a little
    (``pitching``: a hand-held camera's; without it a principal point off in y and a focal length off trade
    against each other)."""
    return np.stack([turning_pose(i, step_deg, pitching=pitching) for i in range(n)])


def turning_pose(i: float, step_deg: float = 12.0, *, pitching: bool = True) -> np.ndarray:
    """The pose of ``turning_poses`` at frame ``i``, any real number: the camera between two frames."""
    eye = (1.8 + 0.05 * i, 1.8, 1.4)
    heading = np.radians(step_deg * i)
    target_z = 1.0 + (0.35 * np.sin(1.3 * i) if pitching else 0.0)
    return look_down_pose(eye, (eye[0] + np.cos(heading), eye[1] + np.sin(heading), target_z))


def cast_boxes(
    cam2world: np.ndarray,
    boxes: list[tuple[tuple[float, ...], tuple[float, ...]]],
    *,
    floor_z: float | None = 0.0,
    intrinsics: Intrinsics = INTRINSICS,
    shape: tuple[int, int] = (HEIGHT, WIDTH),
    distortion: tuple[float, ...] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) float32 and instance (H, W) int (-1: floor or nothing, i: ``boxes[i]``) of a world
    of axis-aligned boxes (min, max) standing on a floor plane z = ``floor_z`` (None: no floor), seen by
    a pinhole camera of ``shape`` (H, W) pixels, through a lens with ``distortion`` (OpenCV's k1, k2, p1, p2, k3)
    when given: exact ray casting, slab method."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    rays_cam = np.stack(((u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)), -1)
    if distortion is not None:  # the ray each pixel of the bent image sees
        import cv2

        matrix = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]])
        pixels = np.stack((u, v), -1).reshape(-1, 1, 2)
        straight = cv2.undistortPoints(pixels, matrix, np.asarray(distortion, float)).reshape(shape[0], shape[1], 2)
        rays_cam = np.concatenate((straight, np.ones_like(u)[..., None]), -1)
    rays = rays_cam @ cam2world[:3, :3].T  # world directions with camera z = 1
    origin = cam2world[:3, 3]
    t_best = np.full(shape, np.inf)
    instance = np.full(shape, -1)
    if floor_z is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (floor_z - origin[2]) / rays[..., 2]
        t_best = np.where((t > 0) & np.isfinite(t), t, np.inf)
    for i, (lo, hi) in enumerate(boxes):
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (np.asarray(lo) - origin) / rays
            t1 = (np.asarray(hi) - origin) / rays
        near = np.nanmax(np.minimum(t0, t1), axis=-1)
        far = np.nanmin(np.maximum(t0, t1), axis=-1)
        hit = (near <= far) & (near > 0) & (near < t_best)
        t_best[hit] = near[hit]
        instance[hit] = i
    depth = np.where(np.isfinite(t_best), t_best, 0.0).astype(np.float32)  # camera z = t (rays have z 1)
    return depth, instance


def scene_frame(
    cam2world: np.ndarray,
    boxes: list,
    *,
    floor_z: float | None = 0.0,
    frame_id: str = "f0",
    device_id: str = "dev",
    map_id: str = "m",
) -> tuple[Frame, np.ndarray]:
    """``cast_boxes`` as a frame, and its instance image."""
    depth, instance = cast_boxes(cam2world, boxes, floor_z=floor_z)
    frame = make_frame(
        np.zeros((HEIGHT, WIDTH, 3), np.uint8),
        depth,
        INTRINSICS,
        cam2world,
        timestamp_s=0.0,
        map_id=map_id,
        device_id=device_id,
        frame_id=frame_id,
    )
    return frame, instance
