"""AR pose conventions through the real app (embedded store; one test on Redis): frames sent as ARKit / ARCore
report them, from a session with its own origin (``device_from_map`` stored by an admin or sent with each frame),
or from a tilted world that declares its up, build the same objects as OpenCV frames in the map's world; the
device alignment routes and their access; refusals naming the field.

ARKit poses here are written out by hand (a z-up map's points in a y-up session: (x, y, z) -> (x, z, -y); camera
axes y and z reversed), not with the module under test.

Real frames (skipped without them under ../shared): every 20th frame of 7-Scenes redkitchen through the real
detector, sent three ways, gives the same boxes within 1 cm: ``native`` (OpenCV, in the gravity-aligned z-up world
``load_seven_scenes(align_gravity=True)`` reads), ``ar`` (the same cameras as ARKit reports them, from two devices
taking turns: ``phone-1``'s session shares the map's origin, ``phone-2``'s stands elsewhere, its alignment stored
through the admin route) and ``tilted`` (the poses as recorded, in the dataset's tilted world, declaring its up).
The detector runs once per image (``OncePerImage``), so that what differs is the pose conversion alone."""

from __future__ import annotations

import asyncio
import hashlib
import json
import threading
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from redis_server import RedisServer
from svc_helpers import LEFT, RIGHT, AppClient, BlobDetector, UvicornThread, make_test_frame, multipart_parts, wait_until

from arcloud.cli import main as cli_main
from arcloud.client import ArcloudClient, AsyncArcloudClient, ServiceError
from arcloud.core.conventions import POSE_CONVENTIONS
from arcloud.core.types import Detection, Frame
from arcloud.datasets.sevenscenes import load_seven_scenes
from arcloud.detectors.factory import make_detector
from arcloud.ports import Detector
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_to_proto
from arcloud.service.runtime import ingest_published_frame
from arcloud.service.schemas import PoseConventionName
from arcloud.service.settings import Settings
from arcloud.stores.memory_alignments import MemoryDeviceAlignments
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
TENTATIVE = {"include": "tentative"}
#: A z-up map's points in a y-up (ARKit, ARCore) session world: (x, y, z) -> (x, z, -y).
Y_UP_FROM_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera x right, y up, z back from x right, y down, z forward
#: Where a second device's session stands in the map: 40 degrees about up, moved 1.5 m, -2 m, 0.3 m.
YAW = np.radians(40.0)
DEVICE_FROM_MAP = np.array(
    [[np.cos(YAW), -np.sin(YAW), 0, 1.5], [np.sin(YAW), np.cos(YAW), 0, -2.0], [0, 0, 1.0, 0.3], [0, 0, 0, 1.0]]
)


def arkit_pose(cam2map: np.ndarray, device_from_map: np.ndarray | None = None) -> np.ndarray:
    """The camera-to-world transform ARKit reports for an OpenCV camera at ``cam2map`` in a z-up map, in a
    session whose world is ``device_from_map`` from the map's (None: the map's origin and heading)."""
    device = cam2map if device_from_map is None else device_from_map @ cam2map
    return Y_UP_FROM_Z_UP @ device @ GL_FROM_CV


def as_device(frame: Frame, pose: np.ndarray, map_id: str, device_id: str | None = None) -> Frame:
    return Frame(
        frame.rgb, frame.depth_m, frame.intrinsics, pose, frame.timestamp_s, map_id, device_id or frame.device_id, frame.frame_id
    )


def body(frame: Frame, **pose: Any) -> bytes:
    return frame_to_proto(frame, **pose).SerializeToString()  # type: ignore[no-any-return]  # protobuf's stubs


def processed(client: AppClient, map_id: str) -> int:
    return int(client.get(f"/v1/maps/{map_id}/stats").json()["frames"]["processed"])


def boxes(client: AppClient, map_id: str) -> list[tuple[str, np.ndarray]]:
    objects = client.get(f"/v1/maps/{map_id}/objects", params=TENTATIVE).json()["objects"]
    return [(o["label"], np.array([*o["aabb"]["min"], *o["aabb"]["max"]])) for o in sorted(objects, key=lambda o: o["id"])]


