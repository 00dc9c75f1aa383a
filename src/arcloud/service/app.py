"""The HTTP API, built by one factory: ``create_app(settings, connect)``.

Nothing happens at import or at ``create_app``: the lifespan calls ``connect`` (the composition root's,
``arcloud.tools.wiring``, which also offers ``create_app`` with the adapters chosen from the settings),
starts the ingest, and stops everything in reverse on shutdown (``runtime``). Routes talk to the ports
(``ObjectStore``) and to the ingest, never to an adapter.

    POST   /v1/maps/{map_id}/frames           protobuf Frame or multipart (meta, rgb, depth) -> 202 queued
    GET    /v1/maps                           the maps the key may read, with counts; ?limit= &cursor=
    GET    /v1/maps/{map_id}/objects          confirmed objects; ?include=tentative &label= &min_score= &bbox=x0,y0,z0,x1,y1,z1 &limit= &cursor=
    GET    /v1/maps/{map_id}/objects/{id}     any object, with its status; ?voxels=true
    DELETE /v1/maps/{map_id}
    GET    /v1/maps/{map_id}/stats
    GET    /v1/maps/{map_id}/retired          objects retired (seen gone), latest first
    GET    /v1/maps/{map_id}/snapshot         the map as one file (admin); PUT it back (?replace=true)
    GET    /v1/maps/{map_id}/export           ?format=json|ply|glb|scannet &include=tentative &color= &voxels=
    GET    /v1/maps/{map_id}/events           server-sent object events (service.event_stream, viewer_routes)
    GET    /v1/maps/{map_id}/frames/{device}/{frame}   where an accepted frame is
    PUT    /v1/maps/{map_id}/devices/{device}/alignment   a device's device_from_map (admin; GET, DELETE: alignment_routes)
    GET    /viewer                            the web viewer (static files, open: they hold no data)
    GET    /                                  open: the service's name and version, and where its pages are
    GET    /healthz  /readyz  /metrics                 open to all (no token): probes and scraping
    GET    /healthz/workers                   whether the workers process what is accepted (apart from /readyz)
    GET    /problems/{name}                   what a problem type means (the ``type`` of every error answer)

Map routes need a key (``service.access``, with auth keys): reading needs a reader, device or admin key
of the map, uploading a device or admin key, deleting an admin key; 401 without a valid token, 403 for a
key of another role or map, 429 (with Retry-After) over the key's or the map's rate.

A map exists once a frame of it was accepted (or a snapshot restored into it); unknown maps and objects answer 404. Listings serve
confirmed objects (``MapObject.confirmed``) unless asked for tentative ones too; every object carries
its ``status``. Errors are RFC 9457 problems (``application/problem+json``: ``type``, ``title``, ``status``,
``detail``, ``field``; built by ``service.problems`` alone): 400 malformed body, 401/403 access, 429 rate limit, 413
body too large, 415 wrong content type, 422 invalid input, 503 store unreachable, queue full or not ready (with
Retry-After), 500 anything unexpected (its traceback logged); ``http_protocol`` answers requests uvicorn cannot parse
the same way.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, MutableMapping
from contextlib import asynccontextmanager, contextmanager
from functools import partial
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, FastAPI, HTTPException, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.routing import Match, Route

from arcloud import __version__
from arcloud.core.checks import MAX_COORDINATE_M, check_id, check_map_id
from arcloud.core.fusion import label_votes
from arcloud.core.types import CLASSES
from arcloud.core.voxels import key_centers
from arcloud.errors import InvalidInput, MapMismatch, StoreUnavailable
from arcloud.ports import MapArchive, MapBeingDeleted, MapDeletion, ObjectMeta, QueueFull
from arcloud.service import frames as frames_in
from arcloud.service.access import Caller, Refused, require
from arcloud.service.exports import EXPORT_RETRY_AFTER_S, MEDIA, ColorBy, ExportFormat, export_from_store, voxel_colors_out
from arcloud.service.logs import bind_log_context
from arcloud.service.map_header import check_map_header, check_not_being_deleted
from arcloud.service.pages import object_page, parse_cursor
from arcloud.service.problems import (
    PROBLEM_TYPES,
    TYPE_PREFIX,
    first_error,
    problem_openapi,
    problem_response,
    validation_location,
    validation_wording,
)
from arcloud.service.runtime import Connect, Runtime, start_runtime, stop_runtime
from arcloud.service.schemas import (
    PROBLEM_RESPONSES,
    FrameAccepted,
    FrameMeta,
    FrameState,
    Health,
    MapDeleted,
    MapDeletionProgress,
    MapList,
    MapRestored,
    MapStats,
    NotReady,
    ObjectDetail,
    ObjectList,
    Problem,
    ProblemTypeOut,
    Ready,
    RetiredList,
    ServiceIndex,
    WorkersHealth,
    WorkersUnavailable,
    iso_time,
    object_out,
)
from arcloud.service.settings import Settings
from arcloud.service.uploads import UploadTicket, admit_upload

log = logging.getLogger(__name__)

Label = Literal[CLASSES]  # type: ignore[valid-type]  # the class names as a Literal, unpacked from the tuple at run time


READY_RETRY_AFTER_S = 5  # a 503 from /readyz or /healthz/workers: ask again in this many seconds


class BodyTooLarge(Exception):
    def __init__(self, limit: int, got: str) -> None:
        self.limit = limit
        super().__init__(f"body: expected at most {limit} bytes, got {got}")


class BodyTooSlow(Exception):
    def __init__(self, timeout_s: float, received: int) -> None:
        super().__init__(
            f"body: expected it whole within {timeout_s:g} s of its first byte (body_timeout_s), got {received} bytes"
        )


class BodyLimit:
    """ASGI middleware refusing bodies over ``max_bytes``: at once from Content-Length, else while
    reading (``BodyTooLarge`` from ``receive``, answered 413 by the app's handler); and bodies still arriving
    ``timeout_s`` after the first read of them (``BodyTooSlow``, answered 408): a client sending a byte at a time
    would hold its upload's place for as long as it liked. Once the body is whole, ``receive`` waits as long as the
    app likes (an event stream waits on it for its client's disconnect)."""

    def __init__(self, app: Callable[..., Awaitable[None]], max_bytes: int, timeout_s: float = 60.0) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s

    async def __call__(
        self,
        scope: MutableMapping[str, Any],
        receive: Callable[[], Awaitable[dict[str, Any]]],
        send: Callable[..., Awaitable[None]],
    ) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None:
            if not declared.isdigit():
                got = declared.decode(errors="replace")
                await problem_response(400, f"content-length: expected a number of bytes, got {got!r}", "content-length")(
                    scope, receive, send
                )
                return
            if int(declared) > self.max_bytes:
                await problem_response(413, str(BodyTooLarge(self.max_bytes, f"{int(declared)} bytes")), "body")(
                    scope, receive, send
                )
                return
        received = 0
        deadline: float | None = None
        whole = False

        async def limited() -> dict[str, Any]:
            nonlocal received, deadline, whole
            if whole:
                return await receive()
            loop = asyncio.get_running_loop()
            deadline = loop.time() + self.timeout_s if deadline is None else deadline
            try:
                message = await asyncio.wait_for(receive(), max(0.0, deadline - loop.time()))
            except TimeoutError:
                raise BodyTooSlow(self.timeout_s, received) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes, f"more than {self.max_bytes} bytes")
            whole = message["type"] != "http.request" or not message.get("more_body", False)
            return message

        await self.app(scope, limited, send)


# --- dependencies ------------------------------------------------------------------------------------
def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
MapId = Annotated[str, Path(description="map id: 1 to 128 letters, digits, '.', '_' or '-'", examples=["office"])]


def known_map(runtime: Runtime, map_id: str, *, same_settings: bool = True) -> str:
    """The map id of a map with accepted frames or restored objects (else 404) written under our settings
    (else 409; not asked when deleting: removing a map reads none of its data)."""
    check_map_id("map_id", map_id)
    if not runtime.ingest.known_map(map_id) and runtime.store.map_header(map_id) is None:
        check_not_being_deleted(runtime.store, map_id)  # 409 rather than 404 while its deletion goes on
        raise HTTPException(404, f"map {map_id!r} not found (no frame of it was accepted, nothing restored into it)")
    if same_settings:
        check_map_header(runtime.store, map_id, runtime.params)
    return map_id


def parse_bbox(text: str) -> tuple[np.ndarray, np.ndarray]:
    """``x0,y0,z0,x1,y1,z1`` -> (lo, hi), each (3,)."""
    try:
        values = np.array([float(v) for v in text.split(",")], np.float64)
    except ValueError:
        raise InvalidInput("bbox", "six numbers x0,y0,z0,x1,y1,z1", repr(text)) from None
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise InvalidInput("bbox", "six finite numbers x0,y0,z0,x1,y1,z1", repr(text))
    if np.any(np.abs(values) > MAX_COORDINATE_M):
        raise InvalidInput("bbox", f"coordinates within {MAX_COORDINATE_M:g} m of the origin", repr(text))
    lo, hi = values[:3], values[3:]
    if np.any(lo > hi):
        raise InvalidInput("bbox", "x0 <= x1, y0 <= y1, z0 <= z1", repr(text))
    return lo, hi


# --- routes ------------------------------------------------------------------------------------------
_META_EXAMPLE = FrameMeta.model_config["json_schema_extra"]["examples"][0]  # type: ignore[index]  # FrameMeta sets a dict of examples
FRAME_BODY_DOC: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "application/x-protobuf": {
                "schema": {
                    "type": "string",
                    "format": "binary",
                    "description": "arcloud.v1.Frame (proto/arcloud/v1/arcloud.proto)",
                },
            },
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["meta", "rgb", "depth"],
                    "properties": {
                        "meta": {
                            "type": "string",
                            "description": "JSON: device_id, frame_id, timestamp (s), intrinsics {fx, fy, cx, cy}, "
                            "cam2world (4x4 row-major), depth_scale (units per metre)",
                            "example": json.dumps(_META_EXAMPLE),
                        },
                        "rgb": {"type": "string", "format": "binary", "description": "JPEG or PNG, same size as the depth"},
                        "depth": {
                            "type": "string",
                            "format": "binary",
                            "description": "single-channel 16-bit PNG of depth units",
                        },
                    },
                }
            },
        },
    }
}

