"""The Redis object store: one map shared by many workers on many machines.

Same semantics as the embedded ``MemoryStore`` (one contract suite tests both). The layout is in
``arcloud.stores.keys`` (every key of a map under the hash tag ``{map_id}``: one Redis Cluster slot per
map), the object encoding in ``arcloud.stores.codec``, the atomic steps in ``stores/lua/*.lua``:

- Spatial index: cubic cells of ``cell_m`` -> SET of object ids, plus a HASH id -> packed bounds.
  ``query_region`` reads the cells the box covers and their objects' bounds in one round trip (Lua),
  then tests the bounds exactly. When the box spans more cells than twice the map's objects (a small
  map, like the embedded store's "fewer occupied cells" shortcut), the script reads the bounds HASH
  instead; a box of more than ``max_query_cells`` cells (or an unbounded one) reads the bounds HASH
  too, to keep one script call short: O(objects of the map) then.
- Locks and space claims: keys holding a random token with a TTL (``SET key token PX ttl``), taken
  all-or-nothing by one Lua script (in sorted order; never some held while waiting), retried until
  ``timeout_s`` (0: try once); released by a script that deletes only the keys still holding the lease's
  token, or by the commit that wrote through the lease (``lua/leases.lua`` in both). A caller that found a
  key busy blocks (BLPOP, at most ``WAKE_MAX_S``, at most the holder's ttl) on that key's wake list, which
  the release pushes a token to, so the next waiter tries again within a round trip of the release and
  waiting costs no CPU (it polled with a backoff of up to 50 ms before: issue 24 measured 0.4-0.5 s of lock
  wait a frame with 16 workers on one map; docs/scaling.md). The embedded store waits on a condition the
  same way.
- Objects: a HASH per object (``version``: the fence, ``cells``: where it is indexed, ``voxels``: the
  ``codec`` blob), the metadata JSON in one HASH per map (listing a map is one read), the bounds in
  another. ``get`` of many ids is one MULTI/EXEC pipeline (a consistent snapshot).
- ``commit``: one Lua script checks every fence (each lease still holds its keys, each object is at the
  expected version, the frame is not recorded yet) and then writes objects, index, bounds and the frame
  mark and releases the leases (waking their waiters: no release round trip after, issue 24), or writes
  nothing and leaves them held. A worker whose lock expired cannot overwrite newer data. Redis runs nothing
  else while a script runs, so one script adds and removes at most ``cells.MAX_SCRIPT_CELLS`` index cells (an object
  covers at most ``cells.MAX_OBJECT_CELLS``; the script counts the cells it would remove before it writes) and
  one lock call takes at most ``cells.MAX_LOCKS_PER_CALL`` objects: a few tens of milliseconds whatever a
  request holds (``TooManyCells`` / ``InvalidInput`` beyond, nothing written).
- The change log (``core.change``): a STREAM per map, appended by the commit script (``XADD`` with the id
  ``<version>-0``, the map's version kept beside it: consecutive, so a reader knows what it missed), before
  the script writes anything and after every check (a refused commit appends nothing), trimmed as it goes
  (``MAXLEN ~ change_log_entries``). ``changes_since`` reads it (``XRANGE`` from a version); how far it was
  published over Zenoh is one more STRING (``mark_published``: only raised, by ``lua/mark_published.lua``).
- Retired objects (the change's ``retired``): deleted like others, their metadata JSON kept in the map's
  history (a HASH, and a ZSET of when each left), trimmed by each commit to ``retired_history_s`` and
  ``RETIRED_HISTORY_MAX_PER_MAP``; ``retired_objects`` reads it.
- Processed frames: a HASH frame key -> when its commit was written, and a counter (``count_frames``).
  A mark is kept ``frame_record_retention_s`` (the frame queue's records are kept as long, and a frame
  settles after its commit, so a frame posted again after its queue record went finds no mark either):
  long enough for any redelivery; after it the frame counts as not processed. Each commit sweeps about
  ``RECORDS_SWEPT_PER_CALL`` marks on from where the last one stopped (HSCAN, ``lua/records.lua``) and
  drops the expired ones, so the HASH holds about a retention's frames. A queue entry given up
  (``give_up_frame``, before the queue dead-letters it) is a STRING of the same retention that the commit
  script looks for: a worker that held the entry and resumes after it was given up writes nothing.
- ``new_ids``: INCRBY on the map's counter, unique across processes.
- ``delete_map``: records the deletion (``arcloud:deletion:{map}``, ``map_deletion`` reads it), takes the map off
  the list and unlinks its header (the map is unknown from then on, and the API refuses its frames), then
  deletes its objects ``DELETE_OBJECTS`` at a time (HSCAN of the bounds registry: each object's hash and the
  index cells it lists, ``DELETE_BATCH`` keys a call, then its registry fields), recording how far it got after
  each step, then unlinks the registries and SCANs ``arcloud:{map}:*`` (on every primary of a cluster) for what
  is left (frame marks, leases, what writers added meanwhile), but for the map's id counter, version and published
  version: it raises the version by one (and the published one to it; ``ObjectStore.delete_map``: a map made again
  never reuses a version or an object id). It logs its progress every ``PROGRESS_LOG_S``:
  Redis answers others between calls whatever the map holds (one script deleting a map of 5 million index cells
  held Redis 9 s). Not atomic against writers of the same map that run at the same time; called again after a
  deletion stopped half way (its process died), it goes on from what is left.

How long a call may take: ``reply_timeout_s`` bounds each wait for a reply or a connection (workers
30 s; the API ``api_redis_timeout_s``, 2 s, so that a hung Redis answers ``StoreUnavailable`` within
about that). A command that meets a connection error (a restarted Redis: its pooled connection is dead)
is sent again once on a new connection; a timeout is not (``connect_redis``). If a commit's
reply is lost and the retry finds the commit already applied, it returns False (with a ``frame_key``:
the frame is recorded) or raises ``StaleLease`` (without): the data was written once either way, and the
leases released by that first run (the caller's release then finds none of their keys: never another
holder's). The lock script is idempotent per token, so a retried acquire does not wait for itself.

On a Redis Cluster (``connect_redis`` with a ``redis+cluster://`` URL: a ``RedisCluster`` client) the same
code runs: every script and every MULTI/EXEC pipeline names keys of one map (one slot; the scripts build
their other keys from the map prefix, so they stay in it: ``tests/stores/test_redis_cluster.py`` checks each
script's keys), the service-wide ``arcloud:maps`` is written by its own command, and ``delete_map``'s SCAN
runs on every primary.

redis-py exceptions become ``arcloud.errors`` at the one boundary of every Redis adapter,
``stores.redis_errors``: ``StoreUnavailable`` (connection, timeout, a Redis busy with a script: ``BUSY``, a
cluster that reaches no node), ``StaleLease`` (a fence failed), ``StoreError`` (anything else). The client
(a connection pool) is safe to share between threads; each process must build its own ``RedisStore``.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from functools import cache
from importlib import resources
from typing import Any, cast
from urllib.parse import unquote

import numpy as np
import redis
from redis.backoff import ExponentialWithJitterBackoff
from redis.cluster import ClusterNode, RedisCluster
from redis.retry import Retry

from arcloud.core.change import ChangesSince, LoggedChange, MapChange, changes_after
from arcloud.core.header import MapHeader
from arcloud.core.ports import MAX_CELLS_PER_CALL, Lease
from arcloud.core.types import MapObject
from arcloud.errors import InvalidInput, LockTimeout, StoreError, StoreUnavailable, TooManyCells
from arcloud.ports import (
    DEFAULT_CHANGE_LOG_ENTRIES,
    DEFAULT_FRAME_RECORD_RETENTION_S,
    DEFAULT_RETIRED_HISTORY_S,
    DELETION_KEPT_S,
    RECORDS_SWEPT_PER_CALL,
    RETIRED_HISTORY_MAX_PER_MAP,
    MapDeletion,
    ObjectMeta,
    RetiredObject,
    check_store_settings,
)
from arcloud.stores import codec, keys
from arcloud.stores.cells import MAX_SCRIPT_CELLS, check_lock_ids, check_object_cells, check_script_cells, count_cells
from arcloud.stores.redis_errors import redis_errors

log = logging.getLogger(__name__)

DEFAULT_URL = "redis://127.0.0.1:6379/0"
MAX_QUERY_CELLS = MAX_CELLS_PER_CALL  # larger query boxes read the bounds HASH instead of the cells
SCAN_CELLS_PER_OBJECT = 2  # a box of more cells than this many per object reads the bounds HASH (cheaper)
WAKE_MAX_S = 0.05  # the longest a lock waiter blocks before trying again (a wake-up may go to another waiter)
GET_BATCH = 256  # objects per pipeline when reading many
SCAN_COUNT = 1000
DELETE_BATCH = 1000  # keys a call when deleting a map
DELETE_OBJECTS = 64  # objects a step of a map's deletion (their hashes and index cells, DELETE_BATCH keys a call)
PROGRESS_LOG_S = 5.0  # a long deletion says how far it got this often
DELETION_FIELDS = ("objects", "objects_removed", "keys_removed", "started_at_s", "updated_at_s", "finished_at_s")


#: URL schemes of a Redis Cluster: ``redis+cluster://[[user]:password@]host:port[,host:port...][/0]`` (any node of
#: the cluster, more for when one is down; TLS with ``rediss+cluster://``).
CLUSTER_SCHEMES = ("redis+cluster", "rediss+cluster")
#: Every URL scheme ``connect_redis`` takes.
URL_SCHEMES = ("redis", "rediss", "unix", *CLUSTER_SCHEMES)

#: A client of one Redis or of a Redis Cluster: every adapter here takes either.
RedisClient = redis.Redis | RedisCluster


def connect_redis(url: str, *, reply_timeout_s: float = 30.0, retries: int = 1) -> RedisClient:
    """A client of ``url`` (binary responses) waiting at most ``reply_timeout_s`` for a reply or a
    connection. A command that meets a connection error is sent again ``retries`` times on a new
    connection (jittered backoff from 10 ms, doubling up to 1 s); a timeout is not retried, so a hung
    Redis costs one ``reply_timeout_s`` per command. A cluster URL (``CLUSTER_SCHEMES``) gives a
    ``RedisCluster``, which reads the slot map from the nodes now (``StoreUnavailable`` when none answers)
    and, on a connection error or a timeout, reads it again and sends the command ``retries`` more times
    (how it follows a failover). ``InvalidInput`` for a bad URL."""
    backoff = ExponentialWithJitterBackoff(base=0.01, cap=1.0)
    scheme = url.split("://", 1)[0] if "://" in url else "none"
    if scheme in CLUSTER_SCHEMES:
        return _connect_cluster(url, reply_timeout_s=reply_timeout_s, retry=Retry(backoff, retries))
    retry = Retry(backoff, retries, supported_errors=(redis.exceptions.ConnectionError,))
    try:
        return redis.Redis.from_url(
            url, socket_connect_timeout=min(5.0, reply_timeout_s), socket_timeout=reply_timeout_s, retry=retry
        )
    except ValueError as exc:
        raise InvalidInput("url", f"a {', '.join(s + '://' for s in URL_SCHEMES)} URL", f"a URL with scheme {scheme!r}") from exc


def cluster_nodes(url: str) -> tuple[list[tuple[str, int]], str | None, str | None]:
    """The (host, port) nodes, user and password of a cluster URL; ``InvalidInput`` naming what is wrong."""
    expected = "redis+cluster://[[user]:password@]host:port[,host:port...][/0]"
    _scheme, _, rest = url.partition("://")
    location, _, path = rest.partition("/")
    userinfo, _, hosts = location.rpartition("@")
    if path.strip("/") not in ("", "0"):
        raise InvalidInput("url", f"{expected} (a cluster has database 0 only)", f"database {path.strip('/')!r}")
    nodes = []
    for node in hosts.split(","):
        host, _, port = node.strip().rpartition(":")
        if not host or not port.isdigit():
            raise InvalidInput("url", expected, f"node {node!r}")
        nodes.append((host.strip("[]"), int(port)))
    user, _, password = userinfo.partition(":")
    return nodes, unquote(user) or None, unquote(password) or None


def _connect_cluster(url: str, *, reply_timeout_s: float, retry: Retry) -> RedisCluster:
    nodes, user, password = cluster_nodes(url)
    with redis_errors("connect", "cluster " + ",".join(f"{host}:{port}" for host, port in nodes)):
        return RedisCluster(
            startup_nodes=[ClusterNode(host, port) for host, port in nodes],  # type: ignore[no-untyped-call]  # redis-py leaves it untyped
            username=user,
            password=password,
            ssl=url.startswith("rediss+"),
            socket_connect_timeout=min(5.0, reply_timeout_s),
            socket_timeout=reply_timeout_s,
            retry=retry,
        )


#: The one ``maxmemory-policy`` that keeps every key when Redis is full: it refuses writes (503s here) and evicts nothing.
SAFE_MAXMEMORY_POLICY = "noeviction"


def memory_reports(client: RedisClient) -> list[dict[str, Any]]:
    """``INFO memory`` of the server, or of each of a cluster's nodes; none where INFO is refused (an ACL)."""
    try:
        with redis_errors("read INFO memory", lambda: where(client)):
            if isinstance(client, RedisCluster):  # each primary's (redis-py asks one node unless told)
                info = client.info("memory", target_nodes=RedisCluster.PRIMARIES)
            else:
                info = client.info("memory")
    except StoreUnavailable:
        raise
    except StoreError as exc:  # refused (an ACL, a managed Redis): nothing to check
        log.debug("INFO memory refused (%s): Redis's memory is not checked", exc)
        return []
    values = list(info.values())
    return [v for v in values if isinstance(v, dict)] if values and all(isinstance(v, dict) for v in values) else [info]


