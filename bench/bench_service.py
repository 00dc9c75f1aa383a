"""Throughput and latency through the service on Redis with 1 and 2 worker processes, against the
in-process step.

Frames: a simulated walk (``generate_room(seed)``, 640x480 by default) uploaded as protobuf (JPEG colour,
16-bit PNG depth) to a real API (uvicorn on 127.0.0.1, in this process) whose Redis store and stream run
on a throwaway redis-server; the API starts ``--workers`` worker processes running ``sim:SEED`` (the
simulator's detector, which ray-casts each frame's instance image: the detector cost of the step).

Rounds (``--rounds``, 3): for each worker count, the in-process step on the frames, then a fresh service
(workers loaded by warm-up frames on another map) with every frame posted at once by 4 concurrent
uploaders (bodies encoded beforehand: the client's cost is not counted); throughput = frames / (last
completion - first post); a last in-process run closes the round. The machine's speed drifts by 10% and
more over minutes (other tenants), so each round gives its own ratios (2 workers over 1; 1 worker over
the mean of the in-process runs just before and after it), and the results are their medians. Then latency, per worker count: the frames posted
at a steady ``--paced`` fraction (0.7) of that throughput; latency = completion - post (p50, p99),
completion seen by polling the store's processed-frames set every 10 ms (every 50 ms during the
throughput bursts, where only the last completion counts). CPU per frame (from /proc) of
each part: this process (the API and the load generator), the workers, Redis; and of the in-process step.

In process: ``process_frame`` on the same frames, one after another, with a fresh detector (no cached
renders, like the service's workers), on the same Redis (each round) and on the embedded store (once).

Threads: the simulated detector's ray cast runs on Open3D's threads. With ``--detector-threads 1`` (the
default) every worker, and the in-process step, casts on one thread: the question is how the service
scales with worker processes, as replicas on machines of their own would. ``--detector-threads 0`` runs
the service as deployed (each worker takes its share of the cores: both with one worker, one each with
two) against an in-process step on every core.

Targets on 2 cores: 2 workers >= 1.7x the throughput of 1; the service's time per frame with one
worker <= 1.25x the in-process step's (Redis store).

    .venv/bin/python bench/bench_service.py [--frames 80] [--out bench/results/service.json]
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import os
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import Redis, cpu_s, environment, free_port, summary_ms, write_json

TARGET_SPEEDUP = 1.7
TARGET_OVERHEAD = 1.25
POLL_S = 0.01  # completion polling period while latency is measured (its resolution)
POLL_BURST_S = 0.05  # ... while throughput is (each poll costs this VM ~0.3 ms of CPU: fewer leave the cores to the service)


def _spin(n: int) -> float:
    started = time.perf_counter()
    total = 0
    for i in range(n):
        total += i * i
    return time.perf_counter() - started


def parallel_probe(n: int = 3_000_000) -> float:
    """How much faster two processes finish two equal CPU-bound tasks than one finishes one, twice
    (2.0 on two idle cores): what the machine can give two workers right now."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(2) as pool:
        pool.map(_spin, [10, 10])
        started = time.perf_counter()
        pool.map(_spin, [n])
        one = time.perf_counter() - started
        started = time.perf_counter()
        pool.map(_spin, [n, n])
        two = time.perf_counter() - started
    return 2 * one / two


