"""Every Redis key arcloud uses, in one place.

All keys of one map share the hash tag ``{<map_id>}``, so a map lives on one Redis Cluster slot (its
Lua scripts touch one slot) while many maps spread over a cluster. Map ids are checked by
``arcloud.core.checks.check_map_id`` (letters, digits, '.', '_', '-'), and ``map_pattern`` escapes glob
characters anyway, so a map's keys match the pattern ``map_pattern(map_id)`` and nothing else.

    arcloud:{m}:header              STRING  the map's header (``core.header.MapHeader``, JSON): the settings its data
                                            is written under; set once, by the map's first ``open_map`` (SET NX)
    arcloud:{m}:ids                 STRING  object id counter (INCRBY); kept by ``delete_map``
    arcloud:{m}:processed           HASH    processed frame key ("<device_id>/<frame_id>") -> when its commit was
                                            written (Unix s); kept ``frame_record_retention_s`` (``RedisStore``)
    arcloud:{m}:processed:count     STRING  frames of the map processed (INCR in the commit; never lowered)
    arcloud:{m}:processed:sweep     STRING  where the commits' sweep of expired marks goes on (HSCAN cursor)
    arcloud:{m}:given-up:<entry>    STRING  a queue entry of the map's frames given up (``give_up_frame``, before its
                                            dead letter): the commit refuses a frame delivered from it; EX
                                            ``frame_record_retention_s``
    arcloud:{m}:bounds              HASH    object id -> 6 float64 little-endian (min xyz, max xyz); the registry of objects
    arcloud:{m}:meta                HASH    object id -> metadata (``codec.encode_meta``): listing needs one read
    arcloud:{m}:obj:<id>            HASH    one object: ``version`` (the fence), ``cells`` (where it is indexed,
                                            "i:j:k i:j:k ..."), ``voxels`` (``codec.encode_voxels``), and its
                                            counters ``missed`` (``n_missed``), ``gone`` (``n_gone``)
    arcloud:{m}:retired             HASH    retired object id -> its metadata JSON when it left: the map's history
    arcloud:{m}:retired:at          ZSET    retired object id, scored by when it left (Unix s); kept
                                            ``retired_history_s``, at most ``RETIRED_HISTORY_MAX_PER_MAP``
    arcloud:{m}:changes             STREAM  the map's change log (``core.change``): entry ``<version>-0`` per commit with
                                            events (``at``, ``frame``, ``events``: ``codec.encode_events``), appended
                                            by the commit script; ``MAXLEN ~`` the store's ``change_log_entries``
    arcloud:{m}:changes:version     STRING  the map's version: the change log's last entry (set by the commit); kept by
                                            ``delete_map``, one more (the deletion)
    arcloud:{m}:changes:published   STRING  the version up to which the log was published over Zenoh (only raised); kept
                                            by ``delete_map``, raised to the version
    arcloud:{m}:changes:began       STRING  when the log began (Redis's TIME, "seconds.microseconds", set with its first
                                            entry): a log made again after a loss begins at another time; kept by
                                            ``delete_map``
    arcloud:{m}:cell:<i>:<j>:<k>    SET     ids of the objects whose bounds touch this index cell
    arcloud:{m}:lock:<id>           STRING  lock token on an object (PX ttl)
    arcloud:{m}:claim:<i>:<j>:<k>   STRING  space-claim token on an index cell (PX ttl)
    <lock or claim key>:wanted      STRING  someone waits for the lock or claim (PX its holder's ttl; set by
                                            ``lua/acquire.lua``): its release wakes one waiter
    <lock or claim key>:wake        LIST    a token for the waiter blocked on it (BLPOP; pushed by the release or
                                            the commit, ``lua/leases.lua``, at most one, PX 1 s)
    arcloud:alignments:{m}          HASH    device id -> its ``device_from_map`` (JSON, 16 numbers row-major;
                                            ``redis_alignments``): outside ``map_pattern``, so that deleting the
                                            map's objects leaves it (the API's map deletion forgets it)
    arcloud:deletion:{m}            STRING  the map's deletion (``ports.MapDeletion`` JSON) while ``delete_map`` runs,
                                            then ``DELETION_KEPT_S`` (EX, renewed as it goes on): outside ``map_pattern``

Ingest shards (``arcloud.stores.redis_queue``): the frame queue is ``n`` shards (the setting ``ingest_shards``,
pinned in Redis), a map's frames going to shard ``k = shard_of(map_id, n)``. Every key of shard ``k`` carries
the hash tag ``t = shard_tag(k, n)`` (``s<k>.<j>``: ``s0.0`` with one shard), its per-map frame records
included, so that the scripts that accept and settle a frame touch one Cluster slot, and the tags put the
shards' slots in equal ranges of the slot space, so that a cluster's primaries share them:

    arcloud:ingest:{t}              STREAM  frames to process (protobuf ``Frame`` bytes), one consumer group of workers
    arcloud:ingest:{t}:dead         STREAM  frames given up on, with the reason (``max_dead_letters``, shared among shards)
    arcloud:ingest:{t}:dead:bytes   STRING  the dead letters' frame bytes together (``max_dead_letter_bytes``)
    arcloud:ingest:{t}:backlog      HASH    ``frames``, ``bytes``, ``frames:<map>``, ``bytes:<map>``: what the stream
                                            holds of frames accepted and not settled, against ``QueueLimits``
    arcloud:ingest:{t}:stats        HASH    the shard's counters (``QueueStats`` fields) and step latency histogram
    arcloud:ingest:{t}:map:<m>:status  HASH  frame key -> "queued <entry id>" | "processed <settled_at_s>" |
                                            "failed <settled_at_s> <dead-letter id> <deliveries> <reason>": the
                                            frames the ingest accepted for the map and keeps a record of
                                            (settled ones for ``frame_record_retention_s``)
    arcloud:ingest:{t}:map:<m>:sweep   STRING  where the sweep of expired records goes on (HSCAN cursor)
    arcloud:ingest:{t}:map:<m>:counts  HASH    ``accepted``, ``failed``: the map's frame counts (records
                                            expiring do not lower them)

Service-wide keys (no tag: single-key commands only):

    arcloud:ingest:shards           STRING  how many ingest shards this Redis's queue has (set by the first
                                            process to prepare the queue; others with another count refuse to start)
    arcloud:ingest:workers          HASH    consumer name -> last heartbeat (Unix seconds)
    arcloud:ingest:worker-settings  HASH    consumer name -> what it maps with (JSON: the map settings, a digest of
                                            its Params), written with its heartbeat
    arcloud:maps                    HASH    map id -> when its objects last changed (Unix s); written by open_map, commit
    arcloud:keys                    HASH    API key id -> its record (JSON, the secret's SHA-256; ``redis_api_keys``)
    arcloud:viewer:<digest>         STRING  a viewer ticket or session (``ViewerGrant`` JSON) by its secret's SHA-256
                                            (``redis_viewer_passes``, PX until it expires)
    arcloud:viewer-key:<key-id>     ZSET    one API key's live viewer passes, digest by expiry (Unix ms): at most
                                            ``MAX_VIEWER_PASSES_PER_KEY``, the first to end ended beyond
    arcloud:rate:<bucket>           STRING  a rate limit's theoretical arrival time (``redis_rate``, PX ttl)

``RedisStore.delete_map`` removes every key matching ``map_pattern`` but the four it keeps (``ids``,
``changes:version``, ``changes:began``, ``changes:published``: a map made again goes on from them); the queue's ``forget_map`` removes the
map's frame records and counts from its shard (not its part of the shard's backlog: frames still queued
leave it when they settle).
"""

