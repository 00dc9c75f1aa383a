"""The Redis adapters when Redis loses its data (FLUSHALL: as a restart without it) or is busy running a
script: the queue's readers recreate the consumer group, a busy Redis is ``StoreUnavailable``."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
from redis_server import RedisServer
from svc_helpers import make_test_frame

from arcloud.errors import StoreUnavailable
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue

pytestmark = pytest.mark.redis

BUSY_SCRIPT_S = 1.5


@pytest.fixture
def server() -> Iterator[RedisServer]:
    with RedisServer.start() as started:
        yield started


def test_the_readers_recreate_the_consumer_group_after_redis_lost_its_data(server: RedisServer) -> None:
    queue = RedisFrameQueue(server.url)
    try:
        queue.prepare()
        queue.put(make_test_frame(0))
        in_hand = queue.take("c1", block_s=0.1)
        assert in_hand is not None and queue.health() == {"redis": "ok", "consumer_group": "ok"}
        with server.client() as client:
            client.flushall()
        assert queue.health()["consumer_group"].startswith("missing")
        queue.heartbeat("c1", in_hand)  # the entry in hand went with the data: no NOGROUP error
        assert queue.claim_abandoned("c2", min_idle_s=0.001) is None  # recreates the group: nothing pending in it
        assert queue.health()["consumer_group"] == "ok"
        with server.client() as client:
            client.flushall()
        queue.put(make_test_frame(1))  # XADD makes the stream again, without the group
        item = queue.take("c1", block_s=0.1)  # recreates the group at the stream's start: reads the frame
        assert item is not None and item.frame_key == "d/f000001"
    finally:
        queue.close()


def test_a_redis_busy_running_a_script_is_unavailable(server: RedisServer) -> None:
    with server.client() as client:
        client.config_set("busy-reply-threshold", 100)  # ms: BUSY replies after this long in a script
    # A script that spins BUSY_SCRIPT_S (its own connection; redis.call('TIME') allowed since Redis 5).
    spin = "local t0 = redis.call('TIME') repeat local t = redis.call('TIME') until (t[1] - t0[1]) * 1e6 + (t[2] - t0[2]) > tonumber(ARGV[1])"

    def run_script() -> None:
        with server.client() as client:
            client.eval(spin, 0, int(BUSY_SCRIPT_S * 1e6))

    runner = threading.Thread(target=run_script, daemon=True)
    store = RedisStore(server.url, retries=0)
    queue = RedisFrameQueue(server.url)
    try:
        runner.start()
        time.sleep(0.3)
        with pytest.raises(StoreUnavailable, match="busy"):
            store.ping()
        with pytest.raises(StoreUnavailable, match="busy"):
            queue.stats()
    finally:
        runner.join(BUSY_SCRIPT_S + 5)
        store.close()
        queue.close()
    assert not runner.is_alive()
