"""Simulated RGB-D sequences: a user's walk through a generated room, rendered into ``Frame`` objects."""

from __future__ import annotations

import logging
import time

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.types import Frame, Intrinsics
from arcloud.errors import InvalidInput
from arcloud.sim.detector import STREAM_DEPTH, DetectorFaults, apply_depth_faults, frame_rng, reported_pose
from arcloud.sim.room import Room, gt_boxes
from arcloud.sim.trajectory import room_walk

log = logging.getLogger(__name__)

#: Kinect-like VGA intrinsics (the depth camera of ScanNet-style data).
DEFAULT_INTRINSICS = Intrinsics(525.0, 525.0, 319.5, 239.5)
FPS = 30.0


def frame_id_of(index: int) -> str:
    """The id of the ``index``-th frame of a sequence: f000000, f000001, ..."""
    return f"f{index:06d}"


def simulate_sequence(
    room: Room,
    *,
    n_frames: int = 300,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    intrinsics: Intrinsics = DEFAULT_INTRINSICS,
    faults: DetectorFaults = DetectorFaults(),
    map_id: str = "sim",
    device_id: str = "user-0",
    poses: list[np.ndarray] | None = None,
) -> list[Frame]:
    """``n_frames`` frames of one user walking through ``room`` (``room_walk(room, n_frames, seed)``,
    or the given true ``poses``), at 30 Hz from t = 0, with ids ``frame_id_of(i)``.

    Depth carries the sensor faults of ``faults`` and each frame's ``cam2world`` is the *reported*
    (noisy) pose; both are drawn from ``(seed, frame_id)``. Detect with
    ``SimulatedDetector(room, faults, seed=seed)``: the same seed and faults recover the true poses."""
    if poses is None:
        poses = room_walk(room, n_frames, seed)
    elif len(poses) != n_frames:
        raise InvalidInput("poses", f"{n_frames} poses (n_frames)", f"{len(poses)}")
    renderer = room.renderer()
    frames = []
    started = time.perf_counter()
    for index, cam2world in enumerate(poses):
        frame_id = frame_id_of(index)
        result = renderer.render(cam2world, intrinsics, width, height)
        depth = apply_depth_faults(result.depth_m, faults, frame_rng(seed, frame_id, STREAM_DEPTH))
        frames.append(
            make_frame(
                result.rgb,
                depth,
                intrinsics,
                reported_pose(cam2world, faults, seed, frame_id),
                timestamp_s=index / FPS,
                map_id=map_id,
                device_id=device_id,
                frame_id=frame_id,
            )
        )
    log.info("simulated %d frames of %dx%d in %.1f s", len(frames), width, height, time.perf_counter() - started)
    return frames


__all__ = ["DEFAULT_INTRINSICS", "FPS", "frame_id_of", "gt_boxes", "simulate_sequence"]
