from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RgbEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    RGB_ENCODING_UNSPECIFIED: _ClassVar[RgbEncoding]
    RGB_ENCODING_JPEG: _ClassVar[RgbEncoding]
    RGB_ENCODING_PNG: _ClassVar[RgbEncoding]
    RGB_ENCODING_RAW_RGB8: _ClassVar[RgbEncoding]

class DepthEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DEPTH_ENCODING_UNSPECIFIED: _ClassVar[DepthEncoding]
    DEPTH_ENCODING_PNG: _ClassVar[DepthEncoding]
    DEPTH_ENCODING_RAW_UINT16: _ClassVar[DepthEncoding]
    DEPTH_ENCODING_RAW_FLOAT32: _ClassVar[DepthEncoding]

class PoseConvention(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    POSE_CONVENTION_UNSPECIFIED: _ClassVar[PoseConvention]
    POSE_CONVENTION_OPENCV: _ClassVar[PoseConvention]
    POSE_CONVENTION_ARKIT: _ClassVar[PoseConvention]
    POSE_CONVENTION_ARCORE: _ClassVar[PoseConvention]
RGB_ENCODING_UNSPECIFIED: RgbEncoding
RGB_ENCODING_JPEG: RgbEncoding
RGB_ENCODING_PNG: RgbEncoding
RGB_ENCODING_RAW_RGB8: RgbEncoding
DEPTH_ENCODING_UNSPECIFIED: DepthEncoding
DEPTH_ENCODING_PNG: DepthEncoding
DEPTH_ENCODING_RAW_UINT16: DepthEncoding
DEPTH_ENCODING_RAW_FLOAT32: DepthEncoding
POSE_CONVENTION_UNSPECIFIED: PoseConvention
POSE_CONVENTION_OPENCV: PoseConvention
POSE_CONVENTION_ARKIT: PoseConvention
POSE_CONVENTION_ARCORE: PoseConvention

class Intrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("map_id", "device_id", "frame_id", "timestamp_s", "intrinsics", "cam2world", "rgb", "rgb_encoding", "depth", "depth_encoding", "depth_scale", "width", "height", "pose_convention", "world_up", "device_from_map")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    DEVICE_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_S_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    CAM2WORLD_FIELD_NUMBER: _ClassVar[int]
    RGB_FIELD_NUMBER: _ClassVar[int]
    RGB_ENCODING_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    DEPTH_ENCODING_FIELD_NUMBER: _ClassVar[int]
    DEPTH_SCALE_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    POSE_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    WORLD_UP_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FROM_MAP_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    device_id: str
    frame_id: str
    timestamp_s: float
    intrinsics: Intrinsics
    cam2world: _containers.RepeatedScalarFieldContainer[float]
    rgb: bytes
    rgb_encoding: RgbEncoding
    depth: bytes
    depth_encoding: DepthEncoding
    depth_scale: float
    width: int
    height: int
    pose_convention: PoseConvention
    world_up: Vec3
    device_from_map: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, map_id: _Optional[str] = ..., device_id: _Optional[str] = ..., frame_id: _Optional[str] = ..., timestamp_s: _Optional[float] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., cam2world: _Optional[_Iterable[float]] = ..., rgb: _Optional[bytes] = ..., rgb_encoding: _Optional[_Union[RgbEncoding, str]] = ..., depth: _Optional[bytes] = ..., depth_encoding: _Optional[_Union[DepthEncoding, str]] = ..., depth_scale: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., pose_convention: _Optional[_Union[PoseConvention, str]] = ..., world_up: _Optional[_Union[Vec3, _Mapping]] = ..., device_from_map: _Optional[_Iterable[float]] = ...) -> None: ...

class Vec3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class Box3(_message.Message):
    __slots__ = ("min", "max")
    MIN_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    min: Vec3
    max: Vec3
    def __init__(self, min: _Optional[_Union[Vec3, _Mapping]] = ..., max: _Optional[_Union[Vec3, _Mapping]] = ...) -> None: ...

class OrientedBox(_message.Message):
    __slots__ = ("center", "size", "yaw_rad", "rotation")
    CENTER_FIELD_NUMBER: _ClassVar[int]
    SIZE_FIELD_NUMBER: _ClassVar[int]
    YAW_RAD_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    center: Vec3
    size: Vec3
    yaw_rad: float
    rotation: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, center: _Optional[_Union[Vec3, _Mapping]] = ..., size: _Optional[_Union[Vec3, _Mapping]] = ..., yaw_rad: _Optional[float] = ..., rotation: _Optional[_Iterable[float]] = ...) -> None: ...

