"""``arcloud serve --api-processes N``: N API processes serve one port on Redis, beside the worker processes; one
that dies is started again, and SIGINT stops them all."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import httpx
import pytest
from svc_helpers import wait_until
from test_service_logs import PROTOBUF, SERVE, ServeProcess, frame_status, room_frame

from arcloud.cli import main as cli_main
from arcloud.proto.convert import frame_to_proto

pytestmark = pytest.mark.redis


def access_pids(serve: ServeProcess) -> set[int]:
    return {line["pid"] for line in serve.lines() if line["logger"] == "uvicorn.access"}


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"


def test_two_api_processes_share_the_port_and_one_that_dies_is_started_again(tmp_path: Path) -> None:
    from redis_server import RedisServer

    with RedisServer.start() as server:
        options = ("--redis", server.url, "--workers", "1", "--auth", "none", "--api-processes", "2")
        serve = ServeProcess(tmp_path, (*SERVE, *options), {})
        try:
            wait_until(serve.ready, 120, "arcloud serve to be ready", interval_s=0.2)
            body = frame_to_proto(room_frame()).SerializeToString()
            response = httpx.post(f"{serve.url}/v1/maps/ops/frames", content=body, headers=PROTOBUF, timeout=10.0)
            assert response.status_code == 202, response.text
            wait_until(lambda: frame_status(serve.url, "ops", "phone", "f000002") == "processed", 60, "the frame processed", 0.1)
            for _ in range(30):  # a connection each: the kernel hands them to both processes
                assert httpx.get(f"{serve.url}/v1/maps", timeout=5.0).status_code == 200
                health = httpx.get(f"{serve.url}/healthz/workers", timeout=5.0).json()  # the pool beside them, by count
                assert health["status"] == "ok" and health["expected"] == 1, health
            first = access_pids(serve)
            assert len(first) == 2, first
            workers = [line["pid"] for line in serve.lines() if "taking frames" in line["message"]]
            assert len(workers) == 1 and workers[0] not in first  # the worker process runs beside them, once

            gone = min(first)
            os.kill(gone, signal.SIGKILL)
            wait_until(lambda: not alive(gone), 10, "the API process killed")

            def replaced() -> bool:
                assert httpx.get(f"{serve.url}/v1/maps", timeout=5.0).status_code == 200  # the other one answers meanwhile
                return len(access_pids(serve) - first) == 1

            wait_until(replaced, 60, "another API process answering", interval_s=0.1)
            started = [line for line in serve.lines() if "api process" in line["message"] and "exited" in line["message"]]
            assert len(started) == 1 and str(gone) in started[0]["message"], started
            children = access_pids(serve) - {gone} | set(workers)
        finally:
            serve.stop()
        assert serve.process.returncode == 0
        assert not [pid for pid in children if alive(pid)]  # SIGINT stopped every process it started


def test_api_processes_need_redis(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["serve", "--api-processes", "2", "--detector", "sim:0", "--port", "1"]) != 0
    assert "--api-processes N needs --redis" in capsys.readouterr().err