def check_memory_policy(client: RedisClient) -> None:
    """``StoreError`` when Redis may evict keys (a ``maxmemory`` and a policy other than ``noeviction``): it would
    delete maps, queued frames and locks without an error, and two workers could then write one object; a
    warning when it has the policy and no ``maxmemory`` yet (CONFIG SET maxmemory would start it evicting)."""
    for report in memory_reports(client):
        policy, limit = str(report.get("maxmemory_policy", SAFE_MAXMEMORY_POLICY)), int(report.get("maxmemory", 0))
        if policy == SAFE_MAXMEMORY_POLICY:
            continue
        advice = f"set maxmemory-policy {SAFE_MAXMEMORY_POLICY} (docs/service.md, Redis's memory)"
        if limit:
            raise StoreError(
                f"Redis at {where(client)} evicts keys when full (maxmemory-policy {policy}, maxmemory {limit} bytes): it "
                f"would delete maps, queued frames and locks without an error; {advice}"
            )
        log.warning(
            "Redis at %s has maxmemory-policy %s: it would evict keys once given a maxmemory; %s", where(client), policy, advice
        )


def memory_full(client: RedisClient) -> str:
    """What is full where Redis holds ``maxmemory`` or more (it refuses writes), else ""."""
    for report in memory_reports(client):
        used, limit = int(report.get("used_memory", 0)), int(report.get("maxmemory", 0))
        if limit and used >= limit:
            return f"{used} bytes used of its maxmemory {limit}: writes are refused until memory is freed or raised"
    return ""


