"""Viewer passes in this process's memory (the embedded service): expired passes are dropped as new ones come."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from arcloud.access import ViewerGrant
from arcloud.errors import StoreUnavailable
from arcloud.ports import MAX_VIEWER_PASSES_PER_KEY

#: Passes kept at most (of ``MAX_VIEWER_PASSES_PER_KEY`` a key: a thousand keys' worth). Beyond, expired ones are
#: dropped; a store still full refuses the pass (503) rather than end another key's viewers.
MAX_PASSES = 100_000


class MemoryViewerPasses:
    """``ViewerPasses`` in memory. ``clock``: Unix seconds (what ``expires_at_s`` is in)."""

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self.clock = clock
        self._lock = threading.Lock()
        self._passes: dict[str, ViewerGrant] = {}
        self._by_key: dict[str, dict[str, None]] = {}  # key id -> its passes' digests (a set, in the order they came)

    def close(self) -> None:
        return None

    def put(self, digest: str, grant: ViewerGrant) -> None:
        with self._lock:
            now = self.clock()
            own = self._by_key.setdefault(grant.key_id, {})
            for old in [d for d in own if self._passes[d].expires_at_s <= now]:
                self._forget(old)
            while len(own) >= MAX_VIEWER_PASSES_PER_KEY:  # the one that would end first (of passes alike, the oldest)
                self._forget(min(own, key=lambda d: self._passes[d].expires_at_s))
            if len(self._passes) >= MAX_PASSES:
                for old in [d for d, g in self._passes.items() if g.expires_at_s <= now]:
                    self._forget(old)
                if len(self._passes) >= MAX_PASSES:
                    raise StoreUnavailable(f"viewer passes: {MAX_PASSES} live ones are kept, the most this process keeps")
            self._passes[digest] = grant
            self._by_key.setdefault(grant.key_id, {})[digest] = None

    def find(self, digest: str) -> ViewerGrant | None:
        with self._lock:
            return self._passes.get(digest)

    def take(self, digest: str) -> ViewerGrant | None:
        with self._lock:
            grant = self._passes.get(digest)
            self._forget(digest)
            return grant

    def _forget(self, digest: str) -> None:
        grant = self._passes.pop(digest, None)
        if grant is not None:
            own = self._by_key.get(grant.key_id)
            if own is not None:
                own.pop(digest, None)
                if not own:
                    del self._by_key[grant.key_id]
