"""The durable frame queue on Redis Streams: the API appends each validated frame to ONE stream
(``arcloud:ingest``), read by a consumer group of worker processes. A frame is acknowledged (and deleted
from the stream, so the stream's length is the backlog) only after its step; a worker that dies leaves it
pending and another claims it (XAUTOCLAIM after ``min_idle_s``).

Why one global stream rather than a stream per map: a consumer group lives on one stream, and
XREADGROUP reads a fixed list of streams, while maps appear at run time; per-map streams would need a
registry of maps, a group per map and a reader per (worker, map). One stream gives one group, one
pending list to claim from, and first-come-first-served across maps. Frames of one map are processed in
parallel by several workers (the per-object locks and space claims of the step make that safe). The
scale-out path beyond one Redis primary is N shard streams (map -> shard by hash), each with its group.

Per map: the SET of accepted frame keys, the SET of failed (dead-lettered) ones, and each frame's status
(its entry id while in the stream, then processed or failed with the reason). ``lua/accept_frame.lua``
records and queues a frame in one step, so no frame is recorded as accepted without its entry; a frame
posted again is a duplicate while its entry is in the stream or it was processed, and is queued again when
it failed or its entry is gone without an outcome (lost, e.g. in the last second before a crash). Service-wide: the counters and the
step latency histogram in one HASH shared by every worker, consumers' heartbeats in another, and the
dead-letter stream. Key templates are in ``keys``; entries carry ``map_id``, ``frame_key``,
``accepted_at_s`` and ``frame`` (``stream_frames``).

``fail`` leaves an entry pending: it is delivered again once claimed, until the worker dead-letters
it. redis-py's connection errors and timeouts, and a Redis busy with a script (``BUSY``), become
``StoreUnavailable`` at this boundary, other Redis errors ``StoreError``.

Recovery: a Redis restarted without its data has no consumer group; the readers (``take``,
``claim_abandoned``) create it again (``NOGROUP`` -> ``prepare``) and read on. Frames queued before
the restart are lost with the data; frames queued since (XADD makes the stream) are read, as the group
starts at the stream's beginning. ``health`` reports a missing group.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any, cast

import redis

from arcloud.core.types import Frame
from arcloud.errors import InvalidInput, StoreError, StoreUnavailable
from arcloud.ports import LATENCY_BUCKETS_S, FrameStatus, QueuedFrame, QueueFull, QueueStats, latency_bucket
from arcloud.stores import keys
from arcloud.stores.redis import connect_redis, is_busy, lua_source
from arcloud.stores.stream_frames import decode_frame, encode_frame

log = logging.getLogger(__name__)

#: XREADGROUP's reply (bytes: no decode_responses): [(stream, [(entry id, fields), ...])], None when nothing came.
_ReadReply = list[tuple[bytes, list[tuple[bytes, dict[bytes, bytes]]]]] | None

#: The stats HASH's counters (``QueueStats`` fields), beside ``latency_le_<bound>`` and ``latency_sum_s``.
STAT_FIELDS = ("accepted", "duplicates", "processed", "redelivered", "failed", "claimed", "retried")


def latency_field(bucket: int) -> str:
    """The stats HASH's field counting the steps of latency bucket ``bucket``."""
    return f"latency_le_{LATENCY_BUCKETS_S[bucket]:g}" if bucket < len(LATENCY_BUCKETS_S) else "latency_le_inf"


def parse_stats(raw: Mapping[bytes | str, bytes | str]) -> QueueStats:
    """The stats HASH as ``QueueStats`` (missing fields are 0)."""
    values = {_text(k): _text(v) for k, v in raw.items()}
    counts: dict[str, Any] = {name: int(values.get(name, 0)) for name in STAT_FIELDS}
    stats = QueueStats(**counts)
    stats.latency_counts = [int(values.get(latency_field(b), 0)) for b in range(len(LATENCY_BUCKETS_S) + 1)]
    stats.latency_sum_s = float(values.get("latency_sum_s", 0.0))
    return stats


def _text(value: bytes | str | None) -> str:
    return value.decode(errors="replace") if isinstance(value, bytes) else (value or "")


