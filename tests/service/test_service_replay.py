"""`arcloud replay` against a real embedded service running the simulator's detector, and the CLI wiring."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest
from svc_helpers import UvicornThread

from arcloud.cli import main as cli_main
from arcloud.core.types import Intrinsics, Params
from arcloud.errors import ArcloudError
from arcloud.eval.metrics import evaluate
from arcloud.eval.protocol import object_boxes, run_map
from arcloud.service.settings import Settings
from arcloud.stores.memory import MemoryStore
from arcloud.tools.service_cli import add_service_commands, settings_from_args
from arcloud.tools.wiring import create_app
from arcloud.tools.worker import main as worker_main

pytestmark = pytest.mark.slow


def parser() -> argparse.ArgumentParser:
    root = argparse.ArgumentParser(prog="arcloud")
    add_service_commands(root.add_subparsers(dest="command", required=True))
    return root


def test_replay_streams_users_and_scores_like_the_in_process_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from arcloud.sim.detector import SimulatedDetector
    from arcloud.sim.room import generate_room
    from arcloud.sim.sequence import simulate_sequence

    out = tmp_path / "deep" / "results.json"
    with UvicornThread(create_app(Settings(detector="sim:0", workers=2))) as server:
        args = parser().parse_args(
            [
                "replay",
                "--url",
                server.url,
                "--map",
                "room",
                "--users",
                "3",
                "--seed",
                "0",
                "--frames",
                "24",
                "--width",
                "160",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        assert args.handler(args) == 0
    results = json.loads(out.read_text())
    (row,) = results["table1"]
    assert {k: row[k] for k in ("approach", "users", "runs", "map25_var", "map50_var")} == {
        "approach": "distributed",
        "users": 3,
        "runs": 1,
        "map25_var": 0.0,
        "map50_var": 0.0,
    }
    assert results["frames"] == {"sent": 24, "accepted": 24, "duplicate": 0, "processed": 24, "failed": 0, "lost": 0}
    assert 0.0 < row["map50_mean"] <= row["map25_mean"] <= 1.0
    printed = capsys.readouterr().out
    assert "mAP@0.25" in printed and "precision/recall@0.25" in printed

    # The room's boxes, in the map's frame, and what a plain GET served, scored against them.
    room = generate_room(0)
    truth = [o.box for o in room.objects]
    assert [(g["label"], g["aabb_min"], g["aabb_max"]) for g in results["ground_truth"]] == [
        (b.label, b.min.tolist(), b.max.tolist()) for b in truth
    ]
    served, counts = results["served"], results["objects"]
    assert served["objects"] == counts["confirmed"] and counts["confirmed"] + counts["tentative"] >= served["objects"]
    for iou, key in ((0.25, "25"), (0.5, "50")):
        matches = served["matches"][f"{iou:g}"]
        assert matches["iou_threshold"] == iou and matches["n_predictions"] == served["objects"] and matches["n_gt"] == len(truth)
        assert served[f"precision{key}"] == (matches["true_positives"] / served["objects"] if served["objects"] else 1.0)
        assert served[f"recall{key}"] == matches["true_positives"] / len(truth)
    assert served["precision50"] <= served["precision25"] and served["recall50"] <= served["recall25"]
    assert served["map25"] is None or 0.0 <= served["map25"] <= 1.0

    # The same frames in order, in process (the centralized run): the service's map scores the same.
    frames = simulate_sequence(
        room, n_frames=24, seed=0, width=160, height=120, intrinsics=Intrinsics(131.25, 131.25, 79.5, 59.5)
    )
    objects = run_map(frames, SimulatedDetector(room, seed=0), Params(), new_store=MemoryStore, users=1)
    centralized = evaluate({"s": object_boxes(objects)}, {"s": truth})
    assert row["map25_mean"] == pytest.approx(centralized.map_at(0.25), abs=0.1)
    assert counts["confirmed"] + counts["tentative"] == pytest.approx(len(objects), abs=2)
    assert counts["confirmed"] == pytest.approx(sum(o.confirmed for o in objects), abs=2)


def test_cli_options_become_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ARCLOUD_LOCK_TTL_S", "4.5")
    args = parser().parse_args(
        [
            "serve",
            "--redis",
            "redis://127.0.0.1:6390/2",
            "--workers",
            "3",
            "--detector",
            "sim:7",
            "--zenoh-listen",
            "tcp/127.0.0.1:7447",
            "--zenoh-listen",
            "tcp/127.0.0.1:7448",
        ]
    )
    settings = settings_from_args(args)
    assert (settings.store, settings.workers, settings.detector, settings.lock_ttl_s) == (
        "redis://127.0.0.1:6390/2",
        3,
        "sim:7",
        4.5,
    )
    assert settings.zenoh_mode == "peer" and settings.zenoh_listen == ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]
    assert (args.host, args.port) == ("127.0.0.1", 8000)
    worker = parser().parse_args(
        ["worker", "--redis", "redis://r:6379/0", "--zenoh-connect", "tcp/zenoh:7447", "--zenoh-mode", "client"]
    )
    assert settings_from_args(worker).zenoh_connect == ["tcp/zenoh:7447"]
    with pytest.raises(SystemExit):
        parser().parse_args(["replay", "--users", "0"])
    with pytest.raises(
        ArcloudError, match=r"store: expected `memory` or a URL.*'mysql://u:\*\*\*@db'; detector: expected PREFIX"
    ):
        settings_from_args(parser().parse_args(["serve", "--redis", "mysql://u:pw@db", "--detector", "foo"]))


def test_serve_and_worker_without_a_model_stop_at_once_with_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    monkeypatch.delenv("ARCLOUD_MODEL", raising=False)
    monkeypatch.delenv("ARCLOUD_DETECTOR", raising=False)
    monkeypatch.setenv("ARCLOUD_MODELS", str(tmp_path))  # an empty model cache
    for argv in (
        ["serve"],
        ["serve", "--redis", "redis://127.0.0.1:1/0", "--workers", "2"],
        ["worker", "--redis", "redis://127.0.0.1:1/0"],
    ):
        assert cli_main(argv) == 2  # before any server, worker process or Redis connection starts
        err = capsys.readouterr().err
        assert err.startswith("arcloud: error: detector spec: expected onnx:PATH to a model file") and "sim:SEED" in err
        assert f"got no file at {tmp_path}/yolo11n-seg-fp32-640.onnx" in err
        assert "get it with `arcloud models pull yolo11n-seg-fp32-640 --from FILE`" in err
        assert "Traceback" not in err and err.count("\n") == 1
    monkeypatch.setenv("ARCLOUD_STORE", "redis://127.0.0.1:1/0")
    assert worker_main([]) == 2  # the container's entry point: logged, exit 2
