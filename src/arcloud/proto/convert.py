"""Conversions between the wire messages (``arcloud.v1``) and the core types.

Frames coming in are decoded (JPEG/PNG with OpenCV) and validated by ``arcloud.core.checks.make_frame``;
every problem is an ``InvalidInput`` naming the message field. A frame's pose is read as the message declares
it (``pose_convention``, ``world_up``, ``device_from_map``: ``arcloud.core.conventions``) and becomes the
OpenCV camera's pose in the map's world, in the frame and in the message (``to_map_world``). Objects and events going out become
``Object`` / ``ObjectEvent`` snapshots (no voxels), with their status (``MapObject.confirmed`` ->
``Object.STATUS_CONFIRMED`` or ``STATUS_TENTATIVE``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Mapping, Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Literal, Protocol

import numpy as np

from arcloud.core.checks import check_pose, make_frame
from arcloud.core.conventions import PoseConvention, cam2map, check_convention, check_device_from_map, check_up
from arcloud.core.types import AABB, OBB, Frame, Intrinsics, ObjectEvent
from arcloud.errors import InvalidInput
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb

if TYPE_CHECKING:
    from arcloud.core.types import MapObject

log = logging.getLogger(__name__)

RgbEncodingName = Literal["jpeg", "png", "raw"]
DepthEncodingName = Literal["png", "raw_uint16", "raw_float32"]

RGB_ENCODINGS: dict[str, pb.RgbEncoding] = {
    "jpeg": pb.RGB_ENCODING_JPEG,
    "png": pb.RGB_ENCODING_PNG,
    "raw": pb.RGB_ENCODING_RAW_RGB8,
}
DEPTH_ENCODINGS: dict[str, pb.DepthEncoding] = {
    "png": pb.DEPTH_ENCODING_PNG,
    "raw_uint16": pb.DEPTH_ENCODING_RAW_UINT16,
    "raw_float32": pb.DEPTH_ENCODING_RAW_FLOAT32,
}
POSE_CONVENTIONS: dict[str, pb.PoseConvention] = {
    "opencv": pb.POSE_CONVENTION_OPENCV,
    "arkit": pb.POSE_CONVENTION_ARKIT,
    "arcore": pb.POSE_CONVENTION_ARCORE,
}
EVENT_KINDS: dict[str, pb.ObjectEvent.Kind] = {
    "created": pb.ObjectEvent.KIND_CREATED,
    "updated": pb.ObjectEvent.KIND_UPDATED,
    "merged": pb.ObjectEvent.KIND_MERGED,
    "deleted": pb.ObjectEvent.KIND_DELETED,
    "retired": pb.ObjectEvent.KIND_RETIRED,
}
DEFAULT_DEPTH_SCALE = 1000.0  # depth units per metre for uint16 encodings: millimetres
UINT16_MAX = 65535


class ObjectLike(Protocol):
    """What an ``Object`` snapshot needs: a ``MapObject`` or a store's ``ObjectMeta`` (read-only, as both are frozen)."""

    @property
    def id(self) -> int: ...

    @property
    def label(self) -> str: ...

    @property
    def score(self) -> float: ...

    @property
    def version(self) -> int: ...

    @property
    def n_frames(self) -> int: ...

    @property
    def devices(self) -> frozenset[str]: ...

    @property
    def created_at_s(self) -> float: ...

    @property
    def updated_at_s(self) -> float: ...

    @property
    def aabb(self) -> AABB | None: ...

    @property
    def obb(self) -> OBB | None: ...

    @property
    def confirmed(self) -> bool: ...

    @property
    def n_voxels(self) -> int: ...


# --- frames in --------------------------------------------------------------------------------------
def declared_convention(msg: pb.Frame) -> PoseConvention:
    """The message's ``pose_convention`` by name (``UNSPECIFIED``: ``opencv``, what frames always meant)."""
    if msg.pose_convention == pb.POSE_CONVENTION_UNSPECIFIED:
        return "opencv"
    for name, value in POSE_CONVENTIONS.items():
        if msg.pose_convention == value:
            return check_convention("pose_convention", name)
    raise InvalidInput("pose_convention", "POSE_CONVENTION_OPENCV, _ARKIT or _ARCORE (or none: OpenCV)", msg.pose_convention)