def assert_same_boxes(client: AppClient, map_id: str, reference: list[tuple[str, np.ndarray]], atol_m: float) -> None:
    got = boxes(client, map_id)
    assert [label for label, _ in got] == [label for label, _ in reference], map_id
    for (_, box), (_, expected) in zip(got, reference, strict=True):
        assert np.allclose(box, expected, atol=atol_m), (map_id, box, expected)


@pytest.fixture
def client() -> Iterator[AppClient]:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as test_client:
        yield test_client


def test_the_schema_names_the_cores_conventions() -> None:
    assert typing.get_args(PoseConventionName) == POSE_CONVENTIONS


def test_arkit_frames_from_two_sessions_build_the_objects_of_opencv_frames(client: AppClient) -> None:
    # depths off the voxel boundaries (2.0 m is one): a pose rounded otherwise in the last bit moves no voxel
    frames = [make_test_frame(i, level=True, boxes=(LEFT, RIGHT), near_m=2.02, far_m=3.02) for i in range(6)]
    answer = client.request("PUT", "/v1/maps/ar/devices/phone-2/alignment", json={"device_from_map": DEVICE_FROM_MAP.tolist()})
    assert answer.status_code == 200, answer.text
    for i, frame in enumerate(frames):
        device = "phone-1" if i % 2 == 0 else "phone-2"
        native = as_device(frame, frame.cam2world, "cv", device)
        sent = {
            "cv": body(native),
            # phone-1's session is the map's; phone-2's stands at DEVICE_FROM_MAP (stored above)
            "ar": body(
                as_device(frame, arkit_pose(frame.cam2world, DEVICE_FROM_MAP if device == "phone-2" else None), "ar", device),
                pose_convention="arkit",
            ),
            # the same second session, its alignment sent with each frame; ARCore names the same axes
            "own": body(
                as_device(frame, arkit_pose(frame.cam2world, DEVICE_FROM_MAP), "own", device),
                pose_convention="arcore",
                device_from_map=DEVICE_FROM_MAP,
            ),
        }
        for map_id, content in sent.items():
            response = client.post(f"/v1/maps/{map_id}/frames", content=content, headers=PROTOBUF)
            assert response.status_code == 202, response.text
    wait_until(lambda: all(processed(client, m) == 6 for m in ("cv", "ar", "own")), 30, "18 frames processed")
    reference = boxes(client, "cv")
    assert len(reference) == 2 and all(label == "chair" for label, _ in reference)
    for map_id in ("ar", "own"):
        assert_same_boxes(client, map_id, reference, atol_m=1e-6)
    # the devices' cameras the viewer draws are in the map's frame, OpenCV axes
    devices = {d.device_id: d for d in client.app.state.runtime.ingest.devices.of_map("ar", within_s=60)}
    assert np.allclose(np.reshape(devices["phone-2"].cam2world, (4, 4)), frames[5].cam2world, atol=1e-9)


def test_multipart_uploads_declare_the_convention_in_meta(client: AppClient) -> None:
    frame = make_test_frame(0, level=True)
    parts = multipart_parts(
        as_device(frame, arkit_pose(frame.cam2world, DEVICE_FROM_MAP), "mp"),
        cam2world=arkit_pose(frame.cam2world, DEVICE_FROM_MAP).tolist(),
        pose_convention="arkit",
        world_up=[0, 1, 0],
        device_from_map=DEVICE_FROM_MAP.tolist(),
    )
    assert client.post("/v1/maps/mp/frames", files=parts).status_code == 202
    (device,) = client.app.state.runtime.ingest.devices.of_map("mp", within_s=60)
    assert np.allclose(np.reshape(device.cam2world, (4, 4)), frame.cam2world, atol=1e-9)
    refused = client.post("/v1/maps/mp/frames", files=multipart_parts(frame, frame_id="x", pose_convention="opengl"))
    assert refused.status_code == 422 and refused.json()["field"] == "meta.pose_convention", refused.text


