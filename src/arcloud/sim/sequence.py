"""Simulated RGB-D sequences: a user's walk through a generated room, rendered into ``Frame`` objects."""

from __future__ import annotations

import logging
import os
import pickle
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.types import Frame, Intrinsics
from arcloud.errors import InvalidInput
from arcloud.sim.detector import (
    STREAM_DEPTH,
    DetectorFaults,
    FrameTruth,
    FrameTruths,
    apply_depth_faults,
    check_truths,
    frame_rng,
    frame_truth,
    reported_pose,
    true_pose,
    truth_key,
)
from arcloud.sim.room import Room, gt_boxes, room_renderer, room_walk

log = logging.getLogger(__name__)

#: Kinect-like VGA intrinsics (the depth camera of ScanNet-style data).
DEFAULT_INTRINSICS = Intrinsics(525.0, 525.0, 319.5, 239.5)
FPS = 30.0
#: Below this many frames ``workers=None`` renders in this process (starting a worker costs ~2 s).
PARALLEL_MIN_FRAMES = 60


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
    poses: Sequence[np.ndarray] | None = None,
    workers: int | None = None,
    truths: FrameTruths | None = None,
) -> list[Frame]:
    """``n_frames`` frames of one user walking through ``room`` (``room_walk(room, n_frames, seed)``,
    or the given true ``poses``), at 30 Hz from t = 0, with ids ``frame_id_of(i)``.

    Depth carries the sensor faults of ``faults`` and each frame's ``cam2world`` is the *reported*
    (noisy) pose; both are drawn from ``(seed, frame_id)``. Detect with
    ``SimulatedDetector(room, faults, seed=seed, truths=truths)``: the same seed and faults recover the
    true poses, and the frames' true instance images, recorded in ``truths`` (a ``FrameTruths`` of the
    room; None: not kept), spare it a second ray cast.

    workers: processes that render (None: one per two cores, up to 4, for 60 frames or more, so one
    on a 2-core machine; 1: this process only). Workers are fresh Python processes; the frames are
    the same for any number. About 65 ms of CPU a VGA frame (two thirds in Open3D's ray cast, which
    uses two threads): 300 frames take about 20 s on a busy 2-core machine."""
    if poses is None:
        poses = room_walk(room, n_frames, seed)
    elif len(poses) != n_frames:
        raise InvalidInput("poses", f"{n_frames} poses (n_frames)", f"{len(poses)}")
    if workers is None:  # Open3D's cast already uses two threads: one process per two cores, up to 4
        workers = max(1, min((os.cpu_count() or 1) // 2, 4)) if n_frames >= PARALLEL_MIN_FRAMES else 1
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidInput("workers", "an integer >= 1 or None", repr(workers))
    check_truths(truths, room)
    started = time.perf_counter()
    jobs = [(index, np.asarray(pose, dtype=np.float64)) for index, pose in enumerate(poses)]
    settings = (seed, width, height, intrinsics, faults, map_id, device_id, truths is not None)
    if workers == 1 or len(jobs) < 2:
        rendered = _render_frames(room, jobs, settings)
    else:
        chunks = [[jobs[i] for i in chunk] for chunk in np.array_split(np.arange(len(jobs)), min(workers, len(jobs)))]
        rendered = [item for part in _render_in_subprocesses(room, chunks, settings) for item in part]
    frames = []
    for frame, key, truth in rendered:
        if truths is not None and truth is not None:
            truths.record(key, truth)
        frames.append(frame)
    log.info(
        "simulated %d frames of %dx%d in %.1f s (%d worker%s)",
        len(frames),
        width,
        height,
        time.perf_counter() - started,
        workers,
        "s" if workers > 1 else "",
    )
    return frames


#: (seed, width, height, intrinsics, faults, map_id, device_id, whether to compute the frames' truths)
_Settings = tuple[int, int, int, Intrinsics, DetectorFaults, str, str, bool]


def _render_frames(
    room: Room, jobs: Sequence[tuple[int, np.ndarray]], settings: _Settings
) -> list[tuple[Frame, tuple, FrameTruth | None]]:
    seed, width, height, intrinsics, faults, map_id, device_id, with_truths = settings
    renderer = room_renderer(room)
    out = []
    for index, cam2world in jobs:
        frame_id = frame_id_of(index)
        reported = reported_pose(cam2world, faults, seed, frame_id)
        # Render at the pose the detector recovers from the reported one (equal to ``cam2world`` up to
        # rounding), so that remembered truths match the detector's own ray cast bit for bit.
        pose = true_pose(reported, faults, seed, frame_id)
        result = renderer.render(pose, intrinsics, width, height)
        depth = apply_depth_faults(result.depth_m, faults, frame_rng(seed, frame_id, STREAM_DEPTH))
        frame = make_frame(
            result.rgb,
            depth,
            intrinsics,
            reported,
            timestamp_s=index / FPS,
            map_id=map_id,
            device_id=device_id,
            frame_id=frame_id,
        )
        truth = frame_truth(room, result.triangle, result.depth_m, pose, intrinsics, result.instance) if with_truths else None
        out.append((frame, truth_key(frame_id, pose, intrinsics, width, height), truth))
    return out


def _render_in_subprocesses(
    room: Room, chunks: Sequence[Sequence[tuple[int, np.ndarray]]], settings: _Settings
) -> list[list[tuple[Frame, tuple, FrameTruth | None]]]:
    """Render each chunk in a fresh Python process (``python -c``, so the caller's main module is never
    re-imported, unlike multiprocessing's spawn; no fork, which is unsafe once Open3D's threads run)."""
    import arcloud

    env = dict(os.environ)
    package_root = os.path.dirname(os.path.dirname(os.path.abspath(arcloud.__file__)))
    env["PYTHONPATH"] = os.pathsep.join([package_root, env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("OMP_NUM_THREADS", "1")
    command = [sys.executable, "-c", "from arcloud.sim.sequence import _worker_main; _worker_main()"]
    procs = []
    try:
        for chunk in chunks:
            errors = tempfile.TemporaryFile()  # noqa: SIM115 - closed in the finally below; a file, not a pipe: a chatty worker cannot block on it
            proc = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=errors, env=env)
            procs.append((proc, errors))
            assert proc.stdin is not None
            pickle.dump((room, list(chunk), settings), proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            proc.stdin.close()
        results = []
        for proc, errors in procs:
            assert proc.stdout is not None
            out = proc.stdout.read()
            if proc.wait() != 0:
                errors.seek(0)
                tail = errors.read().decode("utf-8", "replace")[-2000:]
                raise RuntimeError(f"a rendering worker failed (exit {proc.returncode}):\n{tail}")
            results.append(pickle.loads(out))
        return results
    finally:
        for proc, errors in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()
            errors.close()


def _worker_main() -> None:
    """Entry of a rendering worker: (room, jobs, settings) pickled on stdin, results pickled on stdout."""
    room, jobs, settings = pickle.load(sys.stdin.buffer)
    result = _render_frames(room, jobs, settings)
    sys.stdout.buffer.write(pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL))
    sys.stdout.buffer.flush()


__all__ = ["DEFAULT_INTRINSICS", "FPS", "frame_id_of", "gt_boxes", "simulate_sequence"]
