"""The ports: the interfaces adapters implement. The step's own (``Detector``, ``MapStore``, ``Lease``,
``UpdatePublisher``) are defined in ``arcloud.core.ports``; a service needs more:

- ``ObjectStore`` (embedded ``stores.memory``, ``stores.redis``), made of narrow ports: the step's ``MapStore``;
  ``ChangeLog``, each map's change log, written by the commit, read by the event stream and the Zenoh feed;
  ``MapReader``, listing and counting a map's objects; ``MapCatalog``, the maps, their headers, deleting one,
  the health check.
- ``FrameQueue`` (embedded ``stores.memory_queue``, Redis Streams ``stores.redis_queue``): validated frames from
  the API to the workers that run the step, bounded by ``QueueLimits`` (frames and bytes, overall and per map;
  how long settled frames are remembered), made of ``FrameIntake`` (the API's side: put, records, per-map
  counts), ``FrameConsumer`` (the workers' side: take, claim, settle, heartbeats) and ``QueueMonitor`` (counters,
  health, live consumers).
- ``KeyStore``: the API keys (``arcloud.access.ApiKey``), hashed (a JSON file ``stores.file_api_keys``,
  Redis ``stores.redis_api_keys``).
- ``RateLimiter``: token buckets shared by every API process (``stores.memory_rate``, ``stores.redis_rate``).
- ``ViewerPasses``: the viewer's tickets and sessions (``arcloud.access.ViewerGrant``), hashed, each kept until it
  expires (``stores.memory_viewer_passes``, ``stores.redis_viewer_passes``).
- ``MapArchive``: a map as one file and back, on any ``ObjectStore`` (``stores.snapshot``).
- ``DeviceAlignments``: each device's ``device_from_map`` per map (``core.conventions``), shared by every API
  process (``stores.memory_alignments``, ``stores.redis_alignments``).

The service (``arcloud.service``) talks to these and never to an adapter; ``arcloud.tools.wiring``
chooses the adapters.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np

from arcloud.access import ApiKey, ViewerGrant
from arcloud.core.change import ChangesSince
from arcloud.core.header import MapHeader
from arcloud.core.ports import Detector, Lease, MapStore, UpdatePublisher
from arcloud.core.types import Frame, MapObject, ObjectMeta, Params
from arcloud.errors import ArcloudError, InvalidInput, StoreError

__all__ = [
    "DEFAULT_CHANGE_LOG_ENTRIES",
    "LATENCY_BUCKETS_S",
    "SETTLED_OUTCOMES",
    "WAIT_BUCKETS_S",
    "ChangeLog",
    "Detector",
    "DeviceAlignments",
    "FailedFrame",
    "FrameConsumer",
    "FrameIntake",
    "FrameQueue",
    "FrameTimings",
    "Histogram",
    "KeyStore",
    "Lease",
    "MapArchive",
    "MapBeingDeleted",
    "MapCatalog",
    "MapDeletion",
    "MapReader",
    "MapStore",
    "ObjectMeta",
    "ObjectStore",
    "QueueFull",
    "QueueLimits",
    "QueueMonitor",
    "QueueStats",
    "QueuedFrame",
    "RateLimiter",
    "RetiredObject",
    "UpdatePublisher",
    "ViewerPasses",
    "latency_bucket",
]


# --- the change log ----------------------------------------------------------------------------------
#: How many entries a map's change log keeps by default (the oldest leave first; Redis trims about as many).
DEFAULT_CHANGE_LOG_ENTRIES = 10_000


class ChangeLog(Protocol):
    """Each map's change log (``core.change``): the events of every commit, appended by the commit itself
    (``MapStore.commit``), numbered by the map's version, the latest ``change_log_entries`` kept; and how far
    the log was announced over Zenoh (``service.change_feed``). Both object stores are one."""

    def changes_since(self, map_id: str, after: int, limit: int) -> ChangesSince:
        """The entries after version ``after``, oldest first, at most ``limit``; ``complete`` False when some
        of those are no longer kept (the reader re-reads the map). ``limit`` 0 reads the map's version alone."""
        ...

    def published_version(self, map_id: str) -> int:
        """The version up to which the map's log was published (0: none)."""
        ...

    def mark_published(self, map_id: str, version: int) -> None:
        """Record that the log was published up to ``version`` (never lowered: a lower one is ignored)."""
        ...