def where(client: RedisClient) -> str:
    """host:port/db of the server (a cluster's nodes), never credentials."""
    if isinstance(client, RedisCluster):
        primaries = client.get_primaries()  # type: ignore[no-untyped-call]  # redis-py leaves it untyped
        return "cluster " + ",".join(sorted(node.name for node in primaries))
    kwargs = client.connection_pool.connection_kwargs
    if "path" in kwargs:
        return f"unix:{kwargs['path']}"
    return f"{kwargs.get('host', '?')}:{kwargs.get('port', '?')}/{kwargs.get('db', 0)}"


class RedisSideStore:
    """What a small store beside the objects (API keys, viewer passes, alignments, rate buckets) holds on
    Redis: ``client`` (shared with the object store, not closed here), else its own connection to ``url``;
    ``_call`` runs one command behind the one Redis error boundary (``redis_errors``)."""

    REPLY_TIMEOUT_S = 2.0  # of its own connection, unless given

    def __init__(self, url: str = "", *, client: RedisClient | None = None, reply_timeout_s: float | None = None) -> None:
        self._owns_client = client is None
        if client is None:
            client = connect_redis(url, reply_timeout_s=self.REPLY_TIMEOUT_S if reply_timeout_s is None else reply_timeout_s)
        self.client = client

    def close(self) -> None:
        if self._owns_client:
            self.client.close()

    def _call(self, doing: str, method: str, *args: object, **options: object) -> object:
        with redis_errors(doing, lambda: where(self.client)):
            return getattr(self.client, method)(*args, **options)


