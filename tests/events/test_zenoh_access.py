"""Zenoh access control, with real sessions on 127.0.0.1: a router in this process runs the example
docs/zenoh-router-acl.json5 (default deny; users and passwords in a dictionary file under tmp_path). The
service connects as user ``arcloud`` through a ``zenoh_config`` file holding its credentials; the devices
and the viewer of map ``office`` with theirs. Waits are bounded: a few seconds at most."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

import numpy as np
import pytest
import zenoh
from pydantic import ValidationError
from svc_helpers import free_port, wait_until

from arcloud.client import ArcloudClient
from arcloud.core.change import MapChange
from arcloud.core.types import AABB, N_CLASSES, MapObject, ObjectEvent
from arcloud.core.voxels import keys_bounds, pack_keys
from arcloud.errors import ArcloudError, InvalidInput
from arcloud.events.zenoh import (
    ZenohPublisher,
    frames_key,
    object_key,
    open_session,
    query_objects,
    subscribe_objects,
    zenoh_config,
)
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.service.settings import Settings
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import build_publisher, worker_publisher

T = TypeVar("T")

ROUTER_EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "zenoh-router-acl.json5"
MAP = "office"  # the map the example's devices and viewer belong to
PASSWORDS = {"arcloud": "service-pw", "office-phone-1": "phone-pw", "office-headset-2": "headset-pw", "office-wall": "wall-pw"}
VOXEL_M = 0.05
SETTLE_S = 0.5  # for declarations to reach the router, and for what it would forward to arrive


@dataclass(frozen=True)
class ZenohRouter:
    endpoint: str
    folder: Path

    def credentials(self, user: str, password: str | None = None) -> Path:
        """A client's Zenoh config file holding ``user``'s password (``password``: another one)."""
        path = self.folder / f"{user}-{password or 'right'}.json5"
        usrpwd = {"user": user, "password": password or PASSWORDS[user]}
        path.write_text(json.dumps({"transport": {"auth": {"usrpwd": usrpwd}}}))
        return path

    def client(self, user: str) -> zenoh.Session:
        return open_session("client", connect=[self.endpoint], config_file=self.credentials(user))


@pytest.fixture
def router(tmp_path: Path) -> Iterator[ZenohRouter]:
    users = tmp_path / "users.txt"
    users.write_text("".join(f"{user}:{password}\n" for user, password in PASSWORDS.items()))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = zenoh_config("router", listen=[endpoint], config_file=ROUTER_EXAMPLE)
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    assert json.loads(config.get_json("access_control/default_permission")) == "deny"
    session = zenoh.open(config)
    try:
        yield ZenohRouter(endpoint, tmp_path)
    finally:
        session.close()


class Received(Generic[T]):
    """What a callback got, from Zenoh's threads."""

    def __init__(self) -> None:
        self.items: list[T] = []
        self._lock = threading.Lock()

    def __call__(self, item: T) -> None:
        with self._lock:
            self.items.append(item)

    def snapshot(self) -> list[T]:
        with self._lock:
            return list(self.items)


def chair(object_id: int, version: int = 1) -> MapObject:
    """A confirmed object of eight voxels, as the store keeps it."""
    keys = np.sort(pack_keys(np.argwhere(np.ones((2, 2, 2), bool)) + object_id * 10))
    lo_m, hi_m = keys_bounds(keys, VOXEL_M)
    votes = np.zeros((keys.size, N_CLASSES), np.float32)
    votes[:, 0] = 1.0
    return MapObject(
        id=object_id,
        keys=keys,
        weights=np.ones(keys.size, np.float32),
        votes=votes,
        version=version,
        label="chair",
        score=0.9,
        n_frames=3,
        updated_at_s=1000.0 + version,
        confirmed=True,
        bounds=AABB(lo_m, hi_m),
    )


