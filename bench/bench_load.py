"""N simulated devices, each posting frames at a fixed rate (open loop, bounded in time), against
`arcloud serve --redis` with one worker process per core and the simulator's detector: latency from each
POST to its frame's commit (p50, p95, p99, max; split into the POST until its 202 and what follows),
frames/s taken and processed, and what one frame costs:
Redis commands (by command) and bytes in and out, CPU seconds of the API, the workers and Redis. Those
costs feed ``bench/scaling_model.py`` (docs/scaling.md).

Devices walk the simulated room 0 at 160 x 120 (the load is the service's, not the detector's).
Writes ``bench/results/load.json`` (one entry per ``--devices`` value).

    .venv/bin/python bench/bench_load.py --devices 10,100 --rate 1 --seconds 30
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import INGEST_ONLY_ENV, Redis, ServeProcess, ServiceMeter, cores, environment, write_json

OUT = Path(__file__).parent / "results" / "load.json"
WIDTH, HEIGHT = 160, 120


def device_bodies(map_id: str, n_devices: int, per_device: int) -> list[list[bytes]]:
    """Each device's frames (protobuf), from one simulated walk of room 0, ids unique per device."""
    from arcloud.core.types import Intrinsics
    from arcloud.proto.convert import frame_to_proto
    from arcloud.sim.room import generate_room
    from arcloud.sim.sequence import simulate_sequence

    scale = WIDTH / 640
    intrinsics = Intrinsics(525.0 * scale, 525.0 * scale, (WIDTH - 1) / 2, (HEIGHT - 1) / 2)
    walk = simulate_sequence(
        generate_room(0), n_frames=60, seed=0, width=WIDTH, height=HEIGHT, intrinsics=intrinsics, map_id=map_id
    )
    bodies = []
    for device in range(n_devices):
        frames = []
        for i in range(per_device):
            message = frame_to_proto(walk[(device * 7 + i) % len(walk)])
            message.device_id, message.frame_id = f"device-{device}", f"f{i:06d}"
            frames.append(message.SerializeToString())
        bodies.append(frames)
    return bodies


def run_load(url: str, redis: Redis, map_id: str, bodies: list[list[bytes]], rate_per_s: float, seconds: float) -> dict[str, Any]:
    """Every device posts ``rate_per_s`` frames a second for ``seconds`` (open loop: a slow answer does not
    delay its next frame); latency from POST to the frame's commit."""
    from arcloud.stores.keys import processed_key

    posted: dict[str, float] = {}
    answered: dict[str, float] = {}  # when the 202 came back
    statuses: list[int] = []
    lock = threading.Lock()
    started = time.time() + 0.5
    n_per_device = int(seconds * rate_per_s)

    def device(k: int, http: httpx.Client) -> None:
        offset = (k / len(bodies)) / rate_per_s  # devices spread over the period
        threads = []
        for i in range(n_per_device):
            time.sleep(max(0.0, started + offset + i / rate_per_s - time.time()))

            def post(body: bytes = bodies[k][i], key: str = f"device-{k}/f{i:06d}") -> None:
                sent = time.time()
                status = http.post(
                    f"/v1/maps/{map_id}/frames", content=body, headers={"content-type": "application/x-protobuf"}
                ).status_code
                with lock:
                    statuses.append(status)
                    if status == 202:
                        posted[key], answered[key] = sent, time.time()

            thread = threading.Thread(target=post, daemon=True)
            thread.start()
            threads.append(thread)
        for thread in threads:
            thread.join(60)

    limits = httpx.Limits(max_connections=max(8, len(bodies)))
    with httpx.Client(base_url=url, timeout=60, limits=limits) as http:
        devices = [threading.Thread(target=device, args=(k, http)) for k in range(len(bodies))]
        for thread in devices:
            thread.start()
        for thread in devices:
            thread.join()
    keys = sorted(posted)
    deadline = time.time() + 600
    while True:
        values = redis.client.hmget(processed_key(map_id), keys) if keys else []
        if all(v is not None for v in values) or time.time() > deadline:
            break
        time.sleep(0.1)
    done = {k: float(v) for k, v in zip(keys, values) if v is not None}
    latency = np.array([done[k] - posted[k] for k in done])
    post_latency = np.array([answered[k] - posted[k] for k in done])
    last = max(done.values()) if done else started
    return {
        "devices": len(bodies),
        "offered_per_s": round(len(bodies) * rate_per_s, 2),
        "sent": len(statuses),
        "accepted": statuses.count(202),
        "refused": {str(s): statuses.count(s) for s in sorted(set(statuses)) if s != 202},
        "processed": len(done),
        "processed_per_s": round(len(done) / max(1e-9, last - started), 2),
        "latency_s": percentiles(latency),
        "post_latency_s": percentiles(post_latency),  # the POST alone: sent -> 202
        "after_202_s": percentiles(latency - post_latency),  # queue, step and commit
    }


def percentiles(seconds: np.ndarray) -> dict[str, float] | None:
    """p50, p95, p99 and max of ``seconds``, rounded to ms (None when empty)."""
    if not len(seconds):
        return None
    return {f"p{q}": round(float(np.percentile(seconds, q)), 3) for q in (50, 95, 99)} | {"max": round(float(seconds.max()), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--devices", default="10,100", help="comma-separated device counts (default 10,100)")
    parser.add_argument("--rate", type=float, default=1.0, help="frames a second per device (default 1)")
    parser.add_argument("--seconds", type=float, default=30.0, help="how long each load runs (default 30)")
    parser.add_argument("--workers", type=int, default=cores(), help="worker processes (default: the cores)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    counts = [int(v) for v in args.devices.split(",")]
    redis = Redis()
    service = ServeProcess(redis.url, workers=args.workers, detector="sim:0", env=INGEST_ONLY_ENV)
    url, server = service.url, service.process
    runs = []
    try:
        for n in counts:
            bodies = device_bodies(f"load-{n}", n, int(args.seconds * args.rate))
            meter = ServiceMeter(server.pid, redis)
            meter.start()
            result = run_load(url, redis, f"load-{n}", bodies, args.rate, args.seconds)
            result["per_frame"] = meter.per_frame(result["processed"], float(np.mean([len(b) for d in bodies for b in d])))
            runs.append(result)
            latency = result["latency_s"] or {}
            print(
                f"{n} devices x {args.rate:g}/s: {result['processed']} of {result['sent']} processed, "
                f"{result['processed_per_s']}/s, latency p50 {latency.get('p50')} s p99 {latency.get('p99')} s "
                f"(the POST alone: {result['post_latency_s']}); "
                f"per frame {result['per_frame']['redis_commands']} Redis commands, cpu {result['per_frame']['cpu_ms']} ms"
            )
    finally:
        service.stop()
        redis.stop()
    write_json(
        args.out,
        {**environment(("arcloud", "numpy", "redis", "fastapi", "uvicorn")), "cores": cores(), "workers": args.workers,
         "rate_per_device": args.rate, "seconds": args.seconds, "frame": f"{WIDTH}x{HEIGHT}", "detector": "sim:0", "runs": runs},
    )  # fmt: skip


if __name__ == "__main__":
    main()
