"""The Redis adapters when Redis loses its data (FLUSHALL: as a restart without it) or is busy running a
script: the queue's readers recreate the consumer group, a busy Redis is ``StoreUnavailable`` to every
adapter and 503 with Retry-After to the API's clients."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import redis
from chaos_helpers import busy
from redis_server import RedisServer
from svc_helpers import AppClient, make_test_frame

from arcloud.access import new_key
from arcloud.errors import StoreUnavailable
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_api_keys import RedisKeyStore
from arcloud.stores.redis_queue import RedisFrameQueue
from arcloud.stores.redis_rate import RedisRateLimiter
from arcloud.tools.wiring import create_app

pytestmark = pytest.mark.redis

BUSY_SCRIPT_S = 1.5
PROTOBUF = {"content-type": "application/x-protobuf"}


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
        queue.heartbeat("c1", [in_hand])  # the entry in hand went with the data: no NOGROUP error
        assert queue.claim_abandoned("c2", min_idle_s=0.001) is None  # recreates the group: nothing pending in it
        assert queue.health()["consumer_group"] == "ok"
        with server.client() as client:
            client.flushall()
        queue.put(make_test_frame(1))  # XADD makes the stream again, without the group
        item = queue.take("c1", block_s=0.1)  # recreates the group at the stream's start: reads the frame
        assert item is not None and item.frame_key == "d/f000001"
    finally:
        queue.close()


def test_a_redis_busy_running_a_script_is_unavailable_to_every_adapter(server: RedisServer) -> None:
    store = RedisStore(server.url, retries=0)
    queue = RedisFrameQueue(server.url)
    keys = RedisKeyStore(server.url)
    limiter = RedisRateLimiter(server.url)
    try:
        with busy(server, BUSY_SCRIPT_S):
            for name, call in [
                ("store", store.ping),
                ("queue", queue.stats),
                ("keys", lambda: keys.find("0123456789ab")),
                ("rate limits", lambda: limiter.take("ip:127.0.0.1", rate_per_s=1.0, burst=1)),
            ]:
                with pytest.raises(StoreUnavailable, match="busy") as caught:
                    call()
                assert isinstance(caught.value.__cause__, redis.exceptions.ResponseError), name
    finally:
        for adapter in (store, queue, keys, limiter):
            adapter.close()


def test_the_api_answers_503_with_retry_after_while_redis_is_busy(server: RedisServer) -> None:
    """Issue 22: a key lookup answered BUSY was a 500 (GET .../stats for 11 s); every route that reads Redis
    answers 503 with Retry-After, whichever adapter met the BUSY reply first."""
    key, token = new_key("admin", ("*",), now_s=time.time())
    keys = RedisKeyStore(server.url)
    keys.add(key)
    keys.close()
    auth = {"authorization": f"Bearer {token}"}
    settings = Settings(store=server.url, detector="sim:0", workers=0, key_cache_s=0.0)
    with AppClient(create_app(settings)) as api:
        body = frame_to_proto(make_test_frame(0, map_id="a")).SerializeToString()
        assert api.post("/v1/maps/a/frames", content=body, headers={**PROTOBUF, **auth}).status_code == 202
        assert api.get("/v1/maps/a/stats", headers=auth).status_code == 200
        with busy(server, BUSY_SCRIPT_S):
            answers = {
                "stats": api.get("/v1/maps/a/stats", headers=auth),
                "objects": api.get("/v1/maps/a/objects", headers=auth),
                "maps": api.get("/v1/maps", headers=auth),
                "upload": api.post("/v1/maps/a/frames", content=body, headers={**PROTOBUF, **auth}),
                "readyz": api.get("/readyz"),
            }
        for route, answer in answers.items():
            assert answer.status_code == 503, (route, answer.status_code, answer.text)
            assert int(answer.headers["retry-after"]) > 0, route
        assert "busy" in answers["stats"].json()["detail"]
        assert api.get("/v1/maps/a/stats", headers=auth).status_code == 200  # the script ended: all is well again
