"""Zenoh events with real sessions on loopback (multicast scouting off): the service's peer publishes
object events, answers the objects query, and takes frames published on arcloud/<map>/frames/<device>."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from svc_helpers import AppClient, BlobDetector, free_port, make_test_frame, wait_until

from arcloud.core.types import ObjectEvent
from arcloud.events.zenoh import ZenohPublisher, connectable, frames_key, object_key, open_session, query_objects, subscribe_objects, zenoh_config
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_to_proto
from arcloud.service.app import create_app
from arcloud.service.settings import Settings
from arcloud.stores.memory import MemoryStore

PROTOBUF = {"content-type": "application/x-protobuf"}


class Collector:
    def __init__(self) -> None:
        self.events: list[pb.ObjectEvent] = []
        self._lock = threading.Lock()

    def __call__(self, event: pb.ObjectEvent) -> None:
        with self._lock:
            self.events.append(event)

    def kinds(self) -> list[int]:
        with self._lock:
            return [e.kind for e in self.events]


@pytest.fixture
def service() -> Iterator[tuple[AppClient, str, MemoryStore]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(detector="sim:0", workers=1, zenoh_mode="peer", zenoh_listen=[endpoint], zenoh_frames=True)
    store = MemoryStore()
    with AppClient(create_app(settings, store=store, detector=BlobDetector())) as api:
        yield api, endpoint, store


def test_events_reach_a_subscriber_and_the_query_answers_the_map(service: tuple[AppClient, str, MemoryStore]) -> None:
    api, endpoint, store = service
    collected = Collector()
    with subscribe_objects("z", collected, connect=[endpoint]):
        time.sleep(0.5)  # the subscription reaches the service's peer
        for i in range(3):
            api.post("/v1/maps/z/frames", content=frame_to_proto(make_test_frame(i, map_id="z")).SerializeToString(), headers=PROTOBUF)
        wait_until(lambda: len(collected.events) >= 3, 20, "3 events")
    (obj,) = store.list_objects("z")
    assert collected.kinds() == [pb.ObjectEvent.KIND_CREATED, pb.ObjectEvent.KIND_UPDATED, pb.ObjectEvent.KIND_UPDATED]
    last = collected.events[-1]
    assert last.map_id == "z" and last.object_id == obj.id and last.object.version == obj.version == 3
    assert last.object.label == "chair" and last.object.n_frames == 3
    assert np.allclose([last.object.aabb.min.x, last.object.aabb.min.y, last.object.aabb.min.z], obj.aabb.min)

    answer = query_objects("z", connect=[endpoint], timeout_s=5)
    assert answer.map_id == "z" and [o.id for o in answer.objects] == [obj.id]
    assert query_objects("empty", connect=[endpoint], timeout_s=5).objects == []
    with pytest.raises(RuntimeError, match="one map"):
        query_objects("*", connect=[endpoint], timeout_s=5)


def test_frames_published_over_zenoh_are_ingested(service: tuple[AppClient, str, MemoryStore]) -> None:
    api, endpoint, store = service
    session = open_session("peer", connect=[endpoint])
    try:
        time.sleep(0.5)
        for i in range(2):
            session.put(frames_key("zf", "d"), frame_to_proto(make_test_frame(i, map_id="zf")).SerializeToString())
        session.put(frames_key("zf", "d"), b"not a frame")  # logged and dropped
        session.put(frames_key("zf", "d"), frame_to_proto(make_test_frame(5, map_id="other")).SerializeToString())  # map ids disagree: dropped
        unnamed = frame_to_proto(make_test_frame(6, map_id="zf"))
        unnamed.map_id = ""  # the key names the map
        session.put(frames_key("zf", "d"), unnamed.SerializeToString())
        wait_until(lambda: store.count_frames("zf") == 3, 20, "3 frames over zenoh processed")
    finally:
        session.close()
    assert api.get("/v1/maps/zf/stats").json()["frames"] == {"accepted": 3, "processed": 3, "failed": 0, "pending": 0}
    assert api.get("/v1/maps/other/stats").status_code == 404


def test_publisher_without_store_and_helpers() -> None:
    port = free_port()
    publisher = ZenohPublisher(mode="peer", listen=[f"tcp/127.0.0.1:{port}"])
    collected = Collector()
    try:
        with subscribe_objects("p", collected, connect=[f"tcp/127.0.0.1:{port}"]):
            time.sleep(0.5)
            publisher.publish([ObjectEvent("deleted", "p", 4), ObjectEvent("merged", "p", 5, merged_into=2), ObjectEvent("deleted", "other", 1)])
            wait_until(lambda: len(collected.events) >= 2, 10, "2 events")
            time.sleep(0.2)
        assert collected.kinds() == [pb.ObjectEvent.KIND_DELETED, pb.ObjectEvent.KIND_MERGED]
        assert collected.events[1].merged_into == 2 and not collected.events[1].HasField("object")
        with pytest.raises(LookupError, match="no answer"):  # nobody serves the map's objects
            query_objects("p", connect=[f"tcp/127.0.0.1:{port}"], timeout_s=0.5)
    finally:
        publisher.close()
    publisher.publish([ObjectEvent("deleted", "p", 4)])  # after close: dropped quietly
    assert object_key("m", 3) == "arcloud/m/objects/3" and frames_key("m", "d") == "arcloud/m/frames/d"
    assert connectable(["tcp/0.0.0.0:7447", "tcp/[::]:7447"]) == ["tcp/127.0.0.1:7447", "tcp/[::1]:7447"]
    assert '"client"' in str(zenoh_config("client", connect=["tcp/127.0.0.1:1"]).get_json("mode"))