# --- the object store --------------------------------------------------------------------------------
#: How long a map's history keeps a retired object by default (``ObjectStore.retired_objects``): a week.
DEFAULT_RETIRED_HISTORY_S = 7 * 86400.0
#: The most retired objects a map's history keeps (the oldest leave first), whatever their age.
RETIRED_HISTORY_MAX_PER_MAP = 10_000


def check_store_settings(
    cell_m: float, change_log_entries: int, frame_record_retention_s: float, retired_history_s: float
) -> None:
    """Refuse an object store's settings that no store can keep (``InvalidInput``): the same on every adapter."""
    for name, value, bound, holds in (
        ("cell_m", cell_m, "> 0", cell_m > 0),
        ("change_log_entries", change_log_entries, ">= 1", change_log_entries >= 1),
        ("frame_record_retention_s", frame_record_retention_s, "> 0", frame_record_retention_s > 0),
        ("retired_history_s", retired_history_s, "> 0", retired_history_s > 0),
    ):
        if not holds:
            raise InvalidInput(name, bound, value)


@dataclass(frozen=True, eq=False, slots=True)
class RetiredObject:
    """An object the step retired (seen gone: ``core.step.count_misses``), as it was when it left the map,
    and when it left (Unix seconds)."""

    meta: ObjectMeta
    retired_at_s: float


#: How long a store keeps the record of a map's deletion after its last progress (``ObjectStore.map_deletion``):
#: a client polling it sees it end, and a deletion whose process died stops refusing the map's frames after it.
DELETION_KEPT_S = 86400.0


@dataclass(frozen=True, slots=True)
class MapDeletion:
    """A map's deletion as the store records it while ``ObjectStore.delete_map`` runs and ``DELETION_KEPT_S``
    after: the objects the map held when it began, how many of them and how many store keys are gone (keys:
    Redis's objects, index cells, leases; 0 embedded), when it began, last went on and ended (Unix s)."""

    map_id: str
    objects: int
    objects_removed: int
    keys_removed: int
    started_at_s: float
    updated_at_s: float
    finished_at_s: float | None = None

    @property
    def done(self) -> bool:
        return self.finished_at_s is not None


class MapBeingDeleted(StoreError):
    """The map is being deleted (``deletion`` says how far it got): its frames and reads are refused until
    it is done (HTTP 409)."""

    def __init__(self, deletion: MapDeletion) -> None:
        self.deletion = deletion
        super().__init__(
            f"map {deletion.map_id} is being deleted: {deletion.objects_removed} of {deletion.objects} objects removed"
        )


class MapReader(Protocol):
    """A map's objects as they are, read for listing, counting and exporting (no locks, no writes)."""

    def list_objects(self, map_id: str) -> list[MapObject]:
        """Every object of the map, by id."""
        ...

    def list_meta(self, map_id: str) -> list[ObjectMeta]:
        """Every object of the map without its voxels (cheaper than ``list_objects``), by id."""
        ...

    def object_meta(self, map_id: str, ids: Sequence[int]) -> list[ObjectMeta]:
        """These objects without their voxels, in the order given; ids that do not exist are skipped."""
        ...

    def object_ids(self, map_id: str) -> list[int]:
        """The ids of the map's objects, sorted: a page of a listing reads these, then only its own objects."""
        ...

    def count_objects(self, map_id: str) -> int:
        """How many objects the map holds (0 for an unknown map)."""
        ...

    def count_frames(self, map_id: str) -> int:
        """How many frames were recorded as processed in this map (a counter: records expiring do not lower it)."""
        ...

    def retired_objects(self, map_id: str) -> list[RetiredObject]:
        """The map's history: the objects retired (a ``MapChange``'s ``retired``) within the store's
        ``retired_history_s`` (at most ``RETIRED_HISTORY_MAX_PER_MAP``), latest first. ``delete_map``
        removes it."""
        ...