class RedisFrameQueue:
    """``FrameQueue`` on Redis Streams. ``client``: an existing ``redis.Redis`` (binary responses) instead
    of connecting to ``url`` (``connect_redis``: then ``socket_timeout_s`` must exceed the longest blocking
    read). ``group``: the consumer group; ``max_queued_frames``: ``put`` refuses beyond this backlog."""

    def __init__(
        self,
        url: str = "redis://127.0.0.1:6379/0",
        *,
        client: redis.Redis | None = None,
        group: str = "arcloud-workers",
        max_queued_frames: int = 1000,
        socket_timeout_s: float = 30.0,
    ) -> None:
        if client is None:
            client = connect_redis(url, reply_timeout_s=socket_timeout_s)
            self._owns_client = True
        else:
            self._owns_client = False
        self.client = client
        self.group = group
        self.max_queued_frames = max_queued_frames
        self._accept = client.register_script(lua_source("accept_frame"))
        self._claim_cursors: dict[str, str] = {}  # consumer -> where its XAUTOCLAIM scan goes on

    def close(self) -> None:
        """Close the connections (when the queue made its client)."""
        if self._owns_client:
            self.client.close()

    @contextmanager
    def _boundary(self, doing: str) -> Iterator[None]:
        """Map redis-py's exceptions to arcloud's."""
        try:
            yield
        except (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError) as exc:
            raise StoreUnavailable(f"cannot {doing}: Redis unreachable ({exc})") from exc
        except redis.exceptions.ResponseError as exc:
            if is_busy(exc):
                raise StoreUnavailable(f"cannot {doing}: Redis busy ({exc})") from exc
            raise StoreError(f"cannot {doing}: Redis failed ({exc})") from exc
        except redis.exceptions.RedisError as exc:
            raise StoreError(f"cannot {doing}: Redis failed ({exc})") from exc

    def _recreate_group(self, exc: redis.exceptions.ResponseError) -> None:
        """Re-raise ``exc`` unless it says the consumer group is gone (``NOGROUP``: Redis restarted
        without its data); then create the group again."""
        if not str(exc).startswith("NOGROUP"):
            raise exc
        log.warning(
            "consumer group %s of %s missing (Redis restarted without its data?); creating it", self.group, keys.INGEST_STREAM
        )
        self.prepare()

    # --- producer ----------------------------------------------------------------------------------
    def put(self, frame: Frame, message: Any = None) -> bool:
        map_id = frame.map_id
        with self._boundary("queue the frame"):
            entry_id = self._accept(
                keys=[
                    keys.ingest_accepted_key(map_id),
                    keys.ingest_failed_key(map_id),
                    keys.ingest_status_key(map_id),
                    keys.INGEST_STREAM,
                    keys.INGEST_STATS,
                ],
                args=[frame.key, self.max_queued_frames, map_id, repr(time.time()), encode_frame(frame, message)],
            )
        if entry_id == -1:
            raise QueueFull(f"{self.max_queued_frames} frames are queued; try again later")
        return bool(entry_id != 0)  # the new entry id, or 0 for a duplicate

    def map_counts(self, map_id: str) -> tuple[int, int]:
        with self._boundary("read the map's counts"):
            pipe = self.client.pipeline(transaction=False)
            pipe.scard(keys.ingest_accepted_key(map_id))
            pipe.scard(keys.ingest_failed_key(map_id))
            accepted, failed = (int(v) for v in pipe.execute())
        return accepted, failed

    def known_map(self, map_id: str) -> bool:
        with self._boundary("look the map up"):
            return bool(self.client.exists(keys.ingest_accepted_key(map_id)))

    def frame_status(self, map_id: str, frame_key: str) -> FrameStatus | None:
        """From the map's status HASH; a frame with an entry is "processing" while the entry is pending
        (delivered, not yet acknowledged), "queued" before; one whose entry is gone is "unknown"."""
        with self._boundary("read the frame's status"):
            pipe = self.client.pipeline(transaction=False)
            pipe.sismember(keys.ingest_accepted_key(map_id), frame_key)
            pipe.hget(keys.ingest_status_key(map_id), frame_key)
            accepted, raw = pipe.execute()
            if not accepted:
                return None
            status, _, detail = _text(raw).partition(" ")
            if status == "processed":
                return FrameStatus("processed")
            if status == "failed":
                return FrameStatus("failed", detail)
            if status != "queued" or not self.client.xrange(keys.INGEST_STREAM, detail, detail):
                return FrameStatus("unknown")  # lost (a retry queues it again), or accepted before statuses were kept
            try:
                pending = self.client.xpending_range(keys.INGEST_STREAM, self.group, min=detail, max=detail, count=1)
            except redis.exceptions.ResponseError as exc:
                if not str(exc).startswith("NOGROUP"):
                    raise
                pending = []  # no group yet: nothing delivered
        return FrameStatus("processing" if pending else "queued")

    def forget_map(self, map_id: str) -> None:
        with self._boundary("forget the map"):
            self.client.delete(keys.ingest_accepted_key(map_id), keys.ingest_failed_key(map_id), keys.ingest_status_key(map_id))

    def stats(self) -> QueueStats:
        with self._boundary("read the ingest counters"):
            pipe = self.client.pipeline(transaction=False)
            pipe.hgetall(keys.INGEST_STATS)
            pipe.xlen(keys.INGEST_STREAM)
            raw, depth = pipe.execute()
        stats = parse_stats(raw)
        stats.queue_depth = int(depth)
        return stats

    def health(self) -> dict[str, str]:
        """``redis``: it answers; ``consumer_group``: the workers' group exists (it does not after Redis
        restarted without its data, until a worker reads again)."""
        try:
            self.client.ping()
        except Exception as exc:  # noqa: BLE001 - readiness reports, never raises
            return {"redis": f"unreachable: {type(exc).__name__}"}
        try:
            groups = self.client.xinfo_groups(keys.INGEST_STREAM)
            found = any(_text(g.get("name")) == self.group for g in groups)
        except redis.exceptions.ResponseError:  # "no such key": no stream, so no group
            found = False
        except Exception as exc:  # noqa: BLE001 - readiness reports, never raises
            return {"redis": f"unreachable: {type(exc).__name__}"}
        return {"redis": "ok", "consumer_group": "ok" if found else f"missing: no group {self.group} on {keys.INGEST_STREAM}"}

    def prepare(self) -> None:
        """Create the consumer group on the stream (and the stream) unless it exists. It starts at the
        stream's beginning so that frames queued before any worker started are read."""
        with self._boundary("create the consumer group"):
            try:
                self.client.xgroup_create(keys.INGEST_STREAM, self.group, id="0", mkstream=True)
            except redis.exceptions.ResponseError as exc:
                if "BUSYGROUP" not in str(exc):
                    raise

    # --- consumer ----------------------------------------------------------------------------------
    def take(self, consumer: str, *, block_s: float) -> QueuedFrame | None:
        block_ms = max(1, int(block_s * 1000))

        def read() -> _ReadReply:
            return cast(
                _ReadReply, self.client.xreadgroup(self.group, consumer, {keys.INGEST_STREAM: ">"}, count=1, block=block_ms)
            )

        with self._boundary("read the ingest stream"):
            try:
                reply = read()
            except redis.exceptions.ResponseError as exc:
                self._recreate_group(exc)
                reply = read()
        for _stream, entries in reply or []:
            for entry_id, fields in entries:
                return self._delivery(consumer, entry_id, fields, deliveries=1)
        return None

    def claim_abandoned(self, consumer: str, *, min_idle_s: float) -> QueuedFrame | None:
        min_idle_ms = max(1, int(min_idle_s * 1000))
        with self._boundary("claim an abandoned entry"):
            try:
                next_cursor, entries, *_deleted = self.client.xautoclaim(
                    keys.INGEST_STREAM,
                    self.group,
                    consumer,
                    min_idle_ms,
                    start_id=self._claim_cursors.get(consumer, "0-0"),
                    count=1,
                )
            except redis.exceptions.ResponseError as exc:
                self._recreate_group(exc)
                self._claim_cursors.pop(consumer, None)
                return None  # a new group has nothing pending
            self._claim_cursors[consumer] = _text(next_cursor) or "0-0"
            for entry_id, fields in entries:
                if not fields:
                    continue  # deleted while pending (Redis drops it from the pending list)
                pending = self.client.xpending_range(keys.INGEST_STREAM, self.group, min=entry_id, max=entry_id, count=1)
                if not pending:
                    continue  # acknowledged by its late worker since: settled
                deliveries = int(pending[0]["times_delivered"])
                self.client.hincrby(keys.INGEST_STATS, "claimed", 1)
                log.warning("%s claimed entry %s (delivery %d)", consumer, _text(entry_id), deliveries)
                return self._delivery(consumer, entry_id, fields, deliveries=deliveries)
        return None

    def _delivery(self, consumer: str, entry_id: bytes | str, fields: dict[bytes, bytes], *, deliveries: int) -> QueuedFrame:
        frame: Frame | None = None
        undecodable = ""
        try:
            frame = decode_frame(fields.get(b"frame", b""))
        except InvalidInput as exc:
            undecodable = str(exc)
        return QueuedFrame(
            _text(fields.get(b"map_id")),
            _text(fields.get(b"frame_key")),
            consumer,
            deliveries,
            frame,
            undecodable,
            receipt=(entry_id, fields),
        )

    def ack(self, item: QueuedFrame, *, redelivered: bool, retries: int = 0, elapsed_s: float = 0.0) -> None:
        entry_id, _fields = item.receipt
        with self._boundary("acknowledge the entry"):
            pipe = self.client.pipeline(transaction=True)  # the entry goes and the outcome is written together
            pipe.xack(keys.INGEST_STREAM, self.group, entry_id)
            pipe.xdel(keys.INGEST_STREAM, entry_id)
            if item.map_id and item.frame_key:
                pipe.hset(keys.ingest_status_key(item.map_id), item.frame_key, "processed")
            if retries:
                pipe.hincrby(keys.INGEST_STATS, "retried", retries)
            if redelivered:
                pipe.hincrby(keys.INGEST_STATS, "redelivered", 1)
            else:
                pipe.hincrby(keys.INGEST_STATS, "processed", 1)
                pipe.hincrby(keys.INGEST_STATS, latency_field(latency_bucket(elapsed_s)), 1)
                pipe.hincrbyfloat(keys.INGEST_STATS, "latency_sum_s", elapsed_s)
            pipe.execute()

    def fail(self, item: QueuedFrame, reason: str) -> None:
        return None  # left pending: claimed again after min_idle_s, dead-lettered by the worker in the end

    def dead_letter(self, item: QueuedFrame, reason: str) -> None:
        """Move the entry to the dead-letter stream (with the reason), record its frame as failed."""
        entry_id, fields = item.receipt
        dead = dict(fields)
        dead.update(
            {
                b"reason": reason.encode(),
                b"entry_id": _text(entry_id).encode(),
                b"deliveries": str(item.deliveries).encode(),
                b"consumer": item.consumer.encode(),
                b"failed_at_s": repr(time.time()).encode(),
            }
        )
        with self._boundary("dead-letter the entry"):
            pipe = self.client.pipeline(transaction=True)  # the entry goes and the outcome is written together
            pipe.xadd(keys.INGEST_DEAD_LETTER_STREAM, dead)
            pipe.xack(keys.INGEST_STREAM, self.group, entry_id)
            pipe.xdel(keys.INGEST_STREAM, entry_id)
            pipe.hincrby(keys.INGEST_STATS, "failed", 1)
            if item.map_id and item.frame_key:
                pipe.hset(keys.ingest_status_key(item.map_id), item.frame_key, f"failed {reason}")
            pipe.execute()
            if item.map_id and item.frame_key and self.client.sismember(keys.ingest_accepted_key(item.map_id), item.frame_key):
                self.client.sadd(
                    keys.ingest_failed_key(item.map_id), item.frame_key
                )  # failed frames are a subset of the accepted ones

    def heartbeat(self, consumer: str, in_hand: QueuedFrame | None) -> None:
        """Write the heartbeat, and reset the idle time of the entry in hand (XCLAIM JUSTID to its own
        consumer: no new delivery) so that a long step is never taken for an abandoned one."""
        with self._boundary("write the heartbeat"):
            self.client.hset(keys.INGEST_WORKERS, consumer, repr(time.time()))
            if in_hand is not None:
                entry_id, _fields = in_hand.receipt
                try:
                    self.client.xclaim(keys.INGEST_STREAM, self.group, consumer, 0, [entry_id], justid=True)
                except redis.exceptions.ResponseError as exc:
                    if not str(exc).startswith("NOGROUP"):
                        raise
                    # The group went with Redis's data, and the entry with it: nothing left to keep fresh.

    def leave(self, consumer: str) -> None:
        with self._boundary("remove the heartbeat"):
            self.client.hdel(keys.INGEST_WORKERS, consumer)

    def live_consumers(self, max_age_s: float) -> list[str]:
        now = time.time()
        with self._boundary("read the heartbeats"):
            beats = self.client.hgetall(keys.INGEST_WORKERS)
        return sorted(_text(name) for name, seen in beats.items() if now - float(seen) <= max_age_s)
