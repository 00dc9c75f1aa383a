"""A throwaway redis-server for tests: started on a free port of 127.0.0.1, no persistence, stopped at the end.

    with RedisServer.start() as server:   # skips the test when redis-server is not on PATH
        store = RedisStore(server.url)

    with LocalCluster.start() as cluster:  # 3 primaries (redis-server --cluster-enabled yes, redis-cli --cluster create)
        store = RedisStore(cluster.url)    # redis+cluster://127.0.0.1:P1,127.0.0.1:P2,127.0.0.1:P3

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
    def start(
        cls, binary: str = "redis-server", *, port: int | None = None, aof_dir: str | None = None, cluster: bool = False
    ) -> RedisServer:
        """Start a server (on ``port``, else a free one) and wait until it answers PING; skip the calling
        test when there is no binary. ``aof_dir``: keep the data there in an append-only file (fsync
        always), which a later server started on the same folder reads back (the folder is the caller's).
        ``cluster``: a node of a Redis Cluster yet to be created (``LocalCluster``), its bus on another free port."""
        path = shutil.which(binary)
        if path is None:
            pytest.skip(f"{binary} not found on PATH (`make test` installs it; or apt-get install redis-server)")
        chosen = port
        for _attempt in range(3):  # the free port may be taken between choosing and binding it
            port = chosen or free_port()
            workdir = tempfile.TemporaryDirectory(prefix="arcloud-redis-")
            persistence = ["--appendonly", "yes", "--appendfsync", "always", "--dir", aof_dir] if aof_dir else []
            node = ["--cluster-enabled", "yes", "--cluster-config-file", "nodes.conf", "--cluster-port", str(free_port())]
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
                    *(node if cluster else []),
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


class LocalCluster:
    """A Redis Cluster of ``masters`` primaries without replicas, each a ``RedisServer`` on 127.0.0.1, the
    slots shared by ``redis-cli --cluster create``. ``url``: ``redis+cluster://`` naming every node."""

    def __init__(self, nodes: list[RedisServer]) -> None:
        self.nodes = nodes
        self.url = "redis+cluster://" + ",".join(f"127.0.0.1:{node.port}" for node in nodes)

    @classmethod
    def start(cls, masters: int = 3) -> LocalCluster:
        """Start the nodes, create the cluster and wait until every node says ``cluster_state:ok``; skip the
        calling test when redis-server or redis-cli is not on PATH."""
        cli = shutil.which("redis-cli")
        if cli is None:
            pytest.skip("redis-cli not found on PATH (it creates the test cluster; apt-get install redis-tools)")
        nodes: list[RedisServer] = []
        cluster = cls(nodes)
        try:
            nodes += [RedisServer.start(cluster=True) for _ in range(masters)]
            cluster.url = cls(nodes).url
            created = subprocess.run(
                [cli, "--cluster", "create", *(f"127.0.0.1:{node.port}" for node in nodes)]
                + ["--cluster-replicas", "0", "--cluster-yes"],
                capture_output=True,
                text=True,
                timeout=60,
            )
            if created.returncode != 0:
                raise RuntimeError(f"redis-cli --cluster create failed:\n{created.stdout}\n{created.stderr}")
            cluster._wait_ok()
        except BaseException:
            cluster.stop()
            raise
        return cluster

    def _wait_ok(self) -> None:
        deadline = time.monotonic() + 30.0
        for node in self.nodes:
            with node.client() as client:
                while client.execute_command("CLUSTER INFO").get("cluster_state") != "ok":  # redis-py parses it into a dict
                    if time.monotonic() > deadline:
                        raise RuntimeError(
                            f"the cluster did not reach cluster_state:ok in 30 s; node {node.port}'s log:\n{node.log_tail()}"
                        )
                    time.sleep(0.05)

    def flush(self) -> None:
        """Empty every node (FLUSHALL on each primary)."""
        for node in self.nodes:
            with node.client() as client:
                client.flushall()

    def stop(self) -> None:
        for node in self.nodes:
            node.stop()

    def __enter__(self) -> LocalCluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


#: The params of a fixture run on the embedded adapter, on one Redis and on a Redis Cluster.
ADAPTERS = ["memory", pytest.param("redis", marks=pytest.mark.redis), pytest.param("cluster", marks=pytest.mark.redis)]


def empty_redis_url(request: pytest.FixtureRequest) -> str:
    """The URL of the session's Redis (the fixtures ``redis_server`` and ``redis_cluster`` for ``request.param`` "redis" and "cluster"), emptied now."""
    if request.param == "cluster":
        cluster: LocalCluster = request.getfixturevalue("redis_cluster")
        cluster.flush()
        return cluster.url
    server: RedisServer = request.getfixturevalue("redis_server")
    with server.client() as client:
        client.flushdb()
    return server.url
