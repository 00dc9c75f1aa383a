"""Ingest: validated frames in, ``process_frame`` run off the event loop, counts out.

Two implementations of one small interface (``Ingest``):

- ``EmbeddedIngest`` (the default, ``arcloud serve``): one process, a bounded in-process queue and a pool
  of worker threads sharing the store. Nothing survives a restart (the embedded store does not either).
- ``RedisIngest`` (``arcloud serve --redis URL``): the API appends each validated frame, as protobuf
  bytes, to ONE Redis Stream (``arcloud:ingest``) read by a consumer group of worker processes
  (``arcloud.service.worker``). Durable: a frame is acknowledged (and deleted from the stream) only after
  its commit; a worker that dies leaves it pending and another claims it.

Why one global stream rather than a stream per map: a consumer group lives on one stream, and
XREADGROUP reads a fixed list of streams, while maps appear at run time; per-map streams would need a
registry of maps, a group per map and a reader per (worker, map). One stream gives one group, one
pending list to claim from, and first-come-first-served across maps. Frames of one map are processed in
parallel by several workers (the per-object locks and space claims of the step make that safe). The
scale-out path beyond one Redis primary is N shard streams (map -> shard by hash), each with its group.

Counts per map: the set of accepted frame keys (a frame posted twice is queued once, unless it failed
before), the store's set of processed frames, the set of failed (dead-lettered) frames; pending is
accepted - processed - failed. Global counters for ``/metrics`` (accepted, processed, failed, the step
latency histogram) live in the process (embedded) or in one Redis hash (shared by every worker).
"""

from __future__ import annotations

import bisect
import logging
import queue
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, Protocol

from arcloud.core.types import Frame, Params
from arcloud.errors import ArcloudError, LockTimeout, StaleLease, StoreUnavailable
from arcloud.ports import Detector, ObjectStore, UpdatePublisher
from arcloud.service.frames import stream_message
from arcloud.stores import keys
from arcloud.stores.keys import INGEST_STREAM

if TYPE_CHECKING:
    import redis

log = logging.getLogger(__name__)

# --- Redis keys of the ingest (templates in arcloud.stores.keys) --------------------------------------
DEAD_LETTER_STREAM = keys.INGEST_DEAD_LETTER_STREAM  # STREAM  frames given up on, with the reason
INGEST_STATS = keys.INGEST_STATS  # HASH    service-wide counters and the step latency histogram
WORKERS = keys.INGEST_WORKERS  # HASH    consumer name -> last heartbeat (Unix seconds)
accepted_key = keys.ingest_accepted_key  # SET of the frame keys accepted for a map (map's hash tag)
failed_key = keys.ingest_failed_key  # SET of the frame keys of a map that were dead-lettered
HEARTBEAT_S = 1.0  # how often a worker writes its heartbeat
LIVE_WORKER_S = 10.0  # a worker whose heartbeat is older is presumed gone


#: Upper bounds (seconds) of the step latency histogram's buckets (+Inf implied).
LATENCY_BUCKETS_S: tuple[float, ...] = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)

#: Errors after which a step is worth trying again at once: nothing was written.
RETRYABLE = (LockTimeout, StaleLease)


class QueueFull(ArcloudError):
    """The ingest queue holds ``max_queued_frames``; the client should retry later (HTTP 503)."""


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


@dataclass(slots=True)
class IngestSnapshot:
    """Service-wide counters for ``/metrics``. ``latency_counts`` are per bucket (not cumulative), the
    last one for +Inf."""

    accepted: int = 0
    duplicates: int = 0
    processed: int = 0
    skipped: int = 0  # re-deliveries of frames processed before (idempotent: not counted as processed)
    failed: int = 0
    claimed: int = 0  # frames taken over from a worker that stopped answering
    retried: int = 0
    queue_depth: int = 0
    latency_counts: list[int] = field(default_factory=lambda: [0] * (len(LATENCY_BUCKETS_S) + 1))
    latency_sum_s: float = 0.0

    @property
    def latency_count(self) -> int:
        return sum(self.latency_counts)


def latency_bucket(seconds: float) -> int:
    """Index of the histogram bucket holding ``seconds``."""
    return bisect.bisect_left(LATENCY_BUCKETS_S, seconds)


