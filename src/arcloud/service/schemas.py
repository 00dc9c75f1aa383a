"""The HTTP API's JSON shapes (pydantic stops here: routes turn core objects into these and back).

Times are ISO 8601 in UTC (``updated_at``), lengths in metres, angles in radians. An object's ``status``
is ``confirmed`` (served by default) or ``tentative`` (shown only when asked for), from the core's
``MapObject.confirmed``.
"""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from arcloud.errors import InvalidInput

Vec3 = tuple[float, float, float]
ObjectStatus = Literal["confirmed", "tentative"]
PoseConventionName = Literal["opencv", "arkit", "arcore"]  # core.conventions.POSE_CONVENTIONS


class FrameAccepted(BaseModel):
    """A frame was validated and queued (or had been before: ``duplicate``); processing is asynchronous."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"map_id": "office", "device_id": "phone-1", "frame_id": "f000042", "status": "queued"}]}
    )

    map_id: str
    device_id: str
    frame_id: str
    status: Literal["queued", "duplicate"]


class Intrinsics(BaseModel):
    model_config = ConfigDict(extra="forbid")

    fx: float
    fy: float
    cx: float
    cy: float


class FrameMeta(BaseModel):
    """The ``meta`` part of a multipart frame upload, read strictly (``frames.parse_meta``): numbers are JSON numbers,
    so ``true`` or ``"1000"`` is refused, not read as 1 or 1000."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "device_id": "phone-1",
                    "frame_id": "f000042",
                    "timestamp": 1.4,
                    "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5},
                    "cam2world": [1, 0, 0, 0.5, 0, 1, 0, 0.2, 0, 0, 1, 1.5, 0, 0, 0, 1],
                    "depth_scale": 1000,
                }
            ]
        },
    )

    device_id: str
    frame_id: str
    timestamp: float = Field(description="seconds")
    intrinsics: Intrinsics
    cam2world: list[float] | list[list[float]] = Field(description="4x4 camera-to-world, row-major: 16 numbers or 4 rows of 4")
    depth_scale: float = Field(1000.0, description="depth units per metre of the 16-bit depth PNG (1000: millimetres)")
    map_id: str | None = Field(None, description="if given, must equal the map id of the path")
    pose_convention: PoseConventionName = Field(
        "opencv",
        description="how cam2world is to be read: opencv (camera x right, y down, z forward), arkit or arcore "
        "(camera x right, y up, z backwards; a y-up world); docs/ar-apps.md",
    )
    world_up: tuple[float, float, float] | None = Field(
        None, description="up in cam2world's world; null: the convention's (opencv: the map's; arkit, arcore: +y)"
    )
    device_from_map: list[float] | list[list[float]] | None = Field(
        None,
        description="rigid 4x4 (16 numbers or 4 rows of 4): map points to this device's gravity-aligned world; "
        "null: the device's stored alignment, if any",
    )

    def flat_pose(self) -> list[float]:
        return _flat(self.cam2world, "meta.cam2world")

    def flat_device_from_map(self) -> list[float]:
        return [] if self.device_from_map is None else _flat(self.device_from_map, "meta.device_from_map")


def _flat(matrix: list[float] | list[list[float]], field: str) -> list[float]:
    """The numbers of a 4x4 matrix given flat or as rows, row by row; rows of other lengths are ``InvalidInput``
    naming ``field`` (flattened, ragged rows made some other matrix of 16 numbers)."""
    if matrix and isinstance(matrix[0], list):
        rows = [row for row in matrix if isinstance(row, list)]
        if len(rows) != len(matrix) or len(rows) != 4 or any(len(row) != 4 for row in rows):
            lengths = [len(row) if isinstance(row, list) else 1 for row in matrix]
            raise InvalidInput(field, "16 numbers (row-major 4x4) or 4 rows of 4", f"rows of {lengths} numbers")
        return [float(v) for row in rows for v in row]
    return [float(v) for v in matrix]  # type: ignore[arg-type]  # not nested: a flat list of numbers


class DeviceAlignmentIn(BaseModel):
    """A device's alignment, to store (``PUT .../devices/{device_id}/alignment``). Strict: numbers are JSON numbers."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        json_schema_extra={"examples": [{"device_from_map": [[0, -1, 0, 2.5], [1, 0, 0, -0.4], [0, 0, 1, 0], [0, 0, 0, 1]]}]},
    )

    device_from_map: list[float] | list[list[float]] = Field(
        description="rigid 4x4 (16 numbers row-major, or 4 rows of 4): map points to the device's world, once its frames "
        "are in the map's axes and up (their convention and world_up applied); a rotation about the map's up and a "
        "translation (a tilt of at most 2 degrees)"
    )

    def flat(self) -> list[float]:
        return _flat(self.device_from_map, "device_from_map")


class DeviceAlignment(BaseModel):
    """A device's stored alignment: applied to every frame of the device that brings none of its own."""

    map_id: str
    device_id: str
    device_from_map: list[list[float]] = Field(description="4 rows of 4: map points to the device's world")


class DeviceAlignmentList(BaseModel):
    map_id: str
    alignments: list[DeviceAlignment] = Field(description="by device id")