router = APIRouter()


@router.post(
    "/v1/maps/{map_id}/frames",
    status_code=202,
    response_model=FrameAccepted,
    summary="Upload one posed RGB-D frame",
    description="Validated in full, then queued; processing is asynchronous (see the map's stats). Posting a frame "
    "(device_id, frame_id) again answers `duplicate` and queues nothing while it is queued, in progress or processed; "
    "one that failed or was lost is queued again (see its status).",
    responses={
        **PROBLEM_RESPONSES,
        400: {"model": Problem, "description": "malformed multipart body (no boundary, too many parts, ...)"},
        413: {"model": Problem, "description": "body too large"},
        415: {"model": Problem, "description": "wrong content type"},
    },
    openapi_extra=FRAME_BODY_DOC,
    tags=["frames"],
)
async def post_frame(
    map_id: MapId, request: Request, runtime: RuntimeDep, upload: Annotated[UploadTicket, Depends(admit_upload)]
) -> FrameAccepted:
    # ``admit_upload``: access, then 429 before the body is read when the map or key has too many uploads in progress
    check_map_id("map_id", map_id)
    settings = runtime.settings
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media in frames_in.PROTOBUF_MEDIA_TYPES:
        msg = frames_in.parse_message(await request.body())
    elif media == frames_in.MULTIPART_MEDIA_TYPE:
        async with request.form(max_files=3, max_fields=3, max_part_size=settings.max_frame_bytes) as form:
            parts: dict[str, bytes] = {}
            for name, what in (("meta", "JSON"), ("rgb", "a JPEG or PNG image"), ("depth", "a 16-bit PNG image")):
                data = frames_in.form_bytes(form, name, what)
                parts[name] = data if data is not None else await form[name].read()  # type: ignore[union-attr]  # form_bytes gave None: an upload, not a str
        msg = frames_in.message_from_parts(frames_in.parse_meta(parts["meta"]), parts["rgb"], parts["depth"], map_id)
    else:
        raise HTTPException(415, f"content-type: expected application/x-protobuf or multipart/form-data, got {media or 'none'}")
    bind_log_context(**frames_in.valid_ids(msg))  # a refusal's log line says whose frame it was
    frame = await upload.decode(  # holding a decoding slot, maps taking turns (service.uploads)
        partial(
            frames_in.validate_message,
            msg,
            map_id,
            max_pixels=settings.max_frame_pixels,
            queue_decoded_png=settings.queue_decoded_png,
            map_up=runtime.params.up,
            alignments=runtime.alignments,
        )
    )
    bind_log_context(map_id=frame.map_id, device_id=frame.device_id, frame_id=frame.frame_id)  # to the response's log line
    # 409 for other settings; a map's first frame opens it (it is listed from then on)
    await upload.run(partial(check_map_header, runtime.store, map_id, runtime.params, open_new=True))
    accepted = await upload.run(partial(runtime.ingest.submit, frame, msg))
    return FrameAccepted(map_id=accepted.map_id, device_id=accepted.device_id, frame_id=accepted.frame_id, status=accepted.status)


