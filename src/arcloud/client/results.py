"""What the SDK returns: the API's JSON answers as frozen dataclasses, one per schema of ``arcloud.service.schemas``
and of the same name (``ObjectOut``, ``MapStats``, ...), and the events of a map's stream (``MapEvent``).

Why a second definition beside the pydantic models: the base install (the client alone) has no pydantic, and the
client may not import the service (``tests/test_layers.py``). ``tests/client/test_client_results.py`` holds the two
together: each dataclass here has the fields of the model of its name. Sequences are tuples, so a result is
immutable all through; fields an answer has and a dataclass lacks (a newer service's) are left out.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any, Literal, TypeVar

from arcloud.errors import ArcloudError

Vec3 = tuple[float, float, float]
T = TypeVar("T")


# --- objects -------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Box:
    min: Vec3
    max: Vec3


@dataclass(frozen=True, slots=True)
class OrientedBox:
    center: Vec3
    size: Vec3  # full extent along the box's own axes, metres
    yaw_rad: float  # rotation about the map's up


@dataclass(frozen=True, slots=True)
class Voxels:
    voxel_size_m: float
    centers: tuple[Vec3, ...]
    weights: tuple[float, ...]
    colors: tuple[tuple[int, int, int], ...] | None = None  # 0-255, in the order of centers; None: unknown


@dataclass(frozen=True, slots=True)
class ObjectOut:
    """An object of the map (``GET /v1/maps/{map}/objects``; ``status`` confirmed or tentative)."""

    id: int
    label: str
    score: float
    aabb: Box | None
    obb: OrientedBox | None
    version: int
    updated_at: str | None  # ISO 8601, UTC
    n_voxels: int
    n_frames: int
    n_devices: int
    status: Literal["confirmed", "tentative"]


@dataclass(frozen=True, slots=True)
class ObjectDetail(ObjectOut):
    """One object (``GET /v1/maps/{map}/objects/{id}``); ``voxels`` with ``voxels=True``."""

    # class -> its detections' votes summed over the voxels, most first (empty from a service before label votes)
    label_votes: Mapping[str, float] = field(default_factory=dict)
    voxels: Voxels | None = None


# --- maps and frames -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class FrameCounts:
    accepted: int
    processed: int
    failed: int
    pending: int


@dataclass(frozen=True, slots=True)
class ObjectCounts:
    """Confirmed and tentative of the first ``max_stats_objects`` objects when ``truncated``; ``total`` exact."""

    confirmed: int
    tentative: int
    total: int
    truncated: bool


@dataclass(frozen=True, slots=True)
class MapSummary:
    """A map of ``GET /v1/maps``: its objects (confirmed and tentative), frames, last change (ISO 8601 UTC)."""

    map_id: str
    objects: int
    frames: FrameCounts
    updated_at: str | None


@dataclass(frozen=True, slots=True)
class MapStats:
    map_id: str
    frames: FrameCounts
    objects: ObjectCounts


@dataclass(frozen=True, slots=True)
class MapDeleted:
    map_id: str
    deleted_objects: int


@dataclass(frozen=True, slots=True)
class MapRestored:
    map_id: str
    restored_objects: int


@dataclass(frozen=True, slots=True)
class FrameAccepted:
    """An upload's answer: ``queued``, or ``duplicate`` (accepted before); processing is asynchronous."""

    map_id: str
    device_id: str
    frame_id: str
    status: Literal["queued", "duplicate"]


@dataclass(frozen=True, slots=True)
class FrameState:
    """Where an accepted frame is: queued, processing, processed, failed (``reason``) or unknown."""

    map_id: str
    device_id: str
    frame_id: str
    status: Literal["queued", "processing", "processed", "failed", "unknown"]
    reason: str | None = None


@dataclass(frozen=True, slots=True)
class DeviceAlignment:
    map_id: str
    device_id: str
    device_from_map: tuple[tuple[float, ...], ...]  # 4 rows of 4: map points to the device's world


@dataclass(frozen=True, slots=True)
class AlignmentDeleted:
    map_id: str
    device_id: str
    deleted: bool  # False: the device had no alignment


# --- the event stream (``GET /v1/maps/{map}/events``) ----------------------------------------------------
@dataclass(frozen=True, slots=True)
class DeviceOut:
    """A device's last accepted frame: its camera pose (4x4 row-major) and intrinsics in pixels of width x height."""

    device_id: str
    frame_id: str
    cam2world: tuple[float, ...]
    intrinsics: Mapping[str, float]  # fx, fy, cx, cy
    width: int
    height: int
    received_at_s: float


