"""Ingest workers on Redis Streams: each process loads its detector once, then reads frames through the
consumer group, runs the step and acknowledges.

One loop per worker (``StreamWorker.run``):

0. A thread writes the worker's heartbeat (``arcloud:ingest:workers``) every second.
1. Every ``claim_interval_s``: XAUTOCLAIM one entry idle for ``claim_min_idle_s`` (its worker died or
   hangs), read how often it was delivered (XPENDING); beyond ``max_deliveries`` it is a poison frame:
   moved to the dead-letter stream, recorded as failed, acknowledged. Otherwise processed here.
2. XREADGROUP one new entry (blocking ``read_block_s``), process it.
3. Processing: decode (protobuf -> validated ``Frame``; an undecodable entry is dead-lettered at once),
   ``process_frame`` (retried in place when locks time out or a lease went stale: nothing was written),
   then one pipeline: XACK + XDEL (acknowledged entries leave the stream, so its length is the backlog)
   and the service counters. Any other error leaves the entry pending: it is claimed again after
   ``claim_min_idle_s``, until ``max_deliveries``.

A frame delivered twice (a worker died after its commit but before XACK) is not counted twice: the
store's commit records the frame key atomically and refuses a second one (the step reports ``skipped``).

``WorkerPool`` starts N such processes (multiprocessing, spawn) and restarts those that die; SIGTERM
stops a worker after its current frame.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from arcloud.allocator import keep_freed_memory
from arcloud.core.types import Frame, Params
from arcloud.errors import InvalidInput
from arcloud.ports import Detector, ObjectStore, UpdatePublisher
from arcloud.service.ingest import (
    DEAD_LETTER_STREAM,
    HEARTBEAT_S,
    INGEST_STATS,
    INGEST_STREAM,
    WORKERS,
    accepted_key,
    ensure_group,
    failed_key,
    latency_bucket,
    latency_field,
    run_step,
)

if TYPE_CHECKING:
    import redis

    from arcloud.service.settings import Settings

log = logging.getLogger(__name__)

DetectorFactory = Callable[[], Detector]


def decode_frame(payload: bytes) -> Frame:
    """A validated ``Frame`` from protobuf bytes; ``InvalidInput`` when they are not one."""
    from google.protobuf.message import DecodeError

    from arcloud.proto.arcloud.v1 import arcloud_pb2
    from arcloud.proto.convert import frame_from_proto

    try:
        message = arcloud_pb2.Frame.FromString(payload)
    except DecodeError as exc:
        raise InvalidInput("frame", "a protobuf arcloud.v1.Frame", f"{len(payload)} undecodable bytes") from exc
    return frame_from_proto(message)


def consumer_name() -> str:
    """``<host>-<pid>``: unique among the group's live consumers."""
    return f"{socket.gethostname()}-{os.getpid()}"


def _text(value: bytes | str | None) -> str:
    return value.decode(errors="replace") if isinstance(value, bytes) else (value or "")