@router.get(
    "/v1/maps/{map_id}/frames/{device_id}/{frame_id}",
    dependencies=[Depends(require("read"))],
    response_model=FrameState,
    response_model_exclude_none=True,
    responses=PROBLEM_RESPONSES,
    tags=["frames"],
    summary="Where an accepted frame is",
    description="`queued`, `processing`, `processed`, `failed` (with the `reason`: a frame failing for a reason that "
    "will not change is failed at once) or `unknown` (accepted, but none of these: posting it again queues it). "
    "404 for a frame never accepted.",
)
def frame_status(map_id: MapId, device_id: str, frame_id: str, runtime: RuntimeDep) -> FrameState:
    check_map_id("map_id", map_id)
    check_id("device_id", device_id)
    check_id("frame_id", frame_id)
    found = runtime.ingest.frame_status(map_id, device_id, frame_id)
    if found is None:
        raise HTTPException(
            404,
            f"frame {device_id}/{frame_id} not found in map {map_id!r} (never accepted, its record expired, or its store "
            "lost it: post it again to queue it)",
        )
    return FrameState(
        map_id=map_id,
        device_id=device_id,
        frame_id=frame_id,
        status=found.status,
        reason=found.reason if found.status == "failed" else None,
    )


@router.get(
    "/v1/maps/{map_id}/objects",
    dependencies=[Depends(require("read"))],
    response_model=ObjectList,
    responses=PROBLEM_RESPONSES,
    tags=["objects"],
    summary="The map's objects",
    description="The served map: confirmed objects only, unless `include=tentative` (then tentative ones too). "
    "A confirmed object may become tentative again, and then leaves the default listing.",
)
def list_objects(
    map_id: MapId,
    runtime: RuntimeDep,
    include: Annotated[
        Literal["tentative"] | None, Query(description="tentative: tentative objects too", examples=["tentative"])
    ] = None,
    label: Annotated[Label | None, Query(description="only this class")] = None,
    min_score: Annotated[float, Query(ge=0.0, le=1.0, description="only objects scoring at least this")] = 0.0,
    bbox: Annotated[
        str | None,
        Query(description="only objects whose voxels' bounds meet this box: x0,y0,z0,x1,y1,z1 (m)", examples=["0,0,0,2,2,2"]),
    ] = None,
    limit: Annotated[int | None, Query(ge=1, le=10_000, description="at most this many objects (then `next_cursor`)")] = None,
    cursor: Annotated[str | None, Query(description="the `next_cursor` of the page before", examples=["17"])] = None,
) -> dict[str, Any]:
    known_map(runtime, map_id)
    after = parse_cursor(cursor)
    if bbox is not None:
        lo, hi = parse_bbox(bbox)
        ids = sorted(runtime.store.query_region(map_id, lo, hi))
    else:
        ids = runtime.store.object_ids(map_id)

    def keep(o: ObjectMeta) -> bool:
        return (include == "tentative" or o.confirmed) and (label is None or o.label == label) and o.score >= min_score

    page, next_id = object_page(runtime.store, map_id, ids, keep, after=after, limit=limit)  # reads what it returns
    return {"objects": [object_out(o) for o in page], "next_cursor": None if next_id is None else str(next_id)}


