"""Scaling on real cores (issue 24): what the detector allows, what the service reaches, and what stops it.

1. ``ceiling``: the real model's bare session (``session.run`` on letterboxed tensors), one intra-op thread,
   in P processes at once, P = 1, 2, 4, ... up to the cores: frames/s of all of them together. No service can
   beat this with one-thread CPU sessions; ``service_over_ceiling`` compares against it.
2. ``service``: ``arcloud serve --redis --workers 0 [--api-processes A]`` (a process of its own) and W worker
   processes started here (``worker_pool``: the real model, one thread each), W = 1, 2, 4, ... up to the cores.
   For each W two layouts: ``one_map`` (every frame into one hot map: the workers fuse the same objects) and
   ``many_maps`` (frames interleaved over ``--maps`` maps). Each layout: its frames POSTed as fast as the service
   takes them (frames/s from the first POST to the last commit; per-frame CPU of the API, the workers and
   Redis, Redis commands and bytes: ``common.ServiceMeter``; the lock wait from the service's own
   ``arcloud_lock_wait_seconds`` counters), then as many more open loop at 70 % of that rate: POST-to-commit
   latency p50/p99, and the queue wait and lock wait there.
3. ``wait``: as 2, but each worker's detector *waits* ``--detector-wait-ms`` (default: the one-thread session's
   median from 1) and then returns the real model's detections of that frame, computed once beforehand: a
   stand-in for a detector on an accelerator or a model server, which the worker waits for without its
   core. So W = 1, 2, 4, 8, 16 workers run on any machine, and what the shell itself (API, step, Redis, this
   load generator) costs shows as the gap to W / wait frames/s (``over_ideal``; the issue's target: 16 workers
   >= 0.9x of 16 / session time). ``bench_shards.py --detector-wait-ms`` did the same with the simulator.

Frames: 7-Scenes redkitchen, VGA (every ``--stride``-th of the first ``--frames`` x stride), uploaded as
protobuf (JPEG colour, PNG depth) on ``--connections`` keep-alive connections; a phase of more frames than
that posts them again as other devices (same images, new device ids: new frames to the service). A phase's
frames go to fresh maps. Everything shares this machine's cores (cores and load average are recorded).

Writes ``bench/results/scaling.json`` (versions, machine, every run) and ``scaling.png`` beside it
(``--plot FILE.json`` draws the plot of a result file again, e.g. one written where matplotlib is not).

    .venv/bin/python bench/bench_scaling.py                      # this machine; about 8 minutes on 2 cores
    .venv/bin/python bench/bench_scaling.py --parts wait --detector-wait-ms 87 --wait-workers 16

On a machine of 16 cores: ``bench/scaling_device.sh prepare`` here, ``bench/scaling_device.sh run`` there
(docs/scaling.md): ``--workers 1,2,4,8,15 --wait-workers 1,2,4,8,16,32 --api-processes 2`` on 60 frames.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import multiprocessing
import os
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import INGEST_ONLY_ENV, SHARED, FramePoster, Redis, ServeProcess, ServiceMeter, cores, environment, write_json

SEQUENCE = SHARED / "data/7scenes-redkitchen"
MODEL = SHARED / "models/yolo11n-seg-fp32-640.onnx"
OUT = Path(__file__).parent / "results" / "scaling.json"
TARGET_OVER_IDEAL = 0.9  # the issue's: 16 waiting workers reach >= 0.9x of 16 / session time
LOAD_FRACTION = 0.7  # latency is measured at this share of the rate reached
#: The queue may hold every frame of a phase: a bench measures throughput, not admission.
BENCH_ENV = {
    **INGEST_ONLY_ENV,
    "ARCLOUD_MAX_QUEUED_BYTES": str(64 * 2**30),
    "ARCLOUD_MAX_QUEUED_BYTES_PER_MAP": str(64 * 2**30),
}


def powers_of_two_to(n: int) -> list[int]:
    """1, 2, 4, ... below ``n``, and ``n``."""
    found = [p for p in (2**k for k in range(8)) if p < n]
    return [*found, n]


def int_list(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v.strip()]


# --- 1. the detector's ceiling -------------------------------------------------------------------------
def _session_process(model: str, tensors_path: str, seconds: float, barrier: Any, results: Any) -> None:
    """One one-thread session running on the tensors for ``seconds`` after every process is ready."""
    from arcloud.detectors.onnx_yolo import YoloSegDetector

    detector = YoloSegDetector(model, intra_op_threads=1)
    session = detector._session  # the bare session: what the detector wraps
    tensors = np.load(tensors_path)
    outputs = [o.name for o in session.get_outputs()]
    for tensor in tensors[:2]:  # warm-up
        session.run(outputs, {detector.input_name: tensor[None]})
    barrier.wait()
    times = []
    started = time.perf_counter()
    while time.perf_counter() - started < seconds:
        t0 = time.perf_counter()
        session.run(outputs, {detector.input_name: tensors[len(times) % len(tensors)][None]})
        times.append(time.perf_counter() - t0)
    results.put((len(times), time.perf_counter() - started, times))


def bench_ceiling(frames: list[Any], processes: list[int], seconds: float, model: Path) -> dict[str, Any]:
    """Frames/s of P one-thread sessions at once, for each P."""
    from arcloud.detectors.onnx_yolo import Letterbox, YoloSegDetector, letterbox_tensor

    size = YoloSegDetector(str(model), intra_op_threads=1).input_size_px
    tensors = np.stack([letterbox_tensor(f.rgb, Letterbox.fit(f.rgb.shape[:2], size))[0] for f in frames[:8]])
    context = multiprocessing.get_context("spawn")
    rows = []
    with tempfile.TemporaryDirectory(prefix="arcloud-bench-") as folder:
        path = str(Path(folder) / "tensors.npy")
        np.save(path, tensors)
        for p in processes:
            barrier, results = context.Barrier(p), context.Queue()
            workers = [
                context.Process(target=_session_process, args=(str(model), path, seconds, barrier, results)) for _ in range(p)
            ]
            for worker in workers:
                worker.start()
            done = [results.get(timeout=seconds + 300) for _ in workers]
            for worker in workers:
                worker.join()
            run_ms = sorted(t * 1000 for _, _, times in done for t in times)
            fps = sum(n / s for n, s, _ in done)
            rows.append(
                {
                    "processes": p,
                    "fps": round(fps, 3),
                    "fps_per_process": round(fps / p, 3),
                    "session_ms_median": round(statistics.median(run_ms), 2),
                    "session_ms_p90": round(run_ms[int(0.9 * (len(run_ms) - 1))], 2),
                    "runs": len(run_ms),
                }
            )
            print(
                f"ceiling: {p} one-thread sessions: {fps:.2f} frames/s (session {rows[-1]['session_ms_median']} ms)", flush=True
            )
    return {"seconds_each": seconds, "threads_per_session": 1, "rows": rows}


# --- the waiting detector ------------------------------------------------------------------------------
def precompute_detections(frames: list[Any], model: Path, path: Path) -> dict[str, Any]:
    """The real model's detections of each frame (its frame id), saved for ``WaitingReplayDetector``."""
    from arcloud.detectors.onnx_yolo import YoloSegDetector

    detector = YoloSegDetector(str(model))
    arrays: dict[str, np.ndarray] = {}
    counts = []
    for frame in frames:
        detections = detector.detect(frame)
        counts.append(len(detections))
        arrays[f"{frame.frame_id}/labels"] = np.array([d.label for d in detections], dtype=str)
        arrays[f"{frame.frame_id}/scores"] = np.array([d.score for d in detections], dtype=np.float64)
        masks = np.array([d.mask for d in detections], dtype=bool).reshape(len(detections), *frame.depth_m.shape)
        arrays[f"{frame.frame_id}/masks"] = np.packbits(masks, axis=-1)
        arrays[f"{frame.frame_id}/width"] = np.array(frame.depth_m.shape[1])
    np.savez_compressed(path, **arrays)
    return {"frames": len(frames), "detections_per_frame": round(float(np.mean(counts)), 2)}


