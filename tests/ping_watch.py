"""Another client's view of Redis while a test's requests run (issue 22: no request of any role may keep Redis
from answering PING for more than ``PING_BOUND_S``). Imported as ``from ping_watch import ...``."""

from __future__ import annotations

import json
import subprocess
import sys

import redis

#: The longest another client's PING may wait while hostile or large requests run.
PING_BOUND_S = 0.1

#: The watcher: PING every 5 ms until its stdin closes, then every round trip's seconds as one JSON line.
_WATCHER = """
import json, sys, threading, time
import redis
client = redis.Redis.from_url(sys.argv[1], socket_timeout=30)
client.ping()
times, stop = [], threading.Event()
def watch():
    while not stop.wait(0.005):
        sent = time.perf_counter()
        client.ping()
        times.append(time.perf_counter() - sent)
thread = threading.Thread(target=watch)
thread.start()
print("ready", flush=True)
sys.stdin.read()
stop.set()
thread.join()
print(json.dumps(times), flush=True)
"""


class PingWatch:
    """Another client's PING every 5 ms, each round trip timed: ``max_s`` is the longest. The client is a process of
    its own: in this one, an API served in a thread (uvicorn, JSON encoding) would hold the GIL and delay the PINGs
    with no help from Redis. ``longest_command_s``: Redis's own account (SLOWLOG, commands of 10 ms and more)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.client = redis.Redis.from_url(url, socket_timeout=30)
        self.client.config_set("slowlog-log-slower-than", 10_000)
        self.client.slowlog_reset()
        self.times_s: list[float] = []
        self.longest_command_s = 0.0

    def __enter__(self) -> PingWatch:
        self._watcher = subprocess.Popen(
            [sys.executable, "-c", _WATCHER, self.url], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        assert self._watcher.stdout is not None and self._watcher.stdout.readline().strip() == "ready"
        return self

    def __exit__(self, *exc: object) -> None:
        out, _ = self._watcher.communicate(timeout=60)
        self.times_s = json.loads(out.strip().splitlines()[-1])
        self.longest_command_s = max((e["duration"] / 1e6 for e in self.client.slowlog_get(1000)), default=0.0)
        self.client.close()

    @property
    def max_s(self) -> float:
        return max(self.times_s)
