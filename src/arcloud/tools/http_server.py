"""uvicorn for ``arcloud serve``: a server that ends the app's event streams as it begins to shut down, and
answers a request it cannot parse with the service's JSON problem (``service.http_protocol``).

uvicorn lets open responses finish before it ends the app's lifespan, and an event stream
(``GET /v1/maps/{map}/events``) never finishes by itself: without this, one open viewer would hold a
stopping service forever. Run under plain ``uvicorn`` (the Docker image), give it
``--timeout-graceful-shutdown`` instead.
"""

from __future__ import annotations

import socket
from typing import Any

import uvicorn
from fastapi import FastAPI

from arcloud.service.event_stream import close_event_streams
from arcloud.service.http_protocol import JsonProblemHTTP


class StreamClosingServer(uvicorn.Server):
    """``uvicorn.Server`` for one FastAPI ``app``: on shutdown, its event streams end first."""

    def __init__(self, config: uvicorn.Config, app: FastAPI) -> None:
        super().__init__(config)
        self.app = app

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        close_event_streams(self.app)
        await super().shutdown(sockets)


def run_server(app: FastAPI, *, host: str, port: int, log_level: str, log_config: dict[str, Any] | None = None) -> None:
    """Serve ``app`` on ``host:port`` until SIGINT or SIGTERM (``log_config``: uvicorn's logging config; None
    leaves logging as the caller configured it)."""
    config = uvicorn.Config(
        app, host=host, port=port, log_level=log_level, log_config=log_config, ws="none", lifespan="on", http=JsonProblemHTTP
    )
    StreamClosingServer(config, app).run()


__all__ = ["StreamClosingServer", "run_server"]
