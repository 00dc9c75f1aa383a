"""Ingest: validated frames into a ``FrameQueue``, the step run on them by workers, counts out.

Who runs the step depends on what the composition root gave the app:

- worker threads in this process (``FrameWorker`` loops sharing the store and the detector): the
  embedded deployment (``arcloud serve``), where the queue is in memory;
- worker processes started here (``WorkerPool``), each with its own adapters: ``arcloud serve --redis
  URL --workers N``;
- neither: the workers run elsewhere (containers, ``arcloud worker``) and read the shared queue.

The pose of each device's last queued frame is kept in this process (``devices``: viewers draw the
devices' cameras from it). Counts per map: frames accepted and failed (the queue's), processed (the store's set of recorded
frames); pending is accepted - processed - failed. Service-wide counters for ``/metrics`` are the
queue's (``QueueStats``: shared by every worker for a shared queue).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

from arcloud.core.types import Frame
from arcloud.ports import FrameQueue, FrameStatus, ObjectStore, QueueFull, QueueStats
from arcloud.service.devices import RecentDevices
from arcloud.service.pool import WorkerPool
from arcloud.service.worker import LIVE_WORKER_S, FrameWorker, consumer_name, of_host

log = logging.getLogger(__name__)

DRAIN_POLL_S = 0.02  # how often ``stop`` looks whether the in-process workers emptied the queue


@dataclass(frozen=True, slots=True)
class Accepted:
    """What ``submit`` did: ``queued``, or ``duplicate`` (the frame was accepted before; not queued)."""

    map_id: str
    device_id: str
    frame_id: str
    status: Literal["queued", "duplicate"]


@dataclass(frozen=True, slots=True)
class MapCounts:
    """Frames of one map."""

    accepted: int
    processed: int
    failed: int

    @property
    def pending(self) -> int:
        return max(0, self.accepted - self.processed - self.failed)


class Ingest:
    """Where the API hands validated frames. ``threads``: workers to run in threads of this process;
    ``pool``: worker processes to start and stop with the ingest. Every method is synchronous and
    thread-safe; the app calls them from a thread pool."""

    def __init__(
        self,
        queue: FrameQueue,
        store: ObjectStore,
        *,
        threads: Sequence[FrameWorker] = (),
        pool: WorkerPool | None = None,
        host_workers: int = 0,
    ) -> None:
        self.queue = queue
        self.store = store
        self.workers = list(threads)
        self.pool = pool
        self.host_workers = host_workers  # worker processes another process of this host runs (serve --api-processes)
        self._threads: list[threading.Thread] = []
        self._stop_threads = threading.Event()
        self._stopping = False
        self.devices = RecentDevices()

    def start(self) -> None:
        self.queue.prepare()
        self._stop_threads.clear()
        for i, worker in enumerate(self.workers):
            thread = threading.Thread(target=worker.run, args=(self._stop_threads,), name=f"arcloud-worker-{i}", daemon=True)
            thread.start()
            self._threads.append(thread)
        if self.pool is not None:
            self.pool.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop accepting, let the worker threads finish what is queued and the worker processes their
        frame in hand (up to ``timeout_s``), then return."""
        self._stopping = True
        deadline = time.monotonic() + timeout_s
        if self._threads:
            while time.monotonic() < deadline and any(t.is_alive() for t in self._threads) and self.queue.stats().queue_depth > 0:
                time.sleep(DRAIN_POLL_S)
            left = self.queue.stats().queue_depth
            self._stop_threads.set()
            for thread in self._threads:
                thread.join(max(0.0, deadline - time.monotonic()))
            alive = [t.name for t in self._threads if t.is_alive()]
            if alive or left:
                log.warning(
                    "ingest stopped with %d frames queued or in progress; %s still busy", left, ", ".join(alive) or "no worker"
                )
            self._threads = []
        if self.pool is not None:
            self.pool.stop(max(0.0, deadline - time.monotonic()))

    def submit(self, frame: Frame, message: Any = None) -> Accepted:
        """Queue a validated frame (``message``: the protobuf ``Frame`` it came as); raises ``QueueFull``."""
        if self._stopping:
            raise QueueFull("the service is shutting down")
        queued = self.queue.put(frame, message)
        if queued:
            self.devices.record(frame)
        return Accepted(frame.map_id, frame.device_id, frame.frame_id, "queued" if queued else "duplicate")

    def counts(self, map_id: str) -> MapCounts:
        accepted, failed = self.queue.map_counts(map_id)
        processed = self.store.count_frames(map_id) if accepted else 0
        return MapCounts(accepted, processed, failed)

    def frame_status(self, map_id: str, device_id: str, frame_id: str) -> FrameStatus | None:
        """The status of the frame (device_id, frame_id) of the map; None when it was never accepted."""
        return self.queue.frame_status(map_id, f"{device_id}/{frame_id}")

    def known_map(self, map_id: str) -> bool:
        """Whether any frame of the map was accepted (without creating anything)."""
        return self.queue.known_map(map_id)

    def forget_map(self, map_id: str) -> None:
        """Drop the map's counts (after its objects were deleted)."""
        self.queue.forget_map(map_id)
        self.devices.forget_map(map_id)

    def stats(self) -> QueueStats:
        return self.queue.stats()

    def live_workers(self) -> int:
        """Workers taking frames: this process's worker threads alive, else the queue's consumers with a
        heartbeat in the last ``LIVE_WORKER_S`` (every host's, for a shared queue)."""
        if self.workers:
            return sum(t.is_alive() for t in self._threads)
        return len(self.queue.live_consumers(LIVE_WORKER_S))

    def workers_health(self) -> WorkersReport:
        """Whether the frames accepted get processed (``/healthz/workers``; not part of this process's readiness):
        the queue's own checks (Redis: it answers, the consumer group exists), the detector of the worker threads,
        and the workers: threads alive; worker processes alive, each with a fresh heartbeat (a worker beats only
        while its reads succeed); workers elsewhere: some fresh heartbeat (``host_workers`` of this host, when another
        process runs them); and the live workers all of one set of map settings (``settings``)."""
        checks = self.queue.health()
        if self.workers:
            alive = [w.consumer for w, t in zip(self.workers, self._threads) if t.is_alive()]
            total = len(self.workers)
            checks["detector"] = "ok"  # the threads' detector, loaded before the app started
            checks["workers"] = "ok" if len(alive) == total else f"{len(alive)} of {total} worker threads alive"
            return WorkersReport(checks, alive, total)
        if self.pool is not None:
            pids = [p.pid for p in self.pool.processes if p.is_alive()]
            total = self.pool.size
            reading: list[str] = []
            if len(pids) < total:
                checks["workers"] = f"{len(pids)} of {total} worker processes alive"
            elif all(v == "ok" for v in checks.values()):
                beating = set(self.queue.live_consumers(LIVE_WORKER_S))
                reading = sorted(consumer_name(pid) for pid in pids if consumer_name(pid) in beating)
                checks["workers"] = (
                    "ok"
                    if len(reading) == total
                    else f"{len(reading)} of {total} worker processes reading (heartbeat in {LIVE_WORKER_S:.0f} s)"
                )
                checks["settings"] = self._settings_check()
            else:
                checks["workers"] = "unknown: the queue is not ready"
            return WorkersReport(checks, reading, total)
        live: list[str] = []
        expected = self.host_workers or None
        if all(v == "ok" for v in checks.values()):
            live = self.queue.live_consumers(LIVE_WORKER_S)
            ours = [name for name in live if of_host(name)]
            if expected is not None and len(ours) < expected:
                checks["workers"] = (
                    f"{len(ours)} of {expected} worker processes of this host reading (heartbeat in {LIVE_WORKER_S:.0f} s)"
                )
            else:
                checks["workers"] = "ok" if live else f"no worker heartbeat in {LIVE_WORKER_S:.0f} s (frames wait in the stream)"
            checks["settings"] = self._settings_check()
        else:
            checks["workers"] = "unknown: the queue is not ready"
        return WorkersReport(checks, live, expected)

    def _settings_check(self) -> str:
        """``ok`` when the live workers map with one set of map settings (``worker_settings``), else how many sets and
        whose: each fails the frames of the maps the others made (other ``Params`` alone are only logged: a release
        that adds one would fail this check through every rollout)."""
        given = self.queue.live_settings(LIVE_WORKER_S)
        kinds: dict[str, list[str]] = {}
        for name, settings in sorted(given.items()):
            kinds.setdefault(json.dumps(settings.get("map"), sort_keys=True), []).append(name)
        if len(kinds) <= 1:
            return "ok"
        groups = "; ".join(", ".join(names) for names in kinds.values())
        return (
            f"the live workers map with {len(kinds)} different map settings ({groups}): each fails the frames of the "
            "maps the others made; run them all with the same --params"
        )


@dataclass(frozen=True, slots=True)
class WorkersReport:
    """``Ingest.workers_health``: check name -> ``ok`` or what is wrong; the workers taking frames (consumer
    names); how many this process started (None: workers run elsewhere, any one will do)."""

    checks: dict[str, str]
    live: list[str]
    expected: int | None

    @property
    def ok(self) -> bool:
        return all(v == "ok" for v in self.checks.values())


__all__ = ["Accepted", "Ingest", "MapCounts", "WorkersReport"]
