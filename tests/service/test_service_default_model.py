"""The service with no detector given runs the catalogue's default model from the model cache: pulled from
../shared/models (skipped with a reason when absent) into a cache of the test's, then a real embedded service on
uvicorn processes a frame with it. Without the model, `serve` stops first (tests/service/test_service_replay.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from svc_helpers import UvicornThread, make_test_frame

from arcloud.cli import main as cli_main
from arcloud.client import ArcloudClient
from arcloud.detectors.catalogue import DEFAULT_MODEL
from arcloud.service.settings import Settings
from arcloud.tools.service_cli import add_service_commands, settings_from_args
from arcloud.tools.wiring import check_model_file, create_app

pytestmark = pytest.mark.shared


def test_serve_without_a_detector_runs_the_default_model_from_the_cache(
    shared: type, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import argparse

    monkeypatch.setenv("ARCLOUD_MODELS", str(tmp_path / "cache"))
    for name in ("ARCLOUD_MODEL", "ARCLOUD_DETECTOR"):
        monkeypatch.delenv(name, raising=False)
    assert cli_main(["models", "pull", DEFAULT_MODEL, "--from", str(shared.path("models"))]) == 0
    root = argparse.ArgumentParser()
    add_service_commands(root.add_subparsers(dest="command"))
    settings = settings_from_args(root.parse_args(["serve"]))  # what `arcloud serve` checks before it starts
    assert settings.detector == "onnx"
    check_model_file(settings.detector)  # found: serve starts
    with UvicornThread(create_app(Settings(workers=1, detector_threads=1))) as server, ArcloudClient(server.url) as client:
        client.send_frame(make_test_frame(0, map_id="cached"))
        assert client.wait_until_processed("cached", timeout_s=60)["frames"] == {
            "sent": 1,
            "processed": 1,
            "failed": 0,
            "lost": 0,
        }