class Ingest(Protocol):
    """Where the API hands validated frames. Every method is synchronous and thread-safe; the app
    calls them from a thread pool."""

    def submit(self, frame: Frame, message: Any) -> Accepted:
        """Queue a validated frame (``message`` is its protobuf ``Frame``); raises ``QueueFull``."""
        ...

    def counts(self, map_id: str) -> MapCounts: ...

    def known_map(self, map_id: str) -> bool:
        """Whether any frame of the map was accepted (without creating anything)."""
        ...

    def forget_map(self, map_id: str) -> None:
        """Drop the map's counts (after its objects were deleted)."""
        ...

    def snapshot(self) -> IngestSnapshot: ...

    def ready(self) -> dict[str, str]:
        """Check name -> "ok" or what is wrong."""
        ...

    def start(self) -> None: ...

    def stop(self, timeout_s: float = 10.0) -> None: ...


def run_step(
    frame: Frame,
    detector: Detector,
    store: ObjectStore,
    params: Params,
    publisher: UpdatePublisher | None,
    *,
    attempts: int,
) -> tuple[Any, int]:
    """``process_frame``, tried again (at most ``attempts`` times) when locks could not be taken or a
    lease went stale: nothing was written then. Returns the result and how many retries it took."""
    from arcloud.core.step import process_frame  # scipy: loaded with the first frame, not at import
    for attempt in range(1, attempts + 1):
        try:
            return process_frame(frame, detector, store, params, publisher), attempt - 1
        except RETRYABLE as exc:
            if attempt == attempts:
                raise
            log.warning("map %s frame %s: %s; trying again (%d/%d)", frame.map_id, frame.key, exc, attempt, attempts)
    raise AssertionError("unreachable")