def to_map_world(
    msg: pb.Frame, *, map_up: Sequence[float] | np.ndarray = (0.0, 0.0, 1.0), device_from_map: np.ndarray | None = None
) -> None:
    """The message's pose, read as it declares it (``pose_convention``, ``world_up``, ``device_from_map``; without
    one of its own, ``device_from_map``: the device's stored alignment, checked when it was stored), written back
    as the OpenCV camera's pose in the world of a map whose up is ``map_up`` (``core.conventions.cam2map``), and
    the declaration cleared: whoever reads the message after this reads that pose. Nothing changes for a message
    that declares nothing when no ``device_from_map`` is given. ``InvalidInput`` names the field at fault."""
    declares = msg.pose_convention != pb.POSE_CONVENTION_UNSPECIFIED or msg.HasField("world_up") or len(msg.device_from_map) > 0
    if not declares and device_from_map is None:
        return
    convention = declared_convention(msg)
    _check_pose_length(msg)
    pose = check_pose("cam2world", np.array(msg.cam2world, np.float64).reshape(4, 4))
    world_up = check_up("world_up", (msg.world_up.x, msg.world_up.y, msg.world_up.z)) if msg.HasField("world_up") else None
    if len(msg.device_from_map) > 0:
        device_from_map = check_device_from_map("device_from_map", np.array(msg.device_from_map, np.float64), map_up)
    converted = cam2map(pose, convention, world_up, map_up, device_from_map)
    del msg.cam2world[:]
    msg.cam2world.extend(float(v) for v in converted.reshape(16))
    for name in ("pose_convention", "world_up", "device_from_map"):
        msg.ClearField(name)


def _check_pose_length(msg: pb.Frame) -> None:
    if len(msg.cam2world) != 16:
        raise InvalidInput("cam2world", "16 values (a row-major 4x4 matrix)", f"{len(msg.cam2world)} values")


def frame_from_proto(
    msg: pb.Frame,
    *,
    lossless_to_raw: bool = False,
    map_up: Sequence[float] | np.ndarray = (0.0, 0.0, 1.0),
    device_from_map: np.ndarray | None = None,
) -> Frame:
    """A validated ``Frame`` from a wire ``Frame``; ``InvalidInput`` names the first wrong field. Its pose is
    the OpenCV camera's in the world of a map whose up is ``map_up``: ``to_map_world`` (with the device's stored
    alignment ``device_from_map``, if any) rewrites the message's first.
    ``lossless_to_raw``: once the frame is valid, the message's PNG images are replaced in place by the
    pixels decoded here (``RAW_UINT16`` depth, ``RAW_RGB8`` colour, with width and height), so that whoever
    carries the message on does not decode them again; JPEG stays as uploaded (lossy: never re-encoded)."""
    if not msg.HasField("intrinsics"):
        raise InvalidInput("intrinsics", "fx, fy, cx, cy", "nothing")
    _check_pose_length(msg)
    to_map_world(msg, map_up=map_up, device_from_map=device_from_map)
    rgb = _decode_rgb(msg)
    depth = _decode_depth(msg)
    if msg.depth_encoding == pb.DEPTH_ENCODING_RAW_FLOAT32:
        depth_scale = None if msg.depth_scale in (0.0, 1.0) else msg.depth_scale
    else:
        depth_scale = msg.depth_scale or None
    intr = msg.intrinsics
    frame = make_frame(
        rgb,
        depth,
        Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy),
        np.array(msg.cam2world, np.float64).reshape(4, 4),
        timestamp_s=msg.timestamp_s,
        map_id=msg.map_id,
        device_id=msg.device_id,
        frame_id=msg.frame_id,
        depth_scale=depth_scale,
    )
    if lossless_to_raw:
        _lossless_to_raw(msg, rgb, depth)
    return frame


