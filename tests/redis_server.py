"""A throwaway redis-server for tests: started on a free port of 127.0.0.1, no persistence, stopped at the end.

    with RedisServer.start() as server:   # skips the test when redis-server is not on PATH
        store = RedisStore(server.url)

Tests import it as ``from redis_server import RedisServer`` (pytest puts ``tests/`` on sys.path through
``tests/conftest.py``). Never a fake or a mock: the real server, so Lua and TTLs behave as in production.
"""

from __future__ import annotations

import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
import redis

START_TIMEOUT_S = 10.0


def free_port() -> int:
    """A TCP port of 127.0.0.1 free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class RedisServer:
    """One redis-server process. ``url`` points at database 0."""

    def __init__(self, process: subprocess.Popen[bytes], port: int, workdir: tempfile.TemporaryDirectory[str]) -> None:
        self.process = process
        self.port = port
        self.workdir = workdir
        self.url = f"redis://127.0.0.1:{port}/0"

    @classmethod
    def start(cls, binary: str = "redis-server", *, port: int | None = None, aof_dir: str | None = None) -> RedisServer:
        """Start a server (on ``port``, else a free one) and wait until it answers PING; skip the calling
        test when there is no binary. ``aof_dir``: keep the data there in an append-only file (fsync
        always), which a later server started on the same folder reads back (the folder is the caller's)."""
        path = shutil.which(binary)
        if path is None:
            pytest.skip(f"{binary} not found on PATH (`make test` installs it; or apt-get install redis-server)")
        chosen = port
        for _attempt in range(3):  # the free port may be taken between choosing and binding it
            port = chosen or free_port()
            workdir = tempfile.TemporaryDirectory(prefix="arcloud-redis-")
            persistence = ["--appendonly", "yes", "--appendfsync", "always", "--dir", aof_dir] if aof_dir else []
            process = subprocess.Popen(
                [
                    path,
                    "--port",
                    str(port),
                    "--bind",
                    "127.0.0.1",
                    "--save",
                    "",
                    "--appendonly",
                    "no",
                    "--dir",
                    workdir.name,
                    "--daemonize",
                    "no",
                    "--loglevel",
                    "warning",
                    "--logfile",
                    str(Path(workdir.name) / "redis.log"),
                    *persistence,
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            server = cls(process, port, workdir)
            if server._wait_ready():
                return server
            log_tail = server.log_tail()
            server.stop()
        raise RuntimeError(f"redis-server did not answer PING within {START_TIMEOUT_S} s (3 attempts); its log ends:\n{log_tail}")

    def log_tail(self, n_lines: int = 20) -> str:
        """The last lines of the server's log."""
        log = Path(self.workdir.name) / "redis.log"
        return "\n".join(log.read_text(errors="replace").splitlines()[-n_lines:]) if log.exists() else "(no log)"

    def _wait_ready(self) -> bool:
        deadline = time.monotonic() + START_TIMEOUT_S
        with redis.Redis(host="127.0.0.1", port=self.port, socket_connect_timeout=0.5) as client:
            while time.monotonic() < deadline:
                if self.process.poll() is not None:
                    return False
                try:
                    if client.ping():
                        return True
                except redis.exceptions.ConnectionError:
                    time.sleep(0.02)
        return False

    def client(self) -> redis.Redis:
        return redis.Redis.from_url(self.url)

    def stop(self) -> None:
        """Terminate the server (kill it if it does not stop in 5 s) and remove its folder."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.workdir.cleanup()

    def __enter__(self) -> RedisServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
