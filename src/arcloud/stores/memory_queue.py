"""The embedded frame queue: frames in this process's memory, for worker threads beside the API.

Frames stay ``Frame`` objects (nothing is encoded). A frame counts its arrays' bytes (``queued_bytes``)
against the ``QueueLimits``, overall and of its map, from ``put`` until ``ack`` or ``dead_letter``.
Nothing is delivered twice: a frame whose step raised is counted failed at once (``fail``), and a frame
accepted again after failing is queued again (as is one accepted but neither queued, in hand, processed
nor failed: the Redis queue's rule).

Records, as on Redis: a settled (processed or failed) frame's record is dropped
``frame_record_retention_s`` after it settled, oldest first, at most ``RECORDS_SWEPT_PER_CALL`` by each
``put``, ``ack`` or ``dead_letter`` of its map; the map's counts are counters. A failed frame keeps its
``Frame`` as its dead letter, for ``retry_failed``, within ``max_dead_letters`` and
``max_dead_letter_bytes`` (oldest dropped first), and until its record goes or it is queued again.

Nothing survives a restart (the embedded store does not either). There are no other processes, so
there is nothing to claim and no heartbeat to keep.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from arcloud.core.types import Frame
from arcloud.ports import (
    RECORDS_SWEPT_PER_CALL,
    FailedFrame,
    FrameStatus,
    FrameTimings,
    QueuedFrame,
    QueueLimits,
    QueueStats,
    latency_bucket,
    not_retriable,
)


def queued_bytes(frame: Frame) -> int:
    """What the embedded queue holds of a frame: its colour and depth arrays."""
    return int(frame.rgb.nbytes + frame.depth_m.nbytes)


@dataclass(slots=True)
class _MapRecords:
    """One map's frames: each recorded frame's status; the settled ones by when they settled (oldest
    first: a frame settling again moves to the end); how many times the failed ones were delivered;
    the counts (``map_counts``)."""

    status: dict[str, FrameStatus] = field(default_factory=dict)
    settled_at_s: dict[str, float] = field(default_factory=dict)
    deliveries: dict[str, int] = field(default_factory=dict)
    accepted: int = 0
    failed: int = 0


@dataclass(frozen=True, slots=True)
class _DeadLetter:
    frame: Frame
    n_bytes: int


class MemoryFrameQueue:
    """In-process ``FrameQueue`` within ``limits`` (default ``QueueLimits()``). ``clock``: Unix seconds
    (records' ages)."""

    def __init__(self, *, limits: QueueLimits | None = None, clock: Callable[[], float] = time.time) -> None:
        self.limits = limits or QueueLimits()
        self._clock = clock
        self._changed = threading.Condition(threading.RLock())  # guards everything below
        self._ready: deque[tuple[Frame, int, float]] = deque()  # (frame, its queued bytes, accepted at), oldest first
        self._in_hand: dict[int, tuple[str, int]] = {}  # receipt -> (map, queued bytes) until settled
        self._frames = 0  # queued or in hand, and their bytes, overall and per map (zeros dropped)
        self._bytes = 0
        self._map_frames: dict[str, int] = {}
        self._map_bytes: dict[str, int] = {}
        self._maps: dict[str, _MapRecords] = {}
        self._dead: dict[tuple[str, str], _DeadLetter] = {}  # (map, frame key) -> dead letter, oldest first
        self._dead_bytes = 0
        self._stats = QueueStats()
        self._receipts = itertools.count(1)

    # --- producer ----------------------------------------------------------------------------------
    def put(self, frame: Frame, message: Any = None) -> bool:
        with self._changed:
            now = self._clock()
            records = self._maps.get(frame.map_id)
            status = None
            if records is not None:
                self._trim(frame.map_id, records, now, frame.key)
                status = records.status.get(frame.key)
            if status is not None and status.status in ("queued", "processing", "processed"):
                self._stats.duplicates += 1
                return False  # one that failed, or was accepted and has no outcome (lost), is queued again
            n_bytes = queued_bytes(frame)
            refusal = self.limits.refusal(
                frame.map_id,
                n_bytes,
                frames=self._frames,
                queued_bytes=self._bytes,
                map_frames=self._map_frames.get(frame.map_id, 0),
                map_bytes=self._map_bytes.get(frame.map_id, 0),
            )
            if refusal is not None:
                raise refusal
            self._ready.append((frame, n_bytes, now))
            self._count(frame.map_id, 1, n_bytes)
            records = self._maps.setdefault(frame.map_id, _MapRecords())
            if status is None:
                records.accepted += 1
            elif status.status == "failed":
                records.failed -= 1
                records.deliveries.pop(frame.key, None)
                self._drop_dead_letter(frame.map_id, frame.key)
            records.settled_at_s.pop(frame.key, None)
            records.status[frame.key] = FrameStatus("queued")
            self._stats.accepted += 1
            self._changed.notify()
        return True

    def map_counts(self, map_id: str) -> tuple[int, int]:
        with self._changed:
            records = self._maps.get(map_id)
            return (records.accepted, records.failed) if records is not None else (0, 0)

    def known_map(self, map_id: str) -> bool:
        with self._changed:
            return map_id in self._maps

    def frame_status(self, map_id: str, frame_key: str) -> FrameStatus | None:
        with self._changed:
            records = self._maps.get(map_id)
            if records is None or frame_key not in records.status or self._expired(records, frame_key, self._clock()):
                return None
            return records.status[frame_key]

    def failed_frames(self, map_id: str, limit: int) -> list[FailedFrame]:
        with self._changed:
            records = self._maps.get(map_id)
            if records is None:
                return []
            now = self._clock()
            found = [
                FailedFrame(
                    key, status.reason, records.deliveries.get(key, 1), records.settled_at_s[key], (map_id, key) in self._dead
                )
                for key, status in records.status.items()
                if status.status == "failed" and not self._expired(records, key, now)
            ]
        return sorted(found, key=lambda f: f.failed_at_s, reverse=True)[:limit]

    def retry_failed(self, map_id: str, frame_key: str) -> bool:
        with self._changed:
            status = self.frame_status(map_id, frame_key)
            dead = self._dead.get((map_id, frame_key))
            if status is None or status.status != "failed" or dead is None:
                raise not_retriable(map_id, frame_key, status.status if status is not None else None)
            return self.put(dead.frame)

    def forget_map(self, map_id: str) -> None:
        with self._changed:
            self._maps.pop(map_id, None)
            self._stats.maps.pop(map_id, None)
            for gone in [k for k in self._dead if k[0] == map_id]:
                self._drop_dead_letter(*gone)

    def stats(self) -> QueueStats:
        with self._changed:
            stats = QueueStats(**{name: getattr(self._stats, name) for name in QueueStats.__dataclass_fields__})
            stats.latency_counts = list(self._stats.latency_counts)
            stats.queue_wait, stats.lock_wait = self._stats.queue_wait.copy(), self._stats.lock_wait.copy()
            stats.maps = {name: dict(counts) for name, counts in self._stats.maps.items()}
            stats.workers = {name: dict(counts) for name, counts in self._stats.workers.items()}
            stats.map_depth = dict(self._map_frames)
            stats.queue_depth = self._frames
            stats.queued_bytes = self._bytes
        return stats

    def health(self) -> dict[str, str]:
        return {}

    def close(self) -> None:
        """Nothing to release."""
        return None

    def prepare(self) -> None:
        return None

    # --- consumer ----------------------------------------------------------------------------------
    def take(self, consumer: str, *, block_s: float) -> QueuedFrame | None:
        deadline = time.monotonic() + block_s
        with self._changed:
            while not self._ready:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._changed.wait(remaining)
            frame, n_bytes, accepted_at_s = self._ready.popleft()
            receipt = next(self._receipts)
            self._in_hand[receipt] = (frame.map_id, n_bytes)
            self._set_status(frame.map_id, frame.key, FrameStatus("processing"))
        return QueuedFrame(
            frame.map_id, frame.key, consumer, 1, frame, str(receipt), accepted_at_s=accepted_at_s, receipt=receipt
        )

    def claim_abandoned(self, consumer: str, *, min_idle_s: float) -> QueuedFrame | None:
        return None  # every consumer is a thread of this process: none is abandoned

    def ack(self, item: QueuedFrame, *, redelivered: bool, retries: int = 0, timings: FrameTimings | None = None) -> None:
        timings = timings or FrameTimings()
        with self._changed:
            if not self._settle(item):
                return
            self._stats.retried += retries
            self._count_settled(item, "redelivered" if redelivered else "processed")
            if redelivered:
                self._stats.redelivered += 1
            else:
                self._stats.processed += 1
                self._stats.latency_counts[latency_bucket(timings.step_s)] += 1
                self._stats.latency_sum_s += timings.step_s
                if timings.queue_wait_s is not None:
                    self._stats.queue_wait.observe(timings.queue_wait_s)
                self._stats.lock_wait.observe(timings.lock_wait_s)
            self._record_outcome(item, FrameStatus("processed"))

    def fail(self, item: QueuedFrame, reason: str) -> None:
        self.dead_letter(item, reason)  # no redelivery in process

    def dead_letter(self, item: QueuedFrame, reason: str) -> None:
        with self._changed:
            if not self._settle(item):
                return
            self._stats.failed += 1
            self._count_settled(item, "failed")
            records = self._record_outcome(item, FrameStatus("failed", reason))
            if records is None:
                return
            records.failed += 1
            records.deliveries[item.frame_key] = item.deliveries
            if item.frame is None:
                return  # nothing to queue again
            dead = _DeadLetter(item.frame, queued_bytes(item.frame))
            self._drop_dead_letter(item.map_id, item.frame_key)
            self._dead[(item.map_id, item.frame_key)] = dead
            self._dead_bytes += dead.n_bytes
            while self._dead and (
                len(self._dead) > self.limits.max_dead_letters or self._dead_bytes > self.limits.max_dead_letter_bytes
            ):
                self._drop_dead_letter(*next(iter(self._dead)))

    # --- records -----------------------------------------------------------------------------------
    def _count(self, map_id: str, frames: int, n_bytes: int) -> None:
        """Under the lock: add to what is queued or in hand (negative: remove), dropping zeros."""
        self._frames += frames
        self._bytes += n_bytes
        for per_map, delta in ((self._map_frames, frames), (self._map_bytes, n_bytes)):
            left = per_map.get(map_id, 0) + delta
            if left > 0:
                per_map[map_id] = left
            else:
                per_map.pop(map_id, None)

    def _count_settled(self, item: QueuedFrame, outcome: str) -> None:
        """Under the lock: count the frame's outcome for its map (while the map is known) and its consumer."""
        if item.map_id in self._maps:
            by_map = self._stats.maps.setdefault(item.map_id, {})
            by_map[outcome] = by_map.get(outcome, 0) + 1
        by_worker = self._stats.workers.setdefault(item.consumer, {})
        by_worker[outcome] = by_worker.get(outcome, 0) + 1

    def _settle(self, item: QueuedFrame) -> bool:
        """Under the lock: the delivery leaves the queue's count; False when it was settled before."""
        held = self._in_hand.pop(item.receipt, None)
        if held is None:
            return False
        self._count(held[0], -1, -held[1])
        return True

    def _record_outcome(self, item: QueuedFrame, status: FrameStatus) -> _MapRecords | None:
        """Under the lock: the frame's record says ``status``, settled now; the map's expired records go.
        The records, or None when the frame has none any more (its map was forgotten meanwhile)."""
        records = self._maps.get(item.map_id)
        if records is None or item.frame_key not in records.status:
            return None
        now = self._clock()
        records.status[item.frame_key] = status
        records.settled_at_s.pop(item.frame_key, None)
        records.settled_at_s[item.frame_key] = now
        self._trim(item.map_id, records, now, None)
        return records

    def _expired(self, records: _MapRecords, frame_key: str, now: float) -> bool:
        settled_at_s = records.settled_at_s.get(frame_key)
        return settled_at_s is not None and settled_at_s < now - self.limits.frame_record_retention_s

    def _trim(self, map_id: str, records: _MapRecords, now: float, frame_key: str | None) -> None:
        """Under the lock: drop the oldest expired records of the map (``RECORDS_SWEPT_PER_CALL`` at most),
        and ``frame_key``'s when it expired."""
        cutoff = now - self.limits.frame_record_retention_s
        expired = list(
            itertools.islice(
                itertools.takewhile(lambda k: records.settled_at_s[k] < cutoff, records.settled_at_s), RECORDS_SWEPT_PER_CALL
            )
        )
        if frame_key is not None and self._expired(records, frame_key, now):
            expired.append(frame_key)
        for key in expired:
            records.settled_at_s.pop(key, None)
            records.status.pop(key, None)
            records.deliveries.pop(key, None)
            self._drop_dead_letter(map_id, key)

    def _drop_dead_letter(self, map_id: str, frame_key: str) -> None:
        dead = self._dead.pop((map_id, frame_key), None)
        if dead is not None:
            self._dead_bytes -= dead.n_bytes

    def _set_status(self, map_id: str, frame_key: str, status: FrameStatus) -> None:
        """Under the lock: the frame's status, where its record is still kept."""
        records = self._maps.get(map_id)
        if records is not None and frame_key in records.status:
            records.status[frame_key] = status

    def heartbeat(self, consumer: str, in_hand: Sequence[QueuedFrame], settings: Mapping[str, object] | None = None) -> None:
        return None

    def leave(self, consumer: str) -> None:
        return None

    def live_consumers(self, max_age_s: float) -> list[str]:
        return []

    def live_settings(self, max_age_s: float) -> dict[str, dict[str, object]]:
        return {}  # one process's worker threads: one set of settings
