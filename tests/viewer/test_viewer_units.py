"""The pure parts of the event stream and the devices record: what one stream tells its client, the bounds of the record. No server."""

from __future__ import annotations

import dataclasses

import numpy as np
from svc_helpers import make_test_frame

from arcloud.ports import ObjectMeta
from arcloud.service.devices import RecentDevices
from arcloud.service.event_stream import Shown, diff_devices, last_event_id, object_event, sse


def meta(object_id: int, version: int = 1, *, confirmed: bool = True) -> ObjectMeta:
    return ObjectMeta(object_id, "chair", 0.8, version, 10, 2, frozenset({"d"}), 1.6, 0.0, 1.0, None, None, None, confirmed)


def test_a_stream_of_the_served_map_removes_an_object_that_becomes_tentative() -> None:
    shown = Shown()
    assert object_event(1, meta(1, confirmed=False), shown, include_tentative=False) is None  # never shown: nothing
    name, data = object_event(1, meta(1, 2), shown, include_tentative=False) or ("", {})
    assert (name, data["id"], data["status"]) == ("upsert", 1, "confirmed") and shown.versions == {1: 2}
    assert object_event(1, meta(1, 2), shown, include_tentative=False) is None  # that state was sent
    assert object_event(1, meta(1, 3, confirmed=False), shown, include_tentative=False) == ("removed", {"id": 1})
    assert shown.versions == {}
    assert object_event(1, None, shown, include_tentative=False) is None  # gone, and not shown: nothing


def test_a_stream_with_tentative_objects_shows_them_and_removes_only_what_is_gone() -> None:
    shown = Shown()
    assert (object_event(1, meta(1, confirmed=False), shown, include_tentative=True) or ("",))[0] == "upsert"
    assert object_event(1, None, shown, include_tentative=True) == ("removed", {"id": 1})


def test_a_resumed_stream_that_does_not_know_what_its_client_shows_removes_each_hidden_object_once() -> None:
    shown = Shown(known=False)
    assert object_event(1, meta(1, 4, confirmed=False), shown, include_tentative=False) == ("removed", {"id": 1})
    assert object_event(1, meta(1, 5, confirmed=False), shown, include_tentative=False) is None
    assert object_event(2, None, shown, include_tentative=False) == ("removed", {"id": 2})


def test_last_event_id_names_a_version_or_nothing() -> None:
    assert [last_event_id(h) for h in ("42", " 7 ", None, "", "abc", "-1", "1-0")] == [
        (42, None), (7, None), None, None, None, None, None
    ]  # fmt: skip
    # with the time its log began: V@seconds.microseconds (anything else there: no id of ours)
    assert [last_event_id(h) for h in ("5@1795850986.935675", "5@", "5@x", "5@1.2.3", "5@" + "1" * 40 + ".0")] == [
        (5, "1795850986.935675"), (5, None), None, None, None
    ]  # fmt: skip
    # digits Python reads but a version is not: a superscript (int() raised: 500), 5,000 digits (over Python's limit),
    # past what a Redis stream id holds (every read of the map's log failed, for all its streams)
    assert [last_event_id(h) for h in ("\u00b2", "9" * 5000, str(2**64 - 1), str(2**63 - 2))] == [
        None,
        None,
        None,
        (2**63 - 2, None),
    ]


def test_an_event_is_one_data_line_of_json_with_its_id_when_given() -> None:
    text = sse("upsert", {"label": "two\nlines", "score": 0.5})
    assert text == 'event: upsert\ndata: {"label":"two\\nlines","score":0.5}\n\n'
    assert sse("removed", {"id": 3}, "12@1.5") == 'id: 12@1.5\nevent: removed\ndata: {"id":3}\n\n'


def test_the_devices_record_keeps_each_devices_last_pose_bounded() -> None:
    now = [100.0]
    devices = RecentDevices(max_maps=2, max_devices=2, clock=lambda: now[0])
    for index, device in enumerate(["a", "b", "a", "c"]):
        devices.record(make_test_frame(index, map_id="m", device_id=device, level=True))
    recent = devices.of_map("m", within_s=60)
    assert [(d.device_id, d.frame_id) for d in recent] == [("a", "f000002"), ("c", "f000003")]  # b heard least lately
    a = recent[0]
    assert (a.width, a.height, a.intrinsics) == (160, 120, (130.0, 130.0, 79.5, 59.5))
    assert np.allclose(np.reshape(a.cam2world, (4, 4))[:3, 3], [0.02, 0.0, 1.0])
    for map_id in ("n", "o"):
        devices.record(make_test_frame(0, map_id=map_id))
    assert devices.of_map("m", within_s=60) == []  # the map heard from least lately went
    now[0] += 61
    assert devices.of_map("o", within_s=60) == []  # no longer recent
    devices.forget_map("n")
    assert devices.of_map("n", within_s=1e9) == []


def test_devices_diff_on_a_new_frame_and_on_going_quiet() -> None:
    devices = RecentDevices()
    a = devices.record(make_test_frame(0, map_id="m", device_id="a"))
    b = devices.record(make_test_frame(0, map_id="m", device_id="b"))
    newer = dataclasses.replace(a, frame_id="f000001")
    assert diff_devices({"a": a, "b": b}, [newer]) == ([newer], ["b"])
    assert diff_devices({"a": a}, [a]) == ([], [])
