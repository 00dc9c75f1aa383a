"""Viewer passes in this process's memory (the embedded service): expired passes are dropped as new ones come."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from arcloud.access import ViewerGrant

#: Passes kept at most: beyond, expired ones are dropped, then the oldest of the key asking for one more (else the
#: oldest): a key drawing passes fast ends its own, never another key's viewers'.
MAX_PASSES = 100_000


class MemoryViewerPasses:
    """``ViewerPasses`` in memory. ``clock``: Unix seconds (what ``expires_at_s`` is in)."""

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self.clock = clock
        self._lock = threading.Lock()
        self._passes: dict[str, ViewerGrant] = {}

    def close(self) -> None:
        return None

    def put(self, digest: str, grant: ViewerGrant) -> None:
        with self._lock:
            if len(self._passes) >= MAX_PASSES:
                now = self.clock()
                self._passes = {d: g for d, g in self._passes.items() if g.expires_at_s > now}
                own = [d for d, g in self._passes.items() if g.key_id == grant.key_id]  # oldest first
                while len(self._passes) >= MAX_PASSES:
                    del self._passes[own.pop(0) if own else next(iter(self._passes))]
            self._passes[digest] = grant

    def find(self, digest: str) -> ViewerGrant | None:
        with self._lock:
            return self._passes.get(digest)

    def take(self, digest: str) -> ViewerGrant | None:
        with self._lock:
            return self._passes.pop(digest, None)