@router.get(
    "/v1/maps/{map_id}/objects/{object_id}",
    dependencies=[Depends(require("read"))],
    response_model=ObjectDetail,
    responses=PROBLEM_RESPONSES,
    tags=["objects"],
    summary="One object",
    description="Any object of the map, confirmed or tentative (see its `status`), with the votes for each label behind "
    "its `label`: an id a client holds keeps answering while the object exists.",
)
def get_object(
    map_id: MapId,
    object_id: Annotated[int, Path(ge=0)],
    runtime: RuntimeDep,
    voxels: Annotated[bool, Query(description="add voxel centres (m), occupancy weights and mean colours")] = False,
) -> dict[str, Any]:
    known_map(runtime, map_id)
    found = runtime.store.get(map_id, [object_id])  # with its voxels: the label votes are theirs
    if not found:
        raise HTTPException(404, f"object {object_id} not found in map {map_id!r}")
    obj = found[0]
    out = object_out(obj) | {"label_votes": label_votes(obj)}
    if voxels:
        size = runtime.params.voxel_size_m
        out["voxels"] = {
            "voxel_size_m": size,
            "centers": key_centers(obj.keys, size).tolist(),
            "weights": obj.weights.astype(float).tolist(),
            "colors": voxel_colors_out(obj),  # 0-255 (r, g, b) a voxel, None: unknown
        }
    return out


@router.get(
    "/v1/maps/{map_id}/export",
    response_class=Response,
    responses={**PROBLEM_RESPONSES, 200: {"content": {m: {} for m, _ in MEDIA.values()}, "description": "the file"}},
    tags=["maps"],
    summary="The map as a file: JSON, PLY (voxels), GLB (boxes) or ScanNet prediction files (zip)",
    description="The served (confirmed) objects, or every object with `include=tentative`, in the map's world frame "
    "(metres, z up). `json`: the objects list (`voxels=true` adds voxel centres, weights and colours); `ply`: one point "
    "per voxel coloured by object, class or its mean RGB (`color`), with an `object` property; `glb`: one glTF node per object (its oriented box; id, "
    "label, score in `extras`); `scannet`: a zip of ScanNet benchmark prediction files for the map as one scene.",
)
def export(
    map_id: MapId,
    runtime: RuntimeDep,
    caller: Annotated[Caller, Depends(require("read"))],
    fmt: Annotated[ExportFormat, Query(alias="format", description="json, ply, glb or scannet")] = "json",
    include: Annotated[Literal["tentative"] | None, Query(description="tentative: tentative objects too")] = None,
    color: Annotated[
        ColorBy, Query(description="ply: colour points by object, by class or by the voxel's mean RGB (grey: unknown)")
    ] = "object",
    voxels: Annotated[bool, Query(description="json: add each object's voxel centres, weights and colours")] = False,
) -> Response:
    known_map(runtime, map_id)
    with export_place(runtime, caller, "export", "format"):
        body = export_from_store(  # 422 over max_export_objects / max_export_voxels, before any voxel is read
            runtime.store,
            map_id,
            runtime.params,
            fmt,
            include_tentative=include == "tentative",
            color=color,
            voxels=voxels,
            max_voxels=runtime.settings.max_export_voxels,
            max_objects=runtime.settings.max_export_objects,
        )
    media, extension = MEDIA[fmt]
    return Response(body, media_type=media, headers={"Content-Disposition": f'attachment; filename="{map_id}.{extension}"'})