class StreamWorker:
    """One consumer of the ingest stream's group."""

    def __init__(
        self,
        client: redis.Redis,
        store: ObjectStore,
        detector: Detector,
        params: Params,
        publisher: UpdatePublisher | None = None,
        *,
        group: str = "arcloud-workers",
        consumer: str | None = None,
        claim_min_idle_s: float = 60.0,
        claim_interval_s: float = 5.0,
        max_deliveries: int = 5,
        read_block_s: float = 1.0,
        attempts: int = 3,
    ) -> None:
        self.client = client
        self.store = store
        self.detector = detector
        self.params = params
        self.publisher = publisher
        self.group = group
        self.consumer = consumer or consumer_name()
        self.claim_min_idle_ms = max(1, int(claim_min_idle_s * 1000))
        self.claim_interval_s = claim_interval_s
        self.max_deliveries = max_deliveries
        self.read_block_ms = max(1, int(read_block_s * 1000))
        self.attempts = attempts
        self._next_claim = 0.0
        self._claim_cursor = "0-0"
        self._in_hand: bytes | str | None = None  # the entry being processed, kept fresh by the heartbeat

    def run(self, stop: threading.Event) -> None:
        """Work until ``stop`` is set; the frame in hand is finished first."""
        ensure_group(self.client, self.group)
        log.info("worker %s reading %s as group %s", self.consumer, INGEST_STREAM, self.group)
        beating = threading.Event()
        heart = threading.Thread(target=self._beat, args=(beating,), name="arcloud-heartbeat", daemon=True)
        heart.start()
        try:
            while not stop.is_set():
                try:
                    self.poll_once()
                except Exception:  # noqa: BLE001 - Redis away for a moment: wait and go on
                    log.exception("worker %s: polling failed; retrying in 1 s", self.consumer)
                    stop.wait(1.0)
        finally:
            beating.set()
            heart.join()
            try:
                self.client.hdel(WORKERS, self.consumer)
            except Exception:  # noqa: BLE001 - leaving anyway; the heartbeat goes stale
                log.debug("worker %s: heartbeat not removed", self.consumer, exc_info=True)
        log.info("worker %s stopped", self.consumer)

    def _beat(self, done: threading.Event) -> None:
        """Write this worker's heartbeat, and reset the idle time of the entry in hand (XCLAIM JUSTID to
        itself: no new delivery), often enough that a long step is never taken for an abandoned one."""
        interval_s = min(HEARTBEAT_S, self.claim_min_idle_ms / 1000 / 3)
        while True:
            try:
                self.client.hset(WORKERS, self.consumer, repr(time.time()))
                in_hand = self._in_hand
                if in_hand is not None:
                    self.client.xclaim(INGEST_STREAM, self.group, self.consumer, 0, [in_hand], justid=True)
            except Exception:  # noqa: BLE001 - Redis away: the loop logs it; try again next beat
                log.debug("worker %s: heartbeat failed", self.consumer, exc_info=True)
            if done.wait(interval_s):
                return

    def poll_once(self) -> int:
        """Claim one abandoned entry when due, else read one new entry (blocking). Returns how many
        entries were handled."""
        now = time.monotonic()
        if now >= self._next_claim:
            if self.claim_abandoned():
                return 1  # there may be more: look again next time round
            self._next_claim = now + self.claim_interval_s
        reply = self.client.xreadgroup(self.group, self.consumer, {INGEST_STREAM: ">"}, count=1, block=self.read_block_ms)
        handled = 0
        for _stream, entries in reply or []:
            for entry_id, fields in entries:
                self.handle(entry_id, fields, deliveries=1)
                handled += 1
        return handled

    def claim_abandoned(self) -> bool:
        """Take over one entry left pending by another consumer for ``claim_min_idle_s``."""
        next_cursor, entries, *_deleted = self.client.xautoclaim(
            INGEST_STREAM, self.group, self.consumer, self.claim_min_idle_ms, start_id=self._claim_cursor, count=1
        )
        self._claim_cursor = _text(next_cursor) or "0-0"
        claimed = False
        for entry_id, fields in entries:
            if not fields:
                continue  # deleted while pending (Redis drops it from the pending list)
            pending = self.client.xpending_range(INGEST_STREAM, self.group, min=entry_id, max=entry_id, count=1)
            deliveries = int(pending[0]["times_delivered"]) if pending else self.max_deliveries + 1
            self.client.hincrby(INGEST_STATS, "claimed", 1)
            log.warning("worker %s claimed entry %s (delivery %d)", self.consumer, _text(entry_id), deliveries)
            self.handle(entry_id, fields, deliveries=deliveries)
            claimed = True
        return claimed

    def handle(self, entry_id: bytes | str, fields: dict[bytes, bytes], *, deliveries: int) -> str:
        """Process one entry; returns what became of it: processed, skipped, dead or pending."""
        map_id = _text(fields.get(b"map_id"))
        frame_key = _text(fields.get(b"frame_key"))
        if deliveries > self.max_deliveries:
            if map_id and frame_key and self.store.is_frame_done(map_id, frame_key):
                # A slow delivery finished after the entry was claimed again: it counts once, as processed.
                pipe = self.client.pipeline(transaction=False)
                pipe.xack(INGEST_STREAM, self.group, entry_id)
                pipe.xdel(INGEST_STREAM, entry_id)
                pipe.hincrby(INGEST_STATS, "skipped", 1)
                pipe.execute()
                return "skipped"
            self.dead_letter(entry_id, fields, f"delivered {deliveries} times (max {self.max_deliveries})", deliveries)
            return "dead"
        try:
            frame = decode_frame(fields.get(b"frame", b""))
        except InvalidInput as exc:
            self.dead_letter(entry_id, fields, f"undecodable: {exc}", deliveries)
            return "dead"
        started = time.perf_counter()
        self._in_hand = entry_id
        try:
            result, retries = run_step(frame, self.detector, self.store, self.params, self.publisher, attempts=self.attempts)
        except Exception:  # noqa: BLE001 - left pending: claimed again later, dead-lettered in the end
            log.exception("worker %s: map %s frame %s failed (delivery %d of %d); left pending",
                          self.consumer, map_id, frame_key, deliveries, self.max_deliveries)
            return "pending"
        finally:
            self._in_hand = None
        elapsed_s = time.perf_counter() - started
        pipe = self.client.pipeline(transaction=False)
        pipe.xack(INGEST_STREAM, self.group, entry_id)
        pipe.xdel(INGEST_STREAM, entry_id)
        if retries:
            pipe.hincrby(INGEST_STATS, "retried", retries)
        if result.skipped:
            pipe.hincrby(INGEST_STATS, "skipped", 1)
        else:
            pipe.hincrby(INGEST_STATS, "processed", 1)
            pipe.hincrby(INGEST_STATS, latency_field(latency_bucket(elapsed_s)), 1)
            pipe.hincrbyfloat(INGEST_STATS, "latency_sum_s", elapsed_s)
        pipe.execute()
        log.debug("worker %s: map %s frame %s %s in %.3f s", self.consumer, map_id, frame_key,
                  "skipped" if result.skipped else "processed", elapsed_s)
        return "skipped" if result.skipped else "processed"

    def dead_letter(self, entry_id: bytes | str, fields: dict[bytes, bytes], reason: str, deliveries: int) -> None:
        """Move an entry to the dead-letter stream (with the reason), record its frame as failed."""
        map_id = _text(fields.get(b"map_id"))
        frame_key = _text(fields.get(b"frame_key"))
        log.error("worker %s: map %s frame %s (entry %s) dead-lettered: %s", self.consumer, map_id or "?", frame_key or "?", _text(entry_id), reason)
        dead = dict(fields)
        dead.update({b"reason": reason.encode(), b"entry_id": _text(entry_id).encode(), b"deliveries": str(deliveries).encode(),
                     b"consumer": self.consumer.encode(), b"failed_at_s": repr(time.time()).encode()})
        pipe = self.client.pipeline(transaction=False)
        pipe.xadd(DEAD_LETTER_STREAM, dead)  # type: ignore[arg-type]
        pipe.xack(INGEST_STREAM, self.group, entry_id)
        pipe.xdel(INGEST_STREAM, entry_id)
        pipe.hincrby(INGEST_STATS, "failed", 1)
        pipe.execute()
        if map_id and frame_key and self.client.sismember(accepted_key(map_id), frame_key):
            self.client.sadd(failed_key(map_id), frame_key)  # failed frames are a subset of the accepted ones


