"""uvicorn's HTTP protocol answering a request it cannot parse (a malformed request line, header or chunk, a
URL or Content-Length past the parser's limits) with the service's problem (``problems``: RFC 9457,
``application/problem+json``) instead of uvicorn's plain text, and refusing a request head that is too large
(over ``MAX_HEAD_BYTES``: 431) or too slow (not complete ``HEAD_TIMEOUT_S`` after the connection opened or its
last answer: 408). httptools, which uvicorn picks when installed, caps neither: a client without a key could send
one endless header and grow the server's memory, or hold connections open a byte at a time.

    uvicorn.run(app, http=JsonProblemHTTP)                              # `arcloud serve`
    uvicorn --http arcloud.service.http_protocol:JsonProblemHTTP ...     # services/Dockerfile

Such a request never reaches the app: the protocol answers and closes the connection. (h11, uvicorn's other
parser, caps a head at 16 kB itself and answers 400; it has no deadline here.)
"""

from __future__ import annotations

import asyncio
import json
from http import HTTPStatus
from typing import Any

from uvicorn.protocols.http.auto import AutoHTTPProtocol

from arcloud.service.problems import PROBLEM_MEDIA_TYPE, problem_body

BAD_REQUEST_BODY = json.dumps(problem_body(400, "request: not a valid HTTP/1.1 request")).encode()
#: The most a request line and its headers may take (a real one is under 8 kB; browsers' cookies stay under 16 kB).
MAX_HEAD_BYTES = 64 * 1024
#: How long a request head may take to arrive, from the connection's start or its previous answer.
HEAD_TIMEOUT_S = 10.0
#: How long a refused connection keeps reading (and dropping) what the client still sends before it closes: closed
#: with unread data, the client would get a reset instead of the answer.
LINGER_S = 2.0


class _HeadTooLarge(Exception):
    """Raised in httptools' callback: the parser stops, and ``send_400_response`` answers 431 instead."""


#: Whether uvicorn's protocol tells when a head is complete (httptools does; h11, which caps heads itself, does not).
_COUNTS_HEADS = hasattr(AutoHTTPProtocol, "on_headers_complete")


class JsonProblemHTTP(AutoHTTPProtocol):  # type: ignore[misc, valid-type]  # a class uvicorn picks at import (httptools, else h11)
    """uvicorn's protocol (httptools when installed, else h11) with a problem for its 400, and a head that must
    arrive within ``MAX_HEAD_BYTES`` and ``HEAD_TIMEOUT_S``."""

    transport: Any
    server_state: Any

    def connection_made(self, transport: asyncio.Transport) -> None:
        super().connection_made(transport)
        self._head_bytes = 0  # bytes received since the last head was complete (its body's too, until it is)
        self._head_fields = 0  # the URL's and headers' bytes of the head being parsed
        self._refusing = 0  # the status a refused connection answered (it drops what comes after)
        self._in_head = _COUNTS_HEADS
        self._head_deadline: asyncio.TimerHandle | None = None
        if _COUNTS_HEADS:
            self._arm_head_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_deadline()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._refusing:
            return
        if self._in_head:
            self._head_bytes += len(data)
        super().data_received(data)
        if self._in_head and self._head_bytes > MAX_HEAD_BYTES and not self._refusing and not self.transport.is_closing():
            self._refuse(431, f"request: its line and headers are over {MAX_HEAD_BYTES} bytes")

    def on_url(self, url: bytes) -> None:
        self._head_fields += len(url)
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._head_fields += len(name) + len(value) + 4
        super().on_header(name, value)

    def on_headers_complete(self) -> None:  # httptools' callback (h11 has its own cap)
        self._in_head = False
        self._head_bytes = 0
        self._cancel_head_deadline()
        if self._head_fields > MAX_HEAD_BYTES:  # a head that came whole in one read
            raise _HeadTooLarge
        self._head_fields = 0
        super().on_headers_complete()

    def on_response_complete(self) -> None:  # the next request on this connection starts its head
        super().on_response_complete()
        idle = self.cycle is None or self.cycle.response_complete  # not a pipelined request started in its place
        if _COUNTS_HEADS and idle and not self.transport.is_closing():
            self._in_head = True
            self._head_bytes = 0
            self._arm_head_deadline()

    def _arm_head_deadline(self) -> None:
        self._cancel_head_deadline()
        self._head_deadline = asyncio.get_running_loop().call_later(HEAD_TIMEOUT_S, self._head_timed_out)

    def _cancel_head_deadline(self) -> None:
        if self._head_deadline is not None:
            self._head_deadline.cancel()
            self._head_deadline = None

    def _head_timed_out(self) -> None:
        self._head_deadline = None
        if self._in_head and not self.transport.is_closing():
            if self._head_bytes:
                self._refuse(408, f"request: its line and headers did not arrive within {HEAD_TIMEOUT_S:g} s", "too-slow")
            else:  # an idle connection: nothing to answer
                self.transport.close()

    def send_400_response(self, msg: str) -> None:
        if self._head_fields > MAX_HEAD_BYTES:  # _HeadTooLarge, through httptools' error
            self._refuse(431, f"request: its line and headers are over {MAX_HEAD_BYTES} bytes")
        else:
            self._refuse(400, "")

    def _refuse(self, status: int, detail: str, kind: str | None = None) -> None:
        """Answer ``status`` with the service's problem (``detail``; 400: ``BAD_REQUEST_BODY``), then drop what the
        client still sends for ``LINGER_S`` and close."""
        if self._refusing:
            return
        self._refusing = status
        self._in_head = False
        self._cancel_head_deadline()
        body = BAD_REQUEST_BODY if status == 400 else json.dumps(problem_body(status, detail, kind=kind)).encode()
        head = [f"HTTP/1.1 {status} {HTTPStatus(status).phrase}\r\n".encode()]
        head += [name + b": " + value + b"\r\n" for name, value in self.server_state.default_headers]
        head += [
            b"content-type: " + PROBLEM_MEDIA_TYPE.encode() + b"\r\n",
            b"content-length: " + str(len(body)).encode() + b"\r\n",
            b"connection: close\r\n\r\n",
        ]
        self.transport.write(b"".join(head) + body)
        if self.transport.can_write_eof():
            self.transport.write_eof()
            asyncio.get_running_loop().call_later(LINGER_S, self.transport.close)
        else:
            self.transport.close()


__all__ = ["BAD_REQUEST_BODY", "HEAD_TIMEOUT_S", "LINGER_S", "MAX_HEAD_BYTES", "JsonProblemHTTP"]
