"""Starting without the Redis a process needs says so in one line: `serve` with a Redis that does not answer stops
before uvicorn starts (not three tracebacks of the API's start-up), a container's worker healthcheck without a Redis
URL answers unhealthy (not a traceback)."""

from __future__ import annotations

import pytest

from arcloud.cli import main as cli_main


def test_serve_with_redis_down_stops_with_one_line(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("ARCLOUD_DETECTOR", "sim:0")
    assert cli_main(["serve", "--redis", "redis://127.0.0.1:1/0", "--port", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("arcloud: error: reach the store (start Redis, or give the URL it answers at): redis at 127.0.0.1:1")
    assert "unreachable" in err


def test_a_worker_healthcheck_without_a_redis_url_says_unhealthy_in_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from arcloud.tools.worker import main as container_worker_main

    monkeypatch.delenv("ARCLOUD_STORE", raising=False)
    assert container_worker_main(["--healthcheck"]) == 1
    printed = capsys.readouterr()
    assert printed.out == "unhealthy: ARCLOUD_STORE is no Redis URL (workers take frames from Redis)\n"
    assert printed.err == ""