class EmbeddedIngest:
    """A bounded queue and ``workers`` threads running the step in this process."""

    def __init__(
        self,
        store: ObjectStore,
        detector: Detector,
        params: Params,
        publisher: UpdatePublisher | None = None,
        *,
        workers: int = 2,
        max_queued_frames: int = 1000,
        attempts: int = 5,
    ) -> None:
        self.store = store
        self.detector = detector
        self.params = params
        self.publisher = publisher
        self.workers = workers
        self.attempts = attempts
        self._queue: queue.Queue[Frame | None] = queue.Queue(maxsize=max_queued_frames)
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._accepted: dict[str, set[str]] = {}
        self._failed: dict[str, set[str]] = {}
        self._stats = IngestSnapshot()
        self._in_flight = 0
        self._stopping = False

    def start(self) -> None:
        for i in range(self.workers):
            thread = threading.Thread(target=self._work, name=f"arcloud-worker-{i}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop accepting, let the workers finish what is queued (up to ``timeout_s``), then return."""
        self._stopping = True
        deadline = time.monotonic() + timeout_s
        for _ in self._threads:
            while True:
                try:
                    self._queue.put(None, timeout=0.1)  # after every queued frame
                    break
                except queue.Full:
                    if time.monotonic() > deadline:
                        break
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        alive = [t.name for t in self._threads if t.is_alive()]
        if alive:
            log.warning("ingest stopped with %d frames queued; %s still busy", self._queue.qsize(), ", ".join(alive))
        self._threads = []

    def submit(self, frame: Frame, message: Any = None) -> Accepted:
        if self._stopping:
            raise QueueFull("the service is shutting down")
        with self._lock:
            accepted = self._accepted.setdefault(frame.map_id, set())
            failed = self._failed.get(frame.map_id, set())
            if frame.key in accepted and frame.key not in failed:
                self._stats.duplicates += 1
                return Accepted(frame.map_id, frame.device_id, frame.frame_id, "duplicate")
            try:
                self._queue.put_nowait(frame)
            except queue.Full:
                raise QueueFull(f"{self._queue.maxsize} frames are queued; try again later") from None
            accepted.add(frame.key)
            failed.discard(frame.key)
            self._stats.accepted += 1
        return Accepted(frame.map_id, frame.device_id, frame.frame_id, "queued")

    def _work(self) -> None:
        while True:
            frame = self._queue.get()
            if frame is None:
                return
            with self._lock:
                self._in_flight += 1
            started = time.perf_counter()
            try:
                result, retries = run_step(frame, self.detector, self.store, self.params, self.publisher, attempts=self.attempts)
            except Exception:
                log.exception("map %s frame %s (device %s) failed", frame.map_id, frame.key, frame.device_id)
                with self._lock:
                    self._in_flight -= 1
                    self._failed.setdefault(frame.map_id, set()).add(frame.key)
                    self._stats.failed += 1
                continue
            elapsed_s = time.perf_counter() - started
            with self._lock:
                self._in_flight -= 1
                self._stats.retried += retries
                if result.skipped:
                    self._stats.skipped += 1
                else:
                    self._stats.processed += 1
                    self._stats.latency_counts[latency_bucket(elapsed_s)] += 1
                    self._stats.latency_sum_s += elapsed_s

    def counts(self, map_id: str) -> MapCounts:
        with self._lock:
            accepted = len(self._accepted.get(map_id, ()))
            failed = len(self._failed.get(map_id, ()))
        processed = self.store.count_frames(map_id) if accepted else 0
        return MapCounts(accepted, processed, failed)

    def known_map(self, map_id: str) -> bool:
        with self._lock:
            return bool(self._accepted.get(map_id))

    def forget_map(self, map_id: str) -> None:
        with self._lock:
            self._accepted.pop(map_id, None)
            self._failed.pop(map_id, None)

    def snapshot(self) -> IngestSnapshot:
        with self._lock:
            snap = IngestSnapshot(**{f: getattr(self._stats, f) for f in IngestSnapshot.__dataclass_fields__})
            snap.latency_counts = list(self._stats.latency_counts)
            snap.queue_depth = self._queue.qsize() + self._in_flight
        return snap

    def ready(self) -> dict[str, str]:
        alive = sum(t.is_alive() for t in self._threads)
        return {"workers": "ok" if alive == self.workers else f"{alive} of {self.workers} worker threads alive"}


# Lua: record a frame key as accepted; 1 when it is new or failed before (queue it), 0 for a duplicate.
_ACCEPT_LUA = """
local added = redis.call('SADD', KEYS[1], ARGV[1])
local refailed = redis.call('SREM', KEYS[2], ARGV[1])
if added == 1 or refailed == 1 then return 1 end
return 0
"""


class RedisIngest:
    """The producer side of the Redis Streams ingest (the API process). Workers run elsewhere
    (``arcloud.service.worker``): in processes this one starts (``pool``) or in other containers."""

    def __init__(
        self,
        client: redis.Redis,
        store: ObjectStore,
        *,
        group: str = "arcloud-workers",
        max_queued_frames: int = 1000,
        pool: Any = None,
    ) -> None:
        self.client = client
        self.store = store
        self.group = group
        self.max_queued_frames = max_queued_frames
        self.pool = pool
        self._accept = client.register_script(_ACCEPT_LUA)

    def start(self) -> None:
        with _redis_errors("create the consumer group"):
            ensure_group(self.client, self.group)
        if self.pool is not None:
            self.pool.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        if self.pool is not None:
            self.pool.stop(timeout_s)

    def submit(self, frame: Frame, message: Any) -> Accepted:
        with _redis_errors("queue the frame"):
            depth = int(self.client.xlen(INGEST_STREAM))
            if depth >= self.max_queued_frames:
                raise QueueFull(f"{depth} frames are queued; try again later")
            fresh = self._accept(keys=[accepted_key(frame.map_id), failed_key(frame.map_id)], args=[frame.key])
            if not fresh:
                self.client.hincrby(INGEST_STATS, "duplicates", 1)
                return Accepted(frame.map_id, frame.device_id, frame.frame_id, "duplicate")
            try:
                fields = {"map_id": frame.map_id, "frame_key": frame.key, "accepted_at_s": repr(time.time()), "frame": stream_message(message, frame).SerializeToString()}
                pipe = self.client.pipeline(transaction=False)
                pipe.xadd(INGEST_STREAM, fields)  # type: ignore[arg-type]
                pipe.hincrby(INGEST_STATS, "accepted", 1)
                pipe.execute()
            except BaseException:
                self.client.srem(accepted_key(frame.map_id), frame.key)  # not queued: let a retry through
                raise
        return Accepted(frame.map_id, frame.device_id, frame.frame_id, "queued")

    def counts(self, map_id: str) -> MapCounts:
        with _redis_errors("read the map's counts"):
            pipe = self.client.pipeline(transaction=False)
            pipe.scard(accepted_key(map_id))
            pipe.scard(failed_key(map_id))
            accepted, failed = (int(v) for v in pipe.execute())
        processed = self.store.count_frames(map_id)
        return MapCounts(accepted, processed, failed)

    def known_map(self, map_id: str) -> bool:
        with _redis_errors("look the map up"):
            return bool(self.client.exists(accepted_key(map_id)))

    def forget_map(self, map_id: str) -> None:
        with _redis_errors("forget the map"):
            self.client.delete(accepted_key(map_id), failed_key(map_id))

    def snapshot(self) -> IngestSnapshot:
        with _redis_errors("read the ingest counters"):
            pipe = self.client.pipeline(transaction=False)
            pipe.hgetall(INGEST_STATS)
            pipe.xlen(INGEST_STREAM)
            raw, depth = pipe.execute()
        snap = parse_stats(raw)
        snap.queue_depth = int(depth)
        return snap

    def ready(self) -> dict[str, str]:
        checks = {}
        try:
            self.client.ping()
            checks["redis"] = "ok"
        except Exception as exc:  # noqa: BLE001 - readiness reports, never raises
            checks["redis"] = f"unreachable: {type(exc).__name__}"
        if self.pool is not None:
            alive, total = self.pool.alive(), self.pool.size
            checks["workers"] = "ok" if alive == total else f"{alive} of {total} worker processes alive"
        elif checks["redis"] == "ok":
            live = len(live_workers(self.client))
            checks["workers"] = "ok" if live else f"no worker heartbeat in {LIVE_WORKER_S:.0f} s (frames wait in the stream)"
        return checks


def live_workers(client: redis.Redis, max_age_s: float = LIVE_WORKER_S) -> list[str]:
    """Consumers whose heartbeat is at most ``max_age_s`` old."""
    now = time.time()
    return sorted(_text_of(name) for name, seen in client.hgetall(WORKERS).items() if now - float(seen) <= max_age_s)


def _text_of(value: bytes | str) -> str:
    return value.decode() if isinstance(value, bytes) else value


def ensure_group(client: redis.Redis, group: str) -> None:
    """Create the consumer group on the ingest stream (and the stream) unless it exists. It starts at
    the stream's beginning so that frames queued before any worker started are read."""
    import redis as redis_lib

    try:
        client.xgroup_create(INGEST_STREAM, group, id="0", mkstream=True)
    except redis_lib.ResponseError as exc:
        if "BUSYGROUP" not in str(exc):
            raise


STAT_FIELDS = ("accepted", "duplicates", "processed", "skipped", "failed", "claimed", "retried")


def latency_field(bucket: int) -> str:
    return f"latency_le_{LATENCY_BUCKETS_S[bucket]:g}" if bucket < len(LATENCY_BUCKETS_S) else "latency_le_inf"


def parse_stats(raw: Mapping[bytes | str, bytes | str]) -> IngestSnapshot:
    """The stats hash as a snapshot (missing fields are 0)."""
    values = {(k.decode() if isinstance(k, bytes) else k): (v.decode() if isinstance(v, bytes) else v) for k, v in raw.items()}
    snap = IngestSnapshot(**{name: int(values.get(name, 0)) for name in STAT_FIELDS})
    snap.latency_counts = [int(values.get(latency_field(b), 0)) for b in range(len(LATENCY_BUCKETS_S) + 1)]
    snap.latency_sum_s = float(values.get("latency_sum_s", 0.0))
    return snap


class _redis_errors:
    """Map redis-py's connection errors to ``StoreUnavailable`` at the boundary."""

    def __init__(self, doing: str) -> None:
        self.doing = doing

    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> bool:
        if exc is None:
            return False
        import redis as redis_lib

        if isinstance(exc, (redis_lib.ConnectionError, redis_lib.TimeoutError)):
            raise StoreUnavailable(f"cannot {self.doing}: Redis unreachable ({exc})") from exc
        return False


__all__ = [
    "Accepted",
    "DEAD_LETTER_STREAM",
    "EmbeddedIngest",
    "INGEST_STATS",
    "INGEST_STREAM",
    "WORKERS",
    "Ingest",
    "IngestSnapshot",
    "LATENCY_BUCKETS_S",
    "MapCounts",
    "QueueFull",
    "RedisIngest",
    "accepted_key",
    "ensure_group",
    "failed_key",
    "latency_bucket",
    "live_workers",
    "parse_stats",
]