def _lossless_to_raw(msg: pb.Frame, rgb: np.ndarray, depth: np.ndarray) -> None:
    """``msg``'s PNG images replaced by ``rgb`` and ``depth``, the pixels decoded from them (valid)."""
    if msg.depth_encoding == pb.DEPTH_ENCODING_PNG:
        msg.depth = depth.astype("<u2", copy=False).tobytes()
        msg.depth_encoding = pb.DEPTH_ENCODING_RAW_UINT16
    if msg.rgb_encoding == pb.RGB_ENCODING_PNG:
        msg.rgb = np.ascontiguousarray(rgb, np.uint8).tobytes()
        msg.rgb_encoding = pb.RGB_ENCODING_RAW_RGB8
    msg.height, msg.width = depth.shape


def _cv2() -> ModuleType:
    import cv2  # imported on first use: heavy

    return cv2


def _imdecode(field: str, data: bytes, flags: int, what: str) -> np.ndarray:
    if not data:
        raise InvalidInput(field, what, "0 bytes")
    cv2 = _cv2()
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:
        raise InvalidInput(field, what, f"{len(data)} bytes OpenCV cannot decode") from exc
    if image is None:
        raise InvalidInput(field, what, f"{len(data)} bytes OpenCV cannot decode")
    return image


def _raw(field: str, data: bytes, dtype: str, msg: pb.Frame, channels: int) -> np.ndarray:
    if msg.width == 0 or msg.height == 0:
        raise InvalidInput("width", f"the image size (width and height) for raw {field}", f"{msg.width} x {msg.height}")
    expected = msg.width * msg.height * channels * np.dtype(dtype).itemsize
    if len(data) != expected:
        raise InvalidInput(field, f"{expected} bytes ({msg.width} x {msg.height} x {channels} {dtype})", f"{len(data)} bytes")
    shape = (msg.height, msg.width, channels) if channels > 1 else (msg.height, msg.width)
    return np.frombuffer(data, dtype).reshape(shape).astype(np.dtype(dtype).newbyteorder("="))  # native, writable


def _check_size(field: str, image: np.ndarray, msg: pb.Frame) -> None:
    if msg.width and msg.height and image.shape[:2] != (msg.height, msg.width):
        raise InvalidInput(field, f"the declared size {msg.width} x {msg.height}", f"{image.shape[1]} x {image.shape[0]}")


def _decode_rgb(msg: pb.Frame) -> np.ndarray:
    encoding = msg.rgb_encoding
    if encoding == pb.RGB_ENCODING_RAW_RGB8:
        return _raw("rgb", msg.rgb, "u1", msg, 3)
    if encoding not in (pb.RGB_ENCODING_JPEG, pb.RGB_ENCODING_PNG):
        raise InvalidInput(
            "rgb_encoding",
            "JPEG, PNG or RAW_RGB8",
            pb.RgbEncoding.Name(encoding) if encoding in pb.RgbEncoding.values() else encoding,
        )
    what = "a JPEG image" if encoding == pb.RGB_ENCODING_JPEG else "a PNG image"
    cv2 = _cv2()
    if hasattr(cv2, "IMREAD_COLOR_RGB"):  # OpenCV >= 4.10
        rgb = _imdecode("rgb", msg.rgb, cv2.IMREAD_COLOR_RGB, what)
    else:
        rgb = np.ascontiguousarray(_imdecode("rgb", msg.rgb, cv2.IMREAD_COLOR, what)[..., ::-1])
    _check_size("rgb", rgb, msg)
    return rgb


def _decode_depth(msg: pb.Frame) -> np.ndarray:
    encoding = msg.depth_encoding
    if encoding == pb.DEPTH_ENCODING_RAW_UINT16:
        return _raw("depth", msg.depth, "<u2", msg, 1)
    if encoding == pb.DEPTH_ENCODING_RAW_FLOAT32:
        return _raw("depth", msg.depth, "<f4", msg, 1)
    if encoding != pb.DEPTH_ENCODING_PNG:
        raise InvalidInput(
            "depth_encoding",
            "PNG, RAW_UINT16 or RAW_FLOAT32",
            pb.DepthEncoding.Name(encoding) if encoding in pb.DepthEncoding.values() else encoding,
        )
    depth = _imdecode("depth", msg.depth, _cv2().IMREAD_UNCHANGED, "a single-channel 16-bit PNG")
    if depth.ndim != 2 or depth.dtype != np.uint16:
        channels = 1 if depth.ndim == 2 else depth.shape[2]
        bits = depth.dtype.itemsize * 8
        raise InvalidInput("depth", "a single-channel 16-bit PNG", f"a {bits}-bit PNG with {channels} channel(s)")
    _check_size("depth", depth, msg)
    return depth