class Object(_message.Message):
    __slots__ = ("id", "map_id", "label", "score", "aabb", "obb", "version", "created_at_s", "updated_at_s", "n_voxels", "n_frames", "n_devices", "status")
    class Status(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        STATUS_UNSPECIFIED: _ClassVar[Object.Status]
        STATUS_CONFIRMED: _ClassVar[Object.Status]
        STATUS_TENTATIVE: _ClassVar[Object.Status]
    STATUS_UNSPECIFIED: Object.Status
    STATUS_CONFIRMED: Object.Status
    STATUS_TENTATIVE: Object.Status
    ID_FIELD_NUMBER: _ClassVar[int]
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    AABB_FIELD_NUMBER: _ClassVar[int]
    OBB_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    CREATED_AT_S_FIELD_NUMBER: _ClassVar[int]
    UPDATED_AT_S_FIELD_NUMBER: _ClassVar[int]
    N_VOXELS_FIELD_NUMBER: _ClassVar[int]
    N_FRAMES_FIELD_NUMBER: _ClassVar[int]
    N_DEVICES_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    id: int
    map_id: str
    label: str
    score: float
    aabb: Box3
    obb: OrientedBox
    version: int
    created_at_s: float
    updated_at_s: float
    n_voxels: int
    n_frames: int
    n_devices: int
    status: Object.Status
    def __init__(self, id: _Optional[int] = ..., map_id: _Optional[str] = ..., label: _Optional[str] = ..., score: _Optional[float] = ..., aabb: _Optional[_Union[Box3, _Mapping]] = ..., obb: _Optional[_Union[OrientedBox, _Mapping]] = ..., version: _Optional[int] = ..., created_at_s: _Optional[float] = ..., updated_at_s: _Optional[float] = ..., n_voxels: _Optional[int] = ..., n_frames: _Optional[int] = ..., n_devices: _Optional[int] = ..., status: _Optional[_Union[Object.Status, str]] = ...) -> None: ...

class ObjectEvent(_message.Message):
    __slots__ = ("kind", "map_id", "object_id", "object", "merged_into", "time_s")
    class Kind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        KIND_UNSPECIFIED: _ClassVar[ObjectEvent.Kind]
        KIND_CREATED: _ClassVar[ObjectEvent.Kind]
        KIND_UPDATED: _ClassVar[ObjectEvent.Kind]
        KIND_MERGED: _ClassVar[ObjectEvent.Kind]
        KIND_DELETED: _ClassVar[ObjectEvent.Kind]
        KIND_RETIRED: _ClassVar[ObjectEvent.Kind]
    KIND_UNSPECIFIED: ObjectEvent.Kind
    KIND_CREATED: ObjectEvent.Kind
    KIND_UPDATED: ObjectEvent.Kind
    KIND_MERGED: ObjectEvent.Kind
    KIND_DELETED: ObjectEvent.Kind
    KIND_RETIRED: ObjectEvent.Kind
    KIND_FIELD_NUMBER: _ClassVar[int]
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    OBJECT_ID_FIELD_NUMBER: _ClassVar[int]
    OBJECT_FIELD_NUMBER: _ClassVar[int]
    MERGED_INTO_FIELD_NUMBER: _ClassVar[int]
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    kind: ObjectEvent.Kind
    map_id: str
    object_id: int
    object: Object
    merged_into: int
    time_s: float
    def __init__(self, kind: _Optional[_Union[ObjectEvent.Kind, str]] = ..., map_id: _Optional[str] = ..., object_id: _Optional[int] = ..., object: _Optional[_Union[Object, _Mapping]] = ..., merged_into: _Optional[int] = ..., time_s: _Optional[float] = ...) -> None: ...

class ObjectList(_message.Message):
    __slots__ = ("map_id", "objects")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    objects: _containers.RepeatedCompositeFieldContainer[Object]
    def __init__(self, map_id: _Optional[str] = ..., objects: _Optional[_Iterable[_Union[Object, _Mapping]]] = ...) -> None: ...