from __future__ import annotations

import binascii
import itertools
import zlib
from functools import cache

PREFIX = "arcloud"
CLUSTER_SLOTS = 16384

# Suffixes after the map prefix; the Lua scripts build per-object and per-cell keys from these.
IDS = "ids"
PROCESSED = "processed"
GIVEN_UP = "given-up"
BOUNDS = "bounds"
META = "meta"
HEADER = "header"
OBJECT = "obj"
CELL = "cell"
LOCK = "lock"
CLAIM = "claim"
WAKE = "wake"
RETIRED = "retired"
CHANGES = "changes"


def map_prefix(map_id: str) -> str:
    """``arcloud:{<map_id>}``: the start of every key of the map (the braces are the hash tag)."""
    return f"{PREFIX}:{{{map_id}}}"


def glob_escape(text: str) -> str:
    """``text`` as a literal in a Redis glob pattern: ``\\``, ``*``, ``?``, ``[`` and ``]`` escaped."""
    return "".join("\\" + c if c in "\\*?[]" else c for c in text)


def map_pattern(map_id: str) -> str:
    """SCAN/KEYS pattern matching every key of the map and no other map's (whatever the id holds)."""
    return f"{glob_escape(map_prefix(map_id))}:*"


def ids_key(map_id: str) -> str:
    return f"{map_prefix(map_id)}:{IDS}"