@dataclasses.dataclass(frozen=True)
class WaitingReplayDetector:
    """Builds a worker's detector (picklable: workers are spawned): each frame takes ``wait_s`` of wall time,
    sleeping, and gives the real model's detections of that frame id from ``path`` (none for other ids)."""

    path: str
    wait_s: float

    def __call__(self) -> Any:
        with np.load(self.path) as saved:
            table: dict[str, dict[str, np.ndarray]] = {}
            for name in saved.files:
                frame_id, _, field = name.rpartition("/")
                table.setdefault(frame_id, {})[field] = saved[name]
        return _WaitingReplay(table, self.wait_s)


@dataclasses.dataclass(frozen=True)
class _WaitingReplay:
    table: dict[str, dict[str, np.ndarray]]
    wait_s: float

    def detect(self, frame: Any) -> list[Any]:
        from arcloud.core.types import Detection

        started = time.perf_counter()
        saved = self.table.get(frame.frame_id)
        detections = []
        if saved is not None and frame.depth_m.shape[1] == int(saved["width"]):
            masks = np.unpackbits(saved["masks"], axis=-1, count=int(saved["width"])).astype(bool)
            detections = [
                Detection(str(label), float(score), mask) for label, score, mask in zip(saved["labels"], saved["scores"], masks)
            ]
        time.sleep(max(0.0, self.wait_s - (time.perf_counter() - started)))
        return detections