def test_a_tilted_world_that_declares_its_up_is_rotated_into_the_map(client: AppClient) -> None:
    up = np.array([0.0, -0.6, 0.8])  # the tilted world's up; its points are the map's turned by `tilt`
    axis = np.cross(up, (0.0, 0.0, 1.0))
    angle = np.arccos(up[2])
    k = axis / np.linalg.norm(axis)
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    map2tilted = np.eye(4)
    map2tilted[:3, :3] = (np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew).T  # takes +z to up
    assert np.allclose(map2tilted[:3, :3] @ (0, 0, 1), up)
    for i in range(4):
        frame = make_test_frame(i, level=True, near_m=2.02, far_m=3.02)
        tilted = as_device(frame, map2tilted @ frame.cam2world, "tilted")
        for map_id, content in (
            ("level", body(as_device(frame, frame.cam2world, "level"))),
            ("tilted", body(tilted, world_up=up)),
        ):
            assert client.post(f"/v1/maps/{map_id}/frames", content=content, headers=PROTOBUF).status_code == 202
    wait_until(lambda: processed(client, "level") == processed(client, "tilted") == 4, 30, "8 frames processed")
    assert_same_boxes(client, "tilted", boxes(client, "level"), atol_m=1e-6)


def test_alignment_routes_store_check_list_and_forget(client: AppClient) -> None:
    route = "/v1/maps/room/devices/phone-2/alignment"
    missing = client.get(route)
    assert missing.status_code == 404 and "has no alignment" in missing.json()["detail"]
    flat = client.request("PUT", route, json={"device_from_map": DEVICE_FROM_MAP.reshape(16).tolist()})
    assert flat.status_code == 200 and np.allclose(flat.json()["device_from_map"], DEVICE_FROM_MAP)
    assert client.get(route).json() == {"map_id": "room", "device_id": "phone-2", "device_from_map": DEVICE_FROM_MAP.tolist()}
    listed = client.get("/v1/maps/room/alignments").json()
    assert [a["device_id"] for a in listed["alignments"]] == ["phone-2"] and listed["map_id"] == "room"

    tilted = DEVICE_FROM_MAP.copy()
    tilted[:3, :3] = np.array([[1.0, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]]) @ tilted[:3, :3]
    scaled = DEVICE_FROM_MAP * 2
    scaled[3, 3] = 1.0
    for bad, says in [
        (tilted.tolist(), "tilts up by 11.46 degrees"),
        (scaled.tolist(), "orthonormal rotation"),
        ([[1.0, 0.0], [0.0, 1.0]], "4 rows of 4, got rows of [2, 2] numbers"),
        (np.eye(4).reshape(16)[:12].tolist(), "shape (4, 4)"),
        ([[1, 0, 0, 1e9], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "a translation of at most 10000 m"),
    ]:
        refused = client.request("PUT", route, json={"device_from_map": bad})
        assert refused.status_code == 422 and refused.json()["field"] == "device_from_map", refused.text
        assert says in refused.json()["detail"], refused.text
    nan = client.request("PUT", route, content=b'{"device_from_map": [NaN, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}')
    assert nan.status_code == 422, nan.text
    assert client.request("PUT", route, json={"device_from_map": np.eye(4).tolist(), "x": 1}).status_code == 422
    truthy = client.request("PUT", route, json={"device_from_map": [[True, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})
    assert truthy.status_code == 422 and "device_from_map" in truthy.json()["field"], truthy.text  # strict: not read as 1
    assert client.request("PUT", "/v1/maps/room/devices/a%2Fb/alignment", json={"device_from_map": np.eye(4).tolist()}).status_code in (404, 422)  # fmt: skip
    assert np.allclose(client.get(route).json()["device_from_map"], DEVICE_FROM_MAP)  # refusals changed nothing

    frame = make_test_frame(0, map_id="room", device_id="phone-2")
    assert client.post("/v1/maps/room/frames", content=body(frame), headers=PROTOBUF).status_code == 202
    wait_until(lambda: processed(client, "room") == 1, 20, "frame processed")
    assert client.delete("/v1/maps/room").status_code == 200
    assert client.get(route).status_code == 404  # deleting the map forgot its alignments
    client.request("PUT", route, json={"device_from_map": DEVICE_FROM_MAP.tolist()})
    gone = client.delete(route)
    assert gone.json() == {"map_id": "room", "device_id": "phone-2", "deleted": True}
    assert client.delete(route).json()["deleted"] is False


def test_a_map_holds_a_bounded_number_of_alignments_and_one_of_alignments_alone_can_be_deleted(
    client: AppClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A review: one admin key stored alignments of any number of devices, on a map that was never made too, which
    DELETE of the map then answered 404 and left in the store."""
    from arcloud.service import alignment_routes

    monkeypatch.setattr(alignment_routes, "MAX_ALIGNED_DEVICES", 3)
    aligned = {"device_from_map": DEVICE_FROM_MAP.tolist()}
    for device in ("a", "b", "c"):
        assert client.request("PUT", f"/v1/maps/x/devices/{device}/alignment", json=aligned).status_code == 200
    full = client.request("PUT", "/v1/maps/x/devices/d/alignment", json=aligned)
    assert full.status_code == 409 and "holds 3 devices' alignments, the most it holds (MAX_ALIGNED_DEVICES)" in full.text
    assert client.request("PUT", "/v1/maps/x/devices/a/alignment", json=aligned).status_code == 200  # set again: no new one
    assert client.get("/v1/maps/x/stats").status_code == 404  # no frame of map x: no map to read
    assert client.delete("/v1/maps/x").json() == {"map_id": "x", "deleted_objects": 0}
    assert client.get("/v1/maps/x/alignments").json()["alignments"] == []
    assert client.delete("/v1/maps/x").status_code == 404  # nothing of it left


@pytest.mark.parametrize(
    ("pose", "field", "says"),
    [
        (
            {"pose_convention": "arkit", "device_from_map": np.diag([1.0, -1.0, -1.0, 1.0])},
            "device_from_map",
            "tilts up by 180.00",
        ),
        ({"pose_convention": "arkit", "world_up": None}, "world_up", "a direction"),  # a zero up: the SDK would refuse it
    ],
)
def test_frames_with_a_wrong_declaration_are_refused_by_name(
    client: AppClient, pose: dict[str, Any], field: str, says: str
) -> None:
    msg = frame_to_proto(make_test_frame(0), **pose)
    if field == "world_up":
        msg.world_up.CopyFrom(pb.Vec3())
    refused = client.post("/v1/maps/m/frames", content=msg.SerializeToString(), headers=PROTOBUF)
    assert refused.status_code == 422 and refused.json()["field"] == field and says in refused.json()["detail"], refused.text
    assert client.get("/v1/maps/m/stats").status_code == 404  # nothing accepted


def test_only_admin_keys_set_alignments_and_readers_read_them(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    keys_file = tmp_path / "keys.json"
    tokens = {}
    for role in ("reader", "device", "admin"):
        capsys.readouterr()
        assert cli_main(["keys", "create", "--file", str(keys_file), "--maps", "room", "--role", role]) == 0
        tokens[role] = capsys.readouterr().out.strip()
    settings = Settings(detector="sim:0", workers=1, keys_file=str(keys_file))
    route = "/v1/maps/room/devices/phone-2/alignment"
    put = {"json": {"device_from_map": DEVICE_FROM_MAP.tolist()}}
    with AppClient(create_app(settings, detector=BlobDetector())) as api:
        assert api.request("PUT", route, **put).status_code == 401
        for role in ("reader", "device"):
            refused = api.request("PUT", route, headers={"authorization": f"Bearer {tokens[role]}"}, **put)
            assert refused.status_code == 403, (role, refused.text)
            assert api.delete(route, headers={"authorization": f"Bearer {tokens[role]}"}).status_code == 403
        assert api.request("PUT", route, headers={"authorization": f"Bearer {tokens['admin']}"}, **put).status_code == 200
        assert api.get(route, headers={"authorization": f"Bearer {tokens['reader']}"}).status_code == 200
        other = api.request(
            "PUT", "/v1/maps/lab/devices/d/alignment", headers={"authorization": f"Bearer {tokens['admin']}"}, **put
        )
        assert other.status_code == 403  # an admin of another map


def test_frames_published_over_zenoh_are_converted_the_same_way() -> None:
    class Taken:
        def __init__(self) -> None:
            self.frames: list[Frame] = []

        def submit(self, frame: Frame, message: object = None) -> None:
            self.frames.append(frame)

    alignments = MemoryDeviceAlignments()
    alignments.put("z", "phone-2", DEVICE_FROM_MAP)
    frame = make_test_frame(0, level=True)
    payload = body(as_device(frame, arkit_pose(frame.cam2world, DEVICE_FROM_MAP), "z", "phone-2"), pose_convention="arkit")
    taken = Taken()
    ingest_published_frame(taken, "z", payload, Settings(detector="sim:0"), alignments=alignments)  # type: ignore[arg-type]  # a stand-in ingest
    assert np.allclose(taken.frames[0].cam2world, frame.cam2world, atol=1e-9)


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    server = RedisServer.start()
    yield server
    server.stop()


@pytest.mark.redis
def test_an_alignment_set_through_one_api_process_applies_in_another(redis_server: RedisServer) -> None:
    with redis_server.client() as data:
        data.flushdb()
    settings = Settings(store=redis_server.url, detector="sim:0", workers=0, auth="none")
    frame = make_test_frame(0, level=True)
    with AppClient(create_app(settings)) as first, AppClient(create_app(settings)) as second:
        answer = first.request("PUT", "/v1/maps/r/devices/phone-2/alignment", json={"device_from_map": DEVICE_FROM_MAP.tolist()})
        assert answer.status_code == 200
        content = body(as_device(frame, arkit_pose(frame.cam2world, DEVICE_FROM_MAP), "r", "phone-2"), pose_convention="arkit")
        assert second.post("/v1/maps/r/frames", content=content, headers=PROTOBUF).status_code == 202
        (device,) = second.app.state.runtime.ingest.devices.of_map("r", within_s=60)
        assert np.allclose(np.reshape(device.cam2world, (4, 4)), frame.cam2world, atol=1e-9)
        assert json.loads(second.get("/v1/maps/r/alignments").content)["alignments"][0]["device_id"] == "phone-2"
        assert second.delete("/v1/maps/r").status_code == 200
        assert first.get("/v1/maps/r/devices/phone-2/alignment").status_code == 404


def test_the_sdk_sends_ar_frames_and_manages_alignments_over_real_http() -> None:
    frame = make_test_frame(0, level=True, near_m=2.02, far_m=3.02)
    with UvicornThread(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as server:
        with ArcloudClient(server.url, max_retries=0) as sdk:
            stored = sdk.set_device_alignment("sdk", "phone-2", DEVICE_FROM_MAP)
            assert np.allclose(stored.device_from_map, DEVICE_FROM_MAP)
            assert sdk.device_alignment("sdk", "phone-2").device_id == "phone-2"
            assert [a.device_id for a in sdk.device_alignments("sdk")] == ["phone-2"]
            for device, session, own in (("phone-1", None, None), ("phone-2", DEVICE_FROM_MAP, None), ("phone-3", DEVICE_FROM_MAP, DEVICE_FROM_MAP)):  # fmt: skip
                sdk.send_frame(
                    map_id="sdk", rgb=frame.rgb, depth=frame.depth_m, intrinsics=frame.intrinsics, device_id=device,
                    frame_id="f0", cam2world=arkit_pose(frame.cam2world, session), pose_convention="arkit", device_from_map=own,
                )  # fmt: skip
            sdk.wait_until_processed("sdk", timeout_s=30)
            objects = sdk.list_objects("sdk", include_tentative=True)
            assert len(objects) == 1 and objects[0].n_devices == 3  # three sessions, one place
            with pytest.raises(ServiceError) as refused:
                sdk.set_device_alignment("sdk", "phone-2", np.diag([1.0, 1.0, -1.0, 1.0]))
            assert refused.value.status == 422 and refused.value.field == "device_from_map"
            assert sdk.delete_device_alignment("sdk", "phone-2").deleted is True

        async def use_async() -> None:
            async with AsyncArcloudClient(server.url, max_retries=0) as client:
                await client.set_device_alignment("sdk", "phone-4", DEVICE_FROM_MAP.reshape(16))
                assert np.array_equal((await client.device_alignment("sdk", "phone-4")).device_from_map, DEVICE_FROM_MAP)
                assert len(await client.device_alignments("sdk")) == 1
                assert (await client.delete_device_alignment("sdk", "phone-4")).deleted is True

        asyncio.run(use_async())


# --- real frames: 7-Scenes redkitchen and the real detector --------------------------------------------------------
STRIDE = 20


class OncePerImage:
    """A detector that runs ``inner`` once per distinct colour image and answers the same detections after."""

    def __init__(self, inner: Detector) -> None:
        self.inner = inner
        self.runs = 0
        self._lock = threading.Lock()
        self._seen: dict[bytes, list[Detection]] = {}

    def detect(self, frame: Frame) -> list[Detection]:
        key = hashlib.sha256(np.ascontiguousarray(frame.rgb).tobytes()).digest()
        with self._lock:
            if key not in self._seen:
                self._seen[key] = self.inner.detect(frame)
                self.runs += 1
            return self._seen[key]


@pytest.mark.shared
@pytest.mark.slow
def test_redkitchen_as_arkit_from_two_sessions_and_from_its_tilted_world_gives_the_native_boxes(shared: type) -> None:
    root = shared.path("data/7scenes-redkitchen/gravity-direction.txt").parent
    model = shared.path("models/yolo11n-seg-fp32-640.onnx")
    aligned = load_seven_scenes(root, align_gravity=True)
    recorded = load_seven_scenes(root)  # the same frames, poses in the recorded (tilted) world
    assert aligned.up_file is not None and np.allclose(aligned.up, (0.0, 0.0, 1.0))
    tilt_deg = np.degrees(np.arccos(aligned.up_file[2]))
    assert tilt_deg > 20  # the recorded world is far from z-up: sent as it is, its boxes would stand askew
    detector = OncePerImage(make_detector(f"onnx:{model}"))
    settings = Settings(detector="sim:0", workers=1, key_rate_per_s=0, map_frame_rate_per_s=0)
    names = aligned.frame_names[::STRIDE]
    with AppClient(create_app(settings, detector=detector)) as client:
        stored = client.request(
            "PUT", "/v1/maps/ar/devices/phone-2/alignment", json={"device_from_map": DEVICE_FROM_MAP.tolist()}
        )
        assert stored.status_code == 200, stored.text
        for i, name in enumerate(names):
            frame = aligned.load_frame(name)
            device = "phone-1" if i % 2 == 0 else "phone-2"
            recorded_pose = recorded.cam2world[recorded.frame_names.index(name)]
            session = DEVICE_FROM_MAP if device == "phone-2" else None
            sent = {
                "native": body(as_device(frame, frame.cam2world, "native", device)),
                "ar": body(as_device(frame, arkit_pose(frame.cam2world, session), "ar", device), pose_convention="arkit"),
                "tilted": body(as_device(frame, recorded_pose, "tilted", device), world_up=aligned.up_file),
            }
            for map_id, content in sent.items():
                response = client.post(f"/v1/maps/{map_id}/frames", content=content, headers=PROTOBUF)
                assert response.status_code == 202, response.text
        wait_until(lambda: all(processed(client, m) == len(names) for m in sent), 600, "every frame processed", interval_s=0.5)
        assert detector.runs <= len(names) + 1  # each image once (and the worker's warm-up frame)
        native = boxes(client, "native")
        assert len(native) >= 5 and {"chair", "table"} <= {label for label, _ in native}
        for map_id in ("ar", "tilted"):
            got = boxes(client, map_id)
            assert [label for label, _ in got] == [label for label, _ in native], map_id
            worst = max(float(np.abs(box - expected).max()) for (_, box), (_, expected) in zip(got, native, strict=True))
            assert worst <= 0.01, (map_id, worst)
