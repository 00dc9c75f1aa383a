"""`serve` with a Redis that does not answer stops at start with one line naming where it looked and what to do,
before uvicorn starts (not three tracebacks of the API's start-up)."""

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