class MapCatalog(Protocol):
    """The maps a store holds: each one's header (the settings its data is written under), the list of them,
    deleting one, and whether the store answers."""

    #: The blob format this store writes and reads (``stores.codec.FORMAT_VERSION``), part of a map's header.
    codec_version: int

    def open_map(self, map_id: str, header: MapHeader) -> MapHeader:
        """The map's header: the one stored, or ``header``, written now when the map has none (atomically:
        of two first writers, one wins and both get its header). ``delete_map`` removes it."""
        ...

    def map_header(self, map_id: str) -> MapHeader | None:
        """The map's stored header; None when nothing opened the map yet."""
        ...

    def list_maps(self) -> dict[str, float]:
        """Every map opened (and not deleted): map id -> when its objects last changed (Unix seconds; when it
        was opened, before any)."""
        ...

    def delete_map(self, map_id: str) -> int:
        """Remove a map and everything under it (objects, header, change log, history); returns the number of
        objects removed. Its version and its object id counter stay, the version one on (the deletion is a change
        of the map, an empty log its only entry): a map made again under the id goes on from them, so no version
        and no object id is given twice. A reader back with a version of the deleted map finds the log incomplete
        and reads the map again (``ChangesSince``), however far the map made again got. The map leaves the list
        and loses its header first, then its objects go a bounded batch at a time, the progress recorded
        (``map_deletion``); called again on a map whose deletion stopped half way, it goes on."""
        ...

    def map_deletion(self, map_id: str) -> MapDeletion | None:
        """The map's deletion, going on or ended within ``DELETION_KEPT_S``; None when there is none."""
        ...

    def ping(self) -> None:
        """Return when the store answers; raise ``StoreUnavailable`` otherwise."""
        ...


class ObjectStore(MapStore, ChangeLog, MapReader, MapCatalog, Protocol):
    """Everything an object store is, for the composition root: the step's ``MapStore``, the maps' change logs
    (``ChangeLog``), reading (``MapReader``) and the maps themselves (``MapCatalog``). A part of the service
    that needs less names the narrow port.

    Every method is safe to call from many threads (and, for a shared store, many processes)."""


# --- the frame queue ---------------------------------------------------------------------------------
#: Upper bounds (seconds) of the step latency histogram's buckets (+Inf implied).
LATENCY_BUCKETS_S: tuple[float, ...] = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
#: Upper bounds (seconds) of the wait histograms' buckets (queue wait, lock wait; +Inf implied): from a
#: lock taken at once (one Redis round trip, under a millisecond) to a backlog of a minute.
WAIT_BUCKETS_S: tuple[float, ...] = (
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0
)  # fmt: skip


def latency_bucket(seconds: float) -> int:
    """Index of the histogram bucket holding ``seconds`` (upper bounds inclusive)."""
    return bisect.bisect_left(LATENCY_BUCKETS_S, seconds)


@dataclass(slots=True)
class Histogram:
    """Observations (seconds) counted in buckets of upper bounds ``bounds_s`` (inclusive), a last bucket
    for +Inf: ``counts`` per bucket (not cumulative, ``len(bounds_s) + 1`` of them) and their ``sum_s``."""

    bounds_s: tuple[float, ...]
    counts: list[int]
    sum_s: float = 0.0

    @classmethod
    def empty(cls, bounds_s: tuple[float, ...]) -> Histogram:
        return cls(bounds_s, [0] * (len(bounds_s) + 1))

    def bucket(self, seconds: float) -> int:
        """Index of the bucket holding ``seconds``."""
        return bisect.bisect_left(self.bounds_s, seconds)

    def observe(self, seconds: float) -> None:
        self.counts[self.bucket(seconds)] += 1
        self.sum_s += seconds

    @property
    def count(self) -> int:
        return sum(self.counts)

    def copy(self) -> Histogram:
        return Histogram(self.bounds_s, list(self.counts), self.sum_s)