# --- processes ---------------------------------------------------------------------------------------
def configure_logging(level: str) -> None:
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(processName)s %(name)s: %(message)s")


def worker_publisher(settings: Settings) -> UpdatePublisher | None:
    """A Zenoh client session for a worker: to ``zenoh_connect`` (a router), else to the API's listen
    endpoints. None when Zenoh is off."""
    if settings.zenoh_mode == "off":
        return None
    from arcloud.events.zenoh import ZenohPublisher, connectable

    endpoints = settings.zenoh_connect or connectable(settings.zenoh_listen)
    if not endpoints:
        log.warning("zenoh is on but no endpoint to connect to: this worker publishes no events")
        return None
    return ZenohPublisher(mode="client", connect=endpoints)


def run_worker(
    settings: Settings, *, detector_factory: DetectorFactory | None = None, stop: threading.Event | None = None, processes: int = 1
) -> None:
    """One worker in this process until SIGTERM/SIGINT (or ``stop``). ``processes``: how many worker
    processes share this machine's cores (the detector's threads default to this one's share)."""
    import redis as redis_lib

    from arcloud.service.components import build_detector, build_store, close_quietly, threads_per_process

    if settings.embedded:
        raise InvalidInput("store", "a Redis URL for stream workers", "memory")
    keep_freed_memory()
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, lambda *_: stop.set())
    params = settings.make_params()
    store = build_store(settings.store, cell_m=params.index_cell_m)
    if detector_factory is not None:
        detector = detector_factory()
    else:
        detector = build_detector(settings.detector, threads=settings.detector_threads or threads_per_process(processes))
    publisher = worker_publisher(settings)
    client = redis_lib.Redis.from_url(settings.store, socket_connect_timeout=5.0, socket_timeout=max(30.0, 2 * settings.read_block_s + 5))
    try:
        StreamWorker(
            client, store, detector, params, publisher,
            group=settings.consumer_group,
            claim_min_idle_s=settings.claim_min_idle_s,
            claim_interval_s=settings.claim_interval_s,
            max_deliveries=settings.max_deliveries,
            read_block_s=settings.read_block_s,
        ).run(stop)
    finally:
        for thing in (publisher, store, client):
            close_quietly(thing)


def _process_main(settings: Settings, detector_factory: DetectorFactory | None, processes: int) -> None:
    configure_logging(settings.log_level)
    run_worker(settings, detector_factory=detector_factory, processes=processes)


#: A worker that dies sooner than this after its start failed to start: the next start waits, twice as
#: long each time (up to ``RESTART_MAX_DELAY_S``), so a broken setup does not spawn a process a second.
QUICK_EXIT_S = 10.0
RESTART_MAX_DELAY_S = 60.0


