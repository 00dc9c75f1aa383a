"""Another client's view of Redis while a test's requests run (issue 22: no request of any role may keep Redis
from answering PING for more than ``PING_BOUND_S``). Imported as ``from ping_watch import ...``."""

from __future__ import annotations

import threading
import time

import redis

#: The longest another client's PING may wait while hostile or large requests run.
PING_BOUND_S = 0.1


class PingWatch:
    """Another client's PING every 5 ms in a thread, each round trip timed: ``max_s`` is the longest."""

    def __init__(self, url: str) -> None:
        self.client = redis.Redis.from_url(url, socket_timeout=30)
        self.client.ping()
        self.client.config_set("slowlog-log-slower-than", 10_000)  # and Redis's own account: commands of 10 ms and more
        self.client.slowlog_reset()
        self.times_s: list[float] = []
        self.longest_command_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="ping-watch", daemon=True)

    def _watch(self) -> None:
        while not self._stop.wait(0.005):
            sent = time.perf_counter()
            self.client.ping()
            self.times_s.append(time.perf_counter() - sent)

    def __enter__(self) -> PingWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(60)
        self.longest_command_s = max((e["duration"] / 1e6 for e in self.client.slowlog_get(1000)), default=0.0)
        self.client.close()

    @property
    def max_s(self) -> float:
        return max(self.times_s)
