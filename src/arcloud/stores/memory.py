"""The embedded object store: every map in this process's memory, safe across threads.

It keeps the semantics of the Redis store so that one contract suite tests both: locks and claims
carry a token and a TTL (an expired lease's write is refused), writes are compare-and-set on the
object version (fencing), frames are recorded once (a processed frame's mark kept
``frame_record_retention_s``, as on Redis, and so is a queue entry given up, whose commits are refused), retired objects stay in the map's history for
``retired_history_s``, each map's change log (``core.change``) keeps its latest ``change_log_entries`` in a
ring buffer, appended under the same lock as the commit's writes. Locks are taken all-or-nothing under one condition variable
per map, so a thread never holds some locks while waiting for others; a successful commit releases the leases it
was given under that lock, waking their waiters.
"""

from __future__ import annotations

import itertools
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from arcloud.core.change import ChangesSince, LoggedChange, MapChange, changes_after
from arcloud.core.header import MapHeader
from arcloud.core.ports import MAX_CELLS_PER_CALL, Lease
from arcloud.core.types import MapObject
from arcloud.errors import FrameGivenUp, InvalidInput, LockTimeout, StaleLease, TooManyCells
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
from arcloud.stores import codec
from arcloud.stores.cells import check_lock_ids, check_object_cells, check_script_cells
from arcloud.stores.codec import logged_events, meta_of

_Name = tuple[str, Any]  # what a lease holds: ("object", id) or ("cell", (i, j, k))


@dataclass(slots=True)
class _Holder:
    token: str
    expires_at: float  # time.monotonic()


@dataclass(slots=True)
class _MapState:
    objects: dict[int, MapObject] = field(default_factory=dict)
    bounds: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    index: dict[tuple[int, int, int], set[int]] = field(default_factory=dict)
    cells_of: dict[int, list[tuple[int, int, int]]] = field(default_factory=dict)
    held: dict[_Name, _Holder] = field(default_factory=dict)
    frames: dict[str, float] = field(default_factory=dict)  # processed frame key -> when (Unix s), oldest first
    n_frames: int = 0  # frames processed (marks expiring do not lower it)
    given_up: dict[str, float] = field(default_factory=dict)  # queue entry given up -> when (Unix s), oldest first
    retired: dict[int, RetiredObject] = field(default_factory=dict)  # the history, oldest first
    next_id: int = 1
    version: int = 0  # the map's version: the last entry of its change log
    began: str = ""  # when its change log began (``ChangesSince.began``): this process's, so another after a restart
    log: deque[LoggedChange] = field(default_factory=deque)  # the change log's latest entries, oldest first
    published: int = 0  # the version its log was published up to
    changed: threading.Condition = field(default_factory=threading.Condition)


class MemoryLease:
    """Locks or claims held in a ``MemoryStore``; releases on exit. ``released``: a release or a successful
    commit let go of them already (a release then does nothing)."""

    def __init__(self, store: MemoryStore, map_id: str, names: list[_Name], token: str) -> None:
        self.store = store
        self.map_id = map_id
        self.names = names
        self.token = token
        self.ids = tuple(name[1] for name in names if name[0] == "object")
        self.released = False

    def release(self) -> None:
        if not self.released:
            self.store._release(self)

    def __enter__(self) -> MemoryLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _let_go(state: _MapState, lease: MemoryLease) -> None:
    """Release what ``lease`` still holds (never another holder's) and wake the waiters; ``state.changed`` held."""
    for name in lease.names:
        holder = state.held.get(name)
        if holder is not None and holder.token == lease.token:
            del state.held[name]
    lease.released = True
    state.changed.notify_all()


