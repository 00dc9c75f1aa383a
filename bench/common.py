"""Shared benchmark helpers: pin to one core, time with warm-up and repeats, write JSON with versions,
start a throwaway redis-server."""

from __future__ import annotations

import json
import os
import platform
import shutil
import socket
import statistics
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

#: The real models and data (never in the repository): ``$ARCLOUD_SHARED``, else ``shared/`` beside the project.
SHARED = Path(os.environ.get("ARCLOUD_SHARED", Path(__file__).resolve().parents[2] / "shared"))


def pin_to_one_core() -> int | None:
    """Run this process on one CPU core (Linux); returns the core or None when not possible."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if hasattr(os, "sched_setaffinity"):
        core = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {core})
        return core
    return None


def time_calls(call: Callable[[int], object], *, warmup: int, repeats: int) -> list[float]:
    """Seconds per call of ``call(i)`` for ``repeats`` calls after ``warmup`` untimed ones."""
    for i in range(warmup):
        call(i)
    times = []
    for i in range(warmup, warmup + repeats):
        started = time.perf_counter()
        call(i)
        times.append(time.perf_counter() - started)
    return times


def summary_ms(times_s: list[float]) -> dict[str, float]:
    """Median and spread in milliseconds."""
    ms = sorted(t * 1000 for t in times_s)
    q = statistics.quantiles(ms, n=10)
    return {
        "median_ms": round(statistics.median(ms), 3),
        "p10_ms": round(q[0], 3),
        "p90_ms": round(q[-1], 3),
        "min_ms": round(ms[0], 3),
        "max_ms": round(ms[-1], 3),
        "n": len(ms),
    }


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment(packages: tuple[str, ...] = ("arcloud", "numpy", "scipy")) -> dict[str, object]:
    versions = {"python": platform.python_version()}
    for name in packages:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "source": source_version(),
        "versions": versions,
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count(), "platform": platform.platform()},
    }


def source_version() -> dict[str, object]:
    """The checkout measured: its commit and whether ``src/`` differs from it (None outside git)."""

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", *args], capture_output=True, text=True, check=True, cwd=Path(__file__).parent)
        except (OSError, subprocess.CalledProcessError):
            return None
        return done.stdout.strip()

    commit = git("rev-parse", "HEAD")
    changed = git("status", "--porcelain", "--", "../src")
    return {"commit": commit, "src_changed": None if changed is None else bool(changed)}


def write_json(path: Path, payload: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2) + "\n")
    print(f"wrote {path}")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Redis:
    """A throwaway redis-server on a free loopback port, no persistence."""

    def __init__(self) -> None:
        binary = shutil.which("redis-server")
        if binary is None:
            raise SystemExit("redis-server not found on PATH (apt-get install redis-server)")
        self.port = free_port()
        self.dir = tempfile.TemporaryDirectory(prefix="arcloud-bench-redis-")
        self.process = subprocess.Popen(
            [
                binary,
                "--port",
                str(self.port),
                "--bind",
                "127.0.0.1",
                "--save",
                "",
                "--appendonly",
                "no",
                "--dir",
                self.dir.name,
                "--loglevel",
                "warning",
            ],
            stdout=subprocess.DEVNULL,
        )
        self.url = f"redis://127.0.0.1:{self.port}/0"
        import redis

        self.client = redis.Redis.from_url(self.url)
        deadline = time.monotonic() + 10
        while True:
            try:
                self.client.ping()
                break
            except redis.ConnectionError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)
        self.version = self.client.info("server")["redis_version"]

    def stop(self) -> None:
        self.client.close()
        self.process.terminate()
        self.process.wait(10)
        self.dir.cleanup()


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) process ``pid`` has used so far (Linux /proc); 0 once it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (the API's worker processes)."""
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as stat:
                    parents[int(entry)] = int(stat.read().rsplit(")", 1)[1].split()[1])
            except OSError:
                continue
    found, frontier = [], [pid]
    while frontier:
        parent = frontier.pop()
        kids = [p for p, pp in parents.items() if pp == parent]
        found += kids
        frontier += kids
    return found


def redis_counters(client: Any) -> tuple[dict[str, int], int, int]:
    """(calls by command, bytes in, bytes out) of the Redis server so far."""
    stats = client.info("commandstats")
    calls = {name.removeprefix("cmdstat_"): int(v["calls"]) for name, v in stats.items()}
    net = client.info("stats")
    return calls, int(net["total_net_input_bytes"]), int(net["total_net_output_bytes"])