@dataclass(frozen=True, slots=True)
class FrameTimings:
    """What one processed frame took and waited (seconds), for the queue's histograms (``QueueStats``):
    ``step_s``, the step (detect to commit, its retries included); ``queue_wait_s``, from the frame's
    acceptance until a worker took it (None: not counted, as for a frame delivered again, whose wait holds
    its earlier deliveries; the API's and the worker's clocks must agree); ``lock_wait_s``, in the store's
    lock and claim calls (a round trip each when nothing else holds the objects or cells)."""

    step_s: float = 0.0
    queue_wait_s: float | None = None
    lock_wait_s: float = 0.0


class QueueFull(ArcloudError):
    """The frame would take the queue (or its map's share of it) past a limit, or the service is stopping;
    retry later (HTTP 503). ``limit``: the ``QueueLimits`` field that refused it (None: stopping)."""

    def __init__(self, message: str, limit: str | None = None) -> None:
        super().__init__(message)
        self.limit = limit


#: Records of settled frames (and the stores' processed-frame marks) looked at per call for expired ones:
#: the sweep rides on the calls of the map (accept, acknowledge, commit), so its work per call is bounded.
RECORDS_SWEPT_PER_CALL = 100
#: How long a settled frame is remembered by default (``QueueLimits.frame_record_retention_s``, and the
#: stores' processed-frame marks): a day, far beyond any redelivery (``max_deliveries`` x ``claim_min_idle_s``).
DEFAULT_FRAME_RECORD_RETENTION_S = 86400.0


@dataclass(frozen=True, slots=True)
class QueueLimits:
    """How much a ``FrameQueue`` holds, and how long it remembers; the same on every adapter.

    A frame counts as one frame and as the bytes the queue holds of it (Redis: the stream entry's frame
    bytes; embedded: its arrays) from its acceptance until it is acknowledged or dead-lettered; a frame
    whose step failed and waits for another delivery still counts. ``put`` refuses a frame that
    would take the queue past ``max_queued_frames`` or ``max_queued_bytes``, or its map past
    ``max_queued_frames_per_map`` or ``max_queued_bytes_per_map``, so one map cannot fill the queue for
    every other.

    A settled (processed or failed) frame's record, its status and its part in the duplicate rule, is
    kept ``frame_record_retention_s`` and then dropped (each later call on the map looks at
    ``RECORDS_SWEPT_PER_CALL`` records for expired ones; past the retention a record counts as gone
    already): the frame is then unknown (``frame_status`` None) and posting it again queues
    it as a new frame. The map's counts are counters and do not shrink. Failed frames keep their payload
    (for ``retry_failed``) in at most ``max_dead_letters`` dead letters of at most
    ``max_dead_letter_bytes`` together, the oldest dropped first."""

    max_queued_frames: int = 1000
    max_queued_bytes: int = 2**30
    max_queued_frames_per_map: int = 250
    max_queued_bytes_per_map: int = 2**28
    frame_record_retention_s: float = DEFAULT_FRAME_RECORD_RETENTION_S
    max_dead_letters: int = 10_000
    max_dead_letter_bytes: int = 2**28

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if not value > 0:
                raise InvalidInput(f"QueueLimits.{name}", "> 0", value)

    def refusal(
        self, map_id: str, frame_bytes: int, *, frames: int, queued_bytes: int, map_frames: int, map_bytes: int
    ) -> QueueFull | None:
        """Whether a frame of ``frame_bytes`` fits beside what is queued (``frames``, ``queued_bytes``
        overall, ``map_frames``, ``map_bytes`` of its map): None, or the ``QueueFull`` that refuses it.
        The overall limits are checked first (when they refuse, every map is refused). The Redis queue
        checks the same in ``lua/accept_frame.lua``."""
        for name, held, adding in (
            ("max_queued_frames", frames, 1),
            ("max_queued_bytes", queued_bytes, frame_bytes),
            ("max_queued_frames_per_map", map_frames, 1),
            ("max_queued_bytes_per_map", map_bytes, frame_bytes),
        ):
            if held + adding > getattr(self, name):
                return self.full(name, map_id, held, frame_bytes)
        return None

    def full(self, limit: str, map_id: str, held: int, frame_bytes: int) -> QueueFull:
        """The ``QueueFull`` of ``limit`` (a field name) holding ``held`` (frames or bytes)."""
        bound = getattr(self, limit)
        if limit.startswith("max_queued_bytes") and frame_bytes > bound:  # the service's settings rule this out
            return QueueFull(f"this frame's {_mb(frame_bytes)} is more than {limit} ({_mb(bound)}): it never fits", limit)
        if limit == "max_queued_frames":
            text = f"the queue holds {held} frames ({limit} {bound})"
        elif limit == "max_queued_frames_per_map":
            text = f"map {map_id} has {held} frames queued ({limit} {bound})"
        else:
            whose = "the queue holds" if limit == "max_queued_bytes" else f"map {map_id} has"
            text = f"{whose} {_mb(held)} queued; this frame's {_mb(frame_bytes)} would pass {limit} ({_mb(bound)})"
        return QueueFull(f"{text}; try again later", limit)


