"""The ports: the interfaces adapters implement. The step's own (``Detector``, ``MapStore``, ``Lease``,
``UpdatePublisher``) are defined in ``arcloud.core.ports``; a service needs more of a store:

- ``ObjectStore``: a ``MapStore`` that also lists, counts and deletes (embedded store, Redis store).
"""

from __future__ import annotations

from typing import Protocol

from arcloud.core.ports import Detector, Lease, MapStore, NullPublisher, UpdatePublisher
from arcloud.core.types import MapObject

__all__ = ["Detector", "Lease", "MapStore", "NullPublisher", "ObjectStore", "UpdatePublisher"]


class ObjectStore(MapStore, Protocol):
    """A ``MapStore`` with what a service needs beside the step: listing, counting, deleting.

    Every method is safe to call from many threads (and, for a shared store, many processes)."""

    def list_objects(self, map_id: str) -> list[MapObject]:
        """Every object of the map."""
        ...

    def delete_map(self, map_id: str) -> int:
        """Remove a map and everything under it; returns the number of objects removed."""
        ...

    def count_frames(self, map_id: str) -> int:
        """How many frames were recorded as processed in this map."""
        ...
