"""Zenoh publishes from the maps' change logs (``service.change_feed``), with real sessions on loopback and a
real redis-server: a worker that dies between its commit and its publishing leaves its events in the log, and
the feed (the API's sweep) still delivers them to a subscriber, once."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from redis_server import RedisServer
from svc_helpers import AppClient, EventCollector, cube, free_port, wait_for_subscriber, wait_until

from arcloud.core.change import MapChange
from arcloud.events.zenoh import ZenohPublisher, object_key, subscribe_objects, tentative_key
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.service.change_feed import ChangeFeed
from arcloud.service.settings import Settings
from arcloud.stores.redis import RedisStore
from arcloud.tools.wiring import create_app

pytestmark = pytest.mark.redis


def of_map(received: EventCollector, map_id: str) -> list[tuple[int, int, int]]:
    """(kind, object id, version) of each event of the map, in arrival order."""
    return [(e.kind, e.object_id, e.object.version) for e in list(received.events) if e.map_id == map_id]


@pytest.fixture(scope="module")
def redis_url() -> Iterator[str]:
    with RedisServer.start() as server:
        yield server.url


def committed_and_never_published(store: RedisStore, map_id: str) -> None:
    """What a worker killed right after its commit leaves: a created object (tentative: cube 3 is) and an updated
    one, in the map's change log, published by nobody."""
    store.commit(map_id, [], MapChange.writing(map_id, [cube(1), cube(3)]), frame_key="dev/f1")
    with store.lock(map_id, [1], ttl_s=5, timeout_s=1) as lease:
        store.commit(map_id, [lease], MapChange.writing(map_id, [cube(1).replace(version=2)]), frame_key="dev/f2")


def test_a_feed_started_after_a_worker_died_publishes_what_it_committed_once(redis_url: str) -> None:
    store = RedisStore(redis_url)
    committed_and_never_published(store, "crash")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    publisher = ZenohPublisher(mode="peer", listen=[endpoint])
    received = EventCollector()
    try:
        with subscribe_objects("crash", received, connect=[endpoint], include_tentative=True):
            wait_for_subscriber(object_key("crash", 0), session=publisher.session)
            wait_for_subscriber(tentative_key("crash", 0), session=publisher.session)
            assert store.published_version("crash") == 0
            feed = ChangeFeed(store, publisher)
            assert feed.sweep(["crash"]) == 3
            wait_until(lambda: len(of_map(received, "crash")) == 3, 10, "the three events")
            assert feed.sweep(["crash"]) == 0  # published up to version 2: nothing again
            time.sleep(0.2)
    finally:
        publisher.close()
        store.close()
    created, updated = pb.ObjectEvent.KIND_CREATED, pb.ObjectEvent.KIND_UPDATED
    assert of_map(received, "crash") == [(created, 1, 1), (created, 3, 1), (updated, 1, 2)]


def test_the_api_sweeps_the_logs_no_worker_published(redis_url: str) -> None:
    """The API on Redis with Zenoh on and no worker of its own: what a worker elsewhere committed and died
    before publishing reaches a subscriber of the API's peer within a sweep."""
    store = RedisStore(redis_url)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(store=redis_url, auth="none", detector="sim:0", workers=0, zenoh_mode="peer", zenoh_listen=[endpoint])
    received = EventCollector()
    try:
        with (
            AppClient(create_app(settings)),
            subscribe_objects("swept", received, connect=[endpoint], include_tentative=True),
        ):
            wait_for_subscriber(object_key("swept", 0), endpoint=endpoint)
            wait_for_subscriber(tentative_key("swept", 0), endpoint=endpoint)
            committed_and_never_published(store, "swept")
            wait_until(lambda: len(of_map(received, "swept")) == 3, 15, "the swept events")
            assert store.published_version("swept") == 2
    finally:
        store.close()
    assert [object_id for _, object_id, _ in of_map(received, "swept")] == [1, 3, 1]


def test_a_subscriber_gets_the_objects_of_a_map_deleted_and_made_again(redis_url: str) -> None:
    """The API (Zenoh on, its sweep publishing) deletes a map whose object went to version 3; a worker makes the
    map again: the subscriber gets the new map's object. (Ids restarted at 1 with the new map, and the API's
    publisher, which drops a state not newer than one it published of the same id, dropped it: never sent.)"""
    from arcloud.core.header import MapHeader
    from arcloud.core.types import Params

    store = RedisStore(redis_url)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(store=redis_url, auth="none", detector="sim:0", workers=0, zenoh_mode="peer", zenoh_listen=[endpoint])
    header = MapHeader.from_params(Params(), codec_version=store.codec_version, created_at_s=1.0)
    received = EventCollector()

    def made(place: int, versions: int) -> int:  # what a worker writes: an object, updated to ``versions``
        store.open_map("again", header)
        (object_id,) = store.new_ids("again", 1)
        obj = cube(place).replace(id=object_id)
        store.commit("again", [], MapChange.writing("again", [obj]))
        for version in range(2, versions + 1):
            with store.lock("again", [object_id], ttl_s=5, timeout_s=1) as lease:
                store.commit("again", [lease], MapChange.writing("again", [obj.replace(version=version)]))
        return object_id

    try:
        with (
            AppClient(create_app(settings)) as api,
            subscribe_objects("again", received, connect=[endpoint], include_tentative=True),
        ):
            wait_for_subscriber(object_key("again", 0), endpoint=endpoint)
            old = made(1, versions=3)
            wait_until(lambda: len(of_map(received, "again")) == 3, 15, "the old map's events")
            assert api.delete("/v1/maps/again").status_code == 200
            new = made(4, versions=1)
            wait_until(lambda: len(of_map(received, "again")) == 4, 15, "the new map's object")
    finally:
        store.close()
    assert new != old and of_map(received, "again")[-1] == (pb.ObjectEvent.KIND_CREATED, new, 1)
