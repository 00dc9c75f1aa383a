"""``arcloud frames failed`` and ``arcloud frames retry`` on a real redis-server: a frame the step refuses is
listed with its reason, queued again from its dead letter (within the queue's limits), and processed by a
worker whose detector takes it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from redis_server import RedisServer
from svc_helpers import BlobDetector, make_test_frame

from arcloud.cli import main
from arcloud.core.types import Params
from arcloud.ports import FrameStatus
from arcloud.service.worker import FrameWorker
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue

pytestmark = pytest.mark.redis

MAP = "kitchen"


@pytest.fixture
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[RedisServer]:
    for name in ("ARCLOUD_STORE", "ARCLOUD_MAX_QUEUED_FRAMES_PER_MAP"):
        monkeypatch.delenv(name, raising=False)
    with RedisServer.start() as started:
        yield started


def work(queue: RedisFrameQueue, store: RedisStore, detector: BlobDetector, n_frames: int) -> None:
    """A worker in this process handles ``n_frames`` frames."""
    worker = FrameWorker(queue, store, detector, Params(), heartbeat_s=None, read_block_s=0.2)
    for _ in range(n_frames):
        assert worker.poll_once() == 1


def test_a_failed_frame_is_listed_with_its_reason_retried_and_then_processed(
    server: RedisServer, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    queue, store = RedisFrameQueue(server.url), RedisStore(server.url)
    try:
        for i in range(3):
            queue.put(make_test_frame(i, map_id=MAP))
        work(queue, store, BlobDetector(refuse_on=["f000001"]), 3)  # the step refuses f000001: dead-lettered
        capsys.readouterr()

        assert main(["frames", "failed", "--map", MAP, "--redis", server.url]) == 0
        lines = capsys.readouterr().out.splitlines()
        assert lines[0] == "map kitchen: 1 failed frames"
        assert lines[1].split()[:3] == ["FRAME", "DELIVERIES", "FAILED"]
        frame, deliveries, _day, _time, retry, *reason = lines[2].split()
        assert (frame, deliveries, retry) == ("d/f000001", "1", "yes")
        assert " ".join(reason).startswith("InvalidInput: detections[0].label")

        # Bad input: one line, exit 2, nothing queued.
        for argv, says in (
            (["failed", "--map", "elsewhere"], "no frame of map 'elsewhere' was accepted"),
            (["failed", "--map", "a b"], "--map: expected a non-empty string"),
            (["retry", "--map", MAP, "d/f000000"], "expected a failed frame of map kitchen, got d/f000000: processed"),
            (["retry", "--map", MAP, "d/f000099"], "got d/f000099: no record"),
            (["retry", "--map", MAP, "f000001"], "DEVICE/FRAME: expected a device id and a frame id"),
            (["retry", "--map", MAP], "expected --all or DEVICE/FRAME"),
            (["retry", "--map", MAP, "--all", "d/f000001"], "expected --all or DEVICE/FRAME"),
        ):
            assert main(["frames", *argv, "--redis", server.url]) == 2, argv
            err = capsys.readouterr().err.strip()
            assert err.startswith("arcloud: error:") and says in err and "\n" not in err, (argv, err)
        assert queue.stats().queue_depth == 0

        # The queue's limits apply: the map's one place is taken.
        monkeypatch.setenv("ARCLOUD_STORE", server.url)
        monkeypatch.setenv("ARCLOUD_MAX_QUEUED_FRAMES_PER_MAP", "1")
        queue.put(make_test_frame(3, map_id=MAP))
        assert main(["frames", "retry", "--map", MAP, "d/f000001"]) == 1
        out = capsys.readouterr().out
        assert "refused d/f000001: map kitchen has 1 frames queued (max_queued_frames_per_map 1)" in out
        assert out.strip().endswith("0 queued, 1 refused")
        work(queue, store, BlobDetector(), 1)

        assert main(["frames", "retry", "--map", MAP, "--all"]) == 0
        assert capsys.readouterr().out.splitlines() == ["queued d/f000001", "map kitchen: 1 queued, 0 refused"]
        assert queue.frame_status(MAP, "d/f000001") == FrameStatus("queued")
        work(queue, store, BlobDetector(), 1)  # a detector that takes it
        assert queue.frame_status(MAP, "d/f000001") == FrameStatus("processed")
        assert store.is_frame_done(MAP, "d/f000001") and store.count_frames(MAP) == 4
        assert queue.map_counts(MAP) == (4, 0)
        assert main(["frames", "failed", "--map", MAP]) == 0
        assert capsys.readouterr().out.strip() == "map kitchen: no failed frames"
    finally:
        queue.close()
        store.close()


def test_another_number_of_ingest_shards_than_the_services_is_refused_with_one_line(
    server: RedisServer, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    queue = RedisFrameQueue(server.url, shards=1)
    try:
        queue.prepare()  # as the service does: the number of shards kept in Redis
        queue.put(make_test_frame(0, map_id=MAP))
        monkeypatch.setenv("ARCLOUD_INGEST_SHARDS", "3")  # the map would be looked for in another shard
        assert main(["frames", "failed", "--map", MAP, "--redis", server.url]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("arcloud: error: ingest_shards: expected 1, the number of shards") and "\n" not in err
        assert "set ARCLOUD_INGEST_SHARDS as the service has it" in err
    finally:
        queue.close()