class Service:
    """The API (uvicorn in a thread of this process) with ``workers`` worker processes, on ``redis``."""

    def __init__(self, redis: Redis, workers: int, seed: int, threads: int) -> None:
        import uvicorn

        from arcloud.service.settings import Settings
        from arcloud.tools.wiring import create_app

        self.redis = redis
        self.workers = workers
        settings = Settings(
            store=redis.url,
            auth="none",  # the bench measures ingest; a key lookup and rate limit cost one cached read and one script a request
            key_rate_per_s=0,
            map_frame_rate_per_s=0,
            detector=f"sim:{seed}",
            detector_threads=threads or None,
            workers=workers,
            max_queued_frames=10_000,
            log_level="WARNING",
        )
        port = free_port()
        self.url = f"http://127.0.0.1:{port}"
        self.app = create_app(settings)
        self.server = uvicorn.Server(
            uvicorn.Config(self.app, host="127.0.0.1", port=port, log_level="warning", ws="none", access_log=False)
        )
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> Service:
        self.thread.start()
        while not self.server.started:
            time.sleep(0.05)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(60)

    def step_stats(self) -> tuple[int, float]:
        from arcloud.stores.redis_queue import RedisFrameQueue

        snap = RedisFrameQueue(client=self.redis.client).stats()  # every shard's (the service's one)
        return snap.latency_count, snap.latency_sum_s

    def cpu_s(self) -> dict[str, float]:
        """CPU seconds used so far by this process (the API, and the load generator), the workers and Redis."""
        workers = self.app.state.runtime.ingest.pool.processes
        return {
            "api_and_load": cpu_s(os.getpid()),
            "workers": sum(cpu_s(p.pid) for p in workers),
            "redis": cpu_s(self.redis.process.pid),
        }

    def run(
        self,
        map_id: str,
        bodies: list[bytes],
        keys: list[str],
        *,
        concurrency: int,
        interval_s: float = 0.0,
        poll_s: float = POLL_S,
    ) -> dict[str, Any]:
        """Post every body (all at once, or one every ``interval_s``); per-frame post and completion times,
        and the CPU time each part used per frame."""
        import httpx

        from arcloud.stores import keys as store_keys

        n = len(bodies)
        posted = np.zeros(n)
        done = np.full(n, np.nan)
        count_before, sum_before = self.step_stats()
        cpu_before = self.cpu_s()

        def poll() -> None:
            """Completion times: the processed-frames set's size every ``poll_s``; which frames, only when it
            grew (the load generator's CPU, counted with the API's, stays small)."""
            processed_key = store_keys.processed_key(map_id)
            seen = -1
            while True:
                pending = np.flatnonzero(np.isnan(done))
                if pending.size == 0:
                    return
                count = int(self.redis.client.hlen(processed_key))
                now = time.perf_counter()
                if count != seen:
                    seen = count
                    marks = self.redis.client.hmget(processed_key, [keys[i] for i in pending])
                    done[pending[np.asarray([mark is not None for mark in marks], bool)]] = now
                if now - posted.max() > 600:
                    return
                time.sleep(poll_s)

        poller = threading.Thread(target=poll, daemon=True)
        with httpx.Client(base_url=self.url, timeout=60, limits=httpx.Limits(max_connections=concurrency)) as http:

            def post(i: int) -> None:
                if interval_s:
                    time.sleep(max(0.0, start + i * interval_s - time.perf_counter()))
                posted[i] = time.perf_counter()
                response = http.post(
                    f"/v1/maps/{map_id}/frames", content=bodies[i], headers={"content-type": "application/x-protobuf"}
                )
                assert response.status_code == 202, response.text

            start = time.perf_counter()
            posted[:] = start
            poller.start()
            with concurrent.futures.ThreadPoolExecutor(concurrency) as pool:
                list(pool.map(post, range(n)))
            poller.join()
        if np.isnan(done).any():
            raise SystemExit(f"{int(np.isnan(done).sum())} frames not processed")
        count_after, sum_after = self.step_stats()
        cpu_after = self.cpu_s()
        cpu_ms = {part: round((cpu_after[part] - cpu_before[part]) / n * 1000, 1) for part in cpu_after}
        wall_s = float(done.max() - posted.min())
        latency_s = list(done - posted)
        return {
            "frames": n,
            "wall_s": round(wall_s, 3),
            "frames_per_s": round(n / wall_s, 3),
            "s_per_frame": round(wall_s / n, 4),
            "latency": {
                "p50_ms": round(float(np.percentile(latency_s, 50)) * 1000, 1),
                "p99_ms": round(float(np.percentile(latency_s, 99)) * 1000, 1),
                **summary_ms(latency_s),
            },
            "worker_step_mean_ms": round((sum_after - sum_before) / (count_after - count_before) * 1000, 2)
            if count_after > count_before
            else None,
            "cpu_ms_per_frame": {**cpu_ms, "total": round(sum(cpu_ms.values()), 1)},
        }


