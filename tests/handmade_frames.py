"""Hand-made frames for core tests: flat depth planes and rectangular masks, exact geometry."""

from __future__ import annotations

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.types import Detection, Frame, Intrinsics

INTRINSICS = Intrinsics(fx=100.0, fy=100.0, cx=40.0, cy=30.0)
HEIGHT, WIDTH = 60, 80


def plane_frame(depth_m: float = 2.0, *, cam2world: np.ndarray | None = None, frame_id: str = "f0",
                device_id: str = "dev", map_id: str = "m", patches: tuple = ()) -> Frame:
    """A frame looking at a wall at ``depth_m``; ``patches`` are (rows, cols, depth) rectangles in front."""
    depth = np.full((HEIGHT, WIDTH), depth_m, np.float32)
    for rows, cols, patch_depth in patches:
        depth[rows, cols] = patch_depth
    return make_frame(
        np.zeros((HEIGHT, WIDTH, 3), np.uint8), depth, INTRINSICS,
        np.eye(4) if cam2world is None else cam2world,
        timestamp_s=0.0, map_id=map_id, device_id=device_id, frame_id=frame_id,
    )


def rect_mask(rows: slice, cols: slice) -> np.ndarray:
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[rows, cols] = True
    return mask


def two_box_frame(frame_id: str = "f0", device_id: str = "dev", map_id: str = "m", shift_m: float = 0.0):
    """A chair-like patch at 1.5 m and a table-like patch at 2.5 m in front of a wall at 4 m."""
    pose = np.eye(4)
    pose[0, 3] = shift_m
    chair = (slice(10, 30), slice(10, 30), 1.5)
    table = (slice(30, 55), slice(45, 75), 2.5)
    frame = plane_frame(4.0, cam2world=pose, frame_id=frame_id, device_id=device_id, map_id=map_id, patches=(chair, table))
    detections = [
        Detection("chair", 0.9, rect_mask(chair[0], chair[1])),
        Detection("table", 0.8, rect_mask(table[0], table[1])),
    ]
    return frame, detections