# --- frames out -------------------------------------------------------------------------------------
def frame_to_proto(
    frame: Frame | None = None,
    *,
    rgb: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    intrinsics: Intrinsics | Mapping[str, float] | Sequence[float] | None = None,
    cam2world: np.ndarray | None = None,
    timestamp_s: float = 0.0,
    map_id: str = "",
    device_id: str = "",
    frame_id: str = "",
    depth_scale: float = DEFAULT_DEPTH_SCALE,
    rgb_encoding: RgbEncodingName = "jpeg",
    depth_encoding: DepthEncodingName = "png",
    jpeg_quality: int = 90,
    pose_convention: PoseConvention = "opencv",
    world_up: Sequence[float] | np.ndarray | None = None,
    device_from_map: Sequence[float] | np.ndarray | None = None,
) -> pb.Frame:
    """A wire ``Frame`` from a ``Frame``, or from arrays (validated first, as ``make_frame`` does).

    rgb (H, W, 3) uint8 RGB; depth (H, W) float32 metres, or uint16 units with ``depth_scale`` units per
    metre. uint16 encodings (``png``, ``raw_uint16``) quantise metres to 1 / ``depth_scale`` (1 mm by
    default); depths beyond 65535 units become 0 (no depth). ``jpeg`` is lossy, ``png`` and ``raw`` are not.

    How the service is to read ``cam2world`` (``arcloud.core.conventions``): ``pose_convention`` (``opencv``,
    ``arkit`` or ``arcore``), ``world_up`` (3 numbers: up in cam2world's world; None: the convention's) and
    ``device_from_map`` (a rigid 4x4: map points to the device's world; None: the device's stored alignment).
    """
    if rgb_encoding not in RGB_ENCODINGS:
        raise InvalidInput("rgb_encoding", f"one of {sorted(RGB_ENCODINGS)}", rgb_encoding)
    if depth_encoding not in DEPTH_ENCODINGS:
        raise InvalidInput("depth_encoding", f"one of {sorted(DEPTH_ENCODINGS)}", depth_encoding)
    if frame is None:
        if rgb is None or depth is None or intrinsics is None or cam2world is None:
            given = {"rgb": rgb, "depth": depth, "intrinsics": intrinsics, "cam2world": cam2world}
            missing = [name for name, value in given.items() if value is None]
            if len(missing) == len(given):
                raise InvalidInput("frame", "a Frame, or rgb, depth, intrinsics and cam2world", "neither")
            raise InvalidInput(missing[0], "a value with the other arrays (or a Frame)", f"none ({', '.join(missing)} missing)")
        depth_array = np.asarray(depth)
        frame = make_frame(
            rgb,
            depth_array,
            intrinsics,
            cam2world,
            timestamp_s=timestamp_s,
            map_id=map_id,
            device_id=device_id,
            frame_id=frame_id,
            depth_scale=depth_scale if depth_array.dtype == np.uint16 else None,
        )
    elif any(v is not None for v in (rgb, depth, intrinsics, cam2world)):
        raise InvalidInput("frame", "a Frame or arrays, not both", "both")
    height, width = frame.shape
    msg = pb.Frame(
        map_id=frame.map_id,
        device_id=frame.device_id,
        frame_id=frame.frame_id,
        timestamp_s=frame.timestamp_s,
        intrinsics=pb.Intrinsics(fx=frame.intrinsics.fx, fy=frame.intrinsics.fy, cx=frame.intrinsics.cx, cy=frame.intrinsics.cy),
        cam2world=frame.cam2world.reshape(16).tolist(),
        rgb_encoding=RGB_ENCODINGS[rgb_encoding],
        depth_encoding=DEPTH_ENCODINGS[depth_encoding],
        width=width,
        height=height,
    )
    if check_convention("pose_convention", pose_convention) != "opencv":
        msg.pose_convention = POSE_CONVENTIONS[pose_convention]
    if world_up is not None:
        x, y, z = (float(v) for v in check_up("world_up", world_up))
        msg.world_up.CopyFrom(pb.Vec3(x=x, y=y, z=z))
    if device_from_map is not None:
        msg.device_from_map.extend(float(v) for v in check_pose("device_from_map", device_from_map).reshape(16))
    msg.rgb = _encode_rgb(frame.rgb, rgb_encoding, jpeg_quality)
    if depth_encoding == "raw_float32":
        msg.depth = frame.depth_m.astype("<f4").tobytes()
    else:
        units = np.rint(frame.depth_m.astype(np.float64) * depth_scale)
        too_far = units > UINT16_MAX
        if too_far.any():
            log.debug("frame %s: %d depths beyond %d units set to 0", frame.key, int(too_far.sum()), UINT16_MAX)
            units[too_far] = 0
        units16 = units.astype(np.uint16)
        msg.depth_scale = depth_scale
        if depth_encoding == "raw_uint16":
            msg.depth = units16.astype("<u2").tobytes()
        else:
            msg.depth = _imencode(".png", units16, [])
    return msg


