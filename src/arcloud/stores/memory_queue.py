"""The embedded frame queue: a bounded queue in this process's memory, for worker threads beside the API.

Frames stay ``Frame`` objects (nothing is encoded). Nothing is delivered twice: a frame whose step
raised is counted failed at once (``fail``), and a frame accepted again after failing is queued again
(as is one accepted but neither queued, in hand, processed nor failed: the Redis queue's rule).
Nothing survives a restart (the embedded store does not either). There are no other processes, so
there is nothing to claim and no heartbeat to keep.
"""

from __future__ import annotations

import itertools
import queue
import threading
from typing import Any

from arcloud.core.types import Frame
from arcloud.ports import FrameStatus, QueuedFrame, QueueFull, QueueStats, latency_bucket

UNKNOWN = FrameStatus("unknown")


class MemoryFrameQueue:
    """In-process ``FrameQueue`` of at most ``max_queued_frames`` frames."""

    def __init__(self, *, max_queued_frames: int = 1000) -> None:
        self._queue: queue.Queue[Frame] = queue.Queue(maxsize=max_queued_frames)
        self._lock = threading.Lock()
        self._accepted: dict[str, set[str]] = {}
        self._failed: dict[str, set[str]] = {}
        self._status: dict[str, dict[str, FrameStatus]] = {}  # map -> frame key -> its status
        self._stats = QueueStats()
        self._in_flight = 0
        self._receipts = itertools.count(1)

    # --- producer ----------------------------------------------------------------------------------
    def put(self, frame: Frame, message: Any = None) -> bool:
        with self._lock:
            accepted = self._accepted.setdefault(frame.map_id, set())
            failed = self._failed.get(frame.map_id, set())
            status = self._status.setdefault(frame.map_id, {})
            if frame.key in accepted and frame.key not in failed and self._queued_in_hand_or_processed(frame, status):
                self._stats.duplicates += 1
                return False  # one that failed, or was accepted and has no outcome (lost), is queued again
            try:
                self._queue.put_nowait(frame)
            except queue.Full:
                raise QueueFull(f"{self._queue.maxsize} frames are queued; try again later") from None
            accepted.add(frame.key)
            failed.discard(frame.key)
            status[frame.key] = FrameStatus("queued")
            self._stats.accepted += 1
        return True

    def map_counts(self, map_id: str) -> tuple[int, int]:
        with self._lock:
            return len(self._accepted.get(map_id, ())), len(self._failed.get(map_id, ()))

    def known_map(self, map_id: str) -> bool:
        with self._lock:
            return bool(self._accepted.get(map_id))

    def frame_status(self, map_id: str, frame_key: str) -> FrameStatus | None:
        with self._lock:
            if frame_key not in self._accepted.get(map_id, ()):
                return None
            return self._status.get(map_id, {}).get(frame_key, UNKNOWN)

    def forget_map(self, map_id: str) -> None:
        with self._lock:
            self._accepted.pop(map_id, None)
            self._failed.pop(map_id, None)
            self._status.pop(map_id, None)

    def stats(self) -> QueueStats:
        with self._lock:
            stats = QueueStats(**{name: getattr(self._stats, name) for name in QueueStats.__dataclass_fields__})
            stats.latency_counts = list(self._stats.latency_counts)
            stats.queue_depth = self._queue.qsize() + self._in_flight
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
        try:
            frame = self._queue.get(timeout=block_s)
        except queue.Empty:
            return None
        with self._lock:
            self._in_flight += 1
            self._set_status(frame.map_id, frame.key, FrameStatus("processing"))
        return QueuedFrame(frame.map_id, frame.key, consumer, 1, frame, receipt=next(self._receipts))

    def claim_abandoned(self, consumer: str, *, min_idle_s: float) -> QueuedFrame | None:
        return None  # every consumer is a thread of this process: none is abandoned

    def ack(self, item: QueuedFrame, *, redelivered: bool, retries: int = 0, elapsed_s: float = 0.0) -> None:
        with self._lock:
            self._in_flight -= 1
            self._set_status(item.map_id, item.frame_key, FrameStatus("processed"))
            self._stats.retried += retries
            if redelivered:
                self._stats.redelivered += 1
            else:
                self._stats.processed += 1
                self._stats.latency_counts[latency_bucket(elapsed_s)] += 1
                self._stats.latency_sum_s += elapsed_s

    def fail(self, item: QueuedFrame, reason: str) -> None:
        self.dead_letter(item, reason)  # no redelivery in process

    def dead_letter(self, item: QueuedFrame, reason: str) -> None:
        with self._lock:
            self._in_flight -= 1
            self._stats.failed += 1
            self._set_status(item.map_id, item.frame_key, FrameStatus("failed", reason))
            if item.frame_key in self._accepted.get(item.map_id, ()):  # failed frames are a subset of the accepted ones
                self._failed.setdefault(item.map_id, set()).add(item.frame_key)

    @staticmethod
    def _queued_in_hand_or_processed(frame: Frame, status: dict[str, FrameStatus]) -> bool:
        """The rule of ``lua/accept_frame.lua``. In process the records are the truth: a frame leaves the
        queue only with the process, and its records with it; one without a status is an accepted frame
        with no outcome (lost)."""
        return status.get(frame.key, UNKNOWN).status in ("queued", "processing", "processed")

    def _set_status(self, map_id: str, frame_key: str, status: FrameStatus) -> None:
        """Under ``self._lock``: the frame's status, where the map is still known (not forgotten)."""
        if map_id in self._status:
            self._status[map_id][frame_key] = status

    def heartbeat(self, consumer: str, in_hand: QueuedFrame | None) -> None:
        return None

    def leave(self, consumer: str) -> None:
        return None

    def live_consumers(self, max_age_s: float) -> list[str]:
        return []
