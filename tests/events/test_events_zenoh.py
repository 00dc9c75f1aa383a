"""Zenoh events with real sessions on loopback (multicast scouting off): the service's peer publishes
object events (the served map's and the tentative ones on their own key spaces), answers the objects
query, and takes frames published on arcloud/<map>/frames/<device>."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack

import numpy as np
import pytest
from svc_helpers import (
    LEFT,
    RIGHT,
    AppClient,
    BlobDetector,
    EventCollector,
    free_port,
    make_test_frame,
    wait_for_subscriber,
    wait_until,
)

from arcloud.core.types import N_CLASSES, MapObject, ObjectEvent
from arcloud.events.zenoh import (
    ServedRouter,
    ZenohPublisher,
    connectable,
    frames_key,
    object_key,
    open_session,
    query_objects,
    subscribe_objects,
    tentative_key,
    zenoh_config,
)
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
CONFIRMED, TENTATIVE = pb.Object.STATUS_CONFIRMED, pb.Object.STATUS_TENTATIVE


@pytest.fixture
def service() -> Iterator[tuple[AppClient, str, MemoryStore, BlobDetector]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    settings = Settings(detector="sim:0", workers=1, zenoh_mode="peer", zenoh_listen=[endpoint], zenoh_frames=True)
    store = MemoryStore()
    detector = BlobDetector()
    with AppClient(create_app(settings, store=store, detector=detector)) as api:
        yield api, endpoint, store, detector


def test_default_subscribers_see_the_served_map_and_are_told_when_an_object_leaves_it(
    service: tuple[AppClient, str, MemoryStore, BlobDetector],
) -> None:
    api, endpoint, store, detector = service

    def send(index: int, boxes: tuple = (LEFT,)) -> None:
        body = frame_to_proto(make_test_frame(index, map_id="z", boxes=boxes, level=True)).SerializeToString()
        assert api.post("/v1/maps/z/frames", content=body, headers=PROTOBUF).status_code == 202
        wait_until(lambda: store.count_frames("z") == index + 1, 20, f"frame {index} processed")

    served, everything = EventCollector(), EventCollector()
    with ExitStack() as subscriptions:  # each known to the service's peer before the next (a key tells of all before)
        subscriptions.enter_context(subscribe_objects("z", served, connect=[endpoint]))
        wait_for_subscriber(object_key("z", 0), endpoint=endpoint)
        subscriptions.enter_context(subscribe_objects("z", everything, connect=[endpoint], include_tentative=True))
        wait_for_subscriber(tentative_key("z", 0), endpoint=endpoint)
        for i in range(6):  # an upright chair seen in six frames: confirmed on the way
            send(i)
        (chair,) = store.list_objects("z")
        assert chair.confirmed
        answer = query_objects("z", connect=[endpoint], timeout_s=5)
        assert [(o.id, o.status) for o in answer.objects] == [(chair.id, CONFIRMED)]

        detector.miss_left_on.update(f"f{i:06d}" for i in range(6, 60))  # in view, no longer detected
        index = 6
        while store.get("z", [chair.id])[0].confirmed:
            assert index < 60, "the missed chair stayed confirmed"
            send(index, (LEFT, RIGHT))
            index += 1
        last = store.get("z", [chair.id])[0]
        wait_until(lambda: (last.version, TENTATIVE) in everything.of(chair.id), 10, "the chair's tentative state")
        wait_until(lambda: (last.version, TENTATIVE) in served.of(chair.id), 10, "the served map's subscriber told")
        time.sleep(0.2)

        answer = query_objects("z", connect=[endpoint], timeout_s=5)
        both = query_objects("z", connect=[endpoint], timeout_s=5, include_tentative=True)
        with open_session("peer", connect=[endpoint]) as session:
            (reply,) = list(session.get("arcloud/z/objects?include=everything", timeout=5))
            assert reply.ok is None and b"include: expected tentative" in reply.err.payload.to_bytes()

    # Subscribed to both key spaces: every state of the chair once, in order, tentative until confirmed.
    states = everything.of(chair.id)
    first = next(v for v, status in states if status == CONFIRMED)
    assert [v for v, _ in states] == list(range(1, last.version + 1))
    assert states == [(v, TENTATIVE if v < first else CONFIRMED) for v in range(1, last.version)] + [(last.version, TENTATIVE)]
    # The served map's subscriber: every confirmed state, then the state that takes the chair out; nothing while tentative.
    assert served.of(chair.id) == [(v, CONFIRMED) for v in range(first, last.version)] + [(last.version, TENTATIVE)]
    assert all(e.object.status == CONFIRMED for e in served.events if e.object_id != chair.id)  # the right chair: once confirmed
    now = {o.id: o.confirmed for o in store.list_objects("z")}
    assert not now[chair.id] and [o.id for o in answer.objects] == sorted(i for i, confirmed in now.items() if confirmed)
    assert {o.id: o.status == CONFIRMED for o in both.objects} == now and {o.status for o in answer.objects} <= {CONFIRMED}
    assert query_objects("empty", connect=[endpoint], timeout_s=5).objects == []
    with pytest.raises(RuntimeError, match="one map"):
        query_objects("*", connect=[endpoint], timeout_s=5)


def test_frames_published_over_zenoh_are_ingested(service: tuple[AppClient, str, MemoryStore, BlobDetector]) -> None:
    api, endpoint, store, _ = service
    session = open_session("peer", connect=[endpoint])
    try:
        wait_for_subscriber(frames_key("zf", "d"), session=session)  # the service's subscriber of frames
        for i in range(2):
            session.put(frames_key("zf", "d"), frame_to_proto(make_test_frame(i, map_id="zf")).SerializeToString())
        session.put(frames_key("zf", "d"), b"not a frame")  # logged and dropped
        session.put(
            frames_key("zf", "d"), frame_to_proto(make_test_frame(5, map_id="other")).SerializeToString()
        )  # map ids disagree: dropped
        unnamed = frame_to_proto(make_test_frame(6, map_id="zf"))
        unnamed.map_id = ""  # the key names the map
        session.put(frames_key("zf", "d"), unnamed.SerializeToString())
        wait_until(lambda: store.count_frames("zf") == 3, 20, "3 frames over zenoh processed")
    finally:
        session.close()
    assert api.get("/v1/maps/zf/stats").json()["frames"] == {"accepted": 3, "processed": 3, "failed": 0, "pending": 0}
    assert api.get("/v1/maps/other/stats").status_code == 404


def state(object_id: int, version: int, confirmed: bool) -> MapObject:
    """An object's state as the step's events carry it (three voxels; what matters is version and status)."""
    return MapObject(
        id=object_id,
        keys=np.arange(3, dtype=np.int64),
        weights=np.ones(3, np.float32),
        votes=np.zeros((3, N_CLASSES), np.float32),
        version=version,
        label="chair",
        score=0.5,
        n_frames=version,
        updated_at_s=1000.0 + version,
        confirmed=confirmed,
    )


def test_router_sends_each_event_to_one_key_space() -> None:
    router = ServedRouter()
    # (event, where it goes) in the order published
    steps = [
        (ObjectEvent("created", "m", 1, state(1, 1, False)), "tentative"),  # new and tentative: nobody was served it
        (ObjectEvent("updated", "m", 1, state(1, 2, False)), "tentative"),
        (ObjectEvent("updated", "m", 1, state(1, 3, True)), "served"),  # confirmed: enters the served map
        (ObjectEvent("updated", "m", 1, state(1, 4, True), was_confirmed=True), "served"),
        (
            ObjectEvent("updated", "m", 1, state(1, 3, True), was_confirmed=True),
            None,
        ),  # older than one published (two workers): dropped
        (
            ObjectEvent("updated", "m", 1, state(1, 5, False), was_confirmed=True),
            "served",
        ),  # turned tentative: the served map's subscribers are told
        (ObjectEvent("updated", "m", 1, state(1, 6, False)), "tentative"),  # and hear no more of it
        (ObjectEvent("updated", "m", 1, state(1, 7, True)), "served"),  # confirmed again
        (ObjectEvent("merged", "m", 1, merged_into=2, was_confirmed=True), "served"),  # merged away: whoever had it is told
        (ObjectEvent("updated", "m", 1, state(1, 8, True)), None),  # nothing of a merged object is newer
        (ObjectEvent("created", "m", 2, state(2, 1, False)), "tentative"),
        (ObjectEvent("deleted", "m", 2), "tentative"),  # never served: the served map's subscribers never had it
        (ObjectEvent("deleted", "m", 3, was_confirmed=True), "served"),
        (ObjectEvent("created", "m", 4, state(4, 1, True)), "served"),
        (ObjectEvent("retired", "m", 4, was_confirmed=True), "served"),  # seen gone: whoever had it is told
        (ObjectEvent("updated", "m", 4, state(4, 2, True)), None),  # nothing of a removed object is newer
        (ObjectEvent("created", "m", 4, state(4, 1, True)), "served"),  # but a map restored keeps ids, versions from 1
        (ObjectEvent("updated", "m", 4, state(4, 2, True)), "served"),
        (ObjectEvent("retired", "m", 5), "tentative"),
        (ObjectEvent("created", "other", 1, state(1, 1, True)), "served"),  # maps are apart
    ]
    assert [router.route(event) for event, _ in steps] == [where for _, where in steps]
    small = ServedRouter(max_objects=2)
    for object_id in (1, 2, 3):
        small.route(ObjectEvent("updated", "m", object_id, state(object_id, 5, True)))
    assert (
        small.route(ObjectEvent("updated", "m", 1, state(1, 4, True))) == "served"
    )  # forgotten (the oldest of 3): not stale any more
    assert small.route(ObjectEvent("updated", "m", 3, state(3, 4, True))) is None


def test_publisher_puts_each_event_on_its_key_space() -> None:
    port = free_port()
    publisher = ZenohPublisher(mode="peer", listen=[f"tcp/127.0.0.1:{port}"])
    received: list[tuple[str, pb.ObjectEvent]] = []
    lock = threading.Lock()

    def on_sample(sample: object) -> None:
        with lock:
            received.append((str(sample.key_expr), pb.ObjectEvent.FromString(sample.payload.to_bytes())))  # type: ignore[attr-defined]  # sample: a zenoh.Sample typed as object

    served, everything = EventCollector(), EventCollector()
    session = open_session("peer", connect=[f"tcp/127.0.0.1:{port}"])
    try:
        with ExitStack() as subscriptions:  # each known to the publisher before the next (a key tells of all before)
            subscriptions.enter_context(subscribe_objects("p", served, session=session))
            wait_for_subscriber(object_key("p", 0), session=publisher.session)
            subscriptions.enter_context(subscribe_objects("p", everything, session=session, include_tentative=True))
            wait_for_subscriber(tentative_key("p", 0), session=publisher.session)
            raw = session.declare_subscriber("arcloud/p/**", on_sample)
            wait_for_subscriber("arcloud/p/raw", session=publisher.session)
            publisher.publish(
                [
                    ObjectEvent("created", "p", 1, state(1, 1, False)),
                    ObjectEvent("updated", "p", 1, state(1, 2, True)),
                    ObjectEvent("updated", "p", 1, state(1, 3, False), was_confirmed=True),
                    ObjectEvent("updated", "p", 1, state(1, 4, False)),
                    ObjectEvent("merged", "p", 5, merged_into=2, was_confirmed=True),
                    ObjectEvent("deleted", "other", 1),
                ]
            )
            wait_until(lambda: len(everything.events) >= 5, 10, "5 events")
            time.sleep(0.2)
        raw.undeclare()
        with pytest.raises(LookupError, match="no answer"):  # nobody serves the map's objects
            query_objects("p", session=session, timeout_s=0.5)
    finally:
        session.close()
        publisher.close()
    assert [(key, e.object.version) for key, e in received if e.HasField("object")] == [
        (tentative_key("p", 1), 1),
        (object_key("p", 1), 2),
        (object_key("p", 1), 3),
        (tentative_key("p", 1), 4),
    ]
    assert [(e.object.version, e.object.status) for e in served.events if e.HasField("object")] == [
        (2, CONFIRMED),
        (3, TENTATIVE),
    ]
    assert served.kinds()[-1] == pb.ObjectEvent.KIND_MERGED and served.events[-1].merged_into == 2
    assert [e.object.version for e in everything.events if e.HasField("object")] == [1, 2, 3, 4] and len(everything.events) == 5
    publisher.publish([ObjectEvent("deleted", "p", 4)])  # after close: dropped quietly
    assert object_key("m", 3) == "arcloud/m/objects/3" and tentative_key("m", 3) == "arcloud/m/objects/tentative/3"
    assert frames_key("m", "d") == "arcloud/m/frames/d"
    assert connectable(["tcp/0.0.0.0:7447", "tcp/[::]:7447"]) == ["tcp/127.0.0.1:7447", "tcp/[::1]:7447"]
    assert '"client"' in str(zenoh_config("client", connect=["tcp/127.0.0.1:1"]).get_json("mode"))
