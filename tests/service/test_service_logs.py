"""Operator logs: one JSON object a line, with the frame's ids on every line logged while it is processed.

The formatter and the context filter on real ``logging`` records; the worker's context around a real
step (memory queue and store, ``BlobDetector``); then ``arcloud serve`` as a real process, embedded and
on Redis with a worker process, and the Docker image's ``uvicorn --factory``, their output read line by line.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from svc_helpers import BlobDetector, free_port, make_test_frame, wait_until

from arcloud.core.types import Frame, Intrinsics
from arcloud.proto.convert import frame_to_proto
from arcloud.service.logs import (
    SECRET_FILTER,
    JsonFormatter,
    LogContextFilter,
    TextFormatter,
    bind_log_context,
    log_context,
    scrub,
)
from arcloud.service.settings import Settings
from arcloud.service.worker import FrameWorker
from arcloud.stores.memory import MemoryStore
from arcloud.stores.memory_queue import MemoryFrameQueue

PROTOBUF = {"content-type": "application/x-protobuf"}
FRAME_FIELDS = ("map_id", "device_id", "frame_id")


@pytest.fixture
def json_lines() -> Iterator[io.StringIO]:
    """What the ``arcloud`` loggers write, as JSON lines with the log context, at DEBUG."""
    written = io.StringIO()
    handler = logging.StreamHandler(written)
    handler.setFormatter(JsonFormatter())
    handler.addFilter(LogContextFilter())
    logger = logging.getLogger("arcloud")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield written
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def parsed(written: io.StringIO) -> list[dict[str, Any]]:
    return [json.loads(line) for line in written.getvalue().splitlines()]


def test_a_json_line_holds_the_record_its_context_and_its_traceback_on_one_line(json_lines: io.StringIO) -> None:
    log = logging.getLogger("arcloud.test")
    with log_context(map_id="office", frame_id="f1"):
        try:
            raise ValueError("two\nlines")
        except ValueError:
            log.exception("frame %s failed:\n%s", "f1", "details", extra={"objects": 3})
    log.info("after the block")

    text = json_lines.getvalue()
    assert text.count("\n") == 2  # the traceback and the message's newline escaped inside one line each
    failed, after = parsed(json_lines)
    assert failed["message"] == "frame f1 failed:\ndetails"
    assert failed["level"] == "ERROR" and failed["logger"] == "arcloud.test"
    assert failed["map_id"] == "office" and failed["frame_id"] == "f1" and failed["objects"] == 3
    assert failed["exception"].startswith("Traceback (most recent call last)")
    assert failed["exception"].endswith("ValueError: two\nlines")
    assert failed["time"].endswith("Z") and failed["time"][10] == "T"
    assert failed["process"] == "MainProcess" and failed["pid"] == os.getpid()
    assert "map_id" not in after and "exception" not in after


def test_the_context_nests_stays_in_its_thread_and_an_extra_field_wins(json_lines: io.StringIO) -> None:
    log = logging.getLogger("arcloud.test")
    with log_context(map_id="a", device_id="d"):
        with log_context(frame_id="f2", device_id="e"):
            log.info("inner", extra={"frame_id": "given"})
        other = threading.Thread(target=log.info, args=("from another thread",))
        other.start()
        other.join()
        log.info("outer")
    inner, elsewhere, outer = parsed(json_lines)
    assert (inner["map_id"], inner["device_id"], inner["frame_id"]) == ("a", "e", "given")
    assert not set(FRAME_FIELDS) & set(elsewhere)
    assert (outer["map_id"], outer["device_id"], "frame_id" in outer) == ("a", "d", False)


def test_bind_lasts_for_the_rest_of_its_context_only(json_lines: io.StringIO) -> None:
    import contextvars

    log = logging.getLogger("arcloud.test")

    def request() -> None:
        bind_log_context(frame_id="f3")
        log.info("in the request")

    contextvars.copy_context().run(request)  # as uvicorn runs each request in a task of its own
    log.info("after it")
    during, after = parsed(json_lines)
    assert during["frame_id"] == "f3" and "frame_id" not in after


def test_text_lines_end_with_the_context() -> None:
    record = logging.makeLogRecord({"name": "arcloud.x", "levelname": "INFO", "msg": "hello", "frame_id": "f4"})
    assert TextFormatter().format(record).endswith("arcloud.x: hello [frame_id=f4]")


def test_every_line_the_worker_and_the_step_log_for_a_frame_carries_its_ids(json_lines: io.StringIO) -> None:
    settings = Settings(detector="sim:0")
    params = settings.make_params()
    queue = MemoryFrameQueue(limits=settings.queue_limits())
    store = MemoryStore(cell_m=params.index_cell_m)
    worker = FrameWorker(queue, store, BlobDetector(refuse_on=["f000001"]), params, consumer="w1", heartbeat_s=None)
    for i in (0, 1):
        queue.put(make_test_frame(i, map_id="logs", device_id="phone"))
    assert [worker.poll_once(), worker.poll_once()] == [1, 1]

    lines = parsed(json_lines)
    by_frame = {f: [line for line in lines if line.get("frame_id") == f] for f in ("f000000", "f000001")}
    assert {line["logger"] for line in by_frame["f000000"]} >= {"arcloud.core.step", "arcloud.service.worker"}
    assert any("dead-lettered" in line["message"] and line["level"] == "ERROR" for line in by_frame["f000001"])
    for line in by_frame["f000000"] + by_frame["f000001"]:
        assert (line["map_id"], line["device_id"], line["deliveries"]) == ("logs", "phone", 1), line
    assert all("frame_id" in line for line in lines), [line for line in lines if "frame_id" not in line]


# --- real processes ------------------------------------------------------------------------------------
#: The API as ``arcloud serve`` starts it, and as the Docker image does (uvicorn's CLI and the factory).
SERVE = ("arcloud.cli", "serve", "--detector", "sim:0")
UVICORN_FACTORY = ("uvicorn", "--factory", "arcloud.tools.wiring:create_app", "--ws", "none")


class ServeProcess:
    """``python -m MODULE OPTIONS... --port P`` (the API) in a process of its own, logging JSON at DEBUG with
    ``environment`` added, its stdout and stderr in files."""

    def __init__(self, tmp_path: Path, command: tuple[str, ...], environment: dict[str, str]) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.stderr_path, self.stdout_path = tmp_path / "stderr.log", tmp_path / "stdout.log"
        env = {**os.environ, "ARCLOUD_LOG_FORMAT": "json", "ARCLOUD_LOG_LEVEL": "DEBUG", **environment}
        command = (sys.executable, "-m", *command, "--port", str(self.port))
        with self.stderr_path.open("ab") as stderr, self.stdout_path.open("ab") as stdout:  # append: processes share them
            self.process = subprocess.Popen(command, env=env, stdout=stdout, stderr=stderr)

    def ready(self) -> bool:
        assert self.process.poll() is None, f"serve exited {self.process.returncode}: {self.stderr_path.read_text()[-3000:]}"
        try:
            return httpx.get(f"{self.url}/readyz", timeout=2.0).status_code == 200
        except httpx.TransportError:
            return False

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)  # uvicorn stops gracefully, the ingest stops its workers
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)

    def lines(self) -> list[dict[str, Any]]:
        """Every line of stderr and stdout, each parsed as JSON (fails on any line that is not)."""
        lines = []
        for path in (self.stderr_path, self.stdout_path):
            for number, text in enumerate(path.read_text().splitlines(), 1):
                try:
                    lines.append(json.loads(text))
                except ValueError:
                    raise AssertionError(f"{path.name} line {number} is not JSON: {text!r}") from None
        return lines


def frame_status(url: str, map_id: str, device_id: str, frame_id: str) -> str:
    return str(httpx.get(f"{url}/v1/maps/{map_id}/frames/{device_id}/{frame_id}", timeout=5.0).json().get("status"))


def room_frame() -> Frame:
    """A 320x240 frame of the simulated room seed 0 (``sim:0`` detects objects in it: the step logs)."""
    from arcloud.sim.room import generate_room
    from arcloud.sim.sequence import simulate_sequence

    intrinsics = Intrinsics(262.5, 262.5, 159.5, 119.5)
    frames = simulate_sequence(
        generate_room(0), n_frames=3, width=320, height=240, intrinsics=intrinsics, map_id="ops", device_id="phone", workers=1
    )
    return frames[2]


def serve_one_frame(
    tmp_path: Path, command: tuple[str, ...], environment: dict[str, str] | None = None
) -> tuple[list[dict[str, Any]], str]:
    """Start the API, post one frame, wait until it is processed, stop; its log lines and /metrics."""
    serve = ServeProcess(tmp_path, command, environment or {})
    try:
        body = frame_to_proto(room_frame()).SerializeToString()
        wait_until(serve.ready, 90, "arcloud serve to be ready", interval_s=0.2)
        response = httpx.post(f"{serve.url}/v1/maps/ops/frames", content=body, headers=PROTOBUF, timeout=10.0)
        assert response.status_code == 202, response.text
        wait_until(lambda: frame_status(serve.url, "ops", "phone", "f000002") == "processed", 60, "the frame processed", 0.1)
        metrics = httpx.get(f"{serve.url}/metrics", timeout=5.0).text
    finally:
        serve.stop()
    return serve.lines(), metrics


def check_frame_lines(lines: list[dict[str, Any]], process: str) -> None:
    """The frame's lines (step, worker in ``process``, the upload's access line) carry its ids; others not."""
    ids = ("ops", "phone", "f000002")
    step = [line for line in lines if line["logger"] == "arcloud.core.step"]
    assert step and all(tuple(line.get(f) for f in FRAME_FIELDS) == ids for line in step), step
    assert all(line["process"] == process and line["deliveries"] == 1 for line in step), step
    done = [line for line in lines if line["logger"] == "arcloud.service.worker" and "processed in" in line["message"]]
    assert [tuple(line.get(f) for f in FRAME_FIELDS) for line in done] == [ids], done
    assert done[0]["worker"].startswith(f"{socket.gethostname()}-{done[0]['pid']}")  # the consumer: <host>-<pid>[-<thread>]
    access = [line for line in lines if line["logger"] == "uvicorn.access"]
    upload = [line for line in access if line["method"] == "POST"]
    assert [(line["path"], line["status"], *(line.get(f) for f in FRAME_FIELDS)) for line in upload] == [
        ("/v1/maps/ops/frames", 202, *ids)
    ]
    others = [line for line in access if line["method"] == "GET"]
    assert others and not any(set(FRAME_FIELDS) & set(line) for line in others)  # the upload's context ended with it
    assert all(line["time"].endswith("Z") and line["level"] for line in lines)


@pytest.mark.parametrize("command", [(*SERVE, "--workers", "1"), UVICORN_FACTORY], ids=["serve", "uvicorn-factory"])
def test_the_embedded_api_logs_json_with_the_frame_ids(tmp_path: Path, command: tuple[str, ...]) -> None:
    lines, metrics = serve_one_frame(tmp_path, command, {"ARCLOUD_DETECTOR": "sim:0", "ARCLOUD_WORKERS": "1"})
    check_frame_lines(lines, "MainProcess")
    assert any(line["logger"] == "uvicorn.error" and "Uvicorn running" in line["message"] for line in lines)
    assert "arcloud_live_workers 1.0" in metrics


def test_arcloud_serve_on_redis_logs_json_from_its_worker_process(tmp_path: Path) -> None:
    from redis_server import RedisServer

    with RedisServer.start() as server:
        lines, metrics = serve_one_frame(tmp_path, (*SERVE, "--redis", server.url, "--workers", "1", "--auth", "none"))
    check_frame_lines(lines, "arcloud-worker-0")
    assert any(line["process"] == "arcloud-worker-0" and "taking frames" in line["message"] for line in lines)
    assert "arcloud_live_workers 1.0" in metrics


# --- no secrets in logs (issue 22: the documented viewer URL /viewer?map=M&token=arc_... was logged in clear) ---------
SECRET_TOKEN = "arc_0123456789ab_" + "S3cr3t" * 7 + "x"  # an API token's form: 12 hex digits, 43 characters


def test_a_record_loses_its_secrets_and_keeps_the_rest(json_lines: io.StringIO) -> None:
    log = logging.getLogger("arcloud.test")
    log.addFilter(SECRET_FILTER)  # as configure_logging puts it on uvicorn's loggers
    try:
        try:
            raise RuntimeError(f"GET http://h/viewer?map=m&token={SECRET_TOKEN}")
        except RuntimeError:
            log.exception(
                "%s %r %d",
                "/viewer?token=arc_secret&map=m",
                {"authorization": "Bearer arc_secret"},
                401,
                extra={"url": "?token=x1"},
            )
        log.info("%s - %s", ("127.0.0.1", 5), f"Authorization: Bearer {SECRET_TOKEN}")
    finally:
        log.removeFilter(SECRET_FILTER)
    text = json_lines.getvalue()
    assert "arc_secret" not in text and "S3cr3t" not in text and "x1" not in text, text
    failed, other = parsed(json_lines)
    assert failed["message"] == "/viewer?token=***&map=m {'authorization': 'Bearer ***'} 401" and failed["url"] == "?token=***"
    assert failed["exception"].endswith("RuntimeError: GET http://h/viewer?map=m&token=***")
    assert other["message"] == "('127.0.0.1', 5) - Authorization: Bearer ***"
    assert scrub(f"key {SECRET_TOKEN} used") == "key arc_0123456789ab_*** used"  # the key id stays: it names the key


@pytest.mark.parametrize("log_format", ["text", "json"])
def test_arcloud_serve_writes_no_token_to_its_logs(tmp_path: Path, log_format: str) -> None:
    from redis_server import RedisServer

    def alive() -> bool:
        try:
            return httpx.get(f"{serve.url}/healthz", timeout=2.0).status_code == 200
        except httpx.TransportError:
            return False

    with RedisServer.start() as server:
        environment = {"ARCLOUD_LOG_FORMAT": log_format, "ARCLOUD_LOG_LEVEL": "INFO"}
        serve = ServeProcess(tmp_path, (*SERVE, "--redis", server.url, "--workers", "0"), environment)
        try:
            wait_until(alive, 60, "arcloud serve to answer", interval_s=0.2)
            viewer = httpx.get(f"{serve.url}/viewer?map=m&token=arc_secret1", timeout=5.0)
            assert viewer.status_code == 400  # refused, and logged scrubbed
            refused = httpx.get(
                f"{serve.url}/v1/maps/m/stats?token=arc_secret2",
                headers={"authorization": f"Bearer {SECRET_TOKEN}"},
                timeout=5.0,
            )
            assert refused.status_code == 401
            assert httpx.get(f"{serve.url}/v1/maps/m/events?access_token=arc_secret3", timeout=5.0).status_code == 401
        finally:
            serve.stop()
    text = serve.stderr_path.read_text() + serve.stdout_path.read_text()
    assert "/viewer?map=m&token=***" in text and "/v1/maps/m/stats?token=***" in text, text[-3000:]
    assert "arc_secret" not in text and "S3cr3t" not in text, text[-3000:]


def test_the_text_log_gives_uvicorns_lines_the_time_and_the_frame_ids(tmp_path: Path) -> None:
    """A new user's review: in text (the default), uvicorn's access lines had neither a time nor the frame's ids."""
    serve_one_frame_text = ServeProcess(
        tmp_path, (*SERVE, "--workers", "1"), {"ARCLOUD_LOG_FORMAT": "text", "ARCLOUD_WORKERS": "1"}
    )
    try:
        wait_until(serve_one_frame_text.ready, 90, "arcloud serve to be ready", interval_s=0.2)
        body = frame_to_proto(room_frame()).SerializeToString()
        assert (
            httpx.post(f"{serve_one_frame_text.url}/v1/maps/ops/frames", content=body, headers=PROTOBUF, timeout=10.0).status_code
            == 202
        )
        # a path that quotes control characters into the refusal: escaped on the line (a review: raw, a terminal
        # escape or a Unicode line break reached the text log)
        odd = httpx.post(f"{serve_one_frame_text.url}/x%1B[2J%0BA%E2%80%A8B/frames", content=b"", timeout=10.0)
        assert odd.status_code == 404
    finally:
        serve_one_frame_text.stop()
    text = serve_one_frame_text.stderr_path.read_text()
    (refused,) = [line for line in text.splitlines() if "[refused=" in line]
    assert all(c.isprintable() for c in refused) and "\\x1b[2J\\x0bA\\u2028B" in refused, refused
    (upload,) = [line for line in text.splitlines() if " uvicorn.access: " in line and '"POST /v1/maps/ops/frames' in line]
    assert re.match(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} INFO MainProcess uvicorn\.access: ", upload), upload
    fields = dict(pair.split("=", 1) for pair in upload.rsplit(" [", 1)[1].rstrip("]").split())
    assert upload.split(" [")[0].endswith(" 202") and fields == {"map_id": "ops", "device_id": "phone", "frame_id": "f000002"}
    assert any(" uvicorn.error: Uvicorn running on " in line for line in text.splitlines())


def test_a_refused_upload_s_log_line_says_whose_frame_and_why(tmp_path: Path) -> None:
    """A new user's review: the access line of a 422-refused upload had no device or frame id and no reason."""
    serve = ServeProcess(tmp_path, (*SERVE, "--workers", "1"), {"ARCLOUD_WORKERS": "1"})
    try:
        wait_until(serve.ready, 90, "arcloud serve to be ready", interval_s=0.2)
        msg = frame_to_proto(room_frame())
        msg.depth_scale = 1.0  # millimetres read as metres: refused
        answer = httpx.post(f"{serve.url}/v1/maps/ops/frames", content=msg.SerializeToString(), headers=PROTOBUF, timeout=10.0)
        assert answer.status_code == 422, answer.text
    finally:
        serve.stop()
    (refused,) = [line for line in serve.lines() if line["logger"] == "uvicorn.access" and line.get("method") == "POST"]
    assert (refused["status"], refused["device_id"], refused["frame_id"]) == (422, "phone", "f000002"), refused
    assert refused["refused"] == answer.json()["detail"] and refused["refused"].startswith("depth: expected depth in metres")
