"""A worker's CPU a frame besides the model's session, part by part, on real 7-Scenes frames.

One process, one thread everywhere (OMP / OpenBLAS / MKL, OpenCV, onnxruntime), as a worker on its share of
the cores. Every ``--stride``-th of the first frames of redkitchen is made into the protobuf a device posts
(``frame_to_proto``: JPEG colour, 16-bit PNG depth), serialised as the Redis stream carries it, and then run
through what a worker does with it, each part timed on its own in the thread's CPU seconds (the machine may be shared):

- ``parse``: the stream entry's protobuf; ``pose``: the frame's pose into the map's world;
- ``decode_jpeg``, ``decode_png``: the images; ``make_frame``: the checks and depth to metres;
- ``preprocess``: letterbox and tensor; ``session``: ``session.run`` (the model, reported apart);
- ``boxes_nms``: scores, thresholds, boxes, NMS; ``masks``: ``instance_masks`` (prototypes, sigmoid, warp);
- ``to_detections``: the adapter's detections (and its empty-mask filter);
- ``voxelize``: ``voxelize_detections`` (with ``check_detections``); ``step_rest``: the rest of
  ``integrate_frame`` on the embedded store;
- ``codec``: what the Redis store would encode and decode for the frame (the objects it wrote, encoded;
  the objects it read, decoded).

``--redis``: instead, a real ``FrameWorker`` (no heartbeat, no prefetch) on a throwaway redis-server's queue
and store, the frames queued beforehand as the API queues them (images as uploaded); each ``poll_once`` is
timed in this process's CPU seconds, the session's CPU seconds taken off: what the worker
spends a frame besides the model, Redis client, codec, logging and queue included (Redis's own CPU not).

Prints a table of milliseconds a frame (median, mean) and writes JSON (``--out``); ``--cprofile FILE`` also
writes the cProfile of the whole run in thread CPU seconds (parts not timed apart show up there; waits on Redis do not).

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python bench/profile_worker.py [--frames 50]
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import os
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402 - after the thread variables above: OpenBLAS reads them as it loads

sys.path.insert(0, str(Path(__file__).parent))
from common import SHARED, environment, write_json  # noqa: E402 - bench/ put on the path just above

SEQUENCE = SHARED / "data/7scenes-redkitchen"
MODEL = SHARED / "models/yolo11n-seg-fp32-640.onnx"
PARTS = (
    "parse",
    "pose",
    "decode_jpeg",
    "decode_png",
    "make_frame",
    "preprocess",
    "session",
    "boxes_nms",
    "masks",
    "to_detections",
    "voxelize",
    "step_rest",
    "codec",
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--stride", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=1, help="passes over the frames (the map grows on)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "profile_worker.json"))
    ap.add_argument("--cprofile", default="")
    ap.add_argument("--redis", action="store_true", help="a real worker on Redis (see above)")
    args = ap.parse_args()
    if args.redis:
        return profile_redis_worker(args)

    import cv2

    cv2.setNumThreads(1)
    from arcloud.core.checks import check_detections, make_frame
    from arcloud.core.step import integrate_frame
    from arcloud.core.types import Intrinsics, Params
    from arcloud.core.voxels import voxelize_detections
    from arcloud.datasets.export import seven_scenes_export_frame
    from arcloud.datasets.sevenscenes import load_seven_scenes
    from arcloud.detectors import onnx_yolo
    from arcloud.detectors.coco import to_detections
    from arcloud.detectors.onnx_yolo import Letterbox, YoloSegDetector, letterbox_tensor
    from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
    from arcloud.proto.convert import _decode_depth, _decode_rgb, frame_to_proto, to_map_world
    from arcloud.service.map_header import open_map_checked
    from arcloud.stores import codec
    from arcloud.stores.memory import MemoryStore

    sequence = load_seven_scenes(SEQUENCE, align_gravity=True)
    params = seven_scenes_export_frame(sequence).params(Params())
    frames = list(sequence.frames(stride=args.stride, limit=args.frames))
    payloads = [bytes(frame_to_proto(f, map_id="profile").SerializeToString()) for f in frames]
    detector = YoloSegDetector(MODEL, intra_op_threads=1)
    store = MemoryStore()
    times: dict[str, list[float]] = defaultdict(list)
    mask_s: list[float] = []
    plain_instance_masks = onnx_yolo.instance_masks

    def timed_instance_masks(*a: Any, **k: Any) -> Any:  # decode's masks, timed apart from the rest of it
        started = time.thread_time()
        try:
            return plain_instance_masks(*a, **k)
        finally:
            mask_s.append(time.thread_time() - started)

    onnx_yolo.instance_masks = timed_instance_masks  # a timer around the same function
    n_detections: list[int] = []

    def run_once(payload: bytes) -> None:
        t = [time.thread_time()]

        def lap(part: str) -> None:
            t.append(time.thread_time())
            times[part].append(t[-1] - t[-2])

        msg = pb.Frame.FromString(payload)
        lap("parse")
        to_map_world(msg)
        lap("pose")
        rgb = _decode_rgb(msg)
        lap("decode_jpeg")
        depth = _decode_depth(msg)
        lap("decode_png")
        i = msg.intrinsics
        frame = make_frame(
            rgb,
            depth,
            Intrinsics(i.fx, i.fy, i.cx, i.cy),
            np.array(msg.cam2world, np.float64).reshape(4, 4),
            timestamp_s=msg.timestamp_s,
            map_id=msg.map_id,
            device_id=msg.device_id,
            frame_id=msg.frame_id,
            depth_scale=msg.depth_scale or None,
        )
        lap("make_frame")
        box = Letterbox.fit(frame.rgb.shape[:2], detector.input_size_px)
        tensor = letterbox_tensor(frame.rgb, box)
        lap("preprocess")
        outputs = detector._session.run(detector._output_names, {detector.input_name: tensor})
        lap("session")
        mask_s.clear()
        raw = detector.decode(*outputs, box, detector._mapped_ids)
        lap("boxes_nms")
        times["boxes_nms"][-1] -= sum(mask_s)
        times["masks"].append(sum(mask_s))
        detections = [d for d in to_detections(raw, detector.class_map) if d.mask.any()]
        lap("to_detections")
        n_detections.append(len(detections))
        voxelize_detections(frame, check_detections(detections, frame.shape), params)
        lap("voxelize")
        open_map_checked(store, frame.map_id, params)
        result = integrate_frame(frame, detections, store, params)
        lap("step_rest")
        times["step_rest"][-1] -= result.timings_s.get("voxelize", 0.0)  # voxelized twice: once is counted above
        written = store.get(frame.map_id, result.created + result.updated)
        blobs = [
            (codec.encode_meta(o), codec.encode_voxels(o.keys, o.weights, o.votes, seen=o.seen, colors=o.colors)) for o in written
        ]
        for j, (meta, voxels) in enumerate(blobs):
            codec.decode_object(written[j].id, meta, voxels)
        lap("codec")

    run_once(payloads[0])  # warm-up
    times.clear()
    n_detections.clear()
    profiler = cProfile.Profile(time.thread_time) if args.cprofile else None
    for _ in range(args.repeats):
        for payload in payloads:
            if profiler is not None:
                profiler.enable()
            run_once(payload)
            if profiler is not None:
                profiler.disable()
    if profiler is not None:
        profiler.dump_stats(args.cprofile)

    rows = {part: np.array(times[part]) * 1e3 for part in PARTS}
    besides = sum(rows[p] for p in PARTS if p != "session")
    print(f"{len(rows['parse'])} frames, {np.mean(n_detections):.1f} detections a frame (max {max(n_detections)})")
    print(f"{'part':16s} {'median ms':>10s} {'mean ms':>10s}")
    for part in PARTS:
        print(f"{part:16s} {np.median(rows[part]):10.2f} {rows[part].mean():10.2f}")
    print(f"{'besides session':16s} {np.median(besides):10.2f} {besides.mean():10.2f}")
    write_json(
        Path(args.out),
        {
            "frames": len(rows["parse"]),
            "detections_mean": float(np.mean(n_detections)),
            "ms_median": {p: float(np.median(rows[p])) for p in PARTS},
            "ms_mean": {p: float(rows[p].mean()) for p in PARTS},
            "besides_session_ms_median": float(np.median(besides)),
            "besides_session_ms_mean": float(besides.mean()),
            "environment": environment(),
        },
    )


class SessionTimer:
    """An onnxruntime session whose ``run`` adds the CPU seconds of the calling thread to ``cpu_s`` (with one
    intra-op thread the session runs in the caller's thread)."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.cpu_s = 0.0

    def run(self, *args: Any, **kwargs: Any) -> Any:
        started = time.thread_time()
        try:
            return self.session.run(*args, **kwargs)
        finally:
            self.cpu_s += time.thread_time() - started


def profile_redis_worker(args: argparse.Namespace) -> None:
    import cv2

    cv2.setNumThreads(1)
    from common import Redis

    from arcloud.core.types import Params
    from arcloud.datasets.export import seven_scenes_export_frame
    from arcloud.datasets.sevenscenes import load_seven_scenes
    from arcloud.detectors.onnx_yolo import YoloSegDetector
    from arcloud.proto.convert import frame_to_proto
    from arcloud.service.frames import validate_message
    from arcloud.service.worker import FrameWorker
    from arcloud.stores.redis import RedisStore
    from arcloud.stores.redis_queue import RedisFrameQueue

    sequence = load_seven_scenes(SEQUENCE, align_gravity=True)
    params = seven_scenes_export_frame(sequence).params(Params())
    frames = list(sequence.frames(stride=args.stride, limit=args.frames))
    detector = YoloSegDetector(MODEL, intra_op_threads=1)
    server = Redis()
    try:
        queue = RedisFrameQueue(server.url)
        store = RedisStore.from_url(server.url)
        queue.prepare()
        session = SessionTimer(detector._session)
        detector._session = session  # its CPU seconds, apart from the worker's
        worker = FrameWorker(queue, store, detector, params, consumer="profile", heartbeat_s=None)
        for repeat in range(args.repeats + 1):  # the first pass warms up
            for frame in frames:
                message = frame_to_proto(dataclasses.replace(frame, device_id=f"profile-{repeat}"), map_id=f"profile-{repeat}")
                queue.put(validate_message(message, message.map_id, queue_decoded_png=False), message)
        cpu_ms, session_ms = [], []
        profiler = cProfile.Profile(time.thread_time) if args.cprofile else None
        for i in range(len(frames) * (args.repeats + 1)):
            if profiler is not None and i >= len(frames):
                profiler.enable()
            session.cpu_s = 0.0
            started = time.process_time()
            settled = worker.poll_once()
            cpu_s = time.process_time() - started
            if profiler is not None:
                profiler.disable()
            if settled != 1:
                raise SystemExit(f"frame {i}: {settled} settled")
            if i >= len(frames):
                cpu_ms.append(cpu_s * 1e3)
                session_ms.append(session.cpu_s * 1e3)
        if profiler is not None:
            profiler.dump_stats(args.cprofile)
        queue.close()
        store.close()
    finally:
        server.stop()
    cpu, session = np.array(cpu_ms), np.array(session_ms)
    besides = cpu - session
    print(f"{cpu.size} frames on Redis; ms a frame (median, mean)")
    for name, values in (("worker CPU", cpu), ("session", session), ("besides session", besides)):
        print(f"{name:16s} {np.median(values):10.2f} {values.mean():10.2f}")
    write_json(
        Path(args.out),
        {
            "frames": int(cpu.size),
            "redis": True,
            "cpu_ms_median": float(np.median(cpu)),
            "session_ms_median": float(np.median(session)),
            "besides_session_ms_median": float(np.median(besides)),
            "besides_session_ms_mean": float(besides.mean()),
            "environment": environment(),
        },
    )


if __name__ == "__main__":
    main()