# --- 2 and 3. the service ------------------------------------------------------------------------------
class Bodies:
    """The frames as protobuf messages, encoded once; ``phase(maps, tag, n)`` gives ``n`` (map, frame key,
    body) in posting order: frame i is base frame i mod N from device ``<tag>-<i // N>``, into map i mod M."""

    def __init__(self, frames: list[Any]) -> None:
        from arcloud.proto.convert import frame_to_proto

        self.messages = [frame_to_proto(frame) for frame in frames]

    def phase(self, maps: Sequence[str], tag: str, n: int) -> list[tuple[str, str, bytes]]:
        from arcloud.proto.arcloud.v1 import arcloud_pb2

        items = []
        for i in range(n):
            message = arcloud_pb2.Frame()
            message.CopyFrom(self.messages[i % len(self.messages)])
            message.map_id = maps[i % len(maps)]
            message.device_id = f"{tag}-{i // len(self.messages)}"
            items.append((message.map_id, f"{message.device_id}/{message.frame_id}", message.SerializeToString()))
        return items


def post_all(url: str, items: list[tuple[str, str, bytes]], *, rate_per_s: float | None, connections: int) -> list[float]:
    """POST every item (as fast as taken, or open loop at ``rate_per_s``); each POST's wall time (Unix s)."""
    posted = [0.0] * len(items)
    poster = FramePoster(url)
    lock = threading.Lock()
    cursor = iter(range(len(items)))
    started = time.perf_counter()
    failures: list[str] = []

    def run() -> None:
        while not failures:
            with lock:
                i = next(cursor, None)
            if i is None:
                return
            if rate_per_s:
                time.sleep(max(0.0, started + i / rate_per_s - time.perf_counter()))
            posted[i] = time.time()
            status, answer = poster.post(f"/v1/maps/{items[i][0]}/frames", items[i][2])
            if status != 202:
                failures.append(f"POST answered {status}: {answer.decode(errors='replace')[:300]}")

    threads = [threading.Thread(target=run) for _ in range(connections)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if failures:
        raise SystemExit(failures[0])
    return posted


def committed_at(redis: Redis, items: list[tuple[str, str, bytes]], timeout_s: float) -> list[float]:
    """Each item's commit time (Unix s) in the store, waiting until every one is committed."""
    from arcloud.stores.keys import processed_key

    by_map: dict[str, list[int]] = {}
    for i, (map_id, _, _) in enumerate(items):
        by_map.setdefault(map_id, []).append(i)
    done: list[float | None] = [None] * len(items)
    deadline = time.time() + timeout_s
    while True:
        for map_id, indices in by_map.items():
            waiting = [i for i in indices if done[i] is None]
            if waiting:
                for i, value in zip(waiting, redis.client.hmget(processed_key(map_id), [items[i][1] for i in waiting])):
                    done[i] = None if value is None else float(value)
        if all(v is not None for v in done):
            return [float(v) for v in done if v is not None]
        if time.time() > deadline:
            raise SystemExit(f"{sum(v is None for v in done)} of {len(items)} frames not processed within {timeout_s} s")
        time.sleep(0.05)


def wait_delta(before: Any, after: Any) -> dict[str, Any]:
    """Mean, p50 and p99 (bucket upper bounds) of a wait histogram between two ``QueueStats`` readings."""
    counts = [a - b for a, b in zip(after.counts, before.counts)]
    n = sum(counts)
    if n == 0:
        return {"count": 0}
    bounds = [*after.bounds_s, math.inf]

    def quantile(q: float) -> float:
        running = 0
        for bound, count in zip(bounds, counts):
            running += count
            if running >= q * n:
                return bound
        return math.inf

    return {
        "count": n,
        "mean_ms": round((after.sum_s - before.sum_s) / n * 1000, 2),
        "p50_le_ms": round(quantile(0.5) * 1000, 2),
        "p99_le_ms": round(quantile(0.99) * 1000, 2),
    }


class Deployment:
    """``arcloud serve --workers 0`` (its own process) and ``workers`` worker processes started here, on a fresh
    Redis database; ``detector_factory`` None: the real model, one thread a worker."""

    def __init__(
        self, redis: Redis, workers: int, *, api_processes: int, model: Path, detector_factory: Any, env: dict[str, str]
    ) -> None:
        from arcloud.service.settings import Settings
        from arcloud.stores.redis_queue import RedisFrameQueue
        from arcloud.tools.wiring import worker_pool

        redis.client.flushall()
        self.redis, self.workers = redis, workers
        self.api = ServeProcess(redis.url, workers=0, detector=f"onnx:{model}", env=env, api_processes=api_processes)
        settings = Settings(
            store=redis.url,
            detector=f"onnx:{model}",
            detector_threads=1,
            workers=workers,
            **{k.removeprefix("ARCLOUD_").lower(): json.loads(v) if k == "ARCLOUD_PARAMS" else v for k, v in env.items()},
        )
        self.pool = worker_pool(settings, workers, detector_factory=detector_factory, restart=False)
        self.pool.start()
        self.queue = RedisFrameQueue(redis.url)
        deadline = time.time() + 60 + 15 * workers
        while len(self.queue.live_consumers(5.0)) < workers:
            if time.time() > deadline or self.pool.alive() < workers:
                self.stop()
                raise SystemExit(
                    f"{len(self.queue.live_consumers(5.0))} of {workers} workers took frames, {self.pool.alive()} alive "
                    "(a worker's error is logged above)"
                )
            time.sleep(0.2)

    def worker_pids(self) -> list[int]:
        return [p.pid for p in self.pool.processes if p.pid is not None]

    def stop(self) -> None:
        self.queue.close()
        self.pool.stop(timeout_s=30)
        self.api.stop()


def run_phase(
    deployment: Deployment, items: list[tuple[str, str, bytes]], *, rate_per_s: float | None, connections: int
) -> dict[str, Any]:
    """Post ``items``, wait for their commits; throughput, latency, per-frame costs and waits."""
    redis = deployment.redis
    meter = ServiceMeter(deployment.api.process.pid, redis, worker_pids=deployment.worker_pids())
    stats_before = deployment.queue.stats()
    meter.start()
    cpu_started = time.process_time()
    posted = post_all(deployment.api.url, items, rate_per_s=rate_per_s, connections=connections)
    done = committed_at(redis, items, timeout_s=600 + 2 * len(items))
    load_cpu_s = time.process_time() - cpu_started
    per_frame = meter.per_frame(len(items), float(np.mean([len(b) for _, _, b in items])))
    stats_after = deployment.queue.stats()
    latency = np.array(done) - np.array(posted)
    seconds = max(done) - min(posted)
    return {
        "frames": len(items),
        "fps": round(len(items) / seconds, 3),
        "offered_per_s": None if rate_per_s is None else round(rate_per_s, 3),
        "latency_p50_s": round(float(np.percentile(latency, 50)), 4),
        "latency_p99_s": round(float(np.percentile(latency, 99)), 4),
        "latency_max_s": round(float(latency.max()), 4),
        "queue_wait": wait_delta(stats_before.queue_wait, stats_after.queue_wait),
        "lock_wait": wait_delta(stats_before.lock_wait, stats_after.lock_wait),
        "load_generator_cpu_ms_per_frame": round(load_cpu_s / len(items) * 1000, 2),
        "per_frame": per_frame,
    }


def bench_service(
    redis: Redis,
    bodies: Bodies,
    workers_list: list[int],
    *,
    label: str,
    frames_for: Any,
    maps: int,
    api_processes: int,
    model: Path,
    detector_factory: Any,
    connections: int,
    env: dict[str, str],
) -> list[dict[str, Any]]:
    """For each W: a fresh deployment, both layouts as fast as taken and at 70 %."""
    rows = []
    for workers in workers_list:
        started = time.perf_counter()
        deployment = Deployment(
            redis, workers, api_processes=api_processes, model=model, detector_factory=detector_factory, env=env
        )
        try:
            ready_s = time.perf_counter() - started
            warm = bodies.phase(["warm-up"], f"warm{workers}", max(2, workers))  # each worker's first frame
            run_phase(deployment, warm, rate_per_s=None, connections=connections)
            row: dict[str, Any] = {"workers": workers, "startup_s": round(ready_s, 1)}
            n = frames_for(workers)
            for layout, names in (("one_map", ["hot"]), ("many_maps", [f"map{m}" for m in range(maps)])):
                tag = f"{layout}-{workers}"
                fast_items = bodies.phase([f"{name}-{tag}-fast" for name in names], tag, n)
                fast = run_phase(deployment, fast_items, rate_per_s=None, connections=connections)
                rate = LOAD_FRACTION * fast["fps"]
                paced_items = bodies.phase([f"{name}-{tag}-70" for name in names], tag, n)
                at_70 = run_phase(deployment, paced_items, rate_per_s=rate, connections=connections)
                row[layout] = {"maps": len(names), "as_fast": fast, "at_70": at_70}
                print(
                    f"{label}: {workers} workers, {layout}: {fast['fps']:.2f} frames/s; at 70 %: p50 {at_70['latency_p50_s']} s, "
                    f"p99 {at_70['latency_p99_s']} s; lock wait mean {fast['lock_wait'].get('mean_ms')} ms; CPU/frame "
                    f"{fast['per_frame']['cpu_ms']}",
                    flush=True,
                )
            rows.append(row)
        finally:
            deployment.stop()
    return rows


# --- the plot ------------------------------------------------------------------------------------------
def plot(result: dict[str, Any], path: Path) -> None:
    """Frames/s against workers (service, waiting detector, their ideals, the sessions' ceiling) and where a
    frame's time goes (CPU of API, workers and Redis per frame; lock wait). Without matplotlib (a lent
    machine), says so: ``--plot FILE.json`` draws it later."""
    try:
        import matplotlib
    except ImportError:
        print(f"no plot: matplotlib is not installed (bench_scaling.py --plot {path.with_suffix('.json')} elsewhere)")
        return

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5))
    ceiling = result.get("ceiling")
    if ceiling:
        xs = [r["processes"] for r in ceiling["rows"]]
        left.plot(xs, [r["fps"] for r in ceiling["rows"]], "k^-", label="one-thread sessions in parallel (ceiling)")
    for part, style in (("service", "o"), ("wait", "s")):
        rows = result.get(part)
        if not rows:
            continue
        xs = [r["workers"] for r in rows["rows"]]
        for layout, colour in (("one_map", "tab:red"), ("many_maps", "tab:blue")):
            left.plot(
                xs, [r[layout]["as_fast"]["fps"] for r in rows["rows"]], f"{style}-", color=colour, label=f"{part}: {layout}"
            )
        if part == "wait":
            left.plot(
                xs, [w / (rows["detector_wait_ms"] / 1000) for w in xs], "k:", label=f"W / {rows['detector_wait_ms']:.0f} ms"
            )
            for layout, colour in (("one_map", "tab:red"), ("many_maps", "tab:blue")):
                cpu = [sum(r[layout]["as_fast"]["per_frame"]["cpu_ms"].values()) for r in rows["rows"]]
                lock = [r[layout]["as_fast"]["lock_wait"].get("mean_ms", 0.0) for r in rows["rows"]]
                right.plot(xs, cpu, f"{style}-", color=colour, label=f"wait, {layout}: CPU ms a frame (API + workers + Redis)")
                right.plot(xs, lock, f"{style}--", color=colour, label=f"wait, {layout}: lock wait ms a frame")
    left.set_xscale("log", base=2)
    left.set_xlabel("worker processes (ceiling: sessions)")
    left.set_ylabel("frames/s")
    left.set_title(f"{result['machine']['cores']} cores: {result['machine']['cpu']}", fontsize=9)
    left.grid(True, alpha=0.3)
    left.legend(fontsize=7)
    right.set_xscale("log", base=2)
    right.set_xlabel("worker processes (waiting detector)")
    right.set_ylabel("ms")
    right.grid(True, alpha=0.3)
    right.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def main() -> None:
    n_cores = cores()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", default="ceiling,service,wait", help="any of ceiling,service,wait (default all)")
    parser.add_argument("--frames", type=int, default=60, help="distinct frames (default 60)")
    parser.add_argument("--stride", type=int, default=10, help="every n-th frame of the sequence (default 10)")
    parser.add_argument("--model", type=Path, default=MODEL)
    parser.add_argument("--ceiling-s", type=float, default=8.0, help="seconds each ceiling run (default 8)")
    parser.add_argument(
        "--ceiling-processes", type=int_list, default=None, help="P for the ceiling (default 1, 2, 4, ... cores, and each W)"
    )
    parser.add_argument(
        "--ceiling-from", type=Path, metavar="JSON", help="take the ceiling from an earlier result file (a run in parts)"
    )
    parser.add_argument(
        "--workers", type=int_list, default=powers_of_two_to(n_cores), help="W for the service (default 1, 2, 4, ... cores)"
    )
    parser.add_argument(
        "--service-frames", type=int, default=48, help="frames a phase per worker with the real model (default 48)"
    )
    parser.add_argument(
        "--wait-workers", type=int_list, default=[1, 2, 4, 8, 16], help="W with the waiting detector (default 1,2,4,8,16)"
    )
    parser.add_argument(
        "--detector-wait-ms",
        type=float,
        default=None,
        help="the waiting detector's time (default: the one-thread session's median)",
    )
    parser.add_argument(
        "--wait-phase-s", type=float, default=3.0, help="a waiting phase's length at the ideal rate (default 3 s)"
    )
    parser.add_argument("--maps", type=int, default=8, help="maps of the many_maps layout (default 8)")
    parser.add_argument("--api-processes", type=int, default=1, help="serve --api-processes (default 1)")
    parser.add_argument("--connections", type=int, default=8, help="keep-alive connections posting (default 8)")
    parser.add_argument(
        "--queued-images", choices=("decoded", "uploaded"), default=None, help="ARCLOUD_QUEUED_IMAGES (default: the service's)"
    )
    parser.add_argument(
        "--worker-prefetch", choices=("on", "off"), default=None, help="ARCLOUD_WORKER_PREFETCH (default: the service's)"
    )
    parser.add_argument("--params", default=None, help="ARCLOUD_PARAMS: JSON overrides of Params (default: none)")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--plot", type=Path, metavar="JSON", help="only draw the plot of a result file, beside it")
    args = parser.parse_args()
    if args.plot:
        plot(json.loads(args.plot.read_text()), args.plot.with_suffix(".png"))
        return
    parts = {p.strip() for p in args.parts.split(",")}
    if not args.model.is_file() or not SEQUENCE.is_dir():
        raise SystemExit(f"needs {args.model} and {SEQUENCE} (the real assets in ../shared, or ARCLOUD_SHARED)")
    from arcloud.allocator import keep_freed_memory
    from arcloud.datasets.sevenscenes import load_seven_scenes

    keep_freed_memory()
    bench_started = time.perf_counter()
    load_start = os.getloadavg()
    frames = list(load_seven_scenes(SEQUENCE, align_gravity=True).frames(stride=args.stride, limit=args.frames))
    from arcloud.service.settings import Settings

    defaults = Settings()
    queued_images = args.queued_images or defaults.queued_images
    worker_prefetch = defaults.worker_prefetch if args.worker_prefetch is None else args.worker_prefetch == "on"
    env = {
        **BENCH_ENV,
        "ARCLOUD_QUEUED_IMAGES": queued_images,
        "ARCLOUD_WORKER_PREFETCH": str(worker_prefetch).lower(),
        **({"ARCLOUD_PARAMS": args.params} if args.params else {}),
    }
    result: dict[str, Any] = {
        "benchmark": "scaling",
        **environment(("arcloud", "numpy", "onnxruntime", "fastapi", "uvicorn", "redis")),
        "setup": {
            "model": args.model.name,
            "frames": len(frames),
            "stride": args.stride,
            "width": int(frames[0].depth_m.shape[1]),
            "height": int(frames[0].depth_m.shape[0]),
            "maps_many": args.maps,
            "api_processes": args.api_processes,
            "connections": args.connections,
            "queued_images": queued_images,
            "worker_prefetch": worker_prefetch,
            "params": args.params,
            "load_fraction": LOAD_FRACTION,
        },
    }
    if "ceiling" in parts:
        processes = sorted(set(args.ceiling_processes or [*powers_of_two_to(n_cores), *args.workers]))
        result["ceiling"] = bench_ceiling(frames, processes, args.ceiling_s, args.model)
    elif args.ceiling_from:
        result["ceiling"] = json.loads(args.ceiling_from.read_text())["ceiling"]
    session_ms = result["ceiling"]["rows"][0]["session_ms_median"] if "ceiling" in result else None
    redis = Redis()
    result["redis_server"] = redis.version
    bodies = Bodies(frames)
    try:
        if "service" in parts:
            rows = bench_service(
                redis,
                bodies,
                args.workers,
                label="service",
                frames_for=lambda w: args.service_frames * w,
                maps=args.maps,
                api_processes=args.api_processes,
                model=args.model,
                detector_factory=None,
                connections=args.connections,
                env=env,
            )
            result["service"] = {"detector": f"onnx:{args.model.name}, one thread a worker", "rows": rows}
            if session_ms:
                ceiling = {r["processes"]: r["fps"] for r in result["ceiling"]["rows"]}
                for row in rows:
                    if row["workers"] in ceiling:
                        for layout in ("one_map", "many_maps"):
                            row[layout]["service_over_ceiling"] = round(
                                row[layout]["as_fast"]["fps"] / ceiling[row["workers"]], 3
                            )
        if "wait" in parts:
            wait_ms = args.detector_wait_ms or session_ms
            if not wait_ms:
                raise SystemExit("--parts wait without ceiling needs --detector-wait-ms")
            with tempfile.TemporaryDirectory(prefix="arcloud-bench-") as folder:
                path = Path(folder) / "detections.npz"
                precomputed = precompute_detections(frames, args.model, path)
                print(
                    f"detections of {precomputed['frames']} frames precomputed; waiting {wait_ms:.1f} ms a detection", flush=True
                )
                rows = bench_service(
                    redis,
                    bodies,
                    args.wait_workers,
                    label="wait",
                    frames_for=lambda w: max(4 * w, 30, round(w / (wait_ms / 1000) * args.wait_phase_s)),
                    maps=args.maps,
                    api_processes=args.api_processes,
                    model=args.model,
                    detector_factory=WaitingReplayDetector(str(path), wait_ms / 1000),
                    connections=args.connections,
                    env=env,
                )
            for row in rows:
                ideal = row["workers"] / (wait_ms / 1000)
                row["ideal_fps"] = round(ideal, 3)
                for layout in ("one_map", "many_maps"):
                    row[layout]["over_ideal"] = round(row[layout]["as_fast"]["fps"] / ideal, 3)
            result["wait"] = {"detector_wait_ms": round(wait_ms, 2), "precomputed": precomputed, "rows": rows}
            biggest = max(rows, key=lambda r: r["workers"])
            result["wait"]["target"] = {
                "workers": biggest["workers"],
                "over_ideal_wanted": TARGET_OVER_IDEAL,
                "one_map": biggest["one_map"]["over_ideal"],
                "many_maps": biggest["many_maps"]["over_ideal"],
                "met": min(biggest["one_map"]["over_ideal"], biggest["many_maps"]["over_ideal"]) >= TARGET_OVER_IDEAL,
            }
    finally:
        redis.stop()
    result["load_average_1_5_15_min"] = {
        "start": [round(v, 2) for v in load_start],
        "end": [round(v, 2) for v in os.getloadavg()],
    }
    result["seconds"] = round(time.perf_counter() - bench_started, 1)
    write_json(args.out, result)
    plot(result, args.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
