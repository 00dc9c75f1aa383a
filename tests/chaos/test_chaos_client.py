"""The SDK's retries against a real TCP server that drops connections or answers 503, and its backoff."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import socket
import threading
import time

import httpx
import pytest

from arcloud.client import ArcloudClient, AsyncArcloudClient, ServiceError
from arcloud.client.http import RetryPolicy, backoff_s
from arcloud.client.results import MapStats

STATS = {
    "map_id": "m",
    "frames": {"accepted": 1, "processed": 1, "failed": 0, "pending": 0},
    "objects": {"confirmed": 0, "tentative": 0, "total": 0, "truncated": False},
}


class FlakyServer:
    """An HTTP server on 127.0.0.1 that drops the first ``drops`` connections (reads the request, closes
    without an answer), answers the next ``unavailable`` with 503 (Retry-After: 0), then ``STATS``."""

    def __init__(self, drops: int, unavailable: int = 0) -> None:
        self.drops = drops
        self.unavailable = unavailable
        self.connections = 0
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.05)  # accept() wakes up to look at the stop flag
        self._stop = threading.Event()
        self.url = f"http://127.0.0.1:{self.listener.getsockname()[1]}"
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn:
                conn.settimeout(5.0)
                self.connections += 1
                conn.recv(65536)
                if self.connections <= self.drops:
                    continue
                if self.connections <= self.drops + self.unavailable:
                    body, status = b'{"detail": "store unavailable", "field": null}', "503 Service Unavailable\r\nRetry-After: 0"
                else:
                    body, status = json.dumps(STATS).encode(), "200 OK"
                head = f"HTTP/1.1 {status}\r\nContent-Type: application/json\r\nContent-Length: {len(body)}\r\nConnection: close\r\n\r\n"
                conn.sendall(head.encode() + body)

    def __enter__(self) -> FlakyServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        self.listener.close()


def test_the_client_retries_dropped_connections_and_503() -> None:
    with (
        FlakyServer(drops=2, unavailable=1) as server,
        ArcloudClient(server.url, max_retries=3, backoff_s=0.01, seed=0) as client,
    ):
        assert dataclasses.asdict(client.stats("m")) == STATS
    assert server.connections == 4


def test_the_async_client_retries_dropped_connections() -> None:
    async def stats(url: str) -> MapStats:
        async with AsyncArcloudClient(url, max_retries=3, backoff_s=0.01, seed=0) as client:
            return await client.stats("m")

    with FlakyServer(drops=3) as server:
        assert dataclasses.asdict(asyncio.run(stats(server.url))) == STATS
    assert server.connections == 4


def test_the_client_gives_up_after_its_retries_saying_so() -> None:
    with (
        FlakyServer(drops=100) as server,
        ArcloudClient(server.url, max_retries=2, backoff_s=0.05, max_backoff_s=0.1, seed=0) as client,
    ):
        started = time.monotonic()
        with pytest.raises(httpx.TransportError) as caught:
            client.stats("m")
        elapsed_s = time.monotonic() - started
    assert server.connections == 3 and elapsed_s < 2.0
    assert any("GET /v1/maps/m/stats: no answer after 3 attempts" in note for note in caught.value.__notes__)


def test_503_after_the_last_retry_is_a_service_error() -> None:
    with (
        FlakyServer(drops=0, unavailable=100) as server,
        ArcloudClient(server.url, max_retries=1, backoff_s=0.01, seed=0) as client,
        pytest.raises(ServiceError) as caught,
    ):
        client.stats("m")
    assert caught.value.status == 503 and server.connections == 2


def test_backoff_doubles_with_jitter_up_to_its_cap_and_honours_retry_after() -> None:
    assert [backoff_s(n, base_s=0.25, max_s=2.0, jitter=0.5) for n in range(6)] == [0.25, 0.5, 1.0, 2.0, 2.0, 2.0]
    assert backoff_s(0, base_s=1.0, max_s=10.0, jitter=0.0) == 0.5 and backoff_s(0, base_s=1.0, max_s=10.0, jitter=0.999) < 1.5
    first, second = RetryPolicy(5, seed=7), RetryPolicy(5, seed=7)
    assert [first.wait_s(n) for n in range(5)] == [second.wait_s(n) for n in range(5)]  # seeded: repeatable
    later = httpx.Response(503, headers={"retry-after": "3"})
    assert 3.0 <= RetryPolicy(5, backoff_s=0.01, seed=0).wait_s(0, later) < 3.01


def test_only_requests_safe_to_send_twice_are_retried() -> None:
    policy = RetryPolicy(3)
    assert policy.retryable("GET", False) and policy.retryable("DELETE", False)
    assert policy.retryable("POST", True)  # a frame upload: the API answers "duplicate" the second time
    assert not policy.retryable("POST", False) and not RetryPolicy(0).retryable("GET", False)