@cache
def lua_source(name: str) -> str:
    """The text of ``stores/lua/<name>.lua``."""
    return (resources.files("arcloud.stores") / "lua" / f"{name}.lua").read_text()


class RedisLease:
    """Locks or space claims held in a ``RedisStore``: the keys, the token, the object ids. ``released``: a
    release or a successful commit let go of the keys already (a release then sends nothing)."""

    def __init__(self, store: RedisStore, map_id: str, lease_keys: list[str], token: str, ids: tuple[int, ...]) -> None:
        self.store = store
        self.map_id = map_id
        self.keys = lease_keys
        self.token = token
        self.ids = ids
        self.released = False

    def release(self) -> None:
        """Release what this lease still holds (never another holder's keys); safe to call twice, and after
        a successful commit, which released it: a no-op then."""
        if not self.released:
            self.store._release(self)
            self.released = True

    def __enter__(self) -> RedisLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"RedisLease(map_id={self.map_id!r}, ids={self.ids}, n_keys={len(self.keys)})"


class RedisStore:
    """``ObjectStore`` on Redis. ``cell_m``: size of the spatial index's cubic cells (every process of
    one deployment must use the same). ``client``: an existing ``redis.Redis`` or ``RedisCluster`` (binary
    responses, i.e. ``decode_responses=False``) instead of connecting to ``url`` (``connect_redis`` with
    ``reply_timeout_s``, ``retries``).
    ``frame_record_retention_s``: how long a processed frame's mark is kept; ``retired_history_s``: how
    long a retired object stays in its map's history; ``change_log_entries``: about how many entries each
    map's change log keeps (``XADD MAXLEN ~``: Redis trims whole nodes of the stream, so it keeps this many
    or up to about a hundred more); ``clock``: Unix seconds."""

    codec_version = codec.FORMAT_VERSION

    def __init__(
        self,
        url: str = DEFAULT_URL,
        *,
        cell_m: float = 1.0,
        client: RedisClient | None = None,
        max_query_cells: int = MAX_QUERY_CELLS,
        reply_timeout_s: float = 30.0,
        retries: int = 1,
        frame_record_retention_s: float = DEFAULT_FRAME_RECORD_RETENTION_S,
        retired_history_s: float = DEFAULT_RETIRED_HISTORY_S,
        change_log_entries: int = DEFAULT_CHANGE_LOG_ENTRIES,
        clock: Callable[[], float] = time.time,
    ) -> None:
        check_store_settings(cell_m, change_log_entries, frame_record_retention_s, retired_history_s)
        self.change_log_entries = int(change_log_entries)
        self.frame_record_retention_s = float(frame_record_retention_s)
        self.retired_history_s = float(retired_history_s)
        self._clock = clock
        if client is None:
            client = connect_redis(url, reply_timeout_s=reply_timeout_s, retries=retries)
            self._owns_client = True
        else:
            self._owns_client = False
        self.client = client
        self.cell_m = float(cell_m)
        if not 1 <= max_query_cells <= MAX_CELLS_PER_CALL:
            raise InvalidInput("max_query_cells", f"1 to {MAX_CELLS_PER_CALL} (MAX_CELLS_PER_CALL)", max_query_cells)
        self.max_query_cells = int(max_query_cells)
        self._scripts = {
            name: client.register_script(lua_source(name)) for name in ("acquire", "query", "mark_published", "give_up_frame")
        }
        self._scripts["release"] = client.register_script(lua_source("leases") + lua_source("release"))
        self._scripts["commit"] = client.register_script(lua_source("records") + lua_source("leases") + lua_source("commit"))

    @classmethod
    def from_url(cls, url: str = DEFAULT_URL, **options: Any) -> RedisStore:
        return cls(url, **options)

    def close(self) -> None:
        """Close the connections (when the store made its client)."""
        if self._owns_client:
            self.client.close()

    def __enter__(self) -> RedisStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"RedisStore({self._where()}, cell_m={self.cell_m})"

    def _where(self) -> str:
        return where(self.client)

    def ping(self) -> None:
        """Raise ``StoreUnavailable`` unless the server answers, and while it is full (``memory_full``: it answers a
        PING, and refuses the writes every request and frame needs)."""
        with redis_errors("ping", self._where):
            self.client.ping()
            full = memory_full(self.client)
            if full:  # as Redis answers a write then: the one boundary makes it StoreUnavailable
                raise redis.exceptions.OutOfMemoryError(f"Redis is full: {full}")

    # --- spatial index -----------------------------------------------------------------------------
    def cells_of(self, lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, int, int]]:
        """Index cells touched by the box [lo, hi] (each (3,), metres)."""
        c_lo = np.floor(np.asarray(lo, np.float64) / self.cell_m).astype(np.int64)
        c_hi = np.floor(np.asarray(hi, np.float64) / self.cell_m).astype(np.int64)
        return [(i, j, k) for i, j, k in itertools.product(*(range(int(a), int(b) + 1) for a, b in zip(c_lo, c_hi)))]

    def _n_cells(self, lo: np.ndarray, hi: np.ndarray) -> float:
        """How many index cells the box [lo, hi] touches (inf when unbounded)."""
        return count_cells(lo, hi, self.cell_m)

    def query_region(self, map_id: str, lo: np.ndarray, hi: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        lo = _vec3("lo", lo)
        hi = _vec3("hi", hi)
        if np.any(lo > hi):
            return {}
        n_cells = self._n_cells(lo, hi)
        pairs: Iterable[tuple[Any, Any]]
        with redis_errors(f"query_region on map {map_id}", self._where):
            if n_cells <= self.max_query_cells:
                c_lo, c_hi = np.floor(lo / self.cell_m), np.floor(hi / self.cell_m)
                ranges = [int(c) for pair in zip(c_lo, c_hi) for c in pair]  # i0 i1 j0 j1 k0 k1
                flat = self._scripts["query"](
                    keys=[keys.bounds_key(map_id)], args=[keys.map_prefix(map_id), *ranges, SCAN_CELLS_PER_OBJECT]
                )
                pairs = zip(flat[::2], flat[1::2])
            else:
                pairs = cast(
                    "dict[bytes, bytes]", self.client.hgetall(keys.bounds_key(map_id))
                ).items()  # bytes: no decode_responses
        ids, blobs = [], []
        for raw_id, blob in pairs:
            ids.append(int(raw_id))
            blobs.append(blob)
        if not ids:
            return {}
        bounds = codec.unpack_boxes(blobs)  # (N, 6): min xyz, max xyz
        hit = np.flatnonzero(np.all(bounds[:, :3] <= hi, axis=1) & np.all(lo <= bounds[:, 3:], axis=1))
        return {ids[n]: (bounds[n, :3], bounds[n, 3:]) for n in hit}

    # --- locks and claims --------------------------------------------------------------------------
    def lock(self, map_id: str, ids: Sequence[int], *, ttl_s: float, timeout_s: float) -> RedisLease:
        held = tuple(sorted({int(i) for i in ids}))
        check_lock_ids(len(held))  # one script takes every key: keep it short
        return self._acquire(map_id, [keys.lock_key(map_id, i) for i in held], held, ttl_s, timeout_s)

    def claim(self, map_id: str, cells: Sequence[tuple[int, int, int]], *, ttl_s: float, timeout_s: float) -> RedisLease:
        ordered = sorted({tuple(int(c) for c in cell) for cell in cells})
        if len(ordered) > MAX_CELLS_PER_CALL:  # one script call takes every key: keep it short
            raise TooManyCells("cells", len(ordered), MAX_CELLS_PER_CALL)
        return self._acquire(map_id, [keys.claim_key(map_id, c) for c in ordered], (), ttl_s, timeout_s)  # type: ignore[arg-type]  # cells are (i, j, k)

    def _acquire(self, map_id: str, lease_keys: list[str], ids: tuple[int, ...], ttl_s: float, timeout_s: float) -> RedisLease:
        token = uuid.uuid4().hex
        lease = RedisLease(self, map_id, lease_keys, token, ids)
        if not lease_keys:
            return lease
        ttl_ms = max(1, math.ceil(ttl_s * 1000))
        deadline = time.monotonic() + timeout_s
        while True:
            with redis_errors(f"lock on map {map_id}", self._where):
                busy, busy_ttl_ms = (list(self._scripts["acquire"](keys=lease_keys, args=[token, ttl_ms])) + [0])[:2]
            if busy == 0:
                return lease
            remaining_s = deadline - time.monotonic()
            if remaining_s <= 0:
                raise LockTimeout(
                    f"map {map_id}: {lease_keys[busy - 1]} busy after {timeout_s:.3g} s "
                    f"({len(lease_keys)} keys requested, none held)"
                )
            wait_s = min(remaining_s, WAKE_MAX_S, busy_ttl_ms / 1000 if busy_ttl_ms > 0 else WAKE_MAX_S)
            with redis_errors(f"wait for a lock on map {map_id}", self._where):  # until released (or the ttl ends)
                self.client.blpop([keys.lease_wake_key(lease_keys[busy - 1])], timeout=max(0.001, wait_s))

    def _release(self, lease: RedisLease) -> None:
        if lease.keys:
            with redis_errors(f"release on map {lease.map_id}", self._where):
                self._scripts["release"](keys=lease.keys, args=[lease.token])

    # --- objects -----------------------------------------------------------------------------------
    def get(self, map_id: str, ids: Sequence[int]) -> list[MapObject]:
        ids = [int(i) for i in ids]
        found = []
        for start in range(0, len(ids), GET_BATCH):
            batch = ids[start : start + GET_BATCH]
            # MULTI/EXEC: one consistent snapshot of the batch
            with redis_errors(f"get on map {map_id}", self._where), self.client.pipeline(transaction=True) as pipe:
                pipe.hmget(keys.meta_key(map_id), batch)
                for object_id in batch:
                    pipe.hmget(keys.object_key(map_id, object_id), ["voxels", "missed", "gone"])
                metas, *fields = pipe.execute()
            found += [
                codec.decode_object(i, meta, blob, n_missed=int(missed or 0), n_gone=int(gone or 0))
                for i, meta, (blob, missed, gone) in zip(batch, metas, fields)
                if meta is not None and blob is not None
            ]
        return found

    def object_meta(self, map_id: str, ids: Sequence[int]) -> list[ObjectMeta]:
        """The objects' metadata without their voxels (one read), in the order given; missing ids skipped."""
        ids = [int(i) for i in ids]
        if not ids:
            return []
        with redis_errors(f"object_meta on map {map_id}", self._where):
            metas = cast("list[bytes | None]", self.client.hmget(keys.meta_key(map_id), ids))  # bytes: no decode_responses
        present = [(i, meta) for i, meta in zip(ids, metas) if meta is not None]
        return codec.decode_metas([i for i, _ in present], [meta for _, meta in present])

    def list_meta(self, map_id: str) -> list[ObjectMeta]:
        """Metadata of every object of the map (one read), by id."""
        with redis_errors(f"list_meta on map {map_id}", self._where):
            metas = cast("dict[bytes, bytes]", self.client.hgetall(keys.meta_key(map_id)))  # bytes: no decode_responses
        ordered = sorted((int(i), meta) for i, meta in metas.items())
        return codec.decode_metas([i for i, _ in ordered], [meta for _, meta in ordered])

    def object_ids(self, map_id: str) -> list[int]:
        """The ids of the map's objects, sorted (one read of the bounds HASH's fields: no metadata, no voxels)."""
        with redis_errors(f"list on map {map_id}", self._where):
            return sorted(int(i) for i in self.client.hkeys(keys.bounds_key(map_id)))

    def new_ids(self, map_id: str, n: int) -> range:
        if n < 0:
            raise InvalidInput("n", ">= 0", n)
        if n == 0:
            return range(0)
        with redis_errors(f"new_ids on map {map_id}", self._where):
            last = int(self.client.incrby(keys.ids_key(map_id), n))
        return range(last - n + 1, last + 1)

    def commit(
        self,
        map_id: str,
        leases: Sequence[Lease],
        change: MapChange,
        *,
        frame_key: str | None = None,
        entry_id: str | None = None,
    ) -> bool:
        own = cast("Sequence[RedisLease]", leases)  # the port's Lease: here always one this store handed out
        for lease in own:
            if lease.map_id != map_id:
                raise InvalidInput("leases", f"leases of map {map_id}", f"a lease of map {lease.map_id}")
        upserts, deletes, retired = change.upserts, change.deletes, change.retired
        new_cells = 0
        for obj in upserts:
            if obj.bounds is None:
                raise InvalidInput(f"object {obj.id}.bounds", "bounds of its voxels (refine the object first)", None)
            new_cells += check_object_cells(f"object {obj.id}.bounds", obj.bounds.min, obj.bounds.max, self.cell_m)
        check_script_cells(new_cells)  # the script adds these and checks them with those it removes
        header: dict[str, Any] = {
            "frame": frame_key or "",
            "entry_id": entry_id or "",
            "now": self._clock(),
            "retention_s": self.frame_record_retention_s,
            "sweep": RECORDS_SWEPT_PER_CALL,
            "leases": [[key, lease.token] for lease in own for key in lease.keys],
            "held": [str(i) for lease in own for i in lease.ids],
            "upserts": [],
            "deletes": [{"id": str(int(o.id)), "version": str(int(o.version))} for o in deletes],
            "misses": [{"id": str(int(i)), "count": str(int(n))} for i, n in change.misses.items()],
            "gone": [{"id": str(int(i)), "count": str(int(n))} for i, n in change.gone.items()],
            "retired": [{"id": str(int(o.id)), "version": str(int(o.version))} for o in retired],
            "history_s": self.retired_history_s,
            "history_max": RETIRED_HISTORY_MAX_PER_MAP,
            "new_cells": new_cells,
            "max_cells": MAX_SCRIPT_CELLS,
            "log_max": self.change_log_entries,
        }
        payload: list[bytes] = [codec.encode_events(change.events) if change.events else b""]
        for obj in upserts:
            assert obj.bounds is not None
            cells = " ".join(keys.cell_name(c) for c in self.cells_of(obj.bounds.min, obj.bounds.max))
            header["upserts"].append(
                {
                    "id": str(int(obj.id)),
                    "version": str(int(obj.version)),
                    "cells": cells,
                    "missed": str(int(obj.n_missed)),
                    "gone": str(int(obj.n_gone)),
                }
            )
            payload += [
                codec.pack_box(obj.bounds),
                codec.encode_meta(obj),
                codec.encode_voxels(obj.keys, obj.weights, obj.votes, seen=obj.seen, colors=obj.colors),
            ]
        with redis_errors(f"commit on map {map_id}", self._where):
            written = self._scripts["commit"](
                keys=[
                    keys.processed_key(map_id),
                    keys.bounds_key(map_id),
                    keys.meta_key(map_id),
                    keys.processed_count_key(map_id),
                    keys.processed_sweep_key(map_id),
                    keys.retired_key(map_id),
                    keys.retired_at_key(map_id),
                    keys.changes_key(map_id),
                    keys.version_key(map_id),
                    keys.began_key(map_id),
                ],
                args=[keys.map_prefix(map_id), json.dumps(header), *payload],
            )
            if int(written) == 1:
                for lease in own:  # the script released them: their release sends nothing
                    lease.released = True
                if upserts or deletes or retired:
                    self.client.hset(keys.MAPS, map_id, repr(time.time()))  # the maps list's last update
        if int(written) < 0:  # the cells it would remove and add, over the bound: nothing written
            check_script_cells(-int(written))
        return int(written) == 1

    # --- the change log ------------------------------------------------------------------------------
    def changes_since(self, map_id: str, after: int, limit: int) -> ChangesSince:
        after = int(after)
        with redis_errors(f"changes_since on map {map_id}", self._where):
            pipe = self.client.pipeline(transaction=True)  # the version and the entries of one moment
            pipe.get(keys.version_key(map_id))
            pipe.get(keys.began_key(map_id))
            if limit > 0:
                pipe.xrange(keys.changes_key(map_id), f"{after + 1}-0", "+", count=int(limit))
            version, began, *read = pipe.execute()
        entries = []
        for entry_id, raw in read[0] if read else []:
            # a cluster's pipeline leaves the fields a flat list: name, value, ...
            fields = raw if isinstance(raw, dict) else dict(zip(raw[::2], raw[1::2]))
            entries.append(
                LoggedChange(
                    int(entry_id.split(b"-")[0]),
                    fields[b"frame"].decode(),
                    codec.decode_events(map_id, fields[b"events"]),
                )
            )
        return changes_after(entries, int(version or 0), after, limit, began.decode() if began else "")

    def published_version(self, map_id: str) -> int:
        with redis_errors(f"published_version of map {map_id}", self._where):
            return int(self.client.get(keys.published_key(map_id)) or 0)

    def mark_published(self, map_id: str, version: int) -> None:
        with redis_errors(f"mark_published on map {map_id}", self._where):
            self._scripts["mark_published"](keys=[keys.published_key(map_id)], args=[int(version)])

    def list_objects(self, map_id: str) -> list[MapObject]:
        return self.get(map_id, self.object_ids(map_id))

    def retired_objects(self, map_id: str) -> list[RetiredObject]:
        cutoff_s = self._clock() - self.retired_history_s
        with redis_errors(f"retired_objects of map {map_id}", self._where):
            pipe = self.client.pipeline(transaction=True)  # one snapshot of the times and the metadata
            pipe.zrevrangebyscore(keys.retired_at_key(map_id), "+inf", cutoff_s, withscores=True)
            pipe.hgetall(keys.retired_key(map_id))
            times, metas = pipe.execute()
        kept = [(int(i), float(at), metas[i]) for i, at in times if i in metas]
        decoded = codec.decode_metas([i for i, _, _ in kept], [meta for _, _, meta in kept])
        return [RetiredObject(meta, at) for meta, (_, at, _) in zip(decoded, kept)]

    def delete_map(self, map_id: str) -> int:
        started = last_log = time.monotonic()
        with redis_errors(f"delete_map {map_id}", self._where):
            n_objects = int(self.client.hlen(keys.bounds_key(map_id)))
            going = self._record_deletion(MapDeletion(map_id, n_objects, 0, 0, self._clock(), self._clock()))
            self.client.hdel(keys.MAPS, map_id)
            self.client.unlink(keys.header_key(map_id))  # from here the map is unknown and its deletion refuses frames
            ids: list[bytes] = []
            for object_id, _ in self.client.hscan_iter(keys.bounds_key(map_id), count=DELETE_OBJECTS):
                ids.append(object_id)
                if len(ids) == DELETE_OBJECTS:
                    going, ids = self._delete_objects(going, ids), []
                    if time.monotonic() - last_log >= PROGRESS_LOG_S:
                        last_log = time.monotonic()
                        log.info(
                            "map %s: deleting, %d of %d objects removed (%d keys) in %.0f s",
                            map_id,
                            going.objects_removed,
                            n_objects,
                            going.keys_removed,
                            last_log - started,
                        )
            if ids:
                going = self._delete_objects(going, ids)
            # What is left: the registries, then by SCAN frame marks, leases and what writers added meanwhile. The
            # map's version and id counter stay: a map made again goes on from them (``ObjectStore.delete_map``).
            kept = {
                k.encode()
                for k in (keys.ids_key(map_id), keys.version_key(map_id), keys.began_key(map_id), keys.published_key(map_id))
            }
            registries = [
                keys.bounds_key(map_id),
                keys.meta_key(map_id),
                keys.processed_key(map_id),
                keys.processed_count_key(map_id),
                keys.processed_sweep_key(map_id),
                keys.retired_key(map_id),
                keys.retired_at_key(map_id),
                keys.changes_key(map_id),
            ]
            removed_keys = int(self.client.unlink(*registries))  # one slot: the map's tag
            batch: list[bytes] = []
            for key in self.client.scan_iter(match=keys.map_pattern(map_id), count=SCAN_COUNT):
                if key in kept:
                    continue
                batch.append(key)
                if len(batch) == DELETE_BATCH:
                    removed_keys += int(self.client.unlink(*batch))
                    batch = []
                    going = self._record_deletion(replace(going, keys_removed=going.keys_removed + removed_keys))
                    removed_keys = 0
            if batch:
                removed_keys += int(self.client.unlink(*batch))
            if self.client.get(keys.version_key(map_id)) is not None:  # the deletion is one more version, logged nowhere
                version = int(self.client.incr(keys.version_key(map_id)))
                self._scripts["mark_published"](keys=[keys.published_key(map_id)], args=[version])  # nothing left to publish
            going = self._record_deletion(replace(going, keys_removed=going.keys_removed + removed_keys), done=True)
        log.info(
            "map %s deleted: %d objects, %d keys in %.1f s", map_id, n_objects, going.keys_removed, time.monotonic() - started
        )
        return n_objects

    def _delete_objects(self, going: MapDeletion, ids: list[bytes]) -> MapDeletion:
        """One step of a deletion: these objects' hashes and the index cells they list (``DELETE_BATCH`` keys a
        call), then their registry fields; the deletion recorded as gone that far."""
        map_id = going.map_id
        pipe = self.client.pipeline(transaction=False)
        for object_id in ids:
            pipe.hget(keys.object_key(map_id, int(object_id)), "cells")
        doomed = [keys.object_key(map_id, int(object_id)) for object_id in ids]
        for cells in pipe.execute():
            if cells:
                doomed += keys.cell_keys_listed(map_id, cells.decode() if isinstance(cells, bytes) else cells)
        removed = sum(int(self.client.unlink(*doomed[at : at + DELETE_BATCH])) for at in range(0, len(doomed), DELETE_BATCH))
        pipe = self.client.pipeline(transaction=False)
        pipe.hdel(keys.bounds_key(map_id), *ids)
        pipe.hdel(keys.meta_key(map_id), *ids)
        gone, _ = pipe.execute()  # SCAN may return an object twice: count what HDEL removed, not the ids
        return self._record_deletion(
            replace(going, objects_removed=going.objects_removed + int(gone), keys_removed=going.keys_removed + removed)
        )

    def _record_deletion(self, deletion: MapDeletion, *, done: bool = False) -> MapDeletion:
        """Store ``deletion`` as of now (``done``: ended now) for ``DELETION_KEPT_S``; returns what it stored."""
        now_s = self._clock()
        stored = replace(deletion, updated_at_s=now_s, finished_at_s=now_s if done else None)
        record = {name: getattr(stored, name) for name in DELETION_FIELDS}
        self.client.set(keys.deletion_key(stored.map_id), json.dumps(record), ex=int(DELETION_KEPT_S))
        return stored

    def map_deletion(self, map_id: str) -> MapDeletion | None:
        with redis_errors(f"read the deletion of map {map_id}", self._where):
            raw = self.client.get(keys.deletion_key(map_id))
        if raw is None:
            return None
        try:
            return MapDeletion(map_id, **{name: json.loads(raw)[name] for name in DELETION_FIELDS})
        except (ValueError, KeyError, TypeError) as exc:
            raise StoreError(f"map {map_id}: the deletion record is not one ({exc})") from exc

    def is_frame_done(self, map_id: str, frame_key: str) -> bool:
        with redis_errors(f"is_frame_done on map {map_id}", self._where):
            recorded_at_s = self.client.hget(keys.processed_key(map_id), frame_key)
        return recorded_at_s is not None and float(recorded_at_s) >= self._clock() - self.frame_record_retention_s

    def give_up_frame(self, map_id: str, frame_key: str, entry_id: str) -> bool:
        kept_ms = max(1, math.ceil(self.frame_record_retention_s * 1000))
        with redis_errors(f"give_up_frame on map {map_id}", self._where):
            given_up = self._scripts["give_up_frame"](
                keys=[keys.processed_key(map_id), keys.given_up_key(map_id, entry_id)],
                args=[frame_key, self._clock(), self.frame_record_retention_s, kept_ms],
            )
        return int(given_up) == 1

    def count_frames(self, map_id: str) -> int:
        with redis_errors(f"count_frames on map {map_id}", self._where):
            return int(self.client.get(keys.processed_count_key(map_id)) or 0)

    def open_map(self, map_id: str, header: MapHeader) -> MapHeader:
        key = keys.header_key(map_id)
        with redis_errors(f"open_map {map_id}", self._where):
            pipe = self.client.pipeline(transaction=True)
            pipe.set(key, json.dumps(header.to_record()), nx=True)
            pipe.get(key)
            created, stored = pipe.execute()
            if created:  # the map's first opening lists it (a commit lists a map opened before the list existed)
                self.client.hsetnx(keys.MAPS, map_id, repr(header.created_at_s))  # service-wide: its own slot
        return _header_of(map_id, stored)

    def list_maps(self) -> dict[str, float]:
        with redis_errors("list the maps", self._where):
            raw = self.client.hgetall(keys.MAPS)
        return {(m.decode() if isinstance(m, bytes) else m): float(t) for m, t in raw.items()}

    def count_objects(self, map_id: str) -> int:
        with redis_errors(f"count the objects of map {map_id}", self._where):
            return int(self.client.hlen(keys.meta_key(map_id)))

    def map_header(self, map_id: str) -> MapHeader | None:
        with redis_errors(f"map_header of map {map_id}", self._where):
            stored = self.client.get(keys.header_key(map_id))
        return None if stored is None else _header_of(map_id, stored)


def _header_of(map_id: str, stored: bytes | str) -> MapHeader:
    """A stored header record; ``StoreError`` when it is not one (written by something else)."""
    try:
        return MapHeader.from_record(json.loads(stored))
    except (ValueError, TypeError, InvalidInput) as exc:
        raise StoreError(f"map {map_id}: its header is not a MapHeader record ({exc})") from exc


def _vec3(field: str, value: object) -> np.ndarray:
    array = np.asarray(value, np.float64)
    if array.shape != (3,):
        raise InvalidInput(field, "shape (3,)", f"shape {array.shape}")
    return array
