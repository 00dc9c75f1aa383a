"""The durable frame queue on Redis Streams: the API appends each validated frame to the stream of its
map's ingest shard (``keys.ingest_stream``, shard ``keys.shard_of(map_id, shards)``), read by one consumer
group of worker processes on each shard. A frame is acknowledged (and deleted from the stream, so the
streams' lengths are the backlog) only after its step; a worker that dies leaves it pending and another
claims it (XAUTOCLAIM after ``min_idle_s``).

Why shards, and not a stream per map: a consumer group lives on one stream, and XREADGROUP reads a fixed
list of streams, while maps appear at run time; per-map streams would need a registry of maps, a group per
map and a reader per (worker, map). A fixed number of shards (the setting ``ingest_shards``, 1 by default:
one stream, one group, first come first served across maps) gives a fixed list of groups to read and
claim from, and spreads the ingest over the primaries of a Redis Cluster. Frames of one map go to one
shard and are processed in parallel by several workers (the per-object locks and space claims of the step
make that safe). Every worker reads every shard: ``take`` looks at each shard once without waiting,
starting from the one after where the worker's last look started (so no shard waits on another), then
waits on one in turn (``block_s`` shared among the shards); with one shard, one blocking read as before.
One XREADGROUP over several streams would do on one Redis, not on a Cluster (one slot a command).

A shard's keys, the records of its maps included, share its hash tag (``keys``), so each script below
touches one Cluster slot. Per map: each accepted frame's record (its status: its entry id while in the
stream, then processed or failed, when, and for a failed frame its dead letter, deliveries and reason),
and the map's counts (accepted, failed: counters). ``lua/accept_frame.lua`` records, counts and queues a
frame in one step, so no frame is recorded as accepted without its entry; a frame posted again is a
duplicate while its entry is in the stream or it was processed, and is queued again when it failed or its
entry is gone without an outcome (lost, e.g. in the last second before a crash). Per shard: the counters
and the step latency histogram in one HASH shared by every worker (``stats`` sums the shards; each map's and
each worker's frames settled too, ``map:<map id>:<outcome>`` and ``worker:<consumer>:<outcome>``), the
dead-letter stream, and the backlog (frames and bytes in the stream, overall and per map). Service-wide:
consumers' heartbeats, and the number of shards (``prepare`` writes it once; a process configured with
another number refuses to start, since the maps' records and queued frames are where that number put
them). Entries carry ``map_id``, ``frame_key``, ``accepted_at_s``, ``bytes`` and ``frame``
(``stream_frames``).

Limits (``QueueLimits``): ``accept_frame.lua`` checks the shard's backlog against the four limits and
adds the frame to it in the step that queues it; ``lua/settle_frame.lua`` acknowledges and deletes an
entry, takes it off the backlog and writes the frame's outcome in one step, and only the call that
deletes the entry takes it off. So each backlog is always the sum over the entries in its stream,
whatever crashes when (a Redis restarted without its data loses the counters with the entries). The
per-map limits hold as they are (a map lives in one shard); the overall limits (and the dead-letter caps)
are shared among the shards (``shard_limits``: an even share, at least a map's limit), so the whole
queue holds about what they say. The backlog is not under a map's key prefix: deleting a map while frames
of it are queued leaves it right. The streams are never trimmed by length (MAXLEN would drop frames not
yet processed): entries leave them only settled, so they hold the backlog and nothing else.

Retention: a settled frame's record carries when it settled (``FrameRecord``), and is dropped
``frame_record_retention_s`` after: each accept or settle of its map sweeps about
``RECORDS_SWEPT_PER_CALL`` records on from where the last sweep stopped (HSCAN, ``lua/records.lua``), and
a record past the retention counts as gone even before it is dropped. Dead letters keep the frame's payload for
``retry_failed``; each shard's dead-letter stream is capped at its share of ``max_dead_letters`` entries
and ``max_dead_letter_bytes`` of payload (the oldest go first), the reason staying in the frame's record.
Times are the callers' clocks (Unix seconds), as the heartbeats': the hosts' clocks must agree (NTP).

``fail`` leaves an entry pending (still counted): it is delivered again once claimed, until the worker
dead-letters it. redis-py's exceptions become arcloud's at the adapters' one boundary, ``stores.redis_errors``
(connection errors, timeouts, a Redis busy with a script: ``StoreUnavailable``).

Consumers: every worker that starts reads as a new consumer (host-pid), so the groups would keep one per
worker start; ``prepare`` removes those of workers gone (``remove_stale_consumers``).

Recovery: a Redis restarted without its data has no consumer groups; the readers (``take``,
``claim_abandoned``) create them again (``NOGROUP`` -> ``prepare``) and read on. Frames queued before
the restart are lost with the data; frames queued since (XADD makes the stream) are read, as the group
starts at the stream's beginning. ``health`` reports a missing group.

On a Redis Cluster (a ``RedisCluster`` client, ``connect_redis``) the same calls run unchanged: every
script and every multi-key command names keys of one shard (one slot); the reads of several shards
(``stats``, ``health``) are separate commands, pipelined without a transaction.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import re
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

import redis

from arcloud.core.types import Frame
from arcloud.errors import InvalidInput, StoreError
from arcloud.ports import (
    LATENCY_BUCKETS_S,
    RECORDS_SWEPT_PER_CALL,
    SETTLED_OUTCOMES,
    WAIT_BUCKETS_S,
    FailedFrame,
    FrameStatus,
    FrameTimings,
    Histogram,
    QueuedFrame,
    QueueFull,
    QueueLimits,
    QueueStats,
    latency_bucket,
    not_retriable,
)
from arcloud.stores import keys
from arcloud.stores.redis import RedisClient, connect_redis, lua_source, where
from arcloud.stores.redis_errors import redis_errors
from arcloud.stores.stream_frames import decode_frame, encode_frame

log = logging.getLogger(__name__)

#: XREADGROUP's reply (bytes: no decode_responses): [(stream, [(entry id, fields), ...])], None when nothing came.
_ReadReply = list[tuple[bytes, list[tuple[bytes, dict[bytes, bytes]]]]] | None

#: The stats HASH's counters (``QueueStats`` fields), beside ``latency_le_<bound>`` and ``latency_sum_s``,
#: and the wait histograms' ``<name>_le_<bound>`` and ``<name>_sum_s`` (``WAIT_HISTOGRAMS``).
STAT_FIELDS = ("accepted", "duplicates", "processed", "redelivered", "failed", "claimed", "retried")
#: The ``QueueStats`` histograms of waits, by the name their fields in the stats HASH start with.
WAIT_HISTOGRAMS = ("queue_wait", "lock_wait")
#: A consumer of the group with no pending entry, idle this long and without a heartbeat this long (a worker
#: that stopped or died) is removed by ``prepare``, with its counters.
STALE_CONSUMER_S = 300.0


def settled_field(kind: str, name: str, outcome: str) -> str:
    """The stats HASH's field counting the frames of map or worker ``name`` (``kind``: ``map`` or ``worker``)
    settled as ``outcome`` (``SETTLED_OUTCOMES``): ``map:<map id>:processed``, ``worker:<consumer>:failed``."""
    return f"{kind}:{name}:{outcome}"


def latency_field(bucket: int) -> str:
    """The stats HASH's field counting the steps of latency bucket ``bucket``."""
    return f"latency_le_{LATENCY_BUCKETS_S[bucket]:g}" if bucket < len(LATENCY_BUCKETS_S) else "latency_le_inf"