@router.get(
    "/v1/maps/{map_id}/snapshot",
    response_class=Response,
    responses={**PROBLEM_RESPONSES, 200: {"content": {"application/zip": {}}, "description": "the snapshot file"}},
    tags=["maps"],
    summary="The whole map as one file (admin), to restore here or into another service",
    description="Header and every object, voxels included (`arcloud.stores.snapshot`); `PUT` it back, here or "
    "into another deployment (embedded or Redis). Objects keep their ids; their versions start again at 1.",
)
def get_snapshot(map_id: MapId, runtime: RuntimeDep, caller: Annotated[Caller, Depends(require("admin"))]) -> Response:
    known_map(runtime, map_id, same_settings=False)
    archive = _archive(runtime)
    with export_place(runtime, caller, "snapshot", "map_id"):
        body = archive.snapshot(runtime.store, map_id)
    return Response(
        body,
        media_type="application/zip",
        headers={"Content-Disposition": f'attachment; filename="{map_id}.snapshot.zip"'},
    )


@router.put(
    "/v1/maps/{map_id}/snapshot",
    response_model=MapRestored,
    responses=PROBLEM_RESPONSES,
    tags=["maps"],
    summary="Restore a map from a snapshot file (admin)",
    description="Into an empty map, or `replace=true` to delete the map first. The body is the file "
    "(`application/zip`), at most the service's body limit.",
    openapi_extra={
        "requestBody": {"required": True, "content": {"application/zip": {"schema": {"type": "string", "format": "binary"}}}}
    },
)
async def put_snapshot(
    map_id: MapId,
    request: Request,
    runtime: RuntimeDep,
    caller: Annotated[Caller, Depends(require("admin"))],
    replace: Annotated[bool, Query(description="delete the map first")] = False,
) -> MapRestored:
    check_map_id("map_id", map_id)
    archive = _archive(runtime)
    data = await request.body()
    with export_place(runtime, caller, "restore", "map_id"):  # its objects unpacked in memory, as an export's file
        restored = await run_in_threadpool(
            lambda: archive.restore(
                runtime.store,
                map_id,
                data,
                replace=replace,
                params=runtime.params,
                forget=lambda: runtime.ingest.forget_map(map_id),
            )
        )
    log.info("map %s restored from a snapshot: %d objects", map_id, restored)
    return MapRestored(map_id=map_id, restored_objects=restored)


@contextmanager
def export_place(runtime: Runtime, caller: Caller, what: str, field: str) -> Iterator[None]:
    """One of the ``max_exports`` places for a map's file built or read in memory (an export, a snapshot, a
    restore; ``ExportPlaces``); 429 with ``Retry-After`` naming ``what`` when every place is taken, or the caller's
    key holds all it may."""
    key_id = caller.key.id if caller.key is not None else None
    refusal = runtime.exports.take(key_id)
    if refusal is not None:
        raise Refused(
            429,
            f"{what}: {refusal}; retry in {EXPORT_RETRY_AFTER_S} s",
            field,
            {"Retry-After": str(EXPORT_RETRY_AFTER_S)},
        )
    try:
        yield
    finally:
        runtime.exports.give_back(key_id)


def _archive(runtime: Runtime) -> MapArchive:
    if runtime.archive is None:
        raise HTTPException(501, "this service was started without map snapshots")
    return runtime.archive


@router.get(
    "/v1/maps",
    response_model=MapList,
    responses=PROBLEM_RESPONSES,
    tags=["maps"],
    summary="The maps, by id",
    description="Every map the key may read (all maps with auth none), by map id, `limit` a page; each with its "
    "number of objects, frame counts and when an object of it last changed.",
)
def list_maps(
    runtime: RuntimeDep,
    caller: Annotated[Caller, Depends(require("read", listing=True))],
    limit: Annotated[int, Query(ge=1, le=1000, description="at most this many maps (then `next_cursor`)")] = 100,
    cursor: Annotated[str | None, Query(description="the `next_cursor` of the page before")] = None,
) -> dict[str, Any]:
    updated = runtime.store.list_maps()
    readable = sorted(m for m in updated if caller.may("read", m))
    if cursor is not None:
        check_map_id("cursor", cursor)
        readable = [m for m in readable if m > cursor]
    page = readable[:limit]
    summaries = []
    for map_id in page:
        counts = runtime.ingest.counts(map_id)
        summaries.append(
            {
                "map_id": map_id,
                "objects": runtime.store.count_objects(map_id),
                "frames": {
                    "accepted": counts.accepted,
                    "processed": counts.processed,
                    "failed": counts.failed,
                    "pending": counts.pending,
                },
                "updated_at": iso_time(updated[map_id]),
            }
        )
    return {"maps": summaries, "next_cursor": page[-1] if len(readable) > limit else None}


@router.get(
    "/v1/maps/{map_id}/retired",
    dependencies=[Depends(require("read"))],
    response_model=RetiredList,
    responses=PROBLEM_RESPONSES,
    tags=["objects"],
    summary="Objects that left the map",
    description="The map's history: objects the step retired because frames saw their place empty (each as it was "
    "when it left, and when), latest first, kept `ARCLOUD_RETIRED_HISTORY_S`.",
)
def retired_objects(map_id: MapId, runtime: RuntimeDep) -> dict[str, Any]:
    known_map(runtime, map_id)
    return {
        "objects": [{**object_out(r.meta), "retired_at": iso_time(r.retired_at_s)} for r in runtime.store.retired_objects(map_id)]
    }