def test_a_device_gets_its_maps_events_and_objects_and_nothing_of_another_map(router: ZenohRouter) -> None:
    store = MemoryStore()
    assert store.commit(MAP, [], MapChange.writing(MAP, [chair(1)])) and store.commit(
        "lab", [], MapChange.writing("lab", [chair(2)])
    )
    service = ZenohPublisher(mode="client", connect=[router.endpoint], store=store, config_file=router.credentials("arcloud"))
    phone = router.credentials("office-phone-1")
    events, lab_events = Received[pb.ObjectEvent](), Received[pb.ObjectEvent]()
    try:
        with (
            subscribe_objects(MAP, events, mode="client", connect=[router.endpoint], config_file=phone),
            subscribe_objects("lab", lab_events, mode="client", connect=[router.endpoint], config_file=phone),
        ):
            time.sleep(SETTLE_S)
            service.publish([ObjectEvent("updated", "lab", 2, chair(2, 2)), ObjectEvent("updated", MAP, 1, chair(1, 2))])
            wait_until(lambda: events.snapshot(), 5, "the office event at the device")
            objects = query_objects(MAP, mode="client", connect=[router.endpoint], config_file=phone, timeout_s=3)
            with pytest.raises(LookupError, match="no answer"):  # the router does not pass the query on
                query_objects("lab", mode="client", connect=[router.endpoint], config_file=phone, timeout_s=1)
            time.sleep(SETTLE_S)
    finally:
        service.close()
    assert [(e.map_id, e.object_id, e.object.version) for e in events.snapshot()] == [(MAP, 1, 2)]
    assert lab_events.snapshot() == []  # published before the office event, on the same link: dropped
    assert [(o.id, o.label) for o in objects.objects] == [(1, "chair")]


def test_the_router_drops_object_events_a_device_publishes(router: ZenohRouter) -> None:
    """A device may not speak for the service: its put on an object key reaches no subscriber, the
    service's put on the same key does."""
    key = object_key(MAP, 123)
    received = Received[bytes]()
    viewer, phone, service = router.client("office-wall"), router.client("office-phone-1"), router.client("arcloud")
    try:
        subscriber = viewer.declare_subscriber(f"arcloud/{MAP}/objects/**", lambda s: received(s.payload.to_bytes()))
        time.sleep(SETTLE_S)
        phone.put(key, b"fake event from a device")
        phone.put(f"arcloud/{MAP}/objects/tentative/123", b"fake event from a device")
        service.put(key, b"event from the service")
        wait_until(lambda: received.snapshot(), 5, "the service's event at the viewer")
        time.sleep(SETTLE_S)
        subscriber.undeclare()
    finally:
        for session in (viewer, phone, service):
            session.close()
    assert received.snapshot() == [b"event from the service"]


def test_frames_reach_the_service_only_from_the_maps_devices(router: ZenohRouter) -> None:
    """With ARCLOUD_ZENOH_FRAMES the router is the only check: a device publishes its map's frames, a
    viewer publishes none, and nobody another map's."""
    frames = Received[tuple[str, bytes]]()
    service = ZenohPublisher(
        mode="client",
        connect=[router.endpoint],
        on_frame=lambda map_id, payload: frames((map_id, payload)),
        config_file=router.credentials("arcloud"),
    )
    phone, viewer = router.client("office-phone-1"), router.client("office-wall")
    try:
        time.sleep(SETTLE_S)
        viewer.put(frames_key(MAP, "office-wall"), b"from the viewer")
        phone.put(frames_key("lab", "office-phone-1"), b"for another map")
        phone.put(frames_key(MAP, "office-phone-1"), b"from the device")
        wait_until(lambda: frames.snapshot(), 5, "the device's frame at the service")
        time.sleep(SETTLE_S)
    finally:
        for session in (phone, viewer):
            session.close()
        service.close()
    assert frames.snapshot() == [(MAP, b"from the device")]


def test_a_session_with_a_wrong_password_or_none_cannot_connect(router: ZenohRouter) -> None:
    started = time.monotonic()
    with pytest.raises(ArcloudError, match=r"no client session .*Unable to connect"):
        open_session("client", connect=[router.endpoint], config_file=router.credentials("arcloud", "wrong"))
    with pytest.raises(ArcloudError, match="if it authenticates, does it accept our user and password"):
        ZenohPublisher(mode="client", connect=[router.endpoint])  # no credentials at all
    with pytest.raises(ArcloudError, match="no client session"):
        subscribe_objects(
            MAP,
            Received[pb.ObjectEvent](),
            mode="client",
            connect=[router.endpoint],
            config_file=router.credentials("office-wall", "x"),
        )
    assert time.monotonic() - started < 5  # refused at once, not after a timeout


def test_a_peer_refused_by_the_router_warns(router: ZenohRouter, caplog: pytest.LogCaptureFixture) -> None:
    """A peer opens all the same (it keeps trying): the API in peer mode says it reached nobody."""
    caplog.set_level(logging.WARNING, logger="arcloud.events.zenoh")
    session = open_session("peer", connect=[router.endpoint], config_file=router.credentials("arcloud", "wrong"))
    session.close()
    assert "reached none of" in caplog.text
    caplog.clear()
    session = open_session("peer", connect=[router.endpoint], config_file=router.credentials("arcloud"))
    session.close()
    assert "reached none of" not in caplog.text


