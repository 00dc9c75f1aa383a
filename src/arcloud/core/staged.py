"""One map's frames integrated as a batch: a ``MapStore`` over another that holds their commits back.

A worker with several frames of one map detected at once (``FrameWorker`` with ``detectors`` > 1) runs the
step on each through a ``StagedStore``, one after the other, then ``flush`` writes what they did in one
commit of the store under it (which records every frame of the batch in the same atomic step). What a frame
of the batch commits is seen by the next (queries, reads, the frames it recorded), so the batch ends as the
frames would have one by one; what it saves is the store's round trips, reads and writes: a hot map's objects
are read, decoded, encoded and written once a batch instead of once a frame, and its locks taken once.

Locks and claims are taken in the store under it and held until the flush's commit releases them. Only a
batch's first lock or claim waits (``timeout_s``); one that would add objects or cells to what the batch holds
tries once, so the batch never waits for more while holding some (``LockTimeout``: the frame is left for a
step of its own after the flush, holding nothing). The flush's commit is fenced by the store as any commit is:
objects written are at the version read + 1, deletes at the version read.

The flush's change is the batch's net change: one upsert per object written (at the version read + 1, or 1
when the batch created it), the objects the batch removed that the store had, counters of objects only
counted, and one event per object in one vocabulary (an object created and removed within the batch is
neither written nor told).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from arcloud.core.change import MapChange
from arcloud.core.errors import InvalidInput, StaleLease
from arcloud.core.ports import Lease, MapStore
from arcloud.core.types import EventKind, MapObject, ObjectEvent

_REMOVALS = ("merged", "deleted", "retired")


@dataclass(slots=True)
class StagedLease:
    """What a staged lock or claim hands the step: the ids it asked for; the store's leases under it are the
    batch's, released by the flush's commit (or ``StagedStore.release``)."""

    map_id: str
    ids: tuple[int, ...]

    def release(self) -> None:
        """Nothing: the batch holds its locks until the flush."""

    def __enter__(self) -> StagedLease:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


class StagedStore:
    """The step's ``MapStore`` for a batch of one map's frames over ``store`` (see the module's docstring)."""

    def __init__(self, store: MapStore, map_id: str) -> None:
        self.store = store
        self.map_id = map_id
        self._leases: list[Lease] = []  # the store's, held until the flush
        self._held: set[int] = set()  # object ids locked in the store
        self._claimed: set[tuple[int, int, int]] = set()  # index cells claimed in the store
        self._new: set[int] = set()  # ids the batch made: unknown to the store, so nobody else can lock them
        self._read: dict[int, MapObject] = {}  # objects as read from the store under the batch's locks
        self._staged: dict[int, MapObject] = {}  # objects written by the batch's frames, as last written
        self._removed: dict[int, ObjectEvent] = {}  # id -> the event that removed it (merged, deleted, retired)
        self._misses: dict[int, int] = {}
        self._gone: dict[int, int] = {}
        self._events: list[ObjectEvent] = []
        self.frames: list[str] = []  # the frames committed into the batch, in order

    def _check_map(self, map_id: str) -> None:
        if map_id != self.map_id:
            raise InvalidInput("map_id", f"the batch's map {self.map_id!r}", map_id)

    # --- the step's MapStore ------------------------------------------------------------------------
    def query_region(self, map_id: str, lo: np.ndarray, hi: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        self._check_map(map_id)
        found = {i: b for i, b in self.store.query_region(map_id, lo, hi).items() if i not in self._removed}
        for object_id, obj in self._staged.items():
            found.pop(object_id, None)
            if object_id not in self._removed and obj.bounds is not None:
                b_lo, b_hi = obj.bounds.min, obj.bounds.max
                if np.all(b_lo <= hi) and np.all(lo <= b_hi):
                    found[object_id] = (b_lo, b_hi)
        return found

    def lock(self, map_id: str, ids: Sequence[int], *, ttl_s: float, timeout_s: float) -> Lease:
        self._check_map(map_id)
        wanted = sorted({int(i) for i in ids} - self._held - self._new)
        if wanted:
            lease = self.store.lock(map_id, wanted, ttl_s=ttl_s, timeout_s=timeout_s if self._holds_nothing() else 0.0)
            self._leases.append(lease)
            self._held.update(wanted)
        return StagedLease(map_id, tuple(int(i) for i in ids))

    def claim(self, map_id: str, cells: Sequence[tuple[int, int, int]], *, ttl_s: float, timeout_s: float) -> Lease:
        self._check_map(map_id)
        wanted = sorted({(int(i), int(j), int(k)) for i, j, k in cells} - self._claimed)
        if wanted:
            lease = self.store.claim(map_id, wanted, ttl_s=ttl_s, timeout_s=timeout_s if self._holds_nothing() else 0.0)
            self._leases.append(lease)
            self._claimed.update(wanted)
        return StagedLease(map_id, ())

    def get(self, map_id: str, ids: Sequence[int]) -> list[MapObject]:
        self._check_map(map_id)
        # An object the batch holds is read from the store once (nobody else writes it meanwhile); others each time.
        missing = [i for i in ids if i not in self._staged and i not in self._removed and i not in self._read]
        fetched = {o.id: o for o in self.store.get(map_id, missing)} if missing else {}
        self._read.update({i: o for i, o in fetched.items() if i in self._held})
        found = []
        for object_id in ids:
            obj = self._staged.get(object_id, self._read.get(object_id, fetched.get(object_id)))
            if obj is None or object_id in self._removed:
                continue
            if object_id in self._misses or object_id in self._gone:
                obj = obj.replace(
                    n_missed=self._misses.get(object_id, obj.n_missed), n_gone=self._gone.get(object_id, obj.n_gone)
                )
            found.append(obj)
        return found

    def new_ids(self, map_id: str, n: int) -> Sequence[int]:
        self._check_map(map_id)
        ids = self.store.new_ids(map_id, n)
        self._new.update(ids)
        return ids

    def commit(
        self, map_id: str, leases: Sequence[Lease], change: MapChange, *, frame_key: str | tuple[str, ...] | None = None
    ) -> bool:
        """Stage ``change`` (written by ``flush``); False when a frame of ``frame_key`` is in the batch or the
        store recorded it."""
        self._check_map(map_id)
        keys = (frame_key,) if isinstance(frame_key, str) else tuple(frame_key or ())
        if any(k in self.frames for k in keys):  # one the store recorded makes the flush refuse the batch
            return False
        removal = {e.object_id: e for e in change.events if e.kind in _REMOVALS}
        removals: tuple[tuple[EventKind, tuple[MapObject, ...]], ...] = (("deleted", change.deletes), ("retired", change.retired))
        for kind, objects in removals:
            for obj in objects:
                self._staged.pop(obj.id, None)
                self._removed[obj.id] = removal.get(obj.id, ObjectEvent(kind, map_id, obj.id))
        for obj in change.upserts:  # a write carries the object's counters
            self._staged[obj.id] = obj
            self._misses.pop(obj.id, None)
            self._gone.pop(obj.id, None)
        for counters, field in ((self._misses, "n_missed"), (self._gone, "n_gone")):
            for object_id, count in (change.misses if field == "n_missed" else change.gone).items():
                if object_id in self._staged:  # written by the batch: its write carries the count
                    self._staged[object_id] = self._staged[object_id].replace(**{field: int(count)})
                else:
                    counters[object_id] = int(count)
        self._events += change.events
        self.frames += keys
        return True

    def is_frame_done(self, map_id: str, frame_key: str) -> bool:
        self._check_map(map_id)
        return frame_key in self.frames or self.store.is_frame_done(map_id, frame_key)

    # --- the batch ----------------------------------------------------------------------------------
    @property
    def held(self) -> frozenset[int]:
        """The object ids the batch has locked in the store."""
        return frozenset(self._held)

    def _holds_nothing(self) -> bool:
        return not self._leases

    def net_change(self) -> MapChange:
        """What the batch did, as one change of the store under it (see the module's docstring)."""
        upserts: list[MapObject] = []
        written: dict[int, MapObject] = {}
        for object_id, obj in self._staged.items():
            base = self._read.get(object_id)
            if base is None and object_id not in self._new:
                raise StaleLease(f"map {self.map_id}: object {object_id} written in a batch without its lock; nothing written")
            final = obj.replace(version=(base.version if base is not None else 0) + 1)
            upserts.append(final)
            written[object_id] = final
        deletes = [self._read[i] for i, e in self._removed.items() if i in self._read and e.kind != "retired"]
        retired = [self._read[i] for i, e in self._removed.items() if i in self._read and e.kind == "retired"]
        touched = set(written) | set(self._removed)
        last: dict[int, ObjectEvent] = {}
        for event in self._events:  # one event per object, in the order of each object's last change
            last.pop(event.object_id, None)
            last[event.object_id] = event
        events = []
        for object_id, event in last.items():
            base = self._read.get(object_id)
            was_confirmed = base is not None and base.confirmed
            if event.kind in _REMOVALS:
                if base is not None:
                    events.append(
                        ObjectEvent(
                            event.kind, self.map_id, object_id, merged_into=event.merged_into, was_confirmed=was_confirmed
                        )
                    )
            elif object_id in written:
                kind: EventKind = "updated" if base is not None else "created"
                events.append(ObjectEvent(kind, self.map_id, object_id, written[object_id], was_confirmed=was_confirmed))
        return MapChange(
            upserts=tuple(upserts),
            deletes=tuple(deletes),
            retired=tuple(retired),
            misses={i: n for i, n in self._misses.items() if i not in touched},
            gone={i: n for i, n in self._gone.items() if i not in touched},
            events=tuple(events),
        )

    def flush(self) -> bool:
        """Write the batch in one commit of the store under it, recording every frame it took; the batch's
        leases are released either way. False (nothing written) when the store had recorded one of its frames
        meanwhile: the caller integrates them one by one. A stale lease raises as the store's commit does."""
        try:
            if not self.frames:
                return True
            return self.store.commit(self.map_id, self._leases, self.net_change(), frame_key=tuple(self.frames))
        finally:
            self.release()

    def release(self) -> None:
        """Release the batch's leases in the store (a no-op for those a commit released)."""
        leases, self._leases = self._leases, []
        for lease in leases:
            lease.release()
