"""The ports of the core: the small interfaces the per-frame step talks to. Adapters implement them;
``arcloud.ports`` re-exports them beside the service's own.

- ``Detector``: frame -> 2D detections (ONNX models, ground-truth-mask replay, the simulator's detector).
- ``MapStore``: objects with their sparse voxels, a spatial index, per-object locks with fencing,
  space claims for creation, unique ids, idempotent frame marks (embedded store, Redis store).
- ``UpdatePublisher``: object change events out (Zenoh, or nothing).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from arcloud.core.change import MapChange
from arcloud.core.types import Detection, Frame, MapObject, ObjectEvent

#: The most index cells one store call takes: a space claim of more raises ``TooManyCells``; a region
#: query over more does not read its cells one by one. One Redis call per cell key costs about 8 µs,
#: so a call stays near 30 ms whatever a frame holds (9.4 M cells once blocked Redis for 72 s).
MAX_CELLS_PER_CALL = 4096


@runtime_checkable
class Detector(Protocol):
    """Turns a frame into 2D instance detections of arcloud's classes (``CLASSES``)."""

    def detect(self, frame: Frame) -> list[Detection]: ...


class Lease(Protocol):
    """Held locks (on object ids) or space claims (on index cells) of one map.

    A lease is a context manager that releases on exit. Locks expire after their TTL; a write made
    through an expired lease is refused (``StaleLease``). A successful ``MapStore.commit`` releases the
    leases it was given. ``ids`` are the object ids held (empty for a space claim)."""

    map_id: str
    ids: tuple[int, ...]

    def release(self) -> None:
        """Release what the lease still holds, never another holder's; a no-op once released (by a release or
        a successful commit)."""
        ...

    def __enter__(self) -> Lease: ...

    def __exit__(self, *exc: object) -> None: ...


class MapStore(Protocol):
    """What the per-frame step needs of a store: objects of many maps, with a spatial index, locks, space
    claims, unique ids and idempotent frame marks (``arcloud.ports.ObjectStore`` adds what a service needs).

    Every method is safe to call from many threads (and, for a shared store, many processes)."""

    def query_region(self, map_id: str, lo: np.ndarray, hi: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Ids and (min, max) bounds of the objects whose bounds intersect the box [lo, hi] (3,) each.
        Reads only the index cells the box covers, never every object."""
        ...

    def lock(self, map_id: str, ids: Sequence[int], *, ttl_s: float, timeout_s: float) -> Lease:
        """Lock objects in sorted id order, blocking up to ``timeout_s`` (0: try once); raise
        ``LockTimeout`` when not all could be taken (none stay held)."""
        ...

    def claim(self, map_id: str, cells: Sequence[tuple[int, int, int]], *, ttl_s: float, timeout_s: float) -> Lease:
        """Claim index cells for creating objects there, in sorted order, like ``lock``; at most
        ``MAX_CELLS_PER_CALL`` cells (more: ``TooManyCells``, nothing claimed)."""
        ...

    def get(self, map_id: str, ids: Sequence[int]) -> list[MapObject]:
        """The objects with these ids, in the order given; ids that do not exist are skipped."""
        ...

    def new_ids(self, map_id: str, n: int) -> Sequence[int]:
        """``n`` object ids never used before in this map, unique across every process of the store (consecutive:
        a ``range``, so that moving the counter past restored ids costs the same for any ``n``)."""
        ...

    def commit(
        self,
        map_id: str,
        leases: Sequence[Lease],
        change: MapChange,
        *,
        frame_key: str | None = None,
        entry_id: str | None = None,
    ) -> bool:
        """Write ``change`` atomically, append its events to the map's change log (``core.change``: one entry,
        the map's version + 1, when it has events) and record ``frame_key`` as processed, in the same step.

        Every existing object written, deleted or counted must be held by one of ``leases`` (new objects need
        none) and be at version ``obj.version - 1`` in the store (deletes and retired: at ``obj.version``),
        and ``entry_id`` (the queue entry the frame was delivered from) must not have been given up
        (``give_up_frame``); otherwise nothing is written, nor logged, and ``StaleLease`` is raised (fencing). Returns False,
        writing nothing, when ``frame_key`` was already recorded (the frame was processed before). A store may
        forget a record after a retention far longer than any redelivery (a day by default); the frame
        then counts as not processed. Retired objects are kept in the map's history, with the commit's
        time, for the store's retention (``ObjectStore.retired_objects``).

        A commit that writes (returns True) releases ``leases`` in the same atomic step, waking whoever waits
        for them (no call after it: a lock is held no longer than the write), and releasing them after (their
        ``release``, a ``with`` block's exit) does nothing. A commit that returns False or raises leaves them
        held: the caller releases them."""
        ...

    def is_frame_done(self, map_id: str, frame_key: str) -> bool:
        """Whether a commit recorded this frame as processed (and the record is kept)."""
        ...

    def give_up_frame(self, map_id: str, frame_key: str, entry_id: str) -> bool:
        """Give up the frame's queue entry ``entry_id`` before the queue counts it failed: from now on a commit from it
        raises ``StaleLease`` (a worker that held it and was paused past its claim writes nothing), for as long as
        a processed frame is recorded. False, recording nothing, when a commit recorded the frame already: it was
        processed, and counts as that. In one step, so that the frame is never both."""
        ...


class UpdatePublisher(Protocol):
    """Sends object change events to whoever listens."""

    def publish(self, events: Sequence[ObjectEvent]) -> None: ...
