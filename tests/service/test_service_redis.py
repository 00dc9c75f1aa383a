"""Redis mode end to end: the API queues frames on a real redis-server's stream, two worker PROCESSES
(spawned, as in production) read them through the consumer group, and publish events over Zenoh to the
API's loopback endpoint. Covers: no frame lost, the served map (confirmed objects) against every object,
idempotent re-delivery, poison frames dead-lettered, a killed worker's frame claimed by another,
graceful stop finishing the frame in hand.

The tests run in file order on one deployment (starting worker processes takes seconds).
"""

from __future__ import annotations

import functools
import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any

import pytest
import redis
from redis_server import RedisServer
from svc_helpers import LEFT, RIGHT, AppClient, free_port, make_blob_detector, make_test_frame, wait_for_subscriber, wait_until

from arcloud.events.zenoh import object_key, query_objects, subscribe_objects, tentative_key
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_to_proto
from arcloud.service.pool import WorkerPool
from arcloud.service.settings import Settings
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue, parse_stats
from arcloud.tools.wiring import create_app, healthy, worker_pool
from arcloud.tools.worker import main as worker_main

pytestmark = [pytest.mark.redis, pytest.mark.slow]

PROTOBUF = {"content-type": "application/x-protobuf"}
# The ingest's keys with one shard (the default): every map's frames in it.
SHARD = keys.shard_tag(0, 1)
INGEST_STREAM, INGEST_STATS, INGEST_BACKLOG = keys.ingest_stream(SHARD), keys.ingest_stats(SHARD), keys.ingest_backlog(SHARD)
DEAD_LETTER_STREAM = keys.ingest_dead_letter_stream(SHARD)
SLOW_FRAME = 800  # frame index the detector takes SLOW_S over
CRASH_FRAME = 900  # frame index the detector raises on
SLOW_S = 1.0
CLAIM_MIN_IDLE_S = 1.5  # > SLOW_S: a frame in progress is never taken over
MISSED = [f"miss{i:03d}" for i in range(60)]  # frame ids in which the detector misses what is left of centre
TENTATIVE = {"include": "tentative"}


@dataclass
class Deployment:
    settings: Settings
    api: AppClient
    pool: WorkerPool
    redis: redis.Redis
    store: RedisStore
    queue: RedisFrameQueue
    zenoh_endpoint: str

    def post(self, map_id: str, index: int, *, level: bool = False, boxes: tuple = (LEFT,), frame_id: str | None = None) -> dict:
        msg = frame_to_proto(make_test_frame(index, map_id=map_id, level=level, boxes=boxes))
        msg.frame_id = frame_id or msg.frame_id
        response = self.api.post(f"/v1/maps/{map_id}/frames", content=msg.SerializeToString(), headers=PROTOBUF)
        assert response.status_code == 202, response.text
        return response.json()  # type: ignore[no-any-return]  # httpx's JSON is Any

    def stats(self) -> object:
        return parse_stats(self.redis.hgetall(INGEST_STATS))

    def idle(self) -> bool:
        """Nothing queued and nothing pending."""
        return (
            int(self.redis.xlen(INGEST_STREAM)) == 0
            and int(self.redis.xpending(INGEST_STREAM, self.settings.consumer_group)["pending"]) == 0
        )

    def holder_pid(self) -> int | None:
        """Pid of the worker holding a pending entry (consumer names are host-pid)."""
        pending = self.redis.xpending_range(INGEST_STREAM, self.settings.consumer_group, min="-", max="+", count=1)
        return int(pending[0]["consumer"].decode().rsplit("-", 1)[1]) if pending else None


@pytest.fixture(scope="module")
def deployment() -> Iterator[Deployment]:
    server = RedisServer.start()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(
        store=server.url,
        auth="none",
        detector="sim:0",
        workers=0,
        claim_min_idle_s=CLAIM_MIN_IDLE_S,
        claim_interval_s=0.2,
        max_deliveries=2,
        read_block_s=0.2,
        zenoh_mode="peer",
        zenoh_listen=[endpoint],
    )
    factory = functools.partial(
        make_blob_detector, delay_s=SLOW_S, slow_on=[f"f{SLOW_FRAME:06d}"], crash_on=[f"f{CRASH_FRAME:06d}"], miss_left_on=MISSED
    )
    pool = worker_pool(settings, 2, detector_factory=factory)
    client = server.client()
    store = RedisStore(server.url)
    queue = RedisFrameQueue(server.url)
    try:
        with AppClient(create_app(settings)) as api:
            pool.start()
            wait_until(lambda: len(queue.live_consumers(3.0)) >= 2, 90, "2 workers reading", 0.1)
            yield Deployment(settings, api, pool, client, store, queue, endpoint)
            pool.stop(20)
    finally:
        pool.stop(5)
        queue.close()
        store.close()
        client.close()
        server.stop()


