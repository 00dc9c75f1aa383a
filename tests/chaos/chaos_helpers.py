"""Helpers of the chaos suite (issue 10, "recover by itself"): the service against real parts that fail,
a real redis-server restarted without its data, hung (SIGSTOP) or busy running a script. Imported as
``from chaos_helpers import ...``."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress

import redis
from redis_server import RedisServer

SHUTDOWN_WAIT_S = 10.0


def restart_empty(server: RedisServer) -> RedisServer:
    """``SHUTDOWN NOSAVE``, then a fresh redis-server on the same port: Redis back without its data.
    Returns the new server (``server`` is stopped)."""
    # The server closes the connection as it goes.
    with (
        redis.Redis(host="127.0.0.1", port=server.port, socket_timeout=5.0) as client,
        suppress(redis.exceptions.ConnectionError),
    ):
        client.shutdown(nosave=True)
    server.process.wait(SHUTDOWN_WAIT_S)
    server.stop()
    return RedisServer.start(port=server.port)


@contextmanager
def frozen(server: RedisServer) -> Iterator[None]:
    """Redis hung: SIGSTOP for the block, SIGCONT after (its socket accepts, nothing answers)."""
    os.kill(server.process.pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(server.process.pid, signal.SIGCONT)


#: A Lua script spinning ARGV[1] microseconds (redis.call('TIME') is allowed in scripts since Redis 5).
SPIN_SCRIPT = (
    "local t0 = redis.call('TIME') repeat local t = redis.call('TIME') "
    "until (t[1] - t0[1]) * 1e6 + (t[2] - t0[2]) > tonumber(ARGV[1])"
)


@contextmanager
def busy(server: RedisServer, seconds: float, *, threshold_ms: int = 100) -> Iterator[None]:
    """Redis busy running a script for ``seconds`` (EVAL on a connection of its own, in a thread): past
    ``threshold_ms`` (busy-reply-threshold) every other command is answered ``BUSY``. The block starts once
    Redis answers so, and the script has ended when it is left."""
    with server.client() as client:
        client.config_set("busy-reply-threshold", threshold_ms)

    def run_script() -> None:
        with server.client() as client:
            client.eval(SPIN_SCRIPT, 0, int(seconds * 1e6))

    runner = threading.Thread(target=run_script, daemon=True)
    runner.start()
    time.sleep(threshold_ms / 1000 + 0.2)
    try:
        yield
    finally:
        runner.join(seconds + 5)
    assert not runner.is_alive()