def _imencode(ext: str, image: np.ndarray, params: list[int]) -> bytes:
    ok, buffer = _cv2().imencode(ext, image, params)
    if not ok:
        raise InvalidInput(
            "image", f"an image OpenCV can encode as {ext}", f"array of shape {image.shape} and dtype {image.dtype}"
        )
    return buffer.tobytes()


def _encode_rgb(rgb: np.ndarray, encoding: str, jpeg_quality: int) -> bytes:
    if encoding == "raw":
        return np.ascontiguousarray(rgb).tobytes()
    bgr = np.ascontiguousarray(rgb[..., ::-1])  # OpenCV writes BGR
    if encoding == "jpeg":
        return _imencode(".jpg", bgr, [_cv2().IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    return _imencode(".png", bgr, [])


# --- objects and events out -------------------------------------------------------------------------
def _vec3(values: np.ndarray) -> pb.Vec3:
    x, y, z = (float(v) for v in values)
    return pb.Vec3(x=x, y=y, z=z)


def object_to_proto(obj: MapObject | ObjectLike, map_id: str) -> pb.Object:
    """An ``Object`` snapshot (no voxels) of a ``MapObject`` or a store's ``ObjectMeta``."""
    msg = pb.Object(
        id=int(obj.id),
        map_id=map_id,
        label=obj.label,
        score=float(obj.score),
        version=int(obj.version),
        created_at_s=float(obj.created_at_s),
        updated_at_s=float(obj.updated_at_s),
        n_voxels=int(obj.n_voxels),
        n_frames=int(obj.n_frames),
        n_devices=len(obj.devices),
        status=pb.Object.STATUS_CONFIRMED if obj.confirmed else pb.Object.STATUS_TENTATIVE,
    )
    if obj.aabb is not None:
        msg.aabb.CopyFrom(pb.Box3(min=_vec3(obj.aabb.min), max=_vec3(obj.aabb.max)))
    if obj.obb is not None:
        msg.obb.CopyFrom(
            pb.OrientedBox(
                center=_vec3(obj.obb.center),
                size=_vec3(obj.obb.size),
                yaw_rad=float(obj.obb.yaw_rad),
                rotation=np.asarray(obj.obb.rotation, np.float64).reshape(9).tolist(),
            )
        )
    return msg


def objects_to_proto(objects: Iterable[MapObject | ObjectLike], map_id: str) -> pb.ObjectList:
    """An ``ObjectList`` of the objects' snapshots."""
    return pb.ObjectList(map_id=map_id, objects=[object_to_proto(o, map_id) for o in objects])


def event_to_proto(event: ObjectEvent, *, time_s: float | None = None) -> pb.ObjectEvent:
    """An ``ObjectEvent``; ``time_s`` defaults to the object's ``updated_at_s``, else now."""
    if time_s is None:
        time_s = event.object.updated_at_s if event.object is not None and event.object.updated_at_s else time.time()
    msg = pb.ObjectEvent(kind=EVENT_KINDS[event.kind], map_id=event.map_id, object_id=int(event.object_id), time_s=float(time_s))
    if event.object is not None:
        msg.object.CopyFrom(object_to_proto(event.object, event.map_id))
    if event.merged_into is not None:
        msg.merged_into = int(event.merged_into)
    return msg