class Events:
    def __init__(self) -> None:
        self.events: list[Any] = []
        self._lock = threading.Lock()

    def __call__(self, event: object) -> None:
        with self._lock:
            self.events.append(event)

    def states(self, status: int | None = None) -> list[int]:
        """Versions of the events carrying a state (of ``status`` when given), in arrival order."""
        with self._lock:
            return [e.object.version for e in self.events if e.HasField("object") and status in (None, e.object.status)]


def test_every_frame_is_processed_once_and_events_reach_a_zenoh_subscriber(deployment: Deployment) -> None:
    served, everything = Events(), Events()
    endpoint = deployment.zenoh_endpoint
    with ExitStack() as subscriptions:  # each known to the API's peer before the next (a key tells of all before)
        subscriptions.enter_context(subscribe_objects("r1", served, connect=[endpoint]))
        wait_for_subscriber(object_key("r1", 0), endpoint=endpoint)
        subscriptions.enter_context(subscribe_objects("r1", everything, connect=[endpoint], include_tentative=True))
        wait_for_subscriber(tentative_key("r1", 0), endpoint=endpoint)
        for i in range(10):
            deployment.post("r1", i, level=True)  # an upright chair: confirmed on the way
        wait_until(
            lambda: deployment.api.get("/v1/maps/r1/stats").json()["frames"]["processed"] == 10, 60, "10 frames processed", 0.05
        )
        wait_until(lambda: 10 in everything.states(), 10, "events from the worker processes")
        time.sleep(0.2)
        answer = query_objects("r1", connect=[deployment.zenoh_endpoint], timeout_s=5)

    stats = deployment.api.get("/v1/maps/r1/stats").json()
    assert stats["frames"] == {"accepted": 10, "processed": 10, "failed": 0, "pending": 0}
    assert stats["objects"] == {"confirmed": 1, "tentative": 0, "total": 1, "truncated": False}
    assert deployment.idle()  # acknowledged and deleted: the stream holds only the backlog
    (obj,) = deployment.api.get("/v1/maps/r1/objects").json()["objects"]
    assert obj["n_frames"] == 10 and obj["label"] == "chair" and obj["status"] == "confirmed" and obj["version"] == 10
    # Two worker processes and the API's sweep publish from the change log, at least once: every state reaches a
    # subscriber of both key spaces, in any order between them, none skipped (a state two publishers both sent
    # arrives twice).
    assert sorted(set(everything.states())) == list(range(1, 11)) and all(
        e.map_id == "r1" and e.object_id == obj["id"] for e in everything.events
    )
    # The served map's subscriber: every confirmed state (and perhaps a worker's unsure removal of the then tentative chair).
    assert (
        set(served.states(pb.Object.STATUS_CONFIRMED)) == set(everything.states(pb.Object.STATUS_CONFIRMED))
        and 10 in served.states()
    )
    assert [(o.id, o.status) for o in answer.objects] == [(obj["id"], pb.Object.STATUS_CONFIRMED)] and answer.objects[
        0
    ].n_frames == 10
    assert "arcloud_frames_processed_total" in deployment.api.get("/metrics").text


