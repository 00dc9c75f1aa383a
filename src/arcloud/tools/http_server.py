"""uvicorn for ``arcloud serve``: a server that ends the app's event streams as it begins to shut down, and
answers a request it cannot parse with the service's JSON problem (``service.http_protocol``).

uvicorn lets open responses finish before it ends the app's lifespan, and an event stream
(``GET /v1/maps/{map}/events``) never finishes by itself: without this, one open viewer would hold a
stopping service forever. Run under plain ``uvicorn`` (the Docker image), give it
``--timeout-graceful-shutdown`` instead.

``serve --api-processes N`` (``run_servers``): the API is stateless on Redis (maps, queue, keys and rate
limits are shared there), so N processes serve one port: this process binds it and spawns N API processes
that accept on it (the kernel hands each connection to one of them), as uvicorn's ``--workers`` does, each
building its own app; this process also runs the worker processes (``settings.workers``), restarts either
kind when one dies, and stops them all on SIGINT or SIGTERM. One API process decodes and validates about
130 VGA frames a second on a core of its own (docs/scaling.md); more need more processes.
"""

from __future__ import annotations

import logging
import signal
import socket
import threading
from typing import TYPE_CHECKING, Any

import uvicorn
from fastapi import FastAPI

from arcloud.service.event_stream import close_event_streams
from arcloud.service.http_protocol import JsonProblemHTTP

if TYPE_CHECKING:
    from arcloud.service.settings import Settings

log = logging.getLogger(__name__)


class StreamClosingServer(uvicorn.Server):
    """``uvicorn.Server`` for one FastAPI ``app``: on shutdown, its event streams end first."""

    def __init__(self, config: uvicorn.Config, app: FastAPI) -> None:
        super().__init__(config)
        self.app = app

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        close_event_streams(self.app)
        await super().shutdown(sockets)


def server_config(app: Any, *, host: str, port: int, log_level: str, log_config: dict[str, Any] | None) -> uvicorn.Config:
    """uvicorn's config for ``arcloud serve``: no websockets, the lifespan on, the JSON problem protocol."""
    return uvicorn.Config(
        app, host=host, port=port, log_level=log_level, log_config=log_config, ws="none", lifespan="on", http=JsonProblemHTTP
    )


def run_server(app: FastAPI, *, host: str, port: int, log_level: str, log_config: dict[str, Any] | None = None) -> None:
    """Serve ``app`` on ``host:port`` until SIGINT or SIGTERM (``log_config``: uvicorn's logging config; None
    leaves logging as the caller configured it)."""
    StreamClosingServer(server_config(app, host=host, port=port, log_level=log_level, log_config=log_config), app).run()


def api_process(
    settings: Settings,
    listening: socket.socket,
    host: str,
    port: int,
    log_level: str,
    log_config: dict[str, Any] | None,
    host_workers: int = 0,
) -> None:
    """The body of one of ``run_servers``' API processes (spawned): its own logging and app, serving on the
    socket the parent bound; ``host_workers``: the worker processes the parent runs (``/healthz/workers``)."""
    from arcloud.service.logs import configure_logging
    from arcloud.tools.wiring import create_app

    configure_logging(settings.log_level, settings.log_format)
    app = create_app(settings, host_workers=host_workers)
    config = server_config(app, host=host, port=port, log_level=log_level, log_config=log_config)
    StreamClosingServer(config, app).run(sockets=[listening])


def run_servers(
    settings: Settings,
    processes: int,
    *,
    host: str,
    port: int,
    log_level: str,
    log_config: dict[str, Any] | None = None,
    stop: threading.Event | None = None,
) -> None:
    """``processes`` API processes on one socket bound to ``host:port`` here, and ``settings.workers`` worker
    processes, until SIGINT or SIGTERM (or ``stop``); a process that dies is started again. On Redis only:
    embedded, the store and the queue live in one process."""
    from arcloud.errors import InvalidInput
    from arcloud.service.pool import WorkerPool
    from arcloud.tools.wiring import worker_pool

    if settings.embedded:
        raise InvalidInput("api_processes", "1 with the embedded store (its maps and queue live in one process)", processes)
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, lambda *_: stop.set())
    listening = server_config(None, host=host, port=port, log_level=log_level, log_config=None).bind_socket()
    api_settings = settings.model_copy(update={"workers": 0})  # this process runs the workers, once
    apis = WorkerPool(
        processes, api_process, (api_settings, listening, host, port, log_level, log_config, settings.workers), kind="api"
    )
    workers = worker_pool(settings, settings.workers) if settings.workers > 0 else None
    try:
        apis.start()
        if workers is not None:
            workers.start()
        log.info("serving on http://%s:%d with %d API processes and %d worker processes", host, port, processes, settings.workers)
        stop.wait()
    finally:
        for pool in (apis, workers):
            if pool is not None:
                pool.stop(timeout_s=30.0)
        listening.close()


__all__ = ["StreamClosingServer", "api_process", "run_server", "run_servers", "server_config"]