#: A deletion without progress this long stopped (its process died): DELETE goes on with it instead of 409.
DELETION_STALE_S = 60.0


@router.delete(
    "/v1/maps/{map_id}",
    response_model=MapDeleted,
    dependencies=[Depends(require("admin"))],
    responses=PROBLEM_RESPONSES,
    tags=["maps"],
    summary="Delete a map, its counts and its devices' alignments",
    description="In bounded steps, each recorded: `GET .../deletion` follows it (from another client too). The map's "
    "frames and reads answer 409 (`/problems/map-deleting`) from its start until it is done.",
)
def delete_map(map_id: MapId, runtime: RuntimeDep) -> MapDeleted:
    check_map_id("map_id", map_id)
    going = runtime.store.map_deletion(map_id)
    stopped = going is not None and not going.done and time.time() - going.updated_at_s > DELETION_STALE_S
    if not stopped:  # a stopped deletion goes on whatever is left of the map
        try:
            known_map(runtime, map_id, same_settings=False)  # 409 while another deletion of it goes on
        except HTTPException as exc:  # a map of alignments alone (set before its first frame): they go, else 404
            if exc.status_code != 404 or runtime.alignments is None or not runtime.alignments.of_map(map_id):
                raise
            runtime.alignments.forget_map(map_id)
            log.info("map %s deleted (its devices' alignments; no object)", map_id)
            return MapDeleted(map_id=map_id, deleted_objects=0)
    runtime.ingest.forget_map(map_id)  # first: the map is unknown to reads (409) while its objects go
    removed = runtime.store.delete_map(map_id)
    if runtime.alignments is not None:
        runtime.alignments.forget_map(map_id)
    log.info("map %s deleted (%d objects)", map_id, removed)
    return MapDeleted(map_id=map_id, deleted_objects=removed)


@router.get(
    "/v1/maps/{map_id}/deletion",
    response_model=MapDeletionProgress,
    dependencies=[Depends(require("admin"))],
    responses=PROBLEM_RESPONSES,
    tags=["maps"],
    summary="How far the map's deletion got",
    description="The map's deletion, going on (`deleting`) or ended in the last day (`deleted`); 404 when there is none.",
)
def map_deletion(map_id: MapId, runtime: RuntimeDep) -> dict[str, Any]:
    check_map_id("map_id", map_id)
    deletion = runtime.store.map_deletion(map_id)
    if deletion is None:
        raise HTTPException(404, f"map {map_id!r}: no deletion going on or ended in the last day")
    return deletion_out(deletion)


def deletion_out(deletion: MapDeletion) -> dict[str, Any]:
    return {
        "map_id": deletion.map_id,
        "state": "deleted" if deletion.done else "deleting",
        "objects": deletion.objects,
        "objects_removed": deletion.objects_removed,
        "keys_removed": deletion.keys_removed,
        "started_at": iso_time(deletion.started_at_s),
        "updated_at": iso_time(deletion.updated_at_s),
        "finished_at": iso_time(deletion.finished_at_s) if deletion.finished_at_s is not None else None,
    }


@router.get(
    "/v1/maps/{map_id}/stats",
    dependencies=[Depends(require("read"))],
    response_model=MapStats,
    responses=PROBLEM_RESPONSES,
    tags=["maps"],
    summary="Frames and objects (confirmed and tentative) of a map",
)
def map_stats(map_id: MapId, runtime: RuntimeDep) -> dict[str, Any]:
    known_map(runtime, map_id)
    counts = runtime.ingest.counts(map_id)
    total = runtime.store.count_objects(map_id)
    counted = runtime.store.object_ids(map_id)[: runtime.settings.max_stats_objects]  # a bounded read: ids are small
    confirmed = sum(1 for o in runtime.store.object_meta(map_id, counted) if o.confirmed)
    return {
        "map_id": map_id,
        "frames": {
            "accepted": counts.accepted,
            "processed": counts.processed,
            "failed": counts.failed,
            "pending": counts.pending,
        },
        "objects": {
            "confirmed": confirmed,
            "tentative": len(counted) - confirmed,
            "total": total,
            "truncated": total > len(counted),
        },
    }


@router.get("/", response_model=ServiceIndex, tags=["operations"], summary="What this service is, and where its pages are")
async def index(request: Request) -> dict[str, str]:
    """Open, on the event loop, touching nothing (a new user's first request answered 404)."""
    root = request.scope.get("root_path", "")
    pages = {"docs": "/docs", "openapi": "/openapi.json", "viewer": "/viewer", "health": "/healthz", "ready": "/readyz"}
    return {"service": "arcloud", "version": __version__} | {name: root + path for name, path in pages.items()}