def encode(frames: list[Any], map_id: str) -> tuple[list[bytes], list[str]]:
    """Protobuf bodies (JPEG colour, 16-bit PNG depth) of ``frames`` posted to ``map_id``, and their keys."""
    from arcloud.proto.convert import frame_to_proto

    return [frame_to_proto(dataclasses.replace(f, map_id=map_id)).SerializeToString() for f in frames], [f.key for f in frames]


def bench_service(
    redis: Redis,
    workers: int,
    seed: int,
    threads: int,
    timed: list[Any],
    warmup: list[Any],
    *,
    concurrency: int,
    paced_rate: float | None = None,
) -> dict[str, Any]:
    """One service start with ``workers`` worker processes: warm-up, then every frame posted at once
    (throughput), or, with ``paced_rate``, one frame every 1 / ``paced_rate`` s (latency)."""
    redis.client.flushdb()
    started = time.perf_counter()
    with Service(redis, workers, seed, threads) as service:
        warm_bodies, warm_keys = encode(warmup, "warmup")
        service.run("warmup", warm_bodies, warm_keys, concurrency=1)  # every worker's detector and room loaded
        ready_s = time.perf_counter() - started
        bodies, keys = encode(timed, "timed")
        if paced_rate:
            row = service.run("timed", bodies, keys, concurrency=concurrency, interval_s=1.0 / paced_rate, poll_s=POLL_S)
        else:
            row = service.run("timed", bodies, keys, concurrency=concurrency, poll_s=POLL_BURST_S)
    return {**row, "startup_and_warmup_s": round(ready_s, 2)}


