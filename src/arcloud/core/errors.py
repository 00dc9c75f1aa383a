"""The exceptions arcloud raises, in one tree.

    ArcloudError                 base of everything below
    ├── InvalidInput (ValueError) a value at an edge is wrong; names the field, what was expected, what came
    │   └── TooManyCells         a frame would make one store call take more index cells than ``MAX_CELLS_PER_CALL``
    ├── ModelError               a detector model cannot be loaded or does not fit its adapter
    ├── DatasetError             a dataset folder is missing files or holds malformed ones
    ├── QueueFull                the frame queue (or a map's share of it) is full, or the service is stopping
    │                            (``arcloud.ports``; HTTP 503)
    ├── ServiceError             the service refused a client's request: its status and problem (``arcloud.client``)
    └── StoreError               the object store failed
        ├── LockTimeout          per-object locks or space claims not acquired in time
        ├── StaleLease           a write whose lock expired or whose object changed since it was read
        │   │                    (fencing): nothing was written
        │   └── FrameGivenUp     a commit from a queue entry given up (dead-lettered): nothing was written, and
        │                        the frame is no longer this delivery's to settle
        ├── StoreUnavailable     the store's server cannot be reached
        ├── MapMismatch          a map was built with other settings (voxel size, up, ...) than ours
        └── MapBeingDeleted      the map's deletion is under way (``arcloud.ports``; HTTP 409)

Adapters map their library's exceptions to these at the boundary (``raise StoreUnavailable(...) from exc``).
"""

from __future__ import annotations


class ArcloudError(Exception):
    """Base class of arcloud's exceptions."""


class InvalidInput(ArcloudError, ValueError):
    """A value given at an edge is wrong. ``field`` names it, ``expected`` and ``got`` say how."""

    def __init__(self, field: str, expected: str, got: object) -> None:
        self.field = field
        self.expected = expected
        self.got = got
        super().__init__(f"{field}: expected {expected}, got {got}")


class TooManyCells(InvalidInput):
    """A frame would make one store call take more index cells than a call may (``core.ports.MAX_CELLS_PER_CALL``):
    its detections span too much space. Permanent: the same frame always would."""

    def __init__(self, field: str, n_cells: int, limit: int) -> None:
        self.n_cells = n_cells
        self.limit = limit
        super().__init__(field, f"at most {limit} index cells in one store call", f"{n_cells} cells")


class ModelError(ArcloudError):
    """A detector model cannot be loaded, or its inputs/outputs do not fit the adapter."""


class DatasetError(ArcloudError):
    """A dataset folder is missing files or holds malformed ones."""


class StoreError(ArcloudError):
    """The object store failed."""


class LockTimeout(StoreError):
    """Locks or space claims were not acquired within the timeout."""


class StaleLease(StoreError):
    """A write was refused: its lease expired, or an object changed since it was read. Nothing was written."""


class FrameGivenUp(StaleLease):
    """A commit was refused because the queue entry its frame was delivered from was given up (another worker
    dead-lettered it: ``MapStore.give_up_frame``). Nothing was written; trying again cannot help."""


class StoreUnavailable(StoreError):
    """The store's server cannot be reached."""


class MapMismatch(StoreError):
    """A map's stored data means something else under our settings (``arcloud.core.header``).
    ``differences``: (setting, the map's value, ours) for each setting that differs."""

    def __init__(self, map_id: str | None, differences: list[tuple[str, object, object]]) -> None:
        self.map_id = map_id
        self.differences = differences
        listed = "; ".join(f"{name}: map {theirs!r}, ours {ours!r}" for name, theirs, ours in differences)
        super().__init__(f"map {map_id or '(unnamed)'} was built with other settings: {listed}")