@router.get("/healthz", response_model=Health, tags=["operations"], summary="The process answers")
async def healthz() -> dict[str, str]:
    """On the event loop, touching nothing: answers while a hung store holds every worker thread."""
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=Ready,
    responses={503: {"model": NotReady, "description": "not ready: `checks` says why (with Retry-After)"}},
    tags=["operations"],
    summary="This process takes and answers requests: store reachable, API keys not lost",
    description="Whether this process can accept frames and answer reads, whatever the workers do (their health is "
    "`/healthz/workers`): a worker outage leaves the API ready, so readers keep being served.",
)
def readyz(runtime: RuntimeDep) -> Response:
    checks: dict[str, str] = {}
    try:
        runtime.store.ping()
        checks["store"] = "ok"
    except Exception as exc:  # noqa: BLE001 - readiness reports
        checks["store"] = f"unreachable: {exc}"
    if runtime.access.keys is not None:
        checks["keys"] = runtime.access.keys_health()
    if all(v == "ok" for v in checks.values()):
        return JSONResponse({"status": "ready", "checks": checks})
    wrong = "; ".join(f"{name}: {value}" for name, value in checks.items() if value != "ok")
    return problem_response(
        503,
        f"not ready ({wrong})",
        kind="not-ready",
        headers={"Retry-After": str(READY_RETRY_AFTER_S)},
        extra={"checks": checks},
    )


@router.get(
    "/healthz/workers",
    response_model=WorkersHealth,
    responses={503: {"model": WorkersUnavailable, "description": "frames are not all processed: `checks` says why"}},
    tags=["operations"],
    summary="The workers take the frames accepted (apart from readiness)",
    description="The queue's own checks (Redis: it answers, the consumer group exists) and whether workers process "
    "frames: this process's worker threads or processes alive, each with a fresh heartbeat; workers elsewhere: some "
    "fresh heartbeat. The same as the gauge `arcloud_workers_up`.",
)
def workers_health(runtime: RuntimeDep) -> Response:
    health = runtime.ingest.workers_health()
    if health.ok:
        return JSONResponse({"status": "ok", "checks": health.checks, "live": health.live, "expected": health.expected})
    wrong = "; ".join(f"{name}: {value}" for name, value in health.checks.items() if value != "ok")
    return problem_response(
        503,
        f"workers unavailable ({wrong})",
        kind="workers-unavailable",
        headers={"Retry-After": str(READY_RETRY_AFTER_S)},
        extra={"checks": health.checks, "live": health.live, "expected": health.expected},
    )


@router.get(
    TYPE_PREFIX + "{name}",
    response_model=ProblemTypeOut,
    responses={404: {"model": Problem, "description": "no such problem type"}},
    tags=["operations"],
    summary="What a problem type means (the `type` of an error answer)",
)
async def problem_type(name: Annotated[str, Path(description="the last part of a problem's `type`")]) -> dict[str, Any]:
    found = PROBLEM_TYPES.get(name)
    if found is None:
        raise HTTPException(404, f"problem type {name[:64]!r} not found: expected one of {', '.join(sorted(PROBLEM_TYPES))}")
    return {"type": found.uri, "title": found.title, "statuses": list(found.statuses), "description": found.description}