class WorkerPool:
    """``size`` worker processes (spawned: no state inherited), restarted when they die; those that die
    right after starting are restarted with a growing delay.

    ``detector_factory``: a picklable callable building each worker's detector (default: the settings'
    spec)."""

    def __init__(self, settings: Settings, size: int, *, detector_factory: DetectorFactory | None = None, restart: bool = True) -> None:
        self.settings = settings
        self.size = size
        self.detector_factory = detector_factory
        self.restart = restart
        self.processes: list[multiprocessing.process.BaseProcess] = []
        self._context = multiprocessing.get_context("spawn")
        self._stopping = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._started_at: dict[int, float] = {}
        self._quick_exits: dict[int, int] = {}  # consecutive quick exits per slot
        self._restart_at: dict[int, float] = {}

    def _spawn(self, index: int) -> multiprocessing.process.BaseProcess:
        process = self._context.Process(
            target=_process_main, args=(self.settings, self.detector_factory, self.size), name=f"arcloud-worker-{index}", daemon=False
        )
        process.start()
        return process

    def start(self) -> None:
        self._stopping.clear()
        self.processes = [self._spawn(i) for i in range(self.size)]
        self._started_at = dict.fromkeys(range(self.size), time.monotonic())
        log.info("started %d worker processes: %s", self.size, ", ".join(str(p.pid) for p in self.processes))
        if self.restart:
            self._supervisor = threading.Thread(target=self._supervise, name="arcloud-worker-supervisor", daemon=True)
            self._supervisor.start()

    def _supervise(self) -> None:
        while not self._stopping.wait(1.0):
            self.tend(time.monotonic())

    def tend(self, now: float) -> None:
        """Restart the workers found dead (the supervisor calls this every second)."""
        for i, process in enumerate(self.processes):
            if process.is_alive() or self._stopping.is_set():
                continue
            if i not in self._restart_at:  # seen dead for the first time
                quick = now - self._started_at.get(i, now) < QUICK_EXIT_S
                self._quick_exits[i] = self._quick_exits.get(i, 0) + 1 if quick else 0
                delay_s = min(RESTART_MAX_DELAY_S, 2.0 ** self._quick_exits[i]) if quick else 0.0
                self._restart_at[i] = now + delay_s
                log.error("worker process %s exited with %s%s; starting another in %.0f s (its frames are claimed after %.0f s)",
                          process.pid, process.exitcode, " right after starting" if quick else "", delay_s, self.settings.claim_min_idle_s)
            if now >= self._restart_at[i]:
                del self._restart_at[i]
                self.processes[i] = self._spawn(i)
                self._started_at[i] = now

    def alive(self) -> int:
        return sum(p.is_alive() for p in self.processes)

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM every worker (each finishes its frame), wait ``timeout_s``, then kill the rest."""
        self._stopping.set()
        if self._supervisor is not None:
            self._supervisor.join()
        for process in self.processes:
            if process.is_alive():
                process.terminate()
        deadline = time.monotonic() + timeout_s
        for process in self.processes:
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                log.warning("worker process %s did not stop in %.0f s; killing it", process.pid, timeout_s)
                process.kill()
                process.join()
        self.processes = []


__all__ = ["StreamWorker", "WorkerPool", "consumer_name", "decode_frame", "run_worker", "worker_publisher"]


def healthy(settings: Settings, host: str | None = None, max_age_s: float = 10.0) -> bool:
    """Whether a worker on ``host`` (default: this one) wrote a heartbeat in the last ``max_age_s``."""
    import redis as redis_lib

    from arcloud.service.ingest import live_workers

    prefix = f"{host or socket.gethostname()}-"
    with redis_lib.Redis.from_url(settings.store, socket_connect_timeout=3.0, socket_timeout=3.0) as client:
        return any(name.startswith(prefix) for name in live_workers(client, max_age_s))


def main(argv: list[str] | None = None) -> int:
    """``python -m arcloud.service.worker``: one worker from ``ARCLOUD_*`` settings until SIGTERM;
    ``--healthcheck``: exit 0 when a worker of this host is alive (container health checks)."""
    import argparse

    from arcloud.service.settings import Settings

    parser = argparse.ArgumentParser(prog="python -m arcloud.service.worker", description=main.__doc__)
    parser.add_argument("--healthcheck", action="store_true", help="check this host's worker heartbeat and exit")
    args = parser.parse_args(argv)
    settings = Settings()
    if args.healthcheck:
        return 0 if healthy(settings) else 1
    configure_logging(settings.log_level)
    from arcloud.detectors.factory import check_model_file

    try:
        check_model_file(settings.detector)
    except InvalidInput as exc:  # a clear line in the container's log, not a traceback
        log.error("%s", exc)
        return 2
    run_worker(settings)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
