"""The service on a real 3-primary Redis Cluster gives the map it gives on one Redis: the API and 2 worker
processes (the simulator's detector, ``sim:0``), on one redis-server with one ingest shard and on the cluster
with three, take the same frames of three maps (one in each shard of three); every map comes out with the
same objects, voxel for voxel, and the same mAP against the room's ground truth.

Each map's frames are posted in order, the next once the last is processed (the step is order-dependent,
the detector deterministic per frame), while the three maps' frames go through the two workers in parallel.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
from redis_server import LocalCluster, RedisServer
from svc_helpers import AppClient, wait_until

from arcloud.core.types import Frame, Intrinsics, MapObject
from arcloud.eval.metrics import evaluate
from arcloud.eval.protocol import object_boxes
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue
from arcloud.tools.wiring import create_app

pytestmark = [pytest.mark.redis, pytest.mark.slow]

PROTOBUF = {"content-type": "application/x-protobuf"}
MAPS = ("room-b", "room-a", "room-c")  # shards 0, 1, 2 of 3 (keys.shard_of)
N_FRAMES = 24


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    from arcloud.sim.room import generate_room
    from arcloud.sim.sequence import simulate_sequence

    return simulate_sequence(
        generate_room(0), n_frames=N_FRAMES, seed=0, width=160, height=120, intrinsics=Intrinsics(131.25, 131.25, 79.5, 59.5)
    )


@pytest.fixture(scope="module")
def single_redis() -> Iterator[RedisServer]:
    server = RedisServer.start()
    yield server
    server.stop()


def run_service(url: str, shards: int, frames: list[Frame]) -> dict[str, list[MapObject]]:
    """The frames through the API and 2 worker processes on ``url``: each map's in order, the maps side by
    side; returns every map's objects as stored."""
    settings = Settings(
        store=url, auth="none", key_rate_per_s=0, detector="sim:0", workers=2, ingest_shards=shards, read_block_s=0.2
    )
    with AppClient(create_app(settings)) as api:

        def processed(map_id: str) -> int:
            return int(api.get(f"/v1/maps/{map_id}/stats").json()["frames"]["processed"])

        for index, frame in enumerate(frames):
            for map_id in MAPS:
                message = frame_to_proto(frame)
                message.map_id = map_id
                posted = api.post(f"/v1/maps/{map_id}/frames", content=message.SerializeToString(), headers=PROTOBUF)
                assert posted.status_code == 202 and posted.json()["status"] == "queued", posted.text
            for map_id in MAPS:
                wait_until(lambda m=map_id, n=index + 1: processed(m) == n, 60, f"frame {index} of {map_id} processed", 0.01)
        with RedisStore(url) as store:
            return {map_id: store.list_objects(map_id) for map_id in MAPS}


def test_the_cluster_gives_the_same_maps_as_one_redis(
    frames: list[Frame], single_redis: RedisServer, redis_cluster: LocalCluster
) -> None:
    from arcloud.sim.room import generate_room

    started = time.monotonic()
    with single_redis.client() as client:
        client.flushdb()
    on_one = run_service(single_redis.url, 1, frames)
    one_s = time.monotonic() - started
    redis_cluster.flush()
    on_cluster = run_service(redis_cluster.url, 3, frames)
    print(
        f"\n{len(MAPS)} maps x {N_FRAMES} frames, 2 workers: one Redis {one_s:.1f} s, cluster {time.monotonic() - started - one_s:.1f} s"
    )

    truth = [o.box for o in generate_room(0).objects]
    for map_id in MAPS:
        want, got = on_one[map_id], on_cluster[map_id]
        assert len(want) >= 3 and [o.id for o in got] == [o.id for o in want]
        for a, b in zip(got, want):
            assert (a.label, a.version, a.n_frames, a.confirmed, a.devices) == (
                b.label,
                b.version,
                b.n_frames,
                b.confirmed,
                b.devices,
            )
            for name in ("keys", "weights", "votes"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{map_id} object {a.id} {name}")
        scores = [evaluate({"s": object_boxes(objs)}, {"s": truth}).map_at(0.25) for objs in (want, got)]
        assert scores[0] == scores[1] > 0.0
    queue = RedisFrameQueue(redis_cluster.url, shards=3)
    try:  # every shard did its map's work, each on its own primary
        for shard, map_id in enumerate(MAPS):
            assert keys.shard_of(map_id, 3) == shard
            assert int(queue.client.hget(keys.ingest_stats(queue.shard_tag(shard)), "processed")) == N_FRAMES
        assert queue.stats().processed == len(MAPS) * N_FRAMES and queue.stats().queue_depth == 0
    finally:
        queue.close()
