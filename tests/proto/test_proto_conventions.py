"""A frame's declared pose convention on the wire (``Frame.pose_convention``, ``world_up``, ``device_from_map``):
``frame_to_proto`` writes it, ``frame_from_proto`` / ``to_map_world`` read it into the map's world with OpenCV
camera axes and clear it from the message, and refuse what is wrong naming the field."""

from __future__ import annotations

import numpy as np
import pytest

from arcloud.core.checks import make_frame
from arcloud.core.conventions import CAMERA_FLIP, cam2map
from arcloud.errors import InvalidInput
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import declared_convention, frame_from_proto, frame_to_proto, to_map_world

#: A y-up session world's points in a z-up map: (x, y, z) -> (x, -z, y).
Z_UP_FROM_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
LEVEL_CAM2MAP = np.array([[1.0, 0.0, 0.0, 0.5], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 1.2], [0.0, 0.0, 0.0, 1.0]])


def small_frame(cam2world: np.ndarray, device_id: str = "phone-1") -> object:
    depth = np.full((48, 64), 2.0, np.float32)
    rgb = np.full((48, 64, 3), 80, np.uint8)
    return make_frame(
        rgb, depth, (50.0, 50.0, 31.5, 23.5), cam2world, timestamp_s=0.0, map_id="m", device_id=device_id, frame_id="1"
    )


def arkit_pose_of(cam2map_pose: np.ndarray, device_from_map: np.ndarray | None = None) -> np.ndarray:
    """What ARKit reports for an OpenCV camera at ``cam2map_pose`` in a z-up map (written out, not the module's inverse)."""
    device = cam2map_pose if device_from_map is None else device_from_map @ cam2map_pose
    return np.linalg.inv(Z_UP_FROM_Y_UP) @ device @ CAMERA_FLIP


def test_an_arkit_frame_arrives_as_the_opencv_camera_in_the_map_and_the_message_forgets_its_declaration() -> None:
    msg = frame_to_proto(small_frame(arkit_pose_of(LEVEL_CAM2MAP)), pose_convention="arkit", rgb_encoding="png")
    assert msg.pose_convention == pb.POSE_CONVENTION_ARKIT and not msg.HasField("world_up") and not msg.device_from_map
    decoded = pb.Frame.FromString(msg.SerializeToString())
    frame = frame_from_proto(decoded)
    assert np.allclose(frame.cam2world, LEVEL_CAM2MAP, atol=1e-12)
    assert decoded.pose_convention == pb.POSE_CONVENTION_UNSPECIFIED and not decoded.HasField("world_up")
    assert np.allclose(np.reshape(decoded.cam2world, (4, 4)), LEVEL_CAM2MAP, atol=1e-12)  # what a queue carries on
    assert np.array_equal(frame_from_proto(decoded).cam2world, frame.cam2world)  # read again: the same, not converted twice


def test_world_up_and_device_from_map_travel_and_are_applied() -> None:
    device_from_map = np.array([[0.0, -1.0, 0.0, 2.0], [1.0, 0.0, 0.0, -1.0], [0.0, 0.0, 1.0, 0.1], [0.0, 0.0, 0.0, 1.0]])
    pose = arkit_pose_of(LEVEL_CAM2MAP, device_from_map)
    msg = frame_to_proto(small_frame(pose), pose_convention="arcore", world_up=(0, 2, 0), device_from_map=device_from_map)
    assert (msg.world_up.x, msg.world_up.y, msg.world_up.z) == (0.0, 1.0, 0.0)
    assert list(msg.device_from_map) == device_from_map.reshape(16).tolist()
    assert np.allclose(frame_from_proto(pb.Frame.FromString(msg.SerializeToString())).cam2world, LEVEL_CAM2MAP, atol=1e-12)


def test_a_stored_alignment_applies_to_frames_without_their_own_and_the_maps_up_is_respected() -> None:
    device_from_map = np.eye(4)
    device_from_map[:3, 3] = (1.0, 2.0, 0.0)
    msg = frame_to_proto(small_frame(device_from_map @ LEVEL_CAM2MAP))
    stored = msg.SerializeToString()
    assert np.allclose(frame_from_proto(pb.Frame.FromString(stored), device_from_map=device_from_map).cam2world, LEVEL_CAM2MAP)
    assert np.array_equal(frame_from_proto(pb.Frame.FromString(stored)).cam2world, device_from_map @ LEVEL_CAM2MAP)
    tilted_up = np.array([0.0, 0.6, 0.8])
    arkit = pb.Frame.FromString(frame_to_proto(small_frame(np.eye(4)), pose_convention="arkit").SerializeToString())
    to_map_world(arkit, map_up=tilted_up)
    assert np.allclose(np.reshape(arkit.cam2world, (4, 4)), cam2map(np.eye(4), "arkit", None, tilted_up), atol=0)
    camera_y_down = np.reshape(arkit.cam2world, (4, 4))[:3, 1]
    assert camera_y_down @ tilted_up == pytest.approx(-1.0)  # ARKit's camera up is the map's up


def test_opencv_frames_that_declare_nothing_are_left_as_they_are() -> None:
    msg = frame_to_proto(small_frame(LEVEL_CAM2MAP))
    before = msg.SerializeToString()
    to_map_world(msg, map_up=(0.0, 0.6, 0.8))
    assert msg.SerializeToString() == before and declared_convention(msg) == "opencv"


@pytest.mark.parametrize(
    ("change", "field", "message"),
    [
        (lambda m: setattr(m, "pose_convention", 9), "pose_convention", "POSE_CONVENTION_OPENCV, _ARKIT or _ARCORE"),
        (lambda m: m.world_up.CopyFrom(pb.Vec3()), "world_up", r"a direction \(3 numbers, not all 0\)"),
        (lambda m: m.device_from_map.extend([1.0] * 15), "device_from_map", r"shape \(4, 4\)"),
        (
            lambda m: m.device_from_map.extend([2.0, 0, 0, 0, 0, 2.0, 0, 0, 0, 0, 2.0, 0, 0, 0, 0, 1.0]),
            "device_from_map",
            "orthonormal",
        ),
        (
            lambda m: m.device_from_map.extend([1.0, 0, 0, 0, 0, 0, -1.0, 0, 0, 1.0, 0, 0, 0, 0, 0, 1.0]),
            "device_from_map",
            "tilts up by 90.00 degrees",
        ),
        (lambda m: m.cam2world.__setitem__(0, 3.0), "cam2world", "orthonormal"),
    ],
)
def test_what_is_wrong_in_a_declaration_is_refused_by_name(change: object, field: str, message: str) -> None:
    msg = frame_to_proto(small_frame(np.eye(4)), pose_convention="arkit")
    change(msg)  # type: ignore[operator]  # the parametrized callables
    with pytest.raises(InvalidInput, match=message) as caught:
        frame_from_proto(msg)
    assert caught.value.field == field


def test_the_sdk_side_refuses_a_bad_declaration_before_sending() -> None:
    with pytest.raises(InvalidInput, match="pose_convention: expected one of opencv, arkit, arcore"):
        frame_to_proto(small_frame(np.eye(4)), pose_convention="opengl")  # type: ignore[arg-type]  # wrong on purpose
    with pytest.raises(InvalidInput, match="device_from_map: expected shape"):
        frame_to_proto(small_frame(np.eye(4)), device_from_map=np.eye(3))