def not_retriable(map_id: str, frame_key: str, status: str | None) -> InvalidInput:
    """Why ``FrameQueue.retry_failed`` cannot queue the frame again: it is ``status`` (None: the map has no
    record of it), or it failed but its dead letter was dropped."""
    if status == "failed":
        return InvalidInput("frame", "a failed frame whose dead letter is kept", f"{frame_key}: dropped (max_dead_letters)")
    what = status or "no record (never accepted, or settled longer ago than frame_record_retention_s)"
    return InvalidInput("frame", f"a failed frame of map {map_id}", f"{frame_key}: {what}")


def _mb(n_bytes: int) -> str:
    return f"{n_bytes / 1e6:.1f} MB"


@dataclass(slots=True)
class QueueStats:
    """Service-wide counters of a ``FrameQueue`` (every worker's, for a shared queue). ``latency_counts``
    are per bucket of ``LATENCY_BUCKETS_S`` (not cumulative), the last one for +Inf. ``queue_wait`` and
    ``lock_wait``: the processed frames' waits (``FrameTimings``) in buckets of ``WAIT_BUCKETS_S``."""

    accepted: int = 0
    duplicates: int = 0
    processed: int = 0
    redelivered: int = 0  # deliveries of frames processed before (idempotent: not counted as processed)
    failed: int = 0
    claimed: int = 0  # frames taken over from a consumer that stopped answering
    retried: int = 0  # steps tried again after a lock timeout or a stale lease
    queue_depth: int = 0  # frames queued or in progress
    queued_bytes: int = 0  # what the queue holds of them (``QueueLimits``)
    latency_counts: list[int] = field(default_factory=lambda: [0] * (len(LATENCY_BUCKETS_S) + 1))
    latency_sum_s: float = 0.0
    queue_wait: Histogram = field(default_factory=lambda: Histogram.empty(WAIT_BUCKETS_S))
    lock_wait: Histogram = field(default_factory=lambda: Histogram.empty(WAIT_BUCKETS_S))
    #: Frames settled, by map and by worker (consumer): name -> outcome (``SETTLED_OUTCOMES``) -> frames. A
    #: map's leave with it (``forget_map``); a worker's with its consumer, once it is gone (Redis: ``prepare``).
    maps: dict[str, dict[str, int]] = field(default_factory=dict)
    workers: dict[str, dict[str, int]] = field(default_factory=dict)
    map_depth: dict[str, int] = field(default_factory=dict)  # map -> frames queued or in progress (none: absent)

    @property
    def latency_count(self) -> int:
        return sum(self.latency_counts)