def histogram_field(name: str, histogram: Histogram, bucket: int) -> str:
    """The stats HASH's field counting bucket ``bucket`` of the histogram ``name`` (``WAIT_HISTOGRAMS``)."""
    bounds = histogram.bounds_s
    return f"{name}_le_{bounds[bucket]:g}" if bucket < len(bounds) else f"{name}_le_inf"


def parse_stats(raw: Mapping[bytes | str, bytes | str]) -> QueueStats:
    """The stats HASH as ``QueueStats`` (missing fields are 0)."""
    values = {_text(k): _text(v) for k, v in raw.items()}
    counts: dict[str, Any] = {name: int(values.get(name, 0)) for name in STAT_FIELDS}
    stats = QueueStats(**counts)
    stats.latency_counts = [int(values.get(latency_field(b), 0)) for b in range(len(LATENCY_BUCKETS_S) + 1)]
    stats.latency_sum_s = float(values.get("latency_sum_s", 0.0))
    for name in WAIT_HISTOGRAMS:
        histogram: Histogram = getattr(stats, name)
        histogram.counts = [int(values.get(histogram_field(name, histogram, b), 0)) for b in range(len(histogram.counts))]
        histogram.sum_s = float(values.get(f"{name}_sum_s", 0.0))
    for field, value in values.items():
        kind, _, rest = field.partition(":")
        name, _, outcome = rest.rpartition(":")
        if kind in ("map", "worker") and name and outcome in SETTLED_OUTCOMES:
            by = stats.maps if kind == "map" else stats.workers
            by.setdefault(name, {})[outcome] = int(value)
    return stats


def _settled(item: QueuedFrame, outcome: str) -> dict[str, int]:
    """The stats HASH's increments counting a settled frame for its map and its consumer."""
    add = {settled_field("worker", item.consumer, outcome): 1}
    if item.map_id:
        add[settled_field("map", item.map_id, outcome)] = 1
    return add