def processed_key(map_id: str) -> str:
    return f"{map_prefix(map_id)}:{PROCESSED}"


def processed_count_key(map_id: str) -> str:
    return f"{map_prefix(map_id)}:{PROCESSED}:count"


def processed_sweep_key(map_id: str) -> str:
    return f"{map_prefix(map_id)}:{PROCESSED}:sweep"


def given_up_key(map_id: str, entry_id: str) -> str:
    return f"{map_prefix(map_id)}:{GIVEN_UP}:{entry_id}"


def bounds_key(map_id: str) -> str:
    return f"{map_prefix(map_id)}:{BOUNDS}"


def meta_key(map_id: str) -> str:
    return f"{map_prefix(map_id)}:{META}"


def retired_key(map_id: str) -> str:
    """The map's history of retired objects: id -> metadata JSON (``RedisStore.retired_objects``)."""
    return f"{map_prefix(map_id)}:{RETIRED}"


def retired_at_key(map_id: str) -> str:
    """When each retired object of the history left the map: a ZSET id -> Unix seconds."""
    return f"{map_prefix(map_id)}:{RETIRED}:at"


def changes_key(map_id: str) -> str:
    """The map's change log (a STREAM, ``core.change``)."""
    return f"{map_prefix(map_id)}:{CHANGES}"


def version_key(map_id: str) -> str:
    """The map's version: the id of its change log's last entry."""
    return f"{map_prefix(map_id)}:{CHANGES}:version"


def began_key(map_id: str) -> str:
    """When the map's change log began (Redis's clock, "seconds.microseconds"): a log made again after Redis lost the
    map begins at another time, which tells a reader holding an old version (``ChangesSince.began``)."""
    return f"{map_prefix(map_id)}:{CHANGES}:began"


def published_key(map_id: str) -> str:
    """The version up to which the map's change log was published (``service.change_feed``)."""
    return f"{map_prefix(map_id)}:{CHANGES}:published"


def header_key(map_id: str) -> str:
    """The map's header (``core.header.MapHeader``, JSON): the settings its data was written under."""
    return f"{map_prefix(map_id)}:{HEADER}"


def alignments_key(map_id: str) -> str:
    """The map's device alignments (``stores.redis_alignments``): the map's hash tag, not its prefix."""
    return f"{PREFIX}:alignments:{{{map_id}}}"


def deletion_key(map_id: str) -> str:
    """The map's deletion record (``RedisStore.delete_map``): the map's hash tag, not its prefix."""
    return f"{PREFIX}:deletion:{{{map_id}}}"


def cell_keys_listed(map_id: str, cells_field: str) -> list[str]:
    """The index cell keys an object hash's ``cells`` field names (\"i:j:k i:j:k ...\")."""
    return [f"{map_prefix(map_id)}:{CELL}:{name}" for name in cells_field.split()]


def object_key(map_id: str, object_id: int) -> str:
    return f"{map_prefix(map_id)}:{OBJECT}:{int(object_id)}"


def cell_name(cell: tuple[int, int, int]) -> str:
    """``i:j:k``: the part of cell and claim keys that names an index cell."""
    i, j, k = (int(c) for c in cell)
    return f"{i}:{j}:{k}"


def cell_key(map_id: str, cell: tuple[int, int, int]) -> str:
    return f"{map_prefix(map_id)}:{CELL}:{cell_name(cell)}"


def lease_wake_key(lease_key: str) -> str:
    """The list a caller waiting for a lock or claim key blocks on (``lua/leases.lua`` builds the same name)."""
    return f"{lease_key}:{WAKE}"