#: What a settled frame became, for the per-map and per-worker counts of ``QueueStats``: its step committed,
#: it had been committed before (delivered again), or it was given up on (dead-lettered).
SETTLED_OUTCOMES: tuple[str, ...] = ("processed", "redelivered", "failed")


#: Where an accepted frame is: in the queue, in a consumer's hands (Redis: pending, also between failed
#: deliveries), done, given up on, or none of these (lost, or accepted before statuses were kept).
FrameStatusName = Literal["queued", "processing", "processed", "failed", "unknown"]


@dataclass(frozen=True, slots=True)
class FrameStatus:
    """An accepted frame's status; ``reason``: why it failed (empty otherwise)."""

    status: FrameStatusName
    reason: str = ""


@dataclass(frozen=True, slots=True)
class FailedFrame:
    """A frame given up on: why, after how many deliveries, when (Unix seconds); ``retriable``: its
    dead letter (the payload) is still kept (``QueueLimits.max_dead_letters``)."""

    frame_key: str
    reason: str
    deliveries: int
    failed_at_s: float
    retriable: bool


@dataclass(frozen=True, eq=False, slots=True)
class QueuedFrame:
    """One delivery of a queued frame to one consumer, until it is acknowledged, failed or dead-lettered.

    ``frame`` is None when the queued bytes do not decode (``undecodable`` says why). ``deliveries``
    counts this one (1 the first time). ``entry_id``: the queue's id of the entry delivered, the same in
    every delivery of it (a frame queued again is another entry). ``accepted_at_s``: when the queue accepted
    the frame (Unix seconds, the accepting process's clock; None when not known). ``receipt`` is the
    adapter's own handle; nothing else reads it."""

    map_id: str
    frame_key: str
    consumer: str
    deliveries: int
    frame: Frame | None
    entry_id: str
    undecodable: str = ""
    accepted_at_s: float | None = None
    receipt: Any = field(default=None, repr=False)


class FrameIntake(Protocol):
    """The API's side of the frame queue: ``put`` (deduplicated per map: a frame accepted before is not queued
    again while it is queued, in hand or processed; one that failed or was lost is; bounded by ``QueueLimits``),
    the frames' records and per-map counts, and the operators' ``failed_frames`` and ``retry_failed``."""

    def put(self, frame: Frame, message: Any = None) -> bool:
        """Queue a validated frame; False (nothing queued) when it was accepted before and is queued, in hand
        or processed (a frame that failed, or was accepted but has none of these outcomes, is queued again).
        ``message``: the protobuf ``arcloud.v1.Frame`` it was validated from, which a queue that
        serialises may carry instead of encoding the frame again. Raises ``QueueFull`` (``QueueLimits``).
        A frame whose record expired (``QueueLimits.frame_record_retention_s``) is queued as a new one."""
        ...

    def map_counts(self, map_id: str) -> tuple[int, int]:
        """(accepted, failed) frames of the map: counters, which records expiring do not lower. A frame
        posted again after failing is no longer counted failed; one posted again after its record expired
        is counted accepted again."""
        ...

    def known_map(self, map_id: str) -> bool:
        """Whether any frame of the map was accepted (creates nothing)."""
        ...

    def frame_status(self, map_id: str, frame_key: str) -> FrameStatus | None:
        """The status of an accepted frame; None when the frame was never accepted or its record expired
        (``QueueLimits.frame_record_retention_s`` after it settled)."""
        ...

    def failed_frames(self, map_id: str, limit: int) -> list[FailedFrame]:
        """The map's failed frames (those whose record is kept), latest first, at most ``limit``."""
        ...

    def retry_failed(self, map_id: str, frame_key: str) -> bool:
        """Queue a failed frame again from its dead letter, as a device posting it again would (the limits
        apply: ``QueueFull``). False when it was queued again since (posted again). ``InvalidInput`` when
        the map has no such failed frame, or its dead letter was dropped."""
        ...

    def forget_map(self, map_id: str) -> None:
        """Drop the map's frame counts (after its objects were deleted)."""
        ...


