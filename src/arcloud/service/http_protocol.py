"""uvicorn's HTTP protocol answering a request it cannot parse (a malformed request line, header or chunk, a
URL or Content-Length past the parser's limits) with the service's problem (``problems``: RFC 9457,
``application/problem+json``) instead of uvicorn's plain text.

    uvicorn.run(app, http=JsonProblemHTTP)                              # `arcloud serve`
    uvicorn --http arcloud.service.http_protocol:JsonProblemHTTP ...     # services/Dockerfile

Such a request never reaches the app: the protocol answers 400 and closes the connection.
"""

from __future__ import annotations

import json
from typing import Any

from uvicorn.protocols.http.auto import AutoHTTPProtocol

from arcloud.service.problems import PROBLEM_MEDIA_TYPE, problem_body

BAD_REQUEST_BODY = json.dumps(problem_body(400, "request: not a valid HTTP/1.1 request")).encode()


class JsonProblemHTTP(AutoHTTPProtocol):  # type: ignore[misc, valid-type]  # a class uvicorn picks at import (httptools, else h11)
    """uvicorn's protocol (httptools when installed, else h11) with a problem for its 400."""

    transport: Any
    server_state: Any

    def send_400_response(self, msg: str) -> None:
        head = [b"HTTP/1.1 400 Bad Request\r\n"]
        head += [name + b": " + value + b"\r\n" for name, value in self.server_state.default_headers]
        head += [
            b"content-type: " + PROBLEM_MEDIA_TYPE.encode() + b"\r\n",
            b"content-length: " + str(len(BAD_REQUEST_BODY)).encode() + b"\r\n",
            b"connection: close\r\n\r\n",
        ]
        self.transport.write(b"".join(head) + BAD_REQUEST_BODY)
        self.transport.close()


__all__ = ["BAD_REQUEST_BODY", "JsonProblemHTTP"]