def run_in_process(
    frames: list[Any], seed: int, threads: int, store: Any, map_id: str, redis: Redis | None = None
) -> dict[str, Any]:
    """``process_frame`` on each frame, timed; CPU per frame of this process and of ``redis`` (its store's)."""
    from arcloud.core.step import process_frame
    from arcloud.core.types import Params
    from arcloud.sim.detector import SimulatedDetector
    from arcloud.sim.room import generate_room

    detector = SimulatedDetector(generate_room(seed), seed=seed, threads=threads)  # a new room: no renders remembered
    params = Params()
    process_frame(dataclasses.replace(frames[0], map_id=f"{map_id}-warmup"), detector, store, params)
    times = []
    cpu_before = (time.process_time(), cpu_s(redis.process.pid) if redis else 0.0)
    for frame in frames:
        started = time.perf_counter()
        process_frame(dataclasses.replace(frame, map_id=map_id), detector, store, params)
        times.append(time.perf_counter() - started)
    cpu_ms = {
        "step": (time.process_time() - cpu_before[0]) / len(frames) * 1000,
        "redis": ((cpu_s(redis.process.pid) if redis else 0.0) - cpu_before[1]) / len(frames) * 1000,
    }
    return {
        "s_per_frame": round(statistics.fmean(times), 4),
        "frames_per_s": round(len(times) / sum(times), 3),
        **summary_ms(times),
        "cpu_ms_per_frame": {**{k: round(v, 1) for k, v in cpu_ms.items()}, "total": round(sum(cpu_ms.values()), 1)},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=80)
    parser.add_argument("--warmup", type=int, default=6, help="frames per worker count before timing")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", default="1,2", help="worker process counts (default 1,2)")
    parser.add_argument(
        "--detector-threads",
        type=int,
        default=1,
        help="ray-casting threads per worker and in process (default 1: each worker on one core, as replicas on "
        "their own machines; 0: the service's default, the cores shared among the worker processes)",
    )
    parser.add_argument("--concurrency", type=int, default=4, help="concurrent uploads")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of (in process, each worker count), medians taken")
    parser.add_argument("--paced", type=float, default=0.7, help="latency run's rate, as a fraction of the measured throughput")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results/service.json")
    args = parser.parse_args()
    from arcloud.allocator import keep_freed_memory

    keep_freed_memory()  # as the CLI's commands and the worker processes do
    load_start = os.getloadavg()  # other processes on the machine share its cores: recorded

    from arcloud.core.types import Intrinsics
    from arcloud.sim.room import generate_room
    from arcloud.sim.sequence import simulate_sequence
    from arcloud.stores.memory import MemoryStore
    from arcloud.stores.redis import RedisStore

    height = args.width * 3 // 4
    scale = args.width / 640
    intrinsics = Intrinsics(525 * scale, 525 * scale, (args.width - 1) / 2, (height - 1) / 2)
    frames = simulate_sequence(
        generate_room(args.seed),
        n_frames=args.frames + args.warmup,
        seed=args.seed,
        width=args.width,
        height=height,
        intrinsics=intrinsics,
        map_id="bench",
    )
    warmup, timed = frames[: args.warmup], frames[args.warmup :]

    probes = [parallel_probe()]
    worker_counts = [int(w) for w in args.workers.split(",")]
    redis = Redis()
    try:
        # Rounds interleave the in-process step and each worker count, so that a drift in the machine's
        # speed (other tenants) reaches all of them alike: in process, 1 worker, in process, 2 workers, ...
        bursts: dict[int, list[dict[str, Any]]] = {w: [] for w in worker_counts}
        in_process_redis: list[list[dict[str, Any]]] = []  # per round: before each worker count, and after the last

        def in_process_now(r: int) -> dict[str, Any]:
            redis.client.flushdb()
            with contextlib.closing(RedisStore(redis.url)) as redis_store:
                row = run_in_process(timed, args.seed, args.detector_threads, redis_store, "inproc", redis)
            print(
                f"round {r + 1}: in process (redis store) {row['s_per_frame'] * 1000:.1f} ms per frame, CPU ms per frame {row['cpu_ms_per_frame']}",
                flush=True,
            )
            return row

        for r in range(args.rounds):
            in_process_redis.append([])
            for w in worker_counts:
                in_process_redis[r].append(in_process_now(r))
                bursts[w].append(
                    bench_service(redis, w, args.seed, args.detector_threads, timed, warmup, concurrency=args.concurrency)
                )
                print(
                    f"round {r + 1}: service, {w} worker(s): {bursts[w][-1]['frames_per_s']:.2f} frames/s, "
                    f"worker step {bursts[w][-1]['worker_step_mean_ms']} ms, CPU ms per frame {bursts[w][-1]['cpu_ms_per_frame']}",
                    flush=True,
                )
            in_process_redis[r].append(in_process_now(r))
        service = []
        for w in worker_counts:
            throughput = statistics.median(b["frames_per_s"] for b in bursts[w])
            paced = bench_service(
                redis,
                w,
                args.seed,
                args.detector_threads,
                timed,
                warmup,
                concurrency=args.concurrency,
                paced_rate=args.paced * throughput,
            )
            service.append(
                {
                    "workers": w,
                    "frames_per_s": round(throughput, 3),
                    "s_per_frame": round(1.0 / throughput, 4),
                    "latency_paced": {"rate_frames_per_s": round(args.paced * throughput, 3), **paced["latency"]},
                    "worker_step_mean_ms": statistics.median(b["worker_step_mean_ms"] for b in bursts[w]),
                    "bursts": bursts[w],
                }
            )
            row = service[-1]
            print(
                f"service, {w} worker(s): {row['frames_per_s']:.2f} frames/s (bursts {[b['frames_per_s'] for b in row['bursts']]}), "
                f"latency at {row['latency_paced']['rate_frames_per_s']:.2f} frames/s: p50 {row['latency_paced']['p50_ms']:.0f} ms, "
                f"p99 {row['latency_paced']['p99_ms']:.0f} ms; worker step {row['worker_step_mean_ms']} ms"
            )
        s_per_frame = statistics.median(row["s_per_frame"] for rnd in in_process_redis for row in rnd)
        in_process = {
            "memory": run_in_process(timed, args.seed, args.detector_threads, MemoryStore(), "inproc"),
            "redis": {
                "s_per_frame": round(s_per_frame, 4),
                "frames_per_s": round(1.0 / s_per_frame, 3),
                "rounds": in_process_redis,
            },
        }
        for name, row in in_process.items():
            print(f"in process ({name} store): {row['frames_per_s']:.2f} frames/s, {row['s_per_frame'] * 1000:.1f} ms per frame")
    finally:
        redis.stop()
    probes.append(parallel_probe())
    print(
        f"the machine's parallel speedup for two CPU-bound processes (before, after): {probes[0]:.2f}, {probes[1]:.2f} (2.0 on idle cores)"
    )

    # Per round: 2 workers' throughput over 1 worker's; 1 worker's time per frame over the mean of the
    # in-process runs just before and after it. Medians over rounds.
    speedups, overheads, cpu_overheads = [], [], []
    for r in range(args.rounds):
        by_w = {w: bursts[w][r] for w in worker_counts}
        if {1, 2} <= set(by_w):
            speedups.append(by_w[2]["frames_per_s"] / by_w[1]["frames_per_s"])
        if 1 in by_w:
            i = worker_counts.index(1)
            around = statistics.fmean(row["s_per_frame"] for row in in_process_redis[r][i : i + 2])
            overheads.append(by_w[1]["s_per_frame"] / around)
            cpu_around = statistics.fmean(row["cpu_ms_per_frame"]["total"] for row in in_process_redis[r][i : i + 2])
            cpu_overheads.append(by_w[1]["cpu_ms_per_frame"]["total"] / cpu_around)
    speedup = statistics.median(speedups) if speedups else None
    overhead = statistics.median(overheads) if overheads else None
    by_workers = {row["workers"]: row for row in service}
    results = {
        "benchmark": "service",
        **environment(("arcloud", "numpy", "scipy", "open3d", "fastapi", "uvicorn", "redis", "protobuf")),
        "redis_server": redis.version,
        "setup": {
            "frames": len(timed),
            "warmup": args.warmup,
            "width": args.width,
            "height": height,
            "seed": args.seed,
            "concurrency": args.concurrency,
            "rounds": args.rounds,
            "paced_fraction": args.paced,
            "poll_s": {"latency": POLL_S, "throughput": POLL_BURST_S},
            "detector": f"sim:{args.seed}",
            "detector_threads": args.detector_threads or "default",
            "upload": "protobuf, JPEG rgb, 16-bit PNG depth",
            "load_average_1_5_15_min": {
                "start": [round(v, 2) for v in load_start],
                "end": [round(v, 2) for v in os.getloadavg()],
            },
        },
        "service": service,
        "in_process": in_process,
        "machine_parallel_speedup_before_after": [round(p, 3) for p in probes],
        "speedup_2_over_1": round(speedup, 3) if speedup else None,
        "speedup_2_over_1_per_round": [round(v, 3) for v in speedups],
        "service_over_in_process_redis_per_round": [round(v, 3) for v in overheads],
        "service_over_in_process_redis": round(overhead, 3) if overhead else None,
        "service_over_in_process_cpu_per_round": [round(v, 3) for v in cpu_overheads],
        "service_over_in_process_cpu": round(statistics.median(cpu_overheads), 3) if cpu_overheads else None,
        "service_over_in_process_memory": round(by_workers[1]["s_per_frame"] / in_process["memory"]["s_per_frame"], 3)
        if 1 in by_workers
        else None,
        "targets": {"speedup_2_over_1": TARGET_SPEEDUP, "service_over_in_process": TARGET_OVERHEAD},
    }
    print(
        f"2 workers / 1 worker: {results['speedup_2_over_1']}x (target >= {TARGET_SPEEDUP}); "
        f"service / in-process: {results['service_over_in_process_redis']}x in time per frame, "
        f"{results['service_over_in_process_cpu']}x in CPU per frame (target <= {TARGET_OVERHEAD})"
    )
    write_json(args.out, results)


if __name__ == "__main__":
    main()