class MemoryStore:
    """In-process ``ObjectStore``. ``cell_m`` is the size of the spatial index's cubic cells;
    ``frame_record_retention_s``: how long a processed frame's mark is kept; ``retired_history_s``: how
    long a retired object stays in its map's history; ``change_log_entries``: how many entries each map's
    change log keeps; ``clock``: Unix seconds."""

    codec_version = codec.FORMAT_VERSION  # objects are kept as they are, but a map's header names the format

    def __init__(
        self,
        *,
        cell_m: float = 1.0,
        frame_record_retention_s: float = DEFAULT_FRAME_RECORD_RETENTION_S,
        retired_history_s: float = DEFAULT_RETIRED_HISTORY_S,
        change_log_entries: int = DEFAULT_CHANGE_LOG_ENTRIES,
        clock: Callable[[], float] = time.time,
    ) -> None:
        check_store_settings(cell_m, change_log_entries, frame_record_retention_s, retired_history_s)
        self.change_log_entries = int(change_log_entries)
        self.cell_m = cell_m
        self.frame_record_retention_s = float(frame_record_retention_s)
        self.retired_history_s = float(retired_history_s)
        self._clock = clock
        self._maps: dict[str, _MapState] = {}
        self._headers: dict[str, MapHeader] = {}
        self._updated: dict[str, float] = {}  # map id -> when its objects last changed (Unix s)
        self._deletions: dict[str, MapDeletion] = {}  # map id -> its deletion, ended at once, kept DELETION_KEPT_S
        self._maps_lock = threading.Lock()

    def _map(self, map_id: str) -> _MapState:
        with self._maps_lock:
            state = self._maps.get(map_id)
            if state is None:
                state = self._maps[map_id] = _MapState(log=deque(maxlen=self.change_log_entries))
            return state

    # --- spatial index -----------------------------------------------------------------------------
    def _cells(self, lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, int, int]]:
        c_lo = np.floor(np.asarray(lo, np.float64) / self.cell_m).astype(np.int64)
        c_hi = np.floor(np.asarray(hi, np.float64) / self.cell_m).astype(np.int64)
        return [(i, j, k) for i, j, k in itertools.product(*(range(a, b + 1) for a, b in zip(c_lo, c_hi)))]

    def query_region(self, map_id: str, lo: np.ndarray, hi: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        state = self._map(map_id)
        with state.changed:
            ids: set[int] = set()
            if len(state.index) < np.prod(np.floor(hi / self.cell_m) - np.floor(lo / self.cell_m) + 1):
                for cell, members in state.index.items():  # fewer occupied cells than the region spans
                    if all(lo[a] <= (cell[a] + 1) * self.cell_m and cell[a] * self.cell_m <= hi[a] for a in range(3)):
                        ids |= members
            else:
                for cell in self._cells(lo, hi):
                    ids |= state.index.get(cell, set())
            found = {}
            lo_xyz, hi_xyz = lo.tolist(), hi.tolist()  # three numbers: Python compares them faster than numpy
            for object_id in ids:
                b_lo, b_hi = state.bounds[object_id]
                if all(a <= b for a, b in zip(b_lo.tolist(), hi_xyz)) and all(a <= b for a, b in zip(lo_xyz, b_hi.tolist())):
                    found[object_id] = (b_lo, b_hi)
            return found

    # --- locks and claims --------------------------------------------------------------------------
    def lock(self, map_id: str, ids: Sequence[int], *, ttl_s: float, timeout_s: float) -> MemoryLease:
        held = sorted({int(i) for i in ids})
        check_lock_ids(len(held))  # as Redis refuses one script of more keys
        return self._acquire(map_id, [("object", i) for i in held], ttl_s, timeout_s)

    def claim(self, map_id: str, cells: Sequence[tuple[int, int, int]], *, ttl_s: float, timeout_s: float) -> MemoryLease:
        names: list[_Name] = [("cell", tuple(int(c) for c in cell)) for cell in sorted(set(cells))]
        if len(names) > MAX_CELLS_PER_CALL:
            raise TooManyCells("cells", len(names), MAX_CELLS_PER_CALL)
        return self._acquire(map_id, names, ttl_s, timeout_s)

    def _acquire(self, map_id: str, names: list[_Name], ttl_s: float, timeout_s: float) -> MemoryLease:
        state = self._map(map_id)
        token = uuid.uuid4().hex
        deadline = time.monotonic() + timeout_s
        with state.changed:
            while True:
                now = time.monotonic()
                busy = [n for n in names if (h := state.held.get(n)) is not None and h.expires_at > now]
                if not busy:
                    for name in names:
                        state.held[name] = _Holder(token, now + ttl_s)
                    return MemoryLease(self, map_id, names, token)
                remaining = deadline - now
                if remaining <= 0:
                    raise LockTimeout(
                        f"map {map_id}: {len(busy)} of {len(names)} locks busy after {timeout_s:.3g} s (first: {busy[0]})"
                    )
                soonest = min(state.held[n].expires_at for n in busy) - now
                state.changed.wait(max(1e-3, min(remaining, soonest)))

    def _release(self, lease: MemoryLease) -> None:
        state = self._map(lease.map_id)
        with state.changed:
            _let_go(state, lease)

    # --- objects -----------------------------------------------------------------------------------
    def get(self, map_id: str, ids: Sequence[int]) -> list[MapObject]:
        state = self._map(map_id)
        with state.changed:
            return [state.objects[i] for i in ids if i in state.objects]

    def new_ids(self, map_id: str, n: int) -> range:
        state = self._map(map_id)
        if n < 0:
            raise InvalidInput("n", ">= 0", n)
        with state.changed:
            first, state.next_id = state.next_id, state.next_id + n
        return range(first, first + n)

    def commit(
        self,
        map_id: str,
        leases: Sequence[Lease],
        change: MapChange,
        *,
        frame_key: str | None = None,
        entry_id: str | None = None,
    ) -> bool:
        own = cast("Sequence[MemoryLease]", leases)  # the port's Lease: here always one this store handed out
        upserts, deletes, retired, misses, gone = change.upserts, change.deletes, change.retired, change.misses, change.gone
        state = self._map(map_id)
        with state.changed:
            given_up_at_s = state.given_up.get(entry_id) if entry_id is not None else None
            if given_up_at_s is not None and given_up_at_s >= self._clock() - self.frame_record_retention_s:
                raise FrameGivenUp(f"map {map_id}: frame {frame_key} of queue entry {entry_id} was given up; nothing written")
            if frame_key is not None and self._recorded(state, frame_key):
                return False
            now = time.monotonic()
            held: set[int] = set()
            for lease in own:
                for name in lease.names:
                    holder = state.held.get(name)
                    if holder is None or holder.token != lease.token or holder.expires_at <= now:
                        raise StaleLease(f"map {map_id}: lease on {name} expired or was taken over; nothing written")
                held.update(lease.ids)
            for obj in upserts:
                current = state.objects.get(obj.id)
                if current is None and obj.version != 1:
                    raise StaleLease(f"map {map_id}: object {obj.id} written at version {obj.version} but it does not exist")
                if current is not None:
                    if obj.id not in held:
                        raise StaleLease(f"map {map_id}: object {obj.id} written without its lock")
                    if current.version != obj.version - 1:
                        raise StaleLease(
                            f"map {map_id}: object {obj.id} is at version {current.version}, write expected {obj.version - 1}"
                        )
                if obj.bounds is None:
                    raise InvalidInput(f"object {obj.id}.bounds", "bounds of its voxels (refine the object first)", None)
            # The index cells this write adds and removes, bounded as Redis bounds one script's (``stores.cells``).
            touched = sum(
                check_object_cells(f"object {o.id}.bounds", o.bounds.min, o.bounds.max, self.cell_m)
                for o in upserts
                if o.bounds is not None
            )
            touched += sum(len(state.cells_of.get(o.id, ())) for o in [*upserts, *deletes, *retired])
            check_script_cells(touched)
            for obj in [*deletes, *retired]:
                current = state.objects.get(obj.id)
                if current is None:
                    continue
                if obj.id not in held or current.version != obj.version:
                    raise StaleLease(f"map {map_id}: object {obj.id} deleted without its lock or at a stale version")
            for object_id in [*misses, *gone]:
                if object_id in state.objects and object_id not in held:
                    raise StaleLease(f"map {map_id}: object {object_id} counted as missed without its lock")
            for object_id, count in misses.items():
                if object_id in state.objects:
                    state.objects[object_id] = state.objects[object_id].replace(n_missed=int(count))
            for object_id, count in gone.items():
                if object_id in state.objects:
                    state.objects[object_id] = state.objects[object_id].replace(n_gone=int(count))
            now_s = self._clock()
            for obj in retired:
                current = state.objects.get(obj.id)
                if current is not None:
                    state.retired.pop(obj.id, None)
                    state.retired[obj.id] = RetiredObject(meta_of(current), now_s)
            for obj in [*deletes, *retired]:
                self._unindex(state, obj.id)
                state.objects.pop(obj.id, None)
            for obj in upserts:
                for array in (obj.keys, obj.weights, obj.votes, obj.seen_counts):
                    array.setflags(write=False)  # stored objects are shared: nobody may edit them in place
                self._unindex(state, obj.id)
                state.objects[obj.id] = obj
                assert obj.bounds is not None
                state.bounds[obj.id] = (obj.bounds.min, obj.bounds.max)
                cells = self._cells(obj.bounds.min, obj.bounds.max)
                state.cells_of[obj.id] = cells
                for cell in cells:
                    state.index.setdefault(cell, set()).add(obj.id)
            if frame_key is not None:
                state.frames.pop(frame_key, None)
                state.frames[frame_key] = self._clock()
                state.n_frames += 1
            cutoff = self._clock() - self.frame_record_retention_s
            for expired in list(
                itertools.islice(itertools.takewhile(lambda k: state.frames[k] < cutoff, state.frames), RECORDS_SWEPT_PER_CALL)
            ):
                del state.frames[expired]
            self._trim_history(state)
            if change.events:
                state.began = state.began or f"{time.time():.6f}"
                state.version += 1
                state.log.append(LoggedChange(state.version, frame_key or "", logged_events(change.events)))
            if upserts or deletes or retired:
                with self._maps_lock:
                    self._updated[map_id] = time.time()
            for lease in own:  # released with the write, as Redis's commit script does
                _let_go(state, lease)
            return True

    # --- the change log ------------------------------------------------------------------------------
    def changes_since(self, map_id: str, after: int, limit: int) -> ChangesSince:
        state = self._map(map_id)
        with state.changed:
            # versions are consecutive: the entries after ``after`` are the last ``version - after`` (those kept),
            # indexed from the right end of the ring buffer, where a reader that keeps up reads
            kept = max(0, min(len(state.log), state.version - int(after)))
            start = len(state.log) - kept
            entries = [state.log[i] for i in range(start, min(len(state.log), start + max(0, limit)))]
            return changes_after(entries, state.version, int(after), limit, state.began)

    def published_version(self, map_id: str) -> int:
        state = self._map(map_id)
        with state.changed:
            return state.published

    def mark_published(self, map_id: str, version: int) -> None:
        state = self._map(map_id)
        with state.changed:
            state.published = max(state.published, int(version))

    def _trim_history(self, state: _MapState) -> None:
        """Under the map's lock: drop the retired objects past ``retired_history_s``, and the oldest
        beyond ``RETIRED_HISTORY_MAX_PER_MAP``."""
        cutoff = self._clock() - self.retired_history_s
        while state.retired:
            oldest = next(iter(state.retired.values()))
            if oldest.retired_at_s >= cutoff and len(state.retired) <= RETIRED_HISTORY_MAX_PER_MAP:
                break
            del state.retired[oldest.meta.id]

    def retired_objects(self, map_id: str) -> list[RetiredObject]:
        state = self._map(map_id)
        with state.changed:
            cutoff = self._clock() - self.retired_history_s
            return [r for r in reversed(state.retired.values()) if r.retired_at_s >= cutoff]

    def _recorded(self, state: _MapState, frame_key: str) -> bool:
        """Under the map's lock: whether a commit recorded the frame within the retention."""
        recorded_at_s = state.frames.get(frame_key)
        return recorded_at_s is not None and recorded_at_s >= self._clock() - self.frame_record_retention_s

    def _unindex(self, state: _MapState, object_id: int) -> None:
        for cell in state.cells_of.pop(object_id, []):
            members = state.index.get(cell)
            if members is not None:
                members.discard(object_id)
                if not members:
                    del state.index[cell]
        state.bounds.pop(object_id, None)

    def list_objects(self, map_id: str) -> list[MapObject]:
        state = self._map(map_id)
        with state.changed:
            return [state.objects[i] for i in sorted(state.objects)]

    def list_meta(self, map_id: str) -> list[ObjectMeta]:
        return [meta_of(obj) for obj in self.list_objects(map_id)]

    def object_meta(self, map_id: str, ids: Sequence[int]) -> list[ObjectMeta]:
        return [meta_of(obj) for obj in self.get(map_id, ids)]

    def object_ids(self, map_id: str) -> list[int]:
        state = self._map(map_id)
        with state.changed:
            return sorted(state.objects)

    def delete_map(self, map_id: str) -> int:
        now_s = self._clock()
        with self._maps_lock:
            state = self._maps.pop(map_id, None)
            if state is not None:  # its versions and object ids go on, as Redis's ``delete_map`` keeps them
                self._maps[map_id] = _MapState(
                    log=deque(maxlen=self.change_log_entries),
                    next_id=state.next_id,
                    version=state.version + 1 if state.version else 0,
                    began=state.began,
                    published=state.version + 1 if state.version else 0,
                )
            self._headers.pop(map_id, None)
            self._updated.pop(map_id, None)
            n_objects = 0 if state is None else len(state.objects)
            for old in [m for m, d in self._deletions.items() if d.updated_at_s < now_s - DELETION_KEPT_S]:
                del self._deletions[old]
            self._deletions[map_id] = MapDeletion(map_id, n_objects, n_objects, 0, now_s, now_s, finished_at_s=now_s)
        return n_objects

    def map_deletion(self, map_id: str) -> MapDeletion | None:
        with self._maps_lock:
            found = self._deletions.get(map_id)
        return found if found is not None and found.updated_at_s >= self._clock() - DELETION_KEPT_S else None

    def is_frame_done(self, map_id: str, frame_key: str) -> bool:
        state = self._map(map_id)
        with state.changed:
            return self._recorded(state, frame_key)

    def give_up_frame(self, map_id: str, frame_key: str, entry_id: str) -> bool:
        state = self._map(map_id)
        with state.changed:
            if self._recorded(state, frame_key):
                return False
            now_s = self._clock()
            state.given_up.pop(entry_id, None)
            state.given_up[entry_id] = now_s
            cutoff = now_s - self.frame_record_retention_s
            for expired in list(itertools.takewhile(lambda k: state.given_up[k] < cutoff, state.given_up)):
                del state.given_up[expired]
            return True

    def count_frames(self, map_id: str) -> int:
        state = self._map(map_id)
        with state.changed:
            return state.n_frames

    def ping(self) -> None:
        """Always answers: the store is this process."""
        return None

    def open_map(self, map_id: str, header: MapHeader) -> MapHeader:
        with self._maps_lock:
            self._updated.setdefault(map_id, header.created_at_s)
            return self._headers.setdefault(map_id, header)

    def list_maps(self) -> dict[str, float]:
        with self._maps_lock:
            return {m: self._updated.get(m, 0.0) for m in self._headers}

    def count_objects(self, map_id: str) -> int:
        with self._maps_lock:
            state = self._maps.get(map_id)
        if state is None:
            return 0
        with state.changed:
            return len(state.objects)

    def map_header(self, map_id: str) -> MapHeader | None:
        with self._maps_lock:
            return self._headers.get(map_id)

    def close(self) -> None:
        """Nothing to release (the maps stay readable)."""
        return None
