"""Helpers of the chaos suite (issue 10, "recover by itself"): the service against real parts that fail,
a real redis-server restarted without its data or hung (SIGSTOP). Imported as ``from chaos_helpers import ...``."""

from __future__ import annotations

import os
import signal
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
