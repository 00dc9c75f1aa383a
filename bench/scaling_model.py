"""What N devices at F frames a second need, from what one frame was measured to cost here (docs/scaling.md).

Inputs (written by the benches on this machine):
- ``bench/results/step.json``: the real model's session and the step, median ms a frame on one core (shown
  beside the workers' measured CPU, which also holds decoding, the Redis client and the codec);
- ``bench/results/throughput.json``: per 640 x 480 frame through the service on Redis with the real model (its
  as-fast run): API, worker and Redis CPU ms, Redis commands and bytes in and out, the upload's size.

``--scaling FILE``: instead, one ``bench_scaling.py`` result (e.g. a run on many cores): its service run at the
most workers over many maps (as fast as taken), whose workers' CPU holds the session as those cores ran it.

The model: frames/s = devices x rate; worker cores = frames/s x worker CPU s / ``CORE_BUSY``; API cores =
frames/s x API CPU s / ``CORE_BUSY``; Redis shards = frames/s x Redis CPU s / ``REDIS_BUSY`` (a shard is one
core, kept 70 % busy at most); network into the API = frames/s x upload bytes; into and out of Redis =
frames/s x the bytes Redis took in and gave out a frame (the queued frame, whose PNG depth travels as its
pixels, the step's reads and writes). Each resource's limit for one instance (one Redis, one API process,
one stream shard) says what breaks first.

    .venv/bin/python bench/scaling_model.py [--devices 1000,100000] [--rate 1]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).parent / "results"
REDIS_BUSY = 0.7  # the share of a Redis core a shard may use
CORE_BUSY = 0.8  # the share of a worker or API core in use at peak


def load(name: str) -> dict[str, Any]:
    path = RESULTS / name
    if not path.is_file():
        raise SystemExit(f"{path}: run bench/{name.replace('.json', '')} first (see docs/scaling.md)")
    data: dict[str, Any] = json.loads(path.read_text())
    return data


def costs() -> dict[str, float]:
    """Per frame, from the benches: seconds of CPU, bytes, commands."""
    step, throughput = load("step.json"), load("throughput.json")
    if step.get("detector") is None:
        raise SystemExit("step.json has no detector timing (the model was not in ../shared when it ran)")
    per_frame = throughput["service"].get("per_frame")
    if per_frame is None:
        raise SystemExit("throughput.json has no per-frame costs: run bench/bench_throughput.py again")
    return {
        "session_s": step["detector"]["median_ms"] / 1000,
        "step_s": step["step"]["median_ms"] / 1000,
        "upload_bytes": throughput["upload_bytes"],
        **service_costs(per_frame),
    }


def service_costs(per_frame: dict[str, Any]) -> dict[str, float]:
    """A service run's ``per_frame`` (``common.ServiceMeter``): CPU seconds of workers, API and Redis, Redis
    commands and bytes."""
    return {
        "worker_s": per_frame["cpu_ms"]["workers"] / 1000,
        "api_s": per_frame["cpu_ms"]["api"] / 1000,
        "redis_s": per_frame["cpu_ms"]["redis"] / 1000,
        "redis_commands": per_frame["redis_commands"],
        "redis_bytes_in": per_frame["redis_bytes_in"],
        "redis_bytes_out": per_frame["redis_bytes_out"],
    }


def costs_of_scaling(path: Path) -> dict[str, float]:
    """Per frame, from a ``bench_scaling.py`` result: the service at its most workers over many maps."""
    data: dict[str, Any] = json.loads(path.read_text())
    row = max(data["service"]["rows"], key=lambda r: r["workers"])
    per_frame = row["many_maps"]["as_fast"]["per_frame"]
    ceiling = {r["processes"]: r for r in data["ceiling"]["rows"]} if data.get("ceiling") else {}
    session = ceiling.get(row["workers"], {}).get("session_ms_median", float("nan"))
    return {
        "session_s": session / 1000,
        "step_s": float("nan"),
        "upload_bytes": per_frame["request_bytes"],
        **service_costs(per_frame),
    }


def plan(devices: int, rate: float, c: dict[str, float]) -> dict[str, float]:
    frames = devices * rate
    return {
        "devices": devices,
        "frames_per_s": frames,
        "worker_cores": math.ceil(frames * c["worker_s"] / CORE_BUSY),
        "api_cores": math.ceil(frames * c["api_s"] / CORE_BUSY),
        "redis_shards": math.ceil(frames * c["redis_s"] / REDIS_BUSY),
        "redis_commands_per_s": round(frames * c["redis_commands"]),
        "api_ingress_mbit_s": round(frames * c["upload_bytes"] * 8 / 1e6, 1),
        "redis_ingress_mbit_s": round(frames * c["redis_bytes_in"] * 8 / 1e6, 1),
        "redis_egress_mbit_s": round(frames * c["redis_bytes_out"] * 8 / 1e6, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--devices", default="1000,100000")
    parser.add_argument("--rate", type=float, default=1.0, help="frames a second per device (default 1)")
    parser.add_argument("--scaling", type=Path, default=None, help="a bench_scaling.py result instead (see above)")
    args = parser.parse_args()
    c = costs() if args.scaling is None else costs_of_scaling(args.scaling)
    step = "" if math.isnan(c["step_s"]) else f" and the step {c['step_s'] * 1000:.1f} ms on one core"
    print(
        f"per frame (measured): workers {c['worker_s'] * 1000:.1f} ms of CPU (the session alone {c['session_s'] * 1000:.1f} ms"
        f"{step}), API {c['api_s'] * 1000:.2f} ms, Redis {c['redis_s'] * 1000:.2f} ms "
        f"and {c['redis_commands']:.0f} commands, {c['redis_bytes_in'] / 1e3:.0f} kB into Redis and {c['redis_bytes_out'] / 1e3:.0f} kB "
        f"out, {c['upload_bytes'] / 1e3:.0f} kB upload\n"
    )
    print(
        "| devices | frames/s | worker cores | API cores | Redis shards | Redis commands/s | into the API | into Redis | out of Redis |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for n in (int(v) for v in args.devices.split(",")):
        p = plan(n, args.rate, c)
        print(
            f"| {n:,} | {p['frames_per_s']:,.0f} | {p['worker_cores']:,} | {p['api_cores']:,} | {p['redis_shards']:,} | "
            f"{p['redis_commands_per_s']:,} | {p['api_ingress_mbit_s']:,} Mbit/s | {p['redis_ingress_mbit_s']:,} Mbit/s | "
            f"{p['redis_egress_mbit_s']:,} Mbit/s |"
        )
    one_redis = REDIS_BUSY / c["redis_s"]
    one_api = CORE_BUSY / c["api_s"]
    one_worker = CORE_BUSY / c["worker_s"]
    print(
        f"\nlimits of one instance: a Redis shard {one_redis:,.0f} frames/s, an API core {one_api:,.0f} frames/s, "
        f"a worker core {one_worker:,.1f} frames/s"
    )


if __name__ == "__main__":
    main()
