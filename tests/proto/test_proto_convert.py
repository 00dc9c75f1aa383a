"""Wire messages <-> core types: round trips, and bad input rejected with the field named."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from arcloud.core.checks import make_frame
from arcloud.core.types import AABB, N_CLASSES, OBB, MapObject, ObjectEvent
from arcloud.errors import InvalidInput
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import event_to_proto, frame_from_proto, frame_to_proto, object_to_proto, objects_to_proto
from arcloud.stores.codec import meta_of

H, W = 24, 32


def sample_frame(seed: int = 0):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 6.0, (H, W)).astype(np.float32)
    depth[0, :5] = 0.0  # no depth there
    yaw = 0.3
    cam2world = np.array([[np.cos(yaw), -np.sin(yaw), 0, 1.5], [np.sin(yaw), np.cos(yaw), 0, -2.0], [0, 0, 1, 0.7], [0, 0, 0, 1]])
    return make_frame(
        rgb, depth, (30.0, 31.0, 15.5, 11.5), cam2world, timestamp_s=12.25, map_id="lab", device_id="phone-1", frame_id="000042"
    )


def through_the_wire(msg: pb.Frame) -> pb.Frame:
    return pb.Frame.FromString(msg.SerializeToString())


def assert_same_pose_and_ids(got, want) -> None:
    np.testing.assert_array_equal(got.cam2world, want.cam2world)
    assert got.intrinsics == want.intrinsics
    assert (got.map_id, got.device_id, got.frame_id, got.timestamp_s) == (
        want.map_id,
        want.device_id,
        want.frame_id,
        want.timestamp_s,
    )


@pytest.mark.parametrize(
    ("rgb_encoding", "depth_encoding", "depth_tolerance_m"),
    [("png", "png", 0.0005), ("raw", "raw_uint16", 0.0005), ("raw", "raw_float32", 0.0), ("png", "raw_float32", 0.0)],
)
def test_lossless_frame_round_trips(rgb_encoding: str, depth_encoding: str, depth_tolerance_m: float) -> None:
    frame = sample_frame()
    got = frame_from_proto(through_the_wire(frame_to_proto(frame, rgb_encoding=rgb_encoding, depth_encoding=depth_encoding)))
    np.testing.assert_array_equal(got.rgb, frame.rgb)
    np.testing.assert_allclose(got.depth_m, frame.depth_m, rtol=0, atol=depth_tolerance_m + 1e-7)
    assert got.depth_m[0, 0] == 0.0
    assert got.depth_m.dtype == np.float32 and got.rgb.dtype == np.uint8
    assert_same_pose_and_ids(got, frame)


def test_jpeg_round_trip_is_close() -> None:
    yy, xx = np.mgrid[0:H, 0:W]
    smooth = np.stack([xx * 8, yy * 10, (xx + yy) * 4], axis=-1).astype(np.uint8)
    frame = sample_frame()
    msg = frame_to_proto(
        rgb=smooth,
        depth=frame.depth_m,
        intrinsics=frame.intrinsics,
        cam2world=frame.cam2world,
        timestamp_s=1.0,
        map_id="lab",
        device_id="d",
        frame_id="f",
        jpeg_quality=95,
    )
    assert msg.rgb[:2] == b"\xff\xd8" and msg.rgb_encoding == pb.RGB_ENCODING_JPEG
    got = frame_from_proto(through_the_wire(msg))
    assert np.abs(got.rgb.astype(int) - smooth).mean() < 4  # lossy, but the channels are in RGB order
    assert got.rgb[..., 0].mean() > got.rgb[..., 2].mean()


def test_arrays_with_uint16_depth_keep_their_units() -> None:
    rng = np.random.default_rng(1)
    units = rng.integers(0, 65535, (H, W)).astype(np.uint16)
    msg = frame_to_proto(
        rgb=np.zeros((H, W, 3), np.uint8),
        depth=units,
        intrinsics=(30, 30, 16, 12),
        cam2world=np.eye(4),
        timestamp_s=0.5,
        map_id="m",
        device_id="d",
        frame_id="f",
        depth_scale=5000.0,
    )
    assert msg.depth_scale == 5000.0 and msg.depth_encoding == pb.DEPTH_ENCODING_PNG
    decoded = cv2.imdecode(np.frombuffer(msg.depth, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(decoded, units)
    np.testing.assert_allclose(frame_from_proto(msg).depth_m, units / np.float32(5000), rtol=1e-6)


def test_depths_beyond_the_uint16_range_become_no_depth() -> None:
    frame = sample_frame()
    far = make_frame(
        frame.rgb,
        np.full((H, W), 70.0, np.float32),
        frame.intrinsics,
        frame.cam2world,
        timestamp_s=0,
        map_id="m",
        device_id="d",
        frame_id="f",
    )
    assert not frame_from_proto(frame_to_proto(far, rgb_encoding="png")).depth_m.any()
    assert np.all(frame_from_proto(frame_to_proto(far, depth_encoding="raw_float32")).depth_m == 70.0)


def good_message() -> pb.Frame:
    return frame_to_proto(sample_frame(), rgb_encoding="png", depth_encoding="png")


def with_changes(**changes) -> pb.Frame:
    msg = good_message()
    for name, value in changes.items():
        if name == "cam2world":
            del msg.cam2world[:]
            msg.cam2world.extend(value)
        else:
            setattr(msg, name, value)
    return msg


def png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


@pytest.mark.parametrize(
    ("msg", "field", "says"),
    [
        (with_changes(rgb=b"\x89PNG not really"), "rgb", "cannot decode"),
        (with_changes(rgb=b""), "rgb", "0 bytes"),
        (with_changes(depth=b"garbage"), "depth", "cannot decode"),
        (with_changes(depth=png(np.full((H, W), 200, np.uint8))), "depth", "8-bit"),
        (with_changes(depth=png(np.zeros((H, W, 3), np.uint16))), "depth", "3 channel"),
        (with_changes(rgb_encoding=pb.RGB_ENCODING_UNSPECIFIED), "rgb_encoding", "UNSPECIFIED"),
        (with_changes(depth_encoding=pb.DEPTH_ENCODING_UNSPECIFIED), "depth_encoding", "UNSPECIFIED"),
        (with_changes(rgb_encoding=pb.RGB_ENCODING_RAW_RGB8), "rgb", "bytes"),
        (with_changes(rgb_encoding=pb.RGB_ENCODING_RAW_RGB8, width=0), "width", "0 x"),
        (with_changes(depth_encoding=pb.DEPTH_ENCODING_RAW_FLOAT32, depth=b"\x00" * 8), "depth", "8 bytes"),
        (with_changes(depth_scale=0.0), "depth_scale", "units per metre"),
        (with_changes(width=W + 1), "rgb", "declared size"),
        (with_changes(depth=png(np.zeros((H, W + 2), np.uint16)), width=0, height=0), "depth", "size"),
        (with_changes(cam2world=[1.0] * 12), "cam2world", "12 values"),
        (with_changes(cam2world=[2.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]), "cam2world", "orthonormal"),
        (with_changes(map_id=""), "map_id", "non-empty"),
        (with_changes(device_id="a/b"), "device_id", "'/'"),
        (with_changes(timestamp_s=float("nan")), "timestamp_s", "finite"),
    ],
)
def test_bad_frames_name_the_field(msg: pb.Frame, field: str, says: str) -> None:
    with pytest.raises(InvalidInput) as caught:
        frame_from_proto(msg)
    assert caught.value.field == field
    assert says in str(caught.value)


def test_frame_without_intrinsics_is_rejected() -> None:
    msg = good_message()
    msg.ClearField("intrinsics")
    with pytest.raises(InvalidInput) as caught:
        frame_from_proto(msg)
    assert caught.value.field == "intrinsics"


def test_frame_to_proto_checks_its_arguments() -> None:
    frame = sample_frame()
    with pytest.raises(InvalidInput, match="rgb_encoding"):
        frame_to_proto(frame, rgb_encoding="gif")  # type: ignore[arg-type]  # on purpose: a refused encoding
    with pytest.raises(InvalidInput, match="depth_encoding"):
        frame_to_proto(frame, depth_encoding="jpeg")  # type: ignore[arg-type]  # on purpose: a refused encoding
    with pytest.raises(InvalidInput, match=r"^frame: expected a Frame, or rgb, depth, intrinsics and cam2world, got neither$"):
        frame_to_proto()
    with pytest.raises(InvalidInput) as missing:  # a new user's review: "got neither" named none of the missing
        frame_to_proto(rgb=frame.rgb, depth=frame.depth_m, cam2world=frame.cam2world)
    assert str(missing.value) == "intrinsics: expected a value with the other arrays (or a Frame), got none (intrinsics missing)"
    with pytest.raises(InvalidInput, match=r"^depth: .* got none \(depth, cam2world missing\)$"):
        frame_to_proto(rgb=frame.rgb, intrinsics=frame.intrinsics)
    with pytest.raises(InvalidInput, match="not both"):
        frame_to_proto(frame, rgb=frame.rgb)
    with pytest.raises(InvalidInput, match="depth"):
        frame_to_proto(
            rgb=frame.rgb,
            depth=frame.depth_m[:, :-1],
            intrinsics=frame.intrinsics,
            cam2world=frame.cam2world,
            map_id="m",
            device_id="d",
            frame_id="f",
        )


def refined_object() -> MapObject:
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return MapObject(
        id=7,
        keys=np.arange(5, dtype=np.int64),
        weights=np.ones(5, np.float32),
        votes=np.zeros((5, N_CLASSES), np.float32),
        n_frames=9,
        devices=frozenset({"a", "b"}),
        score_sum=4.0,
        version=3,
        created_at_s=100.0,
        updated_at_s=250.5,
        label="couch",
        score=0.75,
        aabb=AABB(np.array([0.0, 1.0, 2.0]), np.array([1.0, 2.0, 3.5])),
        obb=OBB(center=np.array([0.5, 1.5, 2.75]), size=np.array([1.0, 0.8, 1.5]), rotation=rotation, yaw_rad=np.pi / 2),
        bounds=AABB(np.zeros(3), np.ones(3)),
    )


def test_object_snapshot() -> None:
    obj = refined_object()
    for source in (obj, meta_of(obj)):
        msg = pb.Object.FromString(object_to_proto(source, "lab").SerializeToString())
        assert (msg.id, msg.map_id, msg.label, msg.score, msg.version) == (7, "lab", "couch", 0.75, 3)
        assert (msg.n_voxels, msg.n_frames, msg.n_devices, msg.created_at_s, msg.updated_at_s) == (5, 9, 2, 100.0, 250.5)
        assert (msg.aabb.min.x, msg.aabb.min.y, msg.aabb.min.z, msg.aabb.max.z) == (0.0, 1.0, 2.0, 3.5)
        assert (msg.obb.center.z, msg.obb.size.y, msg.obb.yaw_rad) == (2.75, 0.8, np.pi / 2)
        np.testing.assert_array_equal(np.reshape(msg.obb.rotation, (3, 3)), obj.obb.rotation)
        assert msg.status == pb.Object.STATUS_TENTATIVE  # not confirmed
    for source in (obj.replace(confirmed=True), meta_of(obj.replace(confirmed=True))):
        assert pb.Object.FromString(object_to_proto(source, "lab").SerializeToString()).status == pb.Object.STATUS_CONFIRMED
    bare = object_to_proto(obj.replace(aabb=None, obb=None, label=""), "lab")
    assert not bare.HasField("aabb") and not bare.HasField("obb") and bare.label == ""
    listed = objects_to_proto([obj, obj.replace(id=8)], "lab")
    assert listed.map_id == "lab" and [o.id for o in listed.objects] == [7, 8]


def test_events() -> None:
    obj = refined_object()
    created = event_to_proto(ObjectEvent("created", "lab", 7, obj))
    assert created.kind == pb.ObjectEvent.KIND_CREATED and created.object.id == 7 and created.time_s == 250.5
    assert not created.HasField("merged_into")
    merged = pb.ObjectEvent.FromString(
        event_to_proto(ObjectEvent("merged", "lab", 9, merged_into=7), time_s=300.0).SerializeToString()
    )
    assert (merged.kind, merged.object_id, merged.merged_into, merged.time_s) == (pb.ObjectEvent.KIND_MERGED, 9, 7, 300.0)
    assert not merged.HasField("object")
    deleted = event_to_proto(ObjectEvent("deleted", "lab", 9))
    assert deleted.kind == pb.ObjectEvent.KIND_DELETED and deleted.time_s > 1.6e9  # now
    retired = pb.ObjectEvent.FromString(event_to_proto(ObjectEvent("retired", "lab", 9), time_s=400.0).SerializeToString())
    assert (retired.kind, retired.object_id, retired.time_s) == (pb.ObjectEvent.KIND_RETIRED, 9, 400.0)
    assert not retired.HasField("object") and not retired.HasField("merged_into")
    assert event_to_proto(ObjectEvent("updated", "lab", 7, obj)).kind == pb.ObjectEvent.KIND_UPDATED