def test_the_api_and_workers_connect_with_the_zenoh_config_file(router: ZenohRouter) -> None:
    settings = Settings(
        detector="sim:0", zenoh_mode="client", zenoh_connect=[router.endpoint], zenoh_config=str(router.credentials("arcloud"))
    )
    store = MemoryStore()
    assert store.commit(MAP, [], MapChange.writing(MAP, [chair(1)]))
    events = Received[pb.ObjectEvent]()
    api = build_publisher(settings, store, None)
    worker = worker_publisher(settings)
    assert isinstance(api, ZenohPublisher) and isinstance(worker, ZenohPublisher)
    try:
        with subscribe_objects(
            MAP, events, mode="client", connect=[router.endpoint], config_file=router.credentials("office-wall")
        ):
            time.sleep(SETTLE_S)
            worker.publish([ObjectEvent("updated", MAP, 1, chair(1, 2))])
            wait_until(lambda: events.snapshot(), 5, "the worker's event at the viewer")
            objects = query_objects(
                MAP, mode="client", connect=[router.endpoint], config_file=router.credentials("office-wall"), timeout_s=3
            )
    finally:
        api.close()
        worker.close()
    assert [o.id for o in objects.objects] == [1]


def test_the_sdk_subscribes_through_the_router_with_a_devices_config_file(router: ZenohRouter) -> None:
    service = ZenohPublisher(mode="client", connect=[router.endpoint], config_file=router.credentials("arcloud"))
    events = Received[pb.ObjectEvent]()
    try:
        with (
            ArcloudClient("http://127.0.0.1:9") as client,  # HTTP is not used: the subscription is Zenoh's
            client.subscribe(MAP, events, [router.endpoint], config_file=router.credentials("office-headset-2")),
        ):
            time.sleep(SETTLE_S)
            service.publish([ObjectEvent("updated", MAP, 7, chair(7, 2))])
            wait_until(lambda: events.snapshot(), 5, "the event at the SDK's subscriber")
    finally:
        service.close()
    assert [e.object_id for e in events.snapshot()] == [7]


# --- a bad zenoh_config stops the service at start, with one line naming it ---------------------------
@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("missing.json5", None, "expected a readable Zenoh config file"),
        ("zenoh.txt", "{}", "expected a Zenoh config file (.json5, .json, .yaml)"),
        ("folder.json5", "folder", "expected a readable Zenoh config file"),
    ],
)
def test_settings_refuse_a_zenoh_config_that_cannot_be_read(tmp_path: Path, name: str, content: str | None, message: str) -> None:
    path = tmp_path / name
    if content == "folder":
        path.mkdir()
    elif content is not None:
        path.write_text(content)
    with pytest.raises(ValidationError) as caught:
        Settings(zenoh_mode="client", zenoh_connect=["tcp/127.0.0.1:7447"], zenoh_config=str(path))
    errors = caught.value.errors()
    assert [e["loc"] for e in errors] == [("zenoh_config",)] and message in errors[0]["msg"]


def test_settings_refuse_a_zenoh_config_with_zenoh_off(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text("{}")
    with pytest.raises(ValidationError, match="zenoh_config: needs zenoh_mode"):
        Settings(zenoh_config=str(path))


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        ('{ transport: { auth: { usrpwd: { user: "arcloud", password: "hunter2" } } }, mode: }', "line 1, column 84: expected"),
        ('{ transport: { auth: { usrpwd: { user: "arcloud", password: "hunter2" } } }, modes: "peer" }', "unknown field `modes`"),
    ],
)
def test_a_config_zenoh_cannot_read_is_one_line_naming_the_setting(tmp_path: Path, content: str, reason: str) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(content)
    Settings(zenoh_mode="client", zenoh_connect=["tcp/127.0.0.1:7447"], zenoh_config=str(path))  # readable: Zenoh's to judge
    with pytest.raises(InvalidInput) as caught:
        ZenohPublisher(mode="client", connect=["tcp/127.0.0.1:7447"], config_file=path)
    message = str(caught.value)
    assert message.startswith(f"zenoh_config: expected a Zenoh config file, got {path}: ") and reason in message
    assert "\n" not in message and "hunter2" not in message and ".rs:" not in message