class AlignmentDeleted(BaseModel):
    map_id: str
    device_id: str
    deleted: bool = Field(description="false: the device had no alignment")


class Box(BaseModel):
    min: Vec3
    max: Vec3


class OrientedBox(BaseModel):
    center: Vec3
    size: Vec3 = Field(description="full extent along the box's own axes, metres")
    yaw_rad: float = Field(description="rotation about world up (z)")


class Voxels(BaseModel):
    voxel_size_m: float
    centers: list[Vec3]
    weights: list[float]
    colors: list[tuple[int, int, int]] | None = Field(
        None,
        description="each voxel's mean colour, 0-255 (r, g, b), in the order of centers; null: unknown (stored before colours)",
    )


#: An object as the API writes it: ObjectOut's example, and ObjectDetail's with its label votes
OBJECT_EXAMPLE: dict[str, Any] = {
    "id": 7,
    "label": "chair",
    "score": 0.83,
    "aabb": {"min": [1.2, 0.4, 0.0], "max": [1.7, 0.95, 0.92]},
    "obb": {"center": [1.45, 0.67, 0.46], "size": [0.5, 0.52, 0.92], "yaw_rad": 0.31},
    "version": 12,
    "updated_at": "2025-01-01T12:00:00.250000Z",
    "n_voxels": 1380,
    "n_frames": 11,
    "n_devices": 2,
    "status": "confirmed",
}


class ObjectOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [OBJECT_EXAMPLE]})

    id: int
    label: str
    score: float
    aabb: Box | None
    obb: OrientedBox | None
    version: int
    updated_at: str | None = Field(description="ISO 8601, UTC")
    n_voxels: int
    n_frames: int
    n_devices: int
    status: ObjectStatus = Field(
        description="confirmed: served by default; tentative: kept, shown only with ?include=tentative "
        "(a confirmed object may become tentative again)"
    )


class ObjectDetail(ObjectOut):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    **OBJECT_EXAMPLE,
                    "label_votes": {"chair": 412.5, "table": 38.25},
                    "voxels": None,
                }
            ]
        }
    )

    label_votes: dict[str, float] = Field(
        description="the evidence for each label: the detections' label votes (score times how well the view saw the "
        "object, in every voxel a detection covered) summed over the object's voxels, most first; classes without "
        "votes left out. The label is the class most of the object's occupancy votes for, voxel by voxel: usually, "
        "not always, the first here"
    )
    voxels: Voxels | None = Field(None, description="present with ?voxels=true")


class ObjectList(BaseModel):
    objects: list[ObjectOut]
    next_cursor: str | None = Field(
        None, description="with `limit`: pass as `cursor` for the next page; null on the last page (or without `limit`)"
    )


class RetiredOut(ObjectOut):
    retired_at: str | None = Field(description="when it left the map (ISO 8601 UTC)")


class RetiredList(BaseModel):
    objects: list[RetiredOut]


class FrameCounts(BaseModel):
    accepted: int
    processed: int
    failed: int
    pending: int


class MapSummary(BaseModel):
    map_id: str
    objects: int = Field(description="objects of the map, confirmed and tentative")
    frames: FrameCounts
    updated_at: str | None = Field(
        description="when an object of the map last changed (ISO 8601 UTC; when it was opened, before)"
    )


class MapList(BaseModel):
    maps: list[MapSummary]
    next_cursor: str | None = Field(None, description="pass as `cursor` for the next page; null on the last page")


class ObjectCounts(BaseModel):
    confirmed: int = Field(description="objects served by default (of the first max_stats_objects, when truncated)")
    tentative: int = Field(description="objects shown only with ?include=tentative (idem)")
    total: int = Field(description="objects of the map, counted exactly")
    truncated: bool = Field(
        description="the map has more than max_stats_objects objects: confirmed and tentative count the first of them by id"
    )


class FrameState(BaseModel):
    """Where an accepted frame is: ``queued``, ``processing`` (in a worker's hands; on Redis also between
    failed deliveries), ``processed``, ``failed`` (given up on: ``reason`` says why) or ``unknown`` (accepted,
    but none of these: lost, and queued again when posted again)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "map_id": "office",
                    "device_id": "phone-1",
                    "frame_id": "f000042",
                    "status": "failed",
                    "reason": "InvalidInput: ...",
                }
            ]
        }
    )

    map_id: str
    device_id: str
    frame_id: str
    status: Literal["queued", "processing", "processed", "failed", "unknown"]
    reason: str | None = None


class MapStats(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "map_id": "office",
                    "frames": {"accepted": 120, "processed": 118, "failed": 0, "pending": 2},
                    "objects": {"confirmed": 14, "tentative": 31, "total": 45, "truncated": False},
                }
            ]
        }
    )

    map_id: str
    frames: FrameCounts
    objects: ObjectCounts


class MapRestored(BaseModel):
    map_id: str
    restored_objects: int


class MapDeleted(BaseModel):
    map_id: str
    deleted_objects: int


class MapDeletionProgress(BaseModel):
    """``GET /v1/maps/{map}/deletion``: a map's deletion, going on (``deleting``) or ended (``deleted``)."""

    map_id: str
    state: Literal["deleting", "deleted"]
    objects: int = Field(description="objects the map held when its deletion began")
    objects_removed: int
    keys_removed: int = Field(description="store keys removed so far (Redis: objects, index cells, leases; 0 embedded)")
    started_at: str
    updated_at: str = Field(description="when it last went on: a `deleting` one long unchanged stopped (DELETE goes on)")
    finished_at: str | None


