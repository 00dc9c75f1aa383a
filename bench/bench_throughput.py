"""Frames a second with the real model, side by side in one run, on the same frames and the same cores:

1. ``bare_onnx``: the YOLOv8n-seg session alone (``session.run`` on letterboxed tensors prepared beforehand),
   one thread per core, before the others and again after them (the ratios use the mean of the two);
2. ``pipeline``: the in-process pipeline, detector (pre- and post-processing included) and the step on the
   embedded store, one thread per core for the session;
3. ``service``: ``arcloud serve --redis`` (a real redis-server, one worker process per core, each detector on
   its share of the cores), frames POSTed as protobuf as fast as it takes them; frames a second from the
   first POST to the last frame's commit, and the latency from each POST to its objects being readable
   (the frame's commit time in the store);
4. ``service_at_70``: the same service fed open loop at 70 % of the rate it reached, for latency p50/p99.

7-Scenes redkitchen frames (every ``--stride``-th of the first ``--frames`` x stride). Writes
``bench/results/throughput.json`` (``bare_onnx_fps``, ``pipeline_fps``, ``service_fps``, ``latency_p50_s``,
``latency_p99_s`` at 70 %, the ratios, versions and machine).

    .venv/bin/python bench/bench_throughput.py [--frames 120] [--workers N]
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import INGEST_ONLY_ENV, SHARED, FramePoster, Redis, ServeProcess, ServiceMeter, cores, environment, write_json

SEQUENCE = SHARED / "data/7scenes-redkitchen"
MODEL = SHARED / "models/yolov8n-seg-fp32-640.onnx"
OUT = Path(__file__).parent / "results" / "throughput.json"


def load_frames(n: int, stride: int) -> list[Any]:
    from arcloud.datasets.sevenscenes import load_seven_scenes

    sequence = load_seven_scenes(SEQUENCE, align_gravity=True)
    return list(sequence.frames(stride=stride, limit=n))


def bench_bare(frames: list[Any], threads: int) -> dict[str, Any]:
    from arcloud.detectors.onnx_yolo import Letterbox, YoloSegDetector, letterbox_tensor

    detector = YoloSegDetector(MODEL, intra_op_threads=threads)
    session = detector._session  # the bare session: what the detector wraps
    tensors = [letterbox_tensor(f.rgb, Letterbox.fit(f.rgb.shape[:2], detector.input_size_px)) for f in frames]
    outputs = [o.name for o in session.get_outputs()]
    session.run(outputs, {detector.input_name: tensors[0]})  # warm-up
    started = time.perf_counter()
    for tensor in tensors:
        session.run(outputs, {detector.input_name: tensor})
    seconds = time.perf_counter() - started
    return {"fps": round(len(frames) / seconds, 3), "ms_per_frame": round(seconds / len(frames) * 1000, 1), "threads": threads}


def bench_pipeline(frames: list[Any], threads: int) -> dict[str, Any]:
    from arcloud.core.step import integrate_frame
    from arcloud.core.types import Params
    from arcloud.detectors.onnx_yolo import YoloSegDetector
    from arcloud.stores.memory import MemoryStore

    detector = YoloSegDetector(MODEL, intra_op_threads=threads)
    params = Params()
    store = MemoryStore(cell_m=params.index_cell_m)
    detector.detect(frames[0])  # warm-up
    detect_s = step_s = 0.0
    for frame in frames:
        t0 = time.perf_counter()
        detections = detector.detect(frame)
        t1 = time.perf_counter()
        integrate_frame(frame, detections, store, params)
        step_s += time.perf_counter() - t1
        detect_s += t1 - t0
    seconds = detect_s + step_s
    return {
        "fps": round(len(frames) / seconds, 3),
        "ms_per_frame": round(seconds / len(frames) * 1000, 1),
        "detector_ms_per_frame": round(detect_s / len(frames) * 1000, 1),
        "step_ms_per_frame": round(step_s / len(frames) * 1000, 1),
        "objects": len(store.list_meta(frames[0].map_id)),
        "threads": threads,
    }


def post_frames(url: str, map_id: str, bodies: list[bytes], *, rate_per_s: float | None, concurrency: int = 8) -> list[float]:
    """POST each body (as fast as taken, or open loop at ``rate_per_s``); the wall time (Unix s) of each POST."""
    posted = [0.0] * len(bodies)
    started = time.perf_counter()
    lock = threading.Lock()
    cursor = iter(range(len(bodies)))

    poster = FramePoster(url)

    def run() -> None:
        while True:
            with lock:
                i = next(cursor, None)
            if i is None:
                return
            if rate_per_s:
                time.sleep(max(0.0, started + i / rate_per_s - time.perf_counter()))
            posted[i] = time.time()
            status, answer = poster.post(f"/v1/maps/{map_id}/frames", bodies[i])
            if status != 202:
                raise SystemExit(f"POST answered {status}: {answer.decode(errors='replace')}")

    threads = [threading.Thread(target=run) for _ in range(concurrency)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return posted


def committed_at(redis: Redis, map_id: str, keys: list[str], timeout_s: float) -> list[float]:
    """Each frame's commit time (Unix s) in the store, waiting until every one is committed."""
    from arcloud.stores.keys import processed_key

    deadline = time.time() + timeout_s
    while True:
        values = redis.client.hmget(processed_key(map_id), keys)
        if all(v is not None for v in values):
            return [float(v) for v in values]
        if time.time() > deadline:
            missing = sum(v is None for v in values)
            raise SystemExit(f"{missing} of {len(keys)} frames not processed within {timeout_s} s")
        time.sleep(0.05)