class ServiceMeter:
    """What a service spends between ``start`` and ``per_frame``: CPU of the API process (``api_pid``), of
    its worker processes (its descendants when started) and of the redis-server; Redis commands and bytes
    in and out. ``per_frame(frames, request_bytes)`` divides them by the frames processed meanwhile.
    ``worker_pids``: the worker processes, when they are not the API's (``serve --workers 0``); the API is
    then ``api_pid`` and its descendants (``serve --api-processes N``)."""

    def __init__(self, api_pid: int, redis: Redis, *, worker_pids: Sequence[int] | None = None) -> None:
        self.api_pid, self.redis = api_pid, redis
        self.worker_pids = None if worker_pids is None else list(worker_pids)
        self.api: list[int] = [api_pid]
        self.workers: list[int] = []
        self._cpu: dict[str, float] = {}
        self._calls: dict[str, int] = {}
        self._bytes = (0, 0)

    def _cpu_now(self) -> dict[str, float]:
        return {
            "api": sum(cpu_s(p) for p in self.api),
            "workers": sum(cpu_s(p) for p in self.workers),
            "redis": cpu_s(self.redis.process.pid),
        }

    def start(self) -> None:
        if self.worker_pids is None:
            self.workers = children(self.api_pid)
        else:
            self.api, self.workers = [self.api_pid, *children(self.api_pid)], self.worker_pids
        self._cpu = self._cpu_now()
        self._calls, *counted = redis_counters(self.redis.client)
        self._bytes = (counted[0], counted[1])

    def per_frame(self, frames: int, request_bytes: float) -> dict[str, Any]:
        cpu_after = self._cpu_now()
        calls_after, in_after, out_after = redis_counters(self.redis.client)
        frames = max(1, frames)
        per_command = {c: round((calls_after[c] - self._calls.get(c, 0)) / frames, 2) for c in calls_after}
        return {
            "redis_commands": round(sum(per_command.values()), 1),
            "redis_commands_by_name": {c: v for c, v in sorted(per_command.items(), key=lambda kv: -kv[1]) if v >= 0.05},
            "redis_bytes_in": round((in_after - self._bytes[0]) / frames),
            "redis_bytes_out": round((out_after - self._bytes[1]) / frames),
            "cpu_ms": {part: round((cpu_after[part] - self._cpu[part]) / frames * 1000, 2) for part in cpu_after},
            "request_bytes": round(request_bytes),
        }


class FramePoster:
    """POSTs protobuf frames to a service over keep-alive HTTP/1.1 connections, one a thread, with the
    standard library's ``http.client``: a load generator on the service's own cores should take as little
    of them as it can (httpx took 4.1 ms of CPU a frame in bench_throughput, this 1.0 ms; measured
    on this 2-core VM). A connection the server closed between two POSTs is opened again and the POST sent
    once more (the service takes a frame once: a second POST of it is a duplicate)."""

    def __init__(self, url: str, *, timeout_s: float = 120.0) -> None:
        from urllib.parse import urlsplit

        parts = urlsplit(url)
        if parts.scheme != "http" or parts.hostname is None or parts.port is None:
            raise ValueError(f"FramePoster: expected http://host:port, got {url!r}")
        self.host, self.port, self.timeout_s = parts.hostname, parts.port, timeout_s
        self._local = threading.local()

    def post(self, path: str, body: bytes) -> tuple[int, bytes]:
        """(status, response body) of POSTing ``body`` (``application/x-protobuf``) to ``path``."""
        import http.client

        for attempt in (1, 2):
            connection = getattr(self._local, "connection", None)
            if connection is None:
                connection = self._local.connection = http.client.HTTPConnection(self.host, self.port, timeout=self.timeout_s)
            try:
                connection.request("POST", path, body, {"content-type": "application/x-protobuf"})
                response = connection.getresponse()
                return response.status, response.read()
            except (http.client.RemoteDisconnected, BrokenPipeError, ConnectionResetError):
                connection.close()
                self._local.connection = None
                if attempt == 2:
                    raise
        raise AssertionError("unreachable")


#: Settings for a service whose ingest a bench measures: no keys, no rate limits, a queue it cannot fill; the load
#: generator's one address (its key, with no keys) may hold a map's every upload, as its many devices would.
INGEST_ONLY_ENV = {
    "ARCLOUD_AUTH": "none",
    "ARCLOUD_KEY_RATE_PER_S": "0",
    "ARCLOUD_MAP_FRAME_RATE_PER_S": "0",
    "ARCLOUD_MAX_UPLOADS_PER_KEY": "16",
    "ARCLOUD_MAX_QUEUED_FRAMES": "100000",
    "ARCLOUD_MAX_QUEUED_FRAMES_PER_MAP": "100000",
    "ARCLOUD_LOG_LEVEL": "WARNING",
}


class ServeProcess:
    """``arcloud serve --redis URL --workers N --detector SPEC [--api-processes A]`` in its own process on a free
    loopback port, with ``env`` (``ARCLOUD_*``) over this process's environment; ready (``/readyz`` 200) when built."""

    def __init__(
        self, redis_url: str, *, workers: int, detector: str, env: dict[str, str], ready_s: float = 180.0, api_processes: int = 1
    ) -> None:
        import sys

        import httpx

        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        command = [sys.executable, "-m", "arcloud.cli", "serve", "--redis", redis_url, "--workers", str(workers)]
        command += ["--detector", detector, "--port", str(self.port), "--api-processes", str(api_processes)]
        self.process = subprocess.Popen(command, env={**os.environ, **env})
        deadline = time.time() + ready_s
        while time.time() < deadline:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.25)
        self.stop()
        raise SystemExit(f"the service did not become ready in {ready_s:g} s")

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(60)