def lock_key(map_id: str, object_id: int) -> str:
    return f"{map_prefix(map_id)}:{LOCK}:{int(object_id)}"


def claim_key(map_id: str, cell: tuple[int, int, int]) -> str:
    return f"{map_prefix(map_id)}:{CLAIM}:{cell_name(cell)}"


def hash_tag(key: str) -> str:
    """The hash tag of a key as Redis Cluster computes it (the text between the first '{' and the
    next '}', when non-empty), or the whole key."""
    start = key.find("{")
    if start >= 0:
        end = key.find("}", start + 1)
        if end > start + 1:
            return key[start + 1 : end]
    return key


def shard_of(map_id: str, n_shards: int) -> int:
    """The ingest shard of a map: CRC-32 of its id modulo ``n_shards`` (the same in every process, unlike
    ``hash``)."""
    return zlib.crc32(map_id.encode()) % n_shards


def cluster_slot(key: str) -> int:
    """The Redis Cluster slot of a key: CRC-16/XMODEM of its hash tag (or of the whole key), mod 16384."""
    return binascii.crc_hqx(hash_tag(key).encode(), 0) % CLUSTER_SLOTS


@cache
def shard_tag(shard: int, n_shards: int) -> str:
    """The hash tag of ingest shard ``shard`` of ``n_shards``: ``s<shard>.<j>``, ``j`` the least integer that
    puts its Cluster slot in the ``shard``-th of ``n_shards`` equal ranges of the slots. A cluster whose
    primaries hold equal ranges (``redis-cli --cluster create``) so holds as many shards on each primary
    as it can (3 shards on 3 primaries: one each), where ``s0``, ``s1``, ``s2`` would put two on one."""
    if not 0 <= shard < n_shards:
        raise ValueError(f"shard {shard} of {n_shards}")
    first, end = shard * CLUSTER_SLOTS // n_shards, (shard + 1) * CLUSTER_SLOTS // n_shards
    for j in itertools.count():
        tag = f"s{shard}.{j}"
        if first <= cluster_slot(tag) < end:
            return tag
    raise AssertionError("unreachable")  # itertools.count never ends


def ingest_stream(tag: str) -> str:
    """``arcloud:ingest:{<tag>}``: a shard's stream (``tag``: its ``shard_tag``), and the start of every key of the shard."""
    return f"{PREFIX}:ingest:{{{tag}}}"


def ingest_dead_letter_stream(tag: str) -> str:
    return f"{ingest_stream(tag)}:dead"


def ingest_dead_letter_bytes(tag: str) -> str:
    return f"{ingest_stream(tag)}:dead:bytes"


def ingest_backlog(tag: str) -> str:
    return f"{ingest_stream(tag)}:backlog"


def ingest_stats(tag: str) -> str:
    return f"{ingest_stream(tag)}:stats"


def ingest_status_key(tag: str, map_id: str) -> str:
    return f"{ingest_stream(tag)}:map:{map_id}:status"


def ingest_sweep_key(tag: str, map_id: str) -> str:
    return f"{ingest_stream(tag)}:map:{map_id}:sweep"


def ingest_counts_key(tag: str, map_id: str) -> str:
    return f"{ingest_stream(tag)}:map:{map_id}:counts"


# Service-wide keys (no tag).
INGEST_SHARDS = f"{PREFIX}:ingest:shards"
INGEST_WORKERS = f"{PREFIX}:ingest:workers"
INGEST_WORKER_SETTINGS = f"{PREFIX}:ingest:worker-settings"
API_KEYS = f"{PREFIX}:keys"
MAPS = f"{PREFIX}:maps"


def viewer_pass_key(digest: str) -> str:
    """A viewer ticket or session, by the SHA-256 (hex) of its secret."""
    return f"{PREFIX}:viewer:{digest}"


def viewer_key_passes_key(key_id: str) -> str:
    """The live viewer passes of one API key: a sorted set of their digests by expiry (Unix ms)."""
    return f"{PREFIX}:viewer-key:{key_id}"


def rate_key(bucket: str) -> str:
    """A rate limit bucket (``key:<key id>``, ``ip:<address>``, ``map:<map id>:frames``, ``auth-failures:<address>``)."""
    return f"{PREFIX}:rate:{bucket}"