def _text(value: bytes | str | None) -> str:
    return value.decode(errors="replace") if isinstance(value, bytes) else (value or "")


def _seconds(value: bytes | None) -> float | None:
    """An entry's time field (Unix seconds) as a float; None when absent or not a number."""
    try:
        return None if value is None else float(value)
    except ValueError:
        return None


_ENTRY_ID = re.compile(r"\d+-\d+")
_SECONDS = re.compile(r"\d[\d.]*")


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """A map's record of one frame, as ``lua/records.lua`` writes it: ``status`` queued (``entry_id``),
    processed or failed (``settled_at_s``; 0 for a record written before records carried their time, so
    expired), and for a failed frame its ``dead_letter_id`` ("" when not linked), ``deliveries``, ``reason``."""

    status: str
    entry_id: str = ""
    settled_at_s: float | None = None
    dead_letter_id: str = ""
    deliveries: int = 0
    reason: str = ""

    @classmethod
    def parse(cls, text: str) -> FrameRecord:
        status, _, rest = text.partition(" ")
        if status == "queued":
            return cls(status, entry_id=rest)
        at, _, after = rest.partition(" ")
        if not _SECONDS.fullmatch(at):
            return cls(status, settled_at_s=0.0, reason=rest)  # written before records carried their time
        if status != "failed":
            return cls(status, settled_at_s=float(at))
        dead_letter_id, _, after = after.partition(" ")
        deliveries, _, reason = after.partition(" ")
        if not (_ENTRY_ID.fullmatch(dead_letter_id) and deliveries.isdigit()):
            return cls(status, settled_at_s=float(at), reason=rest)
        return cls(status, settled_at_s=float(at), dead_letter_id=dead_letter_id, deliveries=int(deliveries), reason=reason)