def test_the_served_map_loses_an_object_that_turns_tentative(deployment: Deployment) -> None:
    api = deployment.api

    def post(index: int, **kwargs: Any) -> None:
        deployment.post("r6", index, level=True, **kwargs)
        wait_until(
            lambda: api.get("/v1/maps/r6/stats").json()["frames"]["processed"] == index + 1, 30, f"frame {index} processed", 0.02
        )

    def status(object_id: int) -> str:
        return str(api.get(f"/v1/maps/r6/objects/{object_id}").json()["status"])

    post(0)
    (chair,) = api.get("/v1/maps/r6/objects", params=TENTATIVE).json()["objects"]
    assert chair["status"] == "tentative" and api.get("/v1/maps/r6/objects").json()["objects"] == []
    assert api.get("/v1/maps/r6/stats").json()["objects"] == {"confirmed": 0, "tentative": 1, "total": 1, "truncated": False}
    for i in range(1, 6):
        post(i)
    assert [(o["id"], o["status"]) for o in api.get("/v1/maps/r6/objects").json()["objects"]] == [(chair["id"], "confirmed")]
    index = 6
    while status(chair["id"]) == "confirmed":  # in view, no longer detected: misses, counted in Redis, until tentative
        assert index < len(MISSED), "the missed chair stayed confirmed"
        post(index, boxes=(LEFT, RIGHT), frame_id=MISSED[index])
        index += 1
    assert chair["id"] not in [o["id"] for o in api.get("/v1/maps/r6/objects").json()["objects"]]
    every = {o["id"]: o["status"] for o in api.get("/v1/maps/r6/objects", params=TENTATIVE).json()["objects"]}
    assert every[chair["id"]] == "tentative" and deployment.store.get("r6", [chair["id"]])[0].n_missed > 0
    counts = api.get("/v1/maps/r6/stats").json()["objects"]
    statuses = list(every.values())
    assert counts == {
        "confirmed": statuses.count("confirmed"),
        "tentative": statuses.count("tentative"),
        "total": len(statuses),
        "truncated": False,
    }


def test_health_checks_see_the_workers_heartbeats(deployment: Deployment, monkeypatch: pytest.MonkeyPatch) -> None:
    assert healthy(deployment.settings) and not healthy(deployment.settings, host="elsewhere")
    monkeypatch.setenv("ARCLOUD_STORE", deployment.settings.store)
    assert worker_main(["--healthcheck"]) == 0
    assert deployment.api.get("/readyz").json() == {"status": "ready", "checks": {"store": "ok"}}
    workers = deployment.api.get("/healthz/workers").json()
    assert workers["status"] == "ok" and workers["checks"] == {
        "redis": "ok",
        "consumer_group": "ok",
        "workers": "ok",
        "settings": "ok",
    }
    assert workers["expected"] is None and workers["live"], workers  # the pool is not the API's: any live worker


def test_a_frame_delivered_twice_counts_once(deployment: Deployment) -> None:
    before = deployment.stats()
    payload = frame_to_proto(make_test_frame(0, map_id="r2")).SerializeToString()
    for _ in range(2):  # as if a worker died after its commit, before XACK: the entry comes again
        deployment.redis.xadd(INGEST_STREAM, {"map_id": "r2", "frame_key": "d/f000000", "frame": payload})
    wait_until(deployment.idle, 30, "both deliveries handled", 0.05)
    after = deployment.stats()
    assert deployment.store.count_frames("r2") == 1
    assert after.processed - before.processed == 1 and after.redelivered - before.redelivered == 1
    (obj,) = deployment.store.list_objects("r2")
    assert obj.n_frames == 1 and obj.version == 1


def test_a_frame_recorded_as_accepted_but_never_queued_is_queued_again_on_retry(deployment: Deployment) -> None:
    # What a crash used to leave between recording a frame and queueing it: the record without the entry.
    deployment.redis.hset(keys.ingest_status_key(SHARD, "r7"), "d/f000000", "queued 1-0")
    deployment.redis.hset(keys.ingest_counts_key(SHARD, "r7"), "accepted", 1)
    before = deployment.stats()
    assert deployment.post("r7", 0)["status"] == "queued"  # not "duplicate"
    wait_until(
        lambda: deployment.api.get("/v1/maps/r7/stats").json()["frames"]["processed"] == 1, 30, "the frame processed", 0.05
    )
    assert deployment.api.get("/v1/maps/r7/frames/d/f000000").json()["status"] == "processed"
    assert deployment.post("r7", 0)["status"] == "duplicate"
    wait_until(deployment.idle, 10, "nothing pending")
    assert deployment.api.get("/v1/maps/r7/stats").json()["frames"] == {"accepted": 1, "processed": 1, "failed": 0, "pending": 0}
    after = deployment.stats()
    assert after.processed - before.processed == 1 and after.redelivered == before.redelivered