@router.get("/metrics", tags=["operations"], summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

    body = await run_in_threadpool(generate_latest, request.app.state.metrics_registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)


def matching_routes(app: FastAPI, scope: MutableMapping[str, Any]) -> list[Route]:
    """Every route whose path matches the request's, whatever its method: the app's own routes and ``router``'s,
    which it includes without a prefix (FastAPI keeps an included router's routes apart from the app's)."""
    return [r for r in [*app.router.routes, *router.routes] if isinstance(r, Route) and r.matches(scope)[0] != Match.NONE]


def allowed_methods(app: FastAPI, scope: MutableMapping[str, Any]) -> str:
    """The methods of every route whose path matches the request's, as an Allow header lists them."""
    methods: set[str] = set()
    for route in matching_routes(app, scope):
        methods |= route.methods or set()
    return ", ".join(sorted(methods))


# --- the factory -------------------------------------------------------------------------------------
def create_app(settings: Settings, connect: Connect) -> FastAPI:
    """The service on the adapters ``connect`` gives (called once, by the lifespan, off the event loop)."""
    from arcloud.service.metrics import HttpMetrics, make_registry

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.runtime = await run_in_threadpool(start_runtime, settings, connect)
        try:
            yield
        finally:
            await run_in_threadpool(stop_runtime, app.state.runtime)

    app = FastAPI(
        title="arcloud",
        version=__version__,
        summary="Multi-user 3D object detection in an AR cloud: posed RGB-D frames in, one shared map of 3D objects out.",
        lifespan=lifespan,
        docs_url=None,  # /docs and /redoc: docs_routes, from the package's files (FastAPI's load them from a CDN)
        redoc_url=None,
    )
    app.state.runtime = None
    metrics = make_registry(lambda: app.state.runtime.ingest if app.state.runtime is not None else None)
    app.state.metrics_registry = metrics.registry

    def problem(
        request: Request,
        status: int,
        detail: str,
        field_name: str | None = None,
        headers: dict[str, str] | None = None,
        kind: str | None = None,
    ) -> Response:
        if request.method == "POST" and request.url.path.endswith("/frames"):
            metrics.rejected.labels(status=str(status)).inc()
            # on the upload's access line: why (an operator sees a device's fault); escaped, as it may quote the client
            bind_log_context(refused=detail[:300].encode("unicode_escape").decode("ascii"))
        return problem_response(status, detail, field_name, kind=kind, headers=headers)

    @app.exception_handler(InvalidInput)
    async def invalid_input(request: Request, exc: InvalidInput) -> Response:
        return problem(request, 422, str(exc), exc.field)

    @app.exception_handler(Refused)
    async def refused(request: Request, exc: Refused) -> Response:
        return problem(request, exc.status, exc.detail, exc.field, exc.headers)

    @app.exception_handler(BodyTooSlow)
    async def too_slow(request: Request, exc: BodyTooSlow) -> Response:
        return problem(request, 408, str(exc), "body")

    @app.exception_handler(BodyTooLarge)
    async def too_large(request: Request, exc: BodyTooLarge) -> Response:
        return problem(request, 413, str(exc), "body")

    @app.exception_handler(QueueFull)
    async def queue_full(request: Request, exc: QueueFull) -> Response:
        return problem(request, 503, f"queue full: {exc}", None, {"Retry-After": "1"}, kind="queue-full")

    @app.exception_handler(MapMismatch)
    async def map_mismatch(request: Request, exc: MapMismatch) -> Response:
        return problem(request, 409, str(exc), "map_id")

    @app.exception_handler(MapBeingDeleted)
    async def map_being_deleted(request: Request, exc: MapBeingDeleted) -> Response:
        going = exc.deletion
        detail = (
            f"{exc} (began {iso_time(going.started_at_s)}, last progress {iso_time(going.updated_at_s)}): its frames "
            f"and reads are refused until GET /v1/maps/{going.map_id}/deletion says deleted"
        )
        return problem(request, 409, detail, "map_id", kind="map-deleting")

    @app.exception_handler(StoreUnavailable)
    async def store_down(request: Request, exc: StoreUnavailable) -> Response:
        log.error("store unavailable: %s", exc)
        return problem(request, 503, f"store unavailable: {exc}", None, {"Retry-After": "5"}, kind="store-unavailable")

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        headers = dict(exc.headers or {})
        detail = str(exc.detail)
        request_line = f"{request.method} {request.url.path[:200]}"
        if exc.status_code == 405:  # Starlette's Allow names the first route of the path only (GET of GET and PUT)
            headers["Allow"] = allowed_methods(request.app, request.scope)
            detail = f"{request_line}: method not allowed (the route takes {headers['Allow']})"
        elif exc.status_code == 404 and detail == "Not Found":  # the router's: no route has this path
            detail = f"{request_line}: no such route (the routes: /openapi.json)"
        return problem(request, exc.status_code, detail, None, headers)

    @app.exception_handler(ClientDisconnect)
    async def client_gone(request: Request, exc: ClientDisconnect) -> Response:
        # The client closed the connection mid-body: nobody reads this answer, but the app must give one (else a
        # 500 and a traceback in the log for every upload a client abandons).
        log.info("%s %s: the client disconnected before sending the whole body", request.method, request.url.path)
        return problem(request, 400, "body: the client disconnected before sending all of it", "body")

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception) -> Response:
        # Starlette's last resort answers 500 in plain text; this answers the usual problem, telling nothing of
        # the cause (the server logs the traceback: Starlette raises the exception again after this answer).
        return problem(request, 500, "internal error: the service's log has the details", None)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError) -> Response:
        first = first_error(exc.errors()) if exc.errors() else {"loc": (), "msg": "a valid request"}
        if first.get("type") == "json_invalid":  # not JSON at all: a malformed body, not a wrong value (was 422, field "0")
            ctx = first.get("ctx")
            reason = str(ctx.get("error", "invalid")) if isinstance(ctx, dict) else "invalid"
            return problem(request, 400, f"body: expected a JSON document, got one that is not ({reason})", "body")
        where = validation_location(first["loc"][1:]) or validation_location(first["loc"])
        got = "none" if first.get("type") == "missing" else None if first.get("input") is None else repr(first["input"])
        detail = f"{where}: expected {validation_wording(first)}" + (f", got {got}" if got is not None else "")
        return problem(request, 422, detail, where or None)

    fastapi_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        """FastAPI's schema (made once), with every error answer documented as sent: ``application/problem+json``."""
        if app.openapi_schema is None:
            app.openapi_schema = problem_openapi(fastapi_openapi())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to change the schema

    app.add_middleware(BodyLimit, max_bytes=settings.max_frame_bytes, timeout_s=settings.body_timeout_s)
    # Outside the body limit: its refusals, answered before routing, are counted too (with the route they were for).
    app.add_middleware(HttpMetrics, metrics=metrics, routes=lambda scope: [r.path for r in matching_routes(app, scope)])
    app.include_router(router)
    from arcloud.service import alignment_routes, docs_routes, event_stream, viewer_routes  # here: most import this module

    app.include_router(event_stream.router)
    app.include_router(viewer_routes.router)
    app.include_router(docs_routes.router)
    app.include_router(alignment_routes.router)
    return app


__all__ = ["BodyLimit", "create_app", "parse_bbox"]