class Problem(BaseModel):
    """Every 4xx/5xx body: an RFC 9457 problem, ``application/problem+json`` (``service.problems``): its ``type``
    (a URI reference: ``GET`` it for the type's description) and ``title``, the ``status``, what was wrong
    (``detail``) and the input at fault (``field``, when one is)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "type": "/problems/invalid-input",
                    "title": "Invalid input",
                    "status": 422,
                    "detail": "cam2world: expected a proper rotation (det +1), got a reflection (det -1)",
                    "field": "cam2world",
                }
            ]
        }
    )

    type: str = Field(description="the kind of problem: a URI reference (`/problems/<name>`), or about:blank")
    title: str = Field(description="the type's title, the same for every occurrence")
    status: int = Field(description="the HTTP status")
    detail: str = Field(description="what was wrong, naming the input at fault first when there is one")
    field: str | None = Field(None, description="the input at fault (a parameter, a part, a field of the frame), or null")


class Health(BaseModel):
    status: Literal["ok"]


class ServiceIndex(BaseModel):
    """``GET /``: what this service is, and where its pages are (paths on this service)."""

    service: Literal["arcloud"]
    version: str
    docs: str = Field(description="the API's interactive reference (Swagger UI); `/redoc` the same as ReDoc")
    openapi: str
    viewer: str = Field(description="the web viewer: `?map=MAP`")
    health: str
    ready: str


class Ready(BaseModel):
    """``/readyz`` 200: this process takes and answers requests (each check ``ok``)."""

    status: Literal["ready"]
    checks: dict[str, str]


class NotReady(Problem):
    """``/readyz`` 503: the problem, with the checks (check name -> ``ok`` or what is wrong)."""

    checks: dict[str, str]


class WorkersHealth(BaseModel):
    """``/healthz/workers``: whether the frames accepted get processed. ``live``: the workers taking frames (their
    consumer names); ``expected``: how many this process started (threads or processes), null for workers that
    run elsewhere (then any one is enough)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "status": "ok",
                    "checks": {"redis": "ok", "consumer_group": "ok", "workers": "ok"},
                    "live": ["w1-7"],
                    "expected": None,
                }
            ]
        }
    )

    status: Literal["ok"]
    checks: dict[str, str]
    live: list[str]
    expected: int | None


class WorkersUnavailable(Problem):
    """``/healthz/workers`` 503: the problem, with the checks and the workers of ``WorkersHealth``."""

    checks: dict[str, str]
    live: list[str]
    expected: int | None


class ProblemTypeOut(BaseModel):
    """What a problem ``type`` means (``GET /problems/{name}``)."""

    type: str
    title: str
    statuses: list[int]
    description: str


def iso_time(seconds: float) -> str | None:
    """Unix seconds as ISO 8601 UTC (``...Z``); None for 0 (never)."""
    if not seconds:
        return None
    return dt.datetime.fromtimestamp(seconds, tz=dt.UTC).isoformat().replace("+00:00", "Z")


def _vec(values: Any) -> Vec3:
    x, y, z = (float(v) for v in np.asarray(values, np.float64).reshape(3))
    return (x, y, z)


def object_status(obj: Any) -> ObjectStatus:
    """``confirmed`` or ``tentative``, of a ``MapObject`` or a store's ``ObjectMeta``."""
    return "confirmed" if obj.confirmed else "tentative"


def object_out(obj: Any) -> dict[str, Any]:
    """JSON-ready dict of a ``MapObject`` or a store's ``ObjectMeta``."""
    return {
        "id": int(obj.id),
        "label": obj.label,
        "score": float(obj.score),
        "aabb": None if obj.aabb is None else {"min": _vec(obj.aabb.min), "max": _vec(obj.aabb.max)},
        "obb": None
        if obj.obb is None
        else {"center": _vec(obj.obb.center), "size": _vec(obj.obb.size), "yaw_rad": float(obj.obb.yaw_rad)},
        "version": int(obj.version),
        "updated_at": iso_time(obj.updated_at_s),
        "n_voxels": int(obj.n_voxels),
        "n_frames": int(obj.n_frames),
        "n_devices": len(obj.devices),
        "status": object_status(obj),
    }


PROBLEM_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": Problem, "description": "no token, or not a valid key's (auth keys)"},
    403: {"model": Problem, "description": "the key's role or maps do not allow this"},
    429: {"model": Problem, "description": "over the key's or the map's rate limit (see Retry-After)"},
    404: {"model": Problem, "description": "unknown map or object"},
    409: {"model": Problem, "description": "the map was written under other settings (voxel size, up, ...) than this service's"},
    422: {"model": Problem, "description": "invalid input"},
    503: {"model": Problem, "description": "store unreachable or queue full"},
}