def test_poison_frames_go_to_the_dead_letter_stream(deployment: Deployment) -> None:
    deployment.redis.xadd(INGEST_STREAM, {"map_id": "r3", "frame_key": "d/garbage", "frame": b"\x0f\xff garbage"})
    deployment.post("r3", 1)
    deployment.post("r3", CRASH_FRAME)  # raises in the detector on every delivery
    wait_until(lambda: deployment.redis.xlen(DEAD_LETTER_STREAM) >= 2, 30, "two dead letters", 0.05)
    wait_until(deployment.idle, 10, "nothing pending")
    dead = {e[1][b"frame_key"].decode(): e[1] for e in deployment.redis.xrange(DEAD_LETTER_STREAM)}
    assert dead["d/garbage"][b"reason"].startswith(b"undecodable")
    assert dead[f"d/f{CRASH_FRAME:06d}"][b"reason"].startswith(b"delivered 3 times")
    stats = deployment.api.get("/v1/maps/r3/stats").json()["frames"]
    assert stats == {"accepted": 2, "processed": 1, "failed": 1, "pending": 0}
    failed = deployment.api.get(f"/v1/maps/r3/frames/d/f{CRASH_FRAME:06d}").json()
    assert failed["status"] == "failed" and failed["reason"].startswith("delivered 3 times")
    assert deployment.api.get("/v1/maps/r3/frames/d/f000001").json()["status"] == "processed"


def test_a_killed_workers_frame_is_claimed_by_another(deployment: Deployment) -> None:
    claimed_before = deployment.stats().claimed
    deployment.post("r4", SLOW_FRAME)
    wait_until(lambda: deployment.holder_pid() is not None, 20, "a worker to take the slow frame", 0.01)
    victim = deployment.holder_pid()
    assert victim in [p.pid for p in deployment.pool.processes]
    os.kill(victim, signal.SIGKILL)  # dies mid-frame: no commit, no XACK
    wait_until(lambda: deployment.store.count_frames("r4") == 1, 30, "the frame processed by another worker", 0.05)
    wait_until(deployment.idle, 10, "nothing pending")
    assert deployment.stats().claimed - claimed_before >= 1
    backlog = deployment.redis.hgetall(INGEST_BACKLOG)  # counted once, taken off once: nothing drifted
    assert all(int(v) == 0 for v in backlog.values()) and deployment.queue.stats().queued_bytes == 0, backlog
    assert deployment.api.get("/v1/maps/r4/stats").json()["frames"] == {"accepted": 1, "processed": 1, "failed": 0, "pending": 0}
    wait_until(lambda: deployment.pool.alive() == 2, 30, "the pool to replace the killed worker")


def test_workers_stop_gracefully_after_the_frame_in_hand(deployment: Deployment) -> None:
    def current_workers_reading() -> bool:
        live = {w.rsplit("-", 1)[1] for w in deployment.queue.live_consumers(3.0)}
        return {str(p.pid) for p in deployment.pool.processes} <= live

    wait_until(current_workers_reading, 60, "the replacement worker reading")
    assert deployment.api.get("/healthz/workers").json()["checks"]["workers"] == "ok"
    deployment.post("r5", SLOW_FRAME)
    wait_until(lambda: deployment.holder_pid() is not None, 20, "a worker to take the slow frame", 0.01)
    processes = list(deployment.pool.processes)
    deployment.pool.stop(20)  # SIGTERM
    assert [p.exitcode for p in processes] == [0, 0]
    assert deployment.store.count_frames("r5") == 1 and deployment.idle()
    stopped = {str(p.pid) for p in processes}
    assert not [
        w for w in deployment.queue.live_consumers(10.0) if w.rsplit("-", 1)[1] in stopped
    ]  # heartbeats removed on the way out


def test_workers_that_die_right_after_starting_are_restarted_later_and_later(monkeypatch: pytest.MonkeyPatch) -> None:
    class Dead:
        pid, exitcode = 1, 1

        def is_alive(self) -> bool:
            return False

    spawned: list[float] = []
    pool = WorkerPool(1, print)
    monkeypatch.setattr(pool, "_spawn", lambda index: Dead())
    pool.processes, pool._started_at = [Dead()], {0: 0.0}
    for tick in range(200):  # a supervisor looking once a second for 200 s at a worker that always fails at once
        before = pool.processes[0]
        pool.tend(float(tick))
        if pool.processes[0] is not before:
            spawned.append(float(tick))
    # Each death is seen a tick after its start, then the next start waits 2, 4, 8, 16, 32 s, then 60 s.
    assert spawned[:5] == [2.0, 7.0, 16.0, 33.0, 66.0]
    assert len(spawned) > 6 and all(b - a == 61.0 for a, b in zip(spawned[4:], spawned[5:]))
    long_lived = Dead()
    pool.processes, pool._started_at, pool._restart_at = [long_lived], {0: 0.0}, {}
    pool.tend(100.0)  # one that ran 100 s: replaced at once, and its slot's delay starts over
    assert pool.processes[0] is not long_lived and pool._quick_exits[0] == 0 and pool._restart_at == {}
