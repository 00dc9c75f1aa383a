"""A Zenoh config file Zenoh cannot read stops `serve`, `worker` and the containers' worker at start with
one line naming the setting, before anything starts (not inside uvicorn's start-up traceback)."""

from __future__ import annotations

from pathlib import Path

import pytest

from arcloud.cli import main as cli_main
from arcloud.tools.worker import main as container_worker_main


def test_an_unreadable_zenoh_config_stops_serve_and_workers_at_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "zenoh.json5"
    broken.write_text('{ "mode": "peer", transport: { auth: { usrpwd: { user: 12 } } } ')  # cut short
    monkeypatch.setenv("ARCLOUD_ZENOH_CONFIG", str(broken))
    monkeypatch.setenv("ARCLOUD_ZENOH_MODE", "peer")
    monkeypatch.setenv("ARCLOUD_DETECTOR", "sim:0")
    assert cli_main(["serve", "--port", "1"]) == 2
    err = capsys.readouterr().err
    assert "zenoh_config" in err and len(err.strip().splitlines()) == 1, err
    monkeypatch.setenv("ARCLOUD_STORE", "redis://127.0.0.1:1/0")
    assert cli_main(["worker"]) == 2
    assert "zenoh_config" in capsys.readouterr().err
    assert container_worker_main([]) == 2