class FrameConsumer(Protocol):
    """A worker's side of the frame queue: ``take`` a new frame or ``claim_abandoned`` one whose consumer stopped
    answering, then exactly one of ``ack`` (the step ran, or the frame had been processed before), ``fail``
    (the step raised) or ``dead_letter`` (given up on: counted as failed); heartbeats keep a consumer's frames
    its own. A queue that redelivers (Redis) leaves a failed frame for a later delivery; one that does not
    (embedded) counts it failed at once."""

    def prepare(self) -> None:
        """Create what the queue needs before frames flow (idempotent)."""
        ...

    def take(self, consumer: str, *, block_s: float) -> QueuedFrame | None:
        """A new frame for ``consumer``, waiting up to ``block_s``; None when there was none."""
        ...

    def claim_abandoned(self, consumer: str, *, min_idle_s: float) -> QueuedFrame | None:
        """A frame another consumer took ``min_idle_s`` ago or more without settling it, or None."""
        ...

    def ack(self, item: QueuedFrame, *, redelivered: bool, retries: int = 0, timings: FrameTimings | None = None) -> None:
        """The step ran (``redelivered``: the frame had been processed before); remove it, count it, and
        (processed) count its ``timings`` in the histograms of ``stats``."""
        ...

    def fail(self, item: QueuedFrame, reason: str) -> None:
        """The step raised: leave the frame for a later delivery, or count it failed at once."""
        ...

    def dead_letter(self, item: QueuedFrame, reason: str) -> None:
        """Give the frame up (kept with ``reason`` where the queue keeps dead letters); counted failed."""
        ...

    def heartbeat(self, consumer: str, in_hand: Sequence[QueuedFrame], settings: Mapping[str, object] | None = None) -> None:
        """``consumer`` is alive, and the frames ``in_hand`` are still being worked on (not abandoned); ``settings``:
        what it maps with (JSON-ready), for ``live_settings``."""
        ...

    def leave(self, consumer: str) -> None:
        """``consumer`` stops (its heartbeat is removed)."""
        ...


class QueueMonitor(Protocol):
    """How the frame queue is doing, for metrics and health: its counters, its dependencies, its live consumers."""

    def stats(self) -> QueueStats: ...

    def health(self) -> dict[str, str]:
        """Check name -> "ok" or what is wrong, for what the queue itself depends on (never raises)."""
        ...

    def live_consumers(self, max_age_s: float) -> list[str]:
        """Consumers whose heartbeat is at most ``max_age_s`` old, sorted."""
        ...

    def live_settings(self, max_age_s: float) -> dict[str, dict[str, object]]:
        """The settings each consumer of ``live_consumers`` last gave its heartbeat (those that gave some)."""
        ...


class FrameQueue(FrameIntake, FrameConsumer, QueueMonitor, Protocol):
    """Validated frames from the API to the consumers that run the step, at least once: the intake, the
    consumers' side and the monitor of one queue, for the composition root (a part of the service that needs
    less names the narrow port).

    Every method is safe to call from many threads; a shared queue's state is every process's."""


# --- access ------------------------------------------------------------------------------------------
class KeyStore(Protocol):
    """The API keys. Safe to call from many threads (and, for a shared store, many processes)."""

    def add(self, key: ApiKey) -> None:
        """Store a new key (its id is new: ``access.new_key`` draws 48 random bits)."""
        ...

    def find(self, key_id: str) -> ApiKey | None:
        """The key with this id; None when there is none (never created, or revoked)."""
        ...

    def list_keys(self) -> list[ApiKey]:
        """Every key, oldest first."""
        ...

    def count_keys(self) -> int:
        """How many keys there are, without reading them (``/readyz`` asks, unauthenticated)."""
        ...

    def revoke(self, key_id: str) -> bool:
        """Remove the key; False when there was none."""
        ...

    def close(self) -> None: ...