@dataclass(frozen=True, slots=True)
class SnapshotEvent:
    """The map as it is when the stream starts (or after a ``ResetEvent``): replaces whatever a viewer held."""

    objects: tuple[ObjectOut, ...]
    devices: tuple[DeviceOut, ...]
    world2gravity: tuple[float, ...]  # 3x3 row-major: the map's up to +z
    version: int = 0  # the map's version it shows (its change log's entry)


@dataclass(frozen=True, slots=True)
class ResetEvent:
    """The stream could not resume where the client was (the map's change log no longer holds what followed: the
    client was away too long, or the map was deleted since): drop what you hold; a ``SnapshotEvent`` follows."""

    reason: str
    version: int


@dataclass(frozen=True, slots=True)
class UpsertEvent:
    object: ObjectOut


@dataclass(frozen=True, slots=True)
class RemovedEvent:
    id: int  # left the stream's view: merged, deleted, retired, or no longer confirmed (without include_tentative)


@dataclass(frozen=True, slots=True)
class DeviceEvent:
    device: DeviceOut


@dataclass(frozen=True, slots=True)
class DeviceRemovedEvent:
    device_id: str


MapEvent = SnapshotEvent | ResetEvent | UpsertEvent | RemovedEvent | DeviceEvent | DeviceRemovedEvent


def map_event(name: str, data: Mapping[str, Any]) -> MapEvent | None:
    """The typed event of a stream's ``event: name`` and its JSON ``data``; None for a name this SDK does not know
    (a newer service's). ``refused`` is no event: the stream's caller raises it."""
    if name == "snapshot":
        return from_json(SnapshotEvent, data)
    if name == "reset":
        return from_json(ResetEvent, data)
    if name == "upsert":
        return UpsertEvent(from_json(ObjectOut, data))
    if name == "removed":
        return from_json(RemovedEvent, data)
    if name == "device":
        return DeviceEvent(from_json(DeviceOut, data))
    if name == "device_removed":
        return from_json(DeviceRemovedEvent, data)
    return None


# --- JSON -> dataclasses ---------------------------------------------------------------------------------
def from_json(cls: type[T], data: Any) -> T:
    """``cls`` (a dataclass of this module) from an answer's JSON ``data``: nested dataclasses, optional ones,
    tuples of them; fields ``data`` lacks take their defaults (none: ``ArcloudError`` naming the type)."""
    if not isinstance(data, Mapping):
        raise ArcloudError(f"{cls.__name__}: expected a JSON object, got {type(data).__name__}")
    hints = _hints(cls)
    values = {f.name: _value(hints[f.name], data[f.name]) for f in fields(cls) if f.name in data}  # type: ignore[arg-type]  # a dataclass, by this module's use
    try:
        return cls(**values)
    except TypeError as exc:  # a field without default missing
        raise ArcloudError(f"{cls.__name__}: the answer lacks a field ({exc})") from exc


_HINTS: dict[type, dict[str, Any]] = {}  # a dataclass -> its fields' types, resolved once


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _value(hint: Any, value: Any) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if value is None:
        return None
    if origin in (types.UnionType, typing.Union):  # X | None: the X
        (inner,) = (a for a in args if a is not type(None))
        return _value(inner, value)
    if is_dataclass(hint):
        return from_json(hint, value)  # type: ignore[arg-type]  # a dataclass type, not an instance
    if origin is tuple:
        item = args[0] if args and (len(args) == 1 or args[1] is Ellipsis) else None
        return tuple(_value(item, v) if item is not None else v for v in value)
    if origin is Mapping:
        return dict(value)
    return value  # a number, a string, a Literal's value


__all__ = [
    "AlignmentDeleted",
    "Box",
    "DeviceAlignment",
    "DeviceEvent",
    "DeviceOut",
    "DeviceRemovedEvent",
    "FrameAccepted",
    "FrameCounts",
    "FrameState",
    "MapDeleted",
    "MapEvent",
    "MapRestored",
    "MapStats",
    "MapSummary",
    "ObjectCounts",
    "ObjectDetail",
    "ObjectOut",
    "OrientedBox",
    "RemovedEvent",
    "ResetEvent",
    "SnapshotEvent",
    "UpsertEvent",
    "Voxels",
    "from_json",
    "map_event",
]