def service_run(redis: Redis, service: ServeProcess, frames: list[Any], map_id: str, rate_per_s: float | None) -> dict[str, Any]:
    """One run through the service; ``per_frame``: what the API, the workers and Redis spent a frame (CPU ms,
    Redis commands and bytes: what docs/scaling.md's model reads)."""
    from arcloud.proto.convert import frame_to_proto

    bodies = []
    for frame in frames:
        message = frame_to_proto(frame)
        message.map_id = map_id
        bodies.append(message.SerializeToString())
    keys = [f.key for f in frames]
    meter = ServiceMeter(service.process.pid, redis)
    meter.start()
    cpu_started = time.process_time()
    posted = post_frames(service.url, map_id, bodies, rate_per_s=rate_per_s)
    done = committed_at(redis, map_id, keys, timeout_s=600)
    load_cpu_s = time.process_time() - cpu_started  # the load generator's own, on the service's cores
    per_frame = meter.per_frame(len(frames), float(np.mean([len(b) for b in bodies])))
    latency = np.array(done) - np.array(posted)
    seconds = max(done) - min(posted)
    return {
        "fps": round(len(frames) / seconds, 3),
        "upload_bytes": round(float(np.mean([len(b) for b in bodies]))),
        "offered_per_s": None if rate_per_s is None else round(rate_per_s, 3),
        "latency_p50_s": round(float(np.percentile(latency, 50)), 3),
        "latency_p99_s": round(float(np.percentile(latency, 99)), 3),
        "latency_max_s": round(float(latency.max()), 3),
        "load_generator_cpu_ms_per_frame": round(load_cpu_s / len(frames) * 1000, 2),
        "per_frame": per_frame,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=120, help="frames (default 120)")
    parser.add_argument("--stride", type=int, default=5, help="every n-th frame of the sequence (default 5)")
    parser.add_argument("--workers", type=int, default=cores(), help="service worker processes (default: the cores)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if not MODEL.is_file() or not SEQUENCE.is_dir():
        raise SystemExit(f"needs {MODEL} and {SEQUENCE} (the real assets in ../shared; see its README)")
    n_cores = cores()
    frames = load_frames(args.frames, args.stride)
    bare_before = bench_bare(frames, n_cores)
    print(f"bare ONNX session: {bare_before['fps']} frames/s")
    pipeline = bench_pipeline(frames, n_cores)
    print(f"pipeline (detector + step): {pipeline['fps']} frames/s (step {pipeline['step_ms_per_frame']} ms)")
    redis = Redis()
    try:
        service = ServeProcess(redis.url, workers=args.workers, detector=f"onnx:{MODEL}", env=INGEST_ONLY_ENV)
        try:
            service_run(redis, service, frames[:4], "warm-up", None)  # sessions loaded, caches warm
            full = service_run(redis, service, frames, "as-fast", None)
            print(f"service: {full['fps']} frames/s")
            at_70 = service_run(redis, service, frames, "at-70", 0.7 * full["fps"])
            print(f"service at 70 %: latency p50 {at_70['latency_p50_s']} s, p99 {at_70['latency_p99_s']} s")
        finally:
            service.stop()
    finally:
        redis.stop()
    # The machine's speed drifts by a few per cent over minutes: the ratio is against the bare session's
    # mean from before and after the others.
    bare_after = bench_bare(frames, n_cores)
    print(f"bare ONNX session again: {bare_after['fps']} frames/s")
    bare = {
        "fps": round((bare_before["fps"] + bare_after["fps"]) / 2, 3),
        "fps_before": bare_before["fps"],
        "fps_after": bare_after["fps"],
        "threads": n_cores,
    }
    result = {
        **environment(("arcloud", "numpy", "onnxruntime", "fastapi", "uvicorn", "redis")),
        "frames": len(frames),
        "cores": n_cores,
        "workers": args.workers,
        "model": MODEL.name,
        "bare_onnx_fps": bare["fps"],
        "pipeline_fps": pipeline["fps"],
        "service_fps": full["fps"],
        "latency_p50_s": at_70["latency_p50_s"],
        "latency_p99_s": at_70["latency_p99_s"],
        "service_over_bare": round(full["fps"] / bare["fps"], 3),
        "upload_bytes": full["upload_bytes"],
        "pipeline_over_bare": round(pipeline["fps"] / bare["fps"], 3),
        "bare_onnx": bare,
        "pipeline": pipeline,
        "service": full,
        "service_at_70": at_70,
    }
    write_json(args.out, result)


if __name__ == "__main__":
    main()