class RateLimiter(Protocol):
    """Token buckets (GCRA): ``rate_per_s`` on average with bursts of up to ``burst``. Shared by every
    process using the same store, so N API replicas enforce one limit."""

    def take(self, bucket: str, *, rate_per_s: float, burst: int) -> float:
        """Spend one token of ``bucket``: 0.0 when allowed, else the seconds until one is (nothing spent)."""
        ...

    def close(self) -> None: ...


#: Live viewer passes (tickets and sessions) one key holds at most: one more ends the key's pass that would end
#: first (of passes alike, its oldest), never another key's (one key drawing sessions filled the memory store's
#: passes and ended others' viewers; on Redis, 2.2 million passes a key in a session's 12 h).
MAX_VIEWER_PASSES_PER_KEY = 100


class ViewerPasses(Protocol):
    """Viewer tickets and sessions by the SHA-256 of their secret (``access.secret_digest``), each kept until its
    ``expires_at_s`` at least (the caller checks expiry). Shared by every API process using the same store."""

    def put(self, digest: str, grant: ViewerGrant) -> None:
        """Keep the pass; when its key holds ``MAX_VIEWER_PASSES_PER_KEY`` live ones, the one of them that would end
        first ends now."""
        ...

    def find(self, digest: str) -> ViewerGrant | None:
        """The pass; None when there is none (never issued, taken, or dropped once expired)."""
        ...

    def take(self, digest: str) -> ViewerGrant | None:
        """``find`` and remove, at once: of two callers taking one ticket, one gets it."""
        ...

    def close(self) -> None: ...


# --- device alignments ------------------------------------------------------------------------------
class DeviceAlignments(Protocol):
    """Each device's ``device_from_map`` per map: a rigid (4, 4), checked before it is put (``core.conventions.
    check_device_from_map``), applied by the API to every frame of the device that brings none of its own.
    Kept apart from the map's objects: deleting the map's objects (``ObjectStore.delete_map``) leaves them,
    ``forget_map`` removes them. Safe to call from many threads (and, shared, many processes)."""

    def get(self, map_id: str, device_id: str) -> np.ndarray | None:
        """The device's alignment, a new (4, 4) float64 array; None when it has none."""
        ...

    def put(self, map_id: str, device_id: str, device_from_map: np.ndarray) -> None:
        """Set (or replace) the device's alignment."""
        ...

    def delete(self, map_id: str, device_id: str) -> bool:
        """Remove the device's alignment; False when it had none."""
        ...

    def of_map(self, map_id: str) -> dict[str, np.ndarray]:
        """Every device of the map with an alignment -> its alignment."""
        ...

    def forget_map(self, map_id: str) -> None:
        """Remove every alignment of the map."""
        ...

    def close(self) -> None: ...


# --- archives ----------------------------------------------------------------------------------------
class MapArchive(Protocol):
    """A map as one file (header and every object, exactly) and back, on any ``ObjectStore``."""

    def snapshot(self, store: ObjectStore, map_id: str) -> bytes:
        """The map as a file's bytes; ``InvalidInput`` for a map never opened."""
        ...

    def restore(
        self,
        store: ObjectStore,
        map_id: str,
        data: bytes,
        *,
        replace: bool = False,
        params: Params | None = None,
        forget: Callable[[], None] | None = None,
    ) -> int:
        """Write a snapshot into ``map_id`` (empty, or deleted first with ``replace``, after ``forget()`` once the
        file is checked: what else the map holds, such as its frame records); how many objects.
        ``InvalidInput`` for a file that is not a snapshot or a map with objects; ``MapMismatch`` for a
        snapshot written under other settings than ``params`` (when given)."""
        ...
