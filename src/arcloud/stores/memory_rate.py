"""Rate limits in this process's memory (the embedded service): the same GCRA as ``lua/rate_limit.lua``."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

#: Buckets kept at most; full buckets (nothing to remember) are dropped first when there are more.
MAX_BUCKETS = 100_000


class MemoryRateLimiter:
    """``RateLimiter`` in memory. ``clock``: seconds, monotonic (tests pass their own)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._lock = threading.Lock()
        self._tat: dict[str, float] = {}  # bucket -> theoretical arrival time

    def close(self) -> None:
        return None

    def take(self, bucket: str, *, rate_per_s: float, burst: int) -> float:
        interval = 1.0 / rate_per_s
        with self._lock:
            now = self.clock()
            new_tat = max(self._tat.get(bucket, now), now) + interval
            allowed_at = new_tat - burst * interval
            if allowed_at > now:
                return allowed_at - now
            if len(self._tat) >= MAX_BUCKETS:
                self._tat = {b: t for b, t in self._tat.items() if t > now}
            self._tat[bucket] = new_tat
            return 0.0