def shard_limits(limits: QueueLimits, shards: int) -> QueueLimits:
    """What one of ``shards`` ingest shards may hold: the overall limits (frames, bytes, dead letters) split
    evenly, each share at least the per-map limit (a map alone fills its shard as it would fill the queue)
    and at most the overall limit; the per-map limits and the retention as they are (a map lives in one
    shard). One shard: ``limits`` unchanged."""

    def share(total: int, at_least: int) -> int:
        return min(total, max(-(-total // shards), at_least))

    return dataclasses.replace(
        limits,
        max_queued_frames=share(limits.max_queued_frames, limits.max_queued_frames_per_map),
        max_queued_bytes=share(limits.max_queued_bytes, limits.max_queued_bytes_per_map),
        max_dead_letters=share(limits.max_dead_letters, 1),
        max_dead_letter_bytes=share(limits.max_dead_letter_bytes, 1),
    )


#: Where a delivery came from: its shard, entry id and fields (``QueuedFrame.receipt``).
Receipt = tuple[int, bytes | str, dict[bytes, bytes]]


class RedisFrameQueue:
    """``FrameQueue`` on Redis Streams. ``client``: an existing ``redis.Redis`` or ``RedisCluster`` (binary
    responses) instead of connecting to ``url`` (``connect_redis``: then ``socket_timeout_s`` must exceed
    the longest blocking read). ``group``: the consumer group; ``limits``: what ``put`` allows (default
    ``QueueLimits()``), the overall ones shared among ``shards`` ingest shards (``shard_limits``);
    ``clock``: Unix seconds (records' ages); ``stale_consumer_s``: how long a consumer of the group without
    pending entries or heartbeat stays before ``prepare`` removes it (``remove_stale_consumers``)."""

    def __init__(
        self,
        url: str = "redis://127.0.0.1:6379/0",
        *,
        client: RedisClient | None = None,
        group: str = "arcloud-workers",
        limits: QueueLimits | None = None,
        shards: int = 1,
        socket_timeout_s: float = 30.0,
        clock: Callable[[], float] = time.time,
        stale_consumer_s: float = STALE_CONSUMER_S,
    ) -> None:
        if not (isinstance(shards, int) and shards >= 1):
            raise InvalidInput("ingest_shards", "an integer >= 1", shards)
        if client is None:
            client = connect_redis(url, reply_timeout_s=socket_timeout_s)
            self._owns_client = True
        else:
            self._owns_client = False
        self.client = client
        self.group = group
        self.limits = limits or QueueLimits()
        self.shards = shards
        self._shard_limits = shard_limits(self.limits, shards)
        self._tags = [keys.shard_tag(shard, shards) for shard in range(shards)]
        self._clock = clock
        self.stale_consumer_s = stale_consumer_s
        self._accept = client.register_script(lua_source("records") + lua_source("accept_frame"))
        self._settle = client.register_script(lua_source("records") + lua_source("settle_frame"))
        self._dead_letters_kept = client.register_script(lua_source("dead_letters_kept"))
        self._claim_cursors: dict[tuple[str, int], str] = {}  # (consumer, shard) -> where its XAUTOCLAIM scan goes on
        self._next_shard: dict[str, int] = {}  # consumer -> the shard its next read starts at
        self._next_claim_shard: dict[str, int] = {}  # consumer -> the shard its next claim starts at

    def close(self) -> None:
        """Close the connections (when the queue made its client)."""
        if self._owns_client:
            self.client.close()

    def shard_of(self, map_id: str) -> int:
        """The ingest shard of the map's frames and records."""
        return keys.shard_of(map_id, self.shards)

    def shard_tag(self, shard: int) -> str:
        """The hash tag of the shard's keys (``keys.shard_tag``)."""
        return self._tags[shard]

    def _tag_of(self, map_id: str) -> str:
        return self._tags[self.shard_of(map_id)]

    def _where(self) -> str:
        return where(self.client)

    def _recreate_group(self, exc: redis.exceptions.ResponseError, shard: int) -> None:
        """Re-raise ``exc`` unless it says the consumer group is gone (``NOGROUP``: Redis restarted
        without its data); then create the groups again."""
        if not str(exc).startswith("NOGROUP"):
            raise exc
        log.warning(
            "consumer group %s of %s missing (Redis restarted without its data?); creating it",
            self.group,
            keys.ingest_stream(self._tags[shard]),
        )
        self.prepare()

    # --- producer ----------------------------------------------------------------------------------
    def put(self, frame: Frame, message: Any = None) -> bool:
        return self._queue(frame.map_id, frame.key, encode_frame(frame, message))

    def _queue(self, map_id: str, frame_key: str, payload: bytes) -> bool:
        """``lua/accept_frame.lua`` on the map's shard: True when queued, False for a duplicate; ``QueueFull``
        over a limit."""
        shard = self.shard_of(map_id)
        tag = self._tags[shard]
        limits = self._shard_limits
        with redis_errors("queue the frame", self._where):
            reply = self._accept(
                keys=[
                    keys.ingest_status_key(tag, map_id),
                    keys.ingest_sweep_key(tag, map_id),
                    keys.ingest_counts_key(tag, map_id),
                    keys.ingest_stream(tag),
                    keys.ingest_stats(tag),
                    keys.ingest_backlog(tag),
                ],
                args=[
                    frame_key,
                    map_id,
                    repr(self._clock()),
                    payload,
                    repr(limits.frame_record_retention_s),
                    RECORDS_SWEPT_PER_CALL,
                    limits.max_queued_frames,
                    limits.max_queued_bytes,
                    limits.max_queued_frames_per_map,
                    limits.max_queued_bytes_per_map,
                ],
            )
        if isinstance(reply, list):
            limit, held, frame_bytes = (_text(reply[0]), int(reply[1]), int(reply[2]))
            full = limits.full(limit, map_id, held, frame_bytes)
            if self.shards > 1 and limit in ("max_queued_frames", "max_queued_bytes"):
                total = getattr(self.limits, limit)
                raise QueueFull(f"ingest shard {shard} of {self.shards} (its share of {limit} {total}): {full}", limit)
            raise full
        return bool(reply != 0)  # the new entry id, or 0 for a duplicate

    def map_counts(self, map_id: str) -> tuple[int, int]:
        with redis_errors("read the map's counts", self._where):
            accepted, failed = self.client.hmget(keys.ingest_counts_key(self._tag_of(map_id), map_id), ["accepted", "failed"])
        return int(accepted or 0), int(failed or 0)

    def known_map(self, map_id: str) -> bool:
        with redis_errors("look the map up", self._where):
            return bool(self.client.exists(keys.ingest_counts_key(self._tag_of(map_id), map_id)))

    def _record(self, map_id: str, frame_key: str) -> FrameRecord | None:
        """The frame's record; None when there is none or it is past the retention."""
        raw = self.client.hget(keys.ingest_status_key(self._tag_of(map_id), map_id), frame_key)
        record = None if raw is None else FrameRecord.parse(_text(raw))
        return None if record is None or self._expired(record) else record

    def _expired(self, record: FrameRecord) -> bool:
        at = record.settled_at_s
        return at is not None and at < self._clock() - self.limits.frame_record_retention_s

    def frame_status(self, map_id: str, frame_key: str) -> FrameStatus | None:
        """From the map's status HASH; a frame with an entry is "processing" while the entry is pending
        (delivered, not yet acknowledged), "queued" before; one whose entry is gone is "unknown". The record
        is read again when the entry is gone: a worker settles the record and deletes the entry in one script
        (``lua/settle_frame.lua``), so a frame settled between the two reads is processed or failed, not lost."""
        stream = keys.ingest_stream(self._tag_of(map_id))
        with redis_errors("read the frame's status", self._where):
            record = self._record(map_id, frame_key)
            gone = (
                record is not None
                and record.status == "queued"
                and not self.client.xrange(stream, record.entry_id, record.entry_id)
            )
            if gone:
                record = self._record(map_id, frame_key)
            if record is None:
                return None
            if record.status == "processed":
                return FrameStatus("processed")
            if record.status == "failed":
                return FrameStatus("failed", record.reason)
            if record.status != "queued" or gone:
                return FrameStatus("unknown")  # lost: a retry queues it again
            entry_id = record.entry_id
            try:
                pending = self.client.xpending_range(stream, self.group, min=entry_id, max=entry_id, count=1)
            except redis.exceptions.ResponseError as exc:
                if not str(exc).startswith("NOGROUP"):
                    raise
                pending = []  # no group yet: nothing delivered
        return FrameStatus("processing" if pending else "queued")

    def failed_frames(self, map_id: str, limit: int) -> list[FailedFrame]:
        """Reads the map's whole status HASH (an operator's command: O(the map's kept records))."""
        tag = self._tag_of(map_id)
        with redis_errors("list the map's failed frames", self._where):
            records = [
                (_text(key), FrameRecord.parse(_text(value)))
                for key, value in self.client.hscan_iter(keys.ingest_status_key(tag, map_id), count=1000)
                if value.startswith(b"failed ")
            ]
            latest = sorted(
                ((key, r) for key, r in records if not self._expired(r)), key=lambda kr: kr[1].settled_at_s or 0.0, reverse=True
            )[:limit]
            linked = [r.dead_letter_id for _, r in latest if r.dead_letter_id]
            kept = self._dead_letters_kept(keys=[keys.ingest_dead_letter_stream(tag)], args=linked) if linked else []
        kept_ids = {dead_id for dead_id, is_kept in zip(linked, kept) if is_kept}
        return [
            FailedFrame(key, r.reason, r.deliveries, r.settled_at_s or 0.0, r.dead_letter_id in kept_ids) for key, r in latest
        ]

    def retry_failed(self, map_id: str, frame_key: str) -> bool:
        """Reads the frame's dead letter and accepts its payload again (``lua/accept_frame.lua``: a frame
        posted again since is a duplicate, False)."""
        with redis_errors("read the frame's dead letter", self._where):
            record = self._record(map_id, frame_key)
            if record is None or record.status != "failed":
                raise not_retriable(map_id, frame_key, None if record is None else record.status)
            dead_id = record.dead_letter_id
            dead_letters = keys.ingest_dead_letter_stream(self._tag_of(map_id))
            found = self.client.xrange(dead_letters, dead_id, dead_id) if dead_id else []
        if not found:
            raise not_retriable(map_id, frame_key, "failed")
        fields = cast("dict[bytes, bytes]", found[0][1])  # bytes: no decode_responses
        if _text(fields.get(b"map_id")) != map_id or _text(fields.get(b"frame_key")) != frame_key:
            raise StoreError(f"dead letter {dead_id} is not frame {frame_key} of map {map_id}")
        return self._queue(map_id, frame_key, fields.get(b"frame", b""))

    def forget_map(self, map_id: str) -> None:
        tag = self._tag_of(map_id)
        with redis_errors("forget the map", self._where):
            self.client.delete(
                keys.ingest_status_key(tag, map_id), keys.ingest_sweep_key(tag, map_id), keys.ingest_counts_key(tag, map_id)
            )
            self.client.hdel(keys.ingest_stats(tag), *(settled_field("map", map_id, o) for o in SETTLED_OUTCOMES))

    def stats(self) -> QueueStats:
        """Every shard's counters summed (one pipelined round trip; on a Cluster one per node)."""
        with redis_errors("read the ingest counters", self._where):
            pipe = self.client.pipeline(transaction=False)
            for tag in self._tags:
                pipe.hgetall(keys.ingest_stats(tag))
                pipe.xlen(keys.ingest_stream(tag))
                pipe.hgetall(keys.ingest_backlog(tag))
            replies = pipe.execute()
        totals: dict[str, float] = {}
        depth = queued_bytes = 0
        map_depth: dict[str, int] = {}
        for shard in range(self.shards):
            raw, shard_depth, backlog = replies[3 * shard : 3 * shard + 3]
            for field, value in raw.items():
                totals[_text(field)] = totals.get(_text(field), 0.0) + float(value)
            depth += int(shard_depth)
            for field, value in backlog.items():  # frames, bytes, frames:<map>, bytes:<map> (zeros dropped)
                name = _text(field)
                if name == "bytes":
                    queued_bytes += int(value)
                elif name.startswith("frames:") and int(value) > 0:
                    map_depth[name.removeprefix("frames:")] = int(value)
        stats = parse_stats({field: repr(v) if field.endswith("_sum_s") else str(int(v)) for field, v in totals.items()})
        stats.queue_depth = depth
        stats.queued_bytes = queued_bytes
        stats.map_depth = map_depth
        return stats

    def health(self) -> dict[str, str]:
        """``redis``: it answers; ``consumer_group``: the workers' group exists on every shard (it does not
        after Redis restarted without its data, until a worker reads again)."""
        try:
            self.client.ping()
        except Exception as exc:  # noqa: BLE001 - readiness reports, never raises
            return {"redis": f"unreachable: {type(exc).__name__}"}
        missing = []
        try:
            for tag in self._tags:
                stream = keys.ingest_stream(tag)
                try:
                    groups = self.client.xinfo_groups(stream)
                except redis.exceptions.ResponseError:  # "no such key": no stream, so no group
                    groups = []
                if not any(_text(g.get("name")) == self.group for g in groups):
                    missing.append(stream)
        except Exception as exc:  # noqa: BLE001 - readiness reports, never raises
            return {"redis": f"unreachable: {type(exc).__name__}"}
        return {"redis": "ok", "consumer_group": f"missing: no group {self.group} on {', '.join(missing)}" if missing else "ok"}

    def prepare(self) -> None:
        """Write the number of shards unless written (``InvalidInput`` naming ``ingest_shards`` when another
        number is), and create each shard's consumer group (and stream) unless it exists. A group starts
        at its stream's beginning so that frames queued before any worker started are read."""
        with redis_errors("create the consumer groups", self._where):
            self.client.set(keys.INGEST_SHARDS, self.shards, nx=True)
        self.check_shards()
        with redis_errors("create the consumer groups", self._where):
            for tag in self._tags:
                try:
                    self.client.xgroup_create(keys.ingest_stream(tag), self.group, id="0", mkstream=True)
                except redis.exceptions.ResponseError as exc:
                    if "BUSYGROUP" not in str(exc):
                        raise
        self.remove_stale_consumers()

    def remove_stale_consumers(self) -> list[str]:
        """Remove the group's consumers left by workers that stopped or died (each start of a worker leaves one:
        consumer names are host-pid): on every shard, a consumer with no pending entry, idle (Redis's ``idle``:
        since it last read or claimed) longer than ``stale_consumer_s`` and without a heartbeat as recent is
        deleted (``XGROUP DELCONSUMER``), and so are heartbeats older than that and the per-worker counters of
        consumers in no group any more. A consumer holding entries stays until they are claimed; a live worker
        beats every second, so it is never taken for a stale one (its next read would create it again anyway).
        Returns the consumers deleted. Called by ``prepare``, so every worker (and API) that starts sweeps."""
        stale_s = self.stale_consumer_s
        now = time.time()
        removed: set[str] = set()
        with redis_errors("remove stale consumers", self._where):
            beats = {_text(name): float(seen) for name, seen in self.client.hgetall(keys.INGEST_WORKERS).items()}
            fresh = {name for name, seen in beats.items() if now - seen <= stale_s}
            kept: set[str] = set()
            for tag in self._tags:
                stream = keys.ingest_stream(tag)
                try:
                    consumers = self.client.xinfo_consumers(stream, self.group)
                except redis.exceptions.ResponseError:  # no stream or no group: no consumers
                    continue
                for consumer in consumers:
                    name = _text(consumer["name"])
                    if int(consumer["pending"]) == 0 and int(consumer["idle"]) > stale_s * 1000 and name not in fresh:
                        self.client.xgroup_delconsumer(stream, self.group, name)
                        removed.add(name)
                    else:
                        kept.add(name)
            old_beats = [name for name in beats if name not in fresh and name not in kept]
            if old_beats:
                self.client.hdel(keys.INGEST_WORKERS, *old_beats)
                self.client.hdel(keys.INGEST_WORKER_SETTINGS, *old_beats)
            for tag in self._tags:
                fields = [_text(f) for f in self.client.hkeys(keys.ingest_stats(tag))]
                gone = [f for f in fields if f.startswith("worker:") and f[7:].rpartition(":")[0] not in kept | fresh]
                if gone:
                    self.client.hdel(keys.ingest_stats(tag), *gone)
        if removed:
            log.info("removed %d stale consumers of group %s: %s", len(removed), self.group, ", ".join(sorted(removed)))
        return sorted(removed)

    def check_shards(self) -> None:
        """``InvalidInput`` naming ``ingest_shards`` when this Redis's queue has another number of shards
        than this one (``prepare`` writes it); reads only."""
        with redis_errors("read the number of ingest shards", self._where):
            pinned = self.client.get(keys.INGEST_SHARDS)
        if pinned is not None and int(pinned) != self.shards:
            raise InvalidInput(
                "ingest_shards",
                f"{int(pinned)}, the number of shards this Redis's queue has ({keys.INGEST_SHARDS}; changing it: "
                "docs/service.md)",
                self.shards,
            )

    # --- consumer ----------------------------------------------------------------------------------
    def _turn(self, turns: dict[str, int], consumer: str) -> list[int]:
        """The shards in the order ``consumer`` looks at them this time: from the one after where it
        started last time, round."""
        first = turns.get(consumer, zlib.crc32(consumer.encode()) % self.shards)
        turns[consumer] = (first + 1) % self.shards
        return [(first + n) % self.shards for n in range(self.shards)]

    def take(self, consumer: str, *, block_s: float) -> QueuedFrame | None:
        """One look at each shard without waiting (one shard: a blocking read at once), then a wait of
        ``block_s`` shared among the shards on the first of them. ``block_s`` 0: no blocking read at all
        (a blocked read times out on Redis's clock, every 1 / ``hz``: BLOCK 1 took 0-100 ms)."""
        order = self._turn(self._next_shard, consumer)
        if self.shards > 1 or block_s <= 0:
            for shard in order:
                item = self._read(shard, consumer, block_ms=None)
                if item is not None:
                    return item
            if block_s <= 0:
                return None
        return self._read(order[0], consumer, block_ms=max(1, int(block_s * 1000 / self.shards)))

    def _read(self, shard: int, consumer: str, *, block_ms: int | None) -> QueuedFrame | None:
        stream = keys.ingest_stream(self._tags[shard])

        def read() -> _ReadReply:
            return cast(_ReadReply, self.client.xreadgroup(self.group, consumer, {stream: ">"}, count=1, block=block_ms))

        with redis_errors("read the ingest stream", self._where):
            try:
                reply = read()
            except redis.exceptions.ResponseError as exc:
                self._recreate_group(exc, shard)
                reply = read()
        for _stream, entries in reply or []:
            for entry_id, fields in entries:
                return self._delivery(consumer, (shard, entry_id, fields), deliveries=1)
        return None

    def claim_abandoned(self, consumer: str, *, min_idle_s: float) -> QueuedFrame | None:
        """One XAUTOCLAIM step on each shard in turn, until one gives an entry."""
        min_idle_ms = max(1, int(min_idle_s * 1000))
        for shard in self._turn(self._next_claim_shard, consumer):
            item = self._claim(shard, consumer, min_idle_ms)
            if item is not None:
                return item
        return None

    def _claim(self, shard: int, consumer: str, min_idle_ms: int) -> QueuedFrame | None:
        stream = keys.ingest_stream(self._tags[shard])
        cursor = (consumer, shard)
        with redis_errors("claim an abandoned entry", self._where):
            try:
                next_cursor, entries, *_deleted = self.client.xautoclaim(
                    stream, self.group, consumer, min_idle_ms, start_id=self._claim_cursors.get(cursor, "0-0"), count=1
                )
            except redis.exceptions.ResponseError as exc:
                self._recreate_group(exc, shard)
                self._claim_cursors.pop(cursor, None)
                return None  # a new group has nothing pending
            self._claim_cursors[cursor] = _text(next_cursor) or "0-0"
            for entry_id, fields in entries:
                if not fields:
                    continue  # deleted while pending (Redis drops it from the pending list)
                pending = self.client.xpending_range(stream, self.group, min=entry_id, max=entry_id, count=1)
                if not pending:
                    continue  # acknowledged by its late worker since: settled
                deliveries = int(pending[0]["times_delivered"])
                self.client.hincrby(keys.ingest_stats(self._tags[shard]), "claimed", 1)
                log.warning("%s claimed entry %s of %s (delivery %d)", consumer, _text(entry_id), stream, deliveries)
                return self._delivery(consumer, (shard, entry_id, fields), deliveries=deliveries)
        return None

    def _delivery(self, consumer: str, receipt: Receipt, *, deliveries: int) -> QueuedFrame:
        _shard, entry_id, fields = receipt
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
            _text(entry_id),
            undecodable,
            accepted_at_s=_seconds(fields.get(b"accepted_at_s")),
            receipt=receipt,
        )

    def ack(self, item: QueuedFrame, *, redelivered: bool, retries: int = 0, timings: FrameTimings | None = None) -> None:
        timings = timings or FrameTimings()
        add = {"retried": retries} if retries else {}
        sums: dict[str, float] = {}
        counters: dict[str, Any] = {"add": add, "sums": sums}
        add |= _settled(item, "redelivered" if redelivered else "processed")
        if redelivered:
            add["redelivered"] = 1
        else:
            add["processed"] = 1
            add[latency_field(latency_bucket(timings.step_s))] = 1
            sums["latency_sum_s"] = timings.step_s
            for name, seconds in (("queue_wait", timings.queue_wait_s), ("lock_wait", timings.lock_wait_s)):
                if seconds is not None:
                    histogram = Histogram.empty(WAIT_BUCKETS_S)
                    add[histogram_field(name, histogram, histogram.bucket(seconds))] = 1
                    sums[f"{name}_sum_s"] = seconds
        with redis_errors("acknowledge the entry", self._where):
            self._settle_entry(item, counters, ["processed"])

    def fail(self, item: QueuedFrame, reason: str) -> None:
        return None  # left pending: claimed again after min_idle_s, dead-lettered by the worker in the end

    def dead_letter(self, item: QueuedFrame, reason: str) -> None:
        """Move the entry to its shard's dead-letter stream (with the reason), record its frame as failed."""
        limits = self._shard_limits
        with redis_errors("dead-letter the entry", self._where):
            self._settle_entry(
                item,
                {"add": {"failed": 1} | _settled(item, "failed")},
                ["failed", reason, item.deliveries, item.consumer, limits.max_dead_letters, limits.max_dead_letter_bytes],
            )

    def _settle_entry(self, item: QueuedFrame, counters: dict[str, Any], outcome: list[Any]) -> None:
        """``lua/settle_frame.lua`` on the delivery's entry, in the shard it came from."""
        shard, entry_id, fields = cast(Receipt, item.receipt)
        tag, map_id, frame_key = self._tags[shard], item.map_id, item.frame_key
        self._settle(
            keys=[
                keys.ingest_stream(tag),
                keys.ingest_stats(tag),
                keys.ingest_backlog(tag),
                keys.ingest_status_key(tag, map_id),
                keys.ingest_sweep_key(tag, map_id),
                keys.ingest_counts_key(tag, map_id),
                keys.ingest_dead_letter_stream(tag),
                keys.ingest_dead_letter_bytes(tag),
            ],
            args=[
                self.group,
                entry_id,
                map_id,
                frame_key,
                fields.get(b"bytes", b""),
                repr(self._clock()),
                repr(self.limits.frame_record_retention_s),
                RECORDS_SWEPT_PER_CALL,
                json.dumps(counters),
                *outcome,
            ],
        )

    def heartbeat(self, consumer: str, in_hand: Sequence[QueuedFrame], settings: Mapping[str, object] | None = None) -> None:
        """Write the heartbeat, and reset the idle time of the entries in hand (XCLAIM JUSTID to its own
        consumer: no new delivery; one call a shard) so that a long step is never taken for an abandoned one."""
        by_shard: dict[int, list[bytes | str]] = {}
        for item in in_hand:
            shard, entry_id, _fields = cast(Receipt, item.receipt)
            by_shard.setdefault(shard, []).append(entry_id)
        with redis_errors("write the heartbeat", self._where):
            self.client.hset(keys.INGEST_WORKERS, consumer, repr(time.time()))
            if settings is not None:
                self.client.hset(keys.INGEST_WORKER_SETTINGS, consumer, json.dumps(settings, sort_keys=True))
            for shard, entry_ids in by_shard.items():
                try:
                    self.client.xclaim(keys.ingest_stream(self._tags[shard]), self.group, consumer, 0, [*entry_ids], justid=True)
                except redis.exceptions.ResponseError as exc:
                    if not str(exc).startswith("NOGROUP"):
                        raise
                    # The group went with Redis's data, and the entries with it: nothing left to keep fresh.

    def leave(self, consumer: str) -> None:
        with redis_errors("remove the heartbeat", self._where):
            self.client.hdel(keys.INGEST_WORKERS, consumer)
            self.client.hdel(keys.INGEST_WORKER_SETTINGS, consumer)

    def live_consumers(self, max_age_s: float) -> list[str]:
        now = time.time()
        with redis_errors("read the heartbeats", self._where):
            beats = self.client.hgetall(keys.INGEST_WORKERS)
        return sorted(_text(name) for name, seen in beats.items() if now - float(seen) <= max_age_s)

    def live_settings(self, max_age_s: float) -> dict[str, dict[str, object]]:
        live = self.live_consumers(max_age_s)
        if not live:
            return {}
        with redis_errors("read the workers' settings", self._where):
            given = self.client.hmget(keys.INGEST_WORKER_SETTINGS, live)
        return {name: json.loads(value) for name, value in zip(live, given, strict=True) if value is not None}
