"""A map's object events over HTTP: ``GET /v1/maps/{map_id}/events``, a server-sent event stream.

Why the API polls its store: the stream must work wherever the step runs, in worker threads of this
process (embedded) or in worker processes elsewhere (Redis, Zenoh on or off), and the store is the one
thing every deployment shares. While a map has streams open, one task of this process (``MapWatch``,
shared by all of them) reads when the map last changed (``ObjectStore.map_updated_at``) every ``event_poll_s``
(0.5 s), and only when that moved since its last read of the map, the map's ``list_meta``, which it diffs with
that read by (version, status). Cost per watched map, however many viewers: one small read a tick (on Redis an
HGET), plus, on a tick after the map changed, the whole map's metadata (an HGETALL of its metadata hash, a few
hundred bytes an object: a 1000-object map changing every tick is about 0.5 MB/s of reads per API process
watching it; the store keeps no per-object changed-since view to read less); nothing for maps no one watches.
Exact, as the store writes the mark after the objects it stands for (two commits of one map stamped with the
same float time in different processes would hide the second until the next change). A change
reaches viewers within a tick; changes within one tick are coalesced (a slow viewer gets each object's
latest state, so what a stream holds back is bounded by the map's size, and never goes back in time).

Events, each ``event: NAME`` and one line of JSON ``data:``:

    snapshot        {"objects": [...], "devices": [...], "world2gravity": [9 numbers]}: first, the map as it
                    is, and the rotation taking the map's up (``Params.up``) to +z (row-major 3x3)
    upsert          an object, with the fields of ``GET /v1/maps/{map}/objects`` (``schemas.object_out``)
    removed         {"id": N}: merged, deleted, or (without ``?include=tentative``) no longer confirmed
    device          a device's last accepted frame (``device_out``): for drawing its camera
    device_removed  {"device_id": D}: nothing from it in ``DEVICE_RECENT_S``
    refused         {"detail": ...}: the key was revoked or lost the map; the stream ends

and a ``: keep-alive`` comment when nothing was sent for ``event_heartbeat_s`` (15 s). Like the objects
listing, a stream carries confirmed objects unless asked ``?include=tentative``. It needs a key that may
read the map (or a viewer session's cookie, ``viewer_routes``), looked at again every ``key_cache_s`` (1 s at least: a revoked key's streams end within
about twice that). Streams are shared fairly: at most ``max_event_streams`` are open in a process (503 beyond),
``max_event_streams_per_map`` of one map and ``max_event_streams_per_key`` of one key (with auth none: one client
address; 429 beyond, both with ``Retry-After`` and the limit named), so that one key cannot take every place from
other maps' viewers (one reader key opened the 100 of a process in 0.88 s before). A stream ends when its client goes, or when ``close_event_streams``
is called (``arcloud serve`` calls it as uvicorn begins to shut down: uvicorn waits for open responses
before it ends the app's lifespan, and a stream never ends by itself).

Devices come from this process's ``Ingest.devices`` (``service.devices``): with several API processes,
a stream shows the devices whose frames its own process took.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request
from fastapi.responses import StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials
from starlette.concurrency import run_in_threadpool

from arcloud.core.types import Params
from arcloud.errors import ArcloudError
from arcloud.ports import ObjectMeta, ObjectStore
from arcloud.service.access import VIEWER_COOKIE, Caller, Refused, bearer_scheme, require
from arcloud.service.app import MapId, RuntimeDep, known_map
from arcloud.service.devices import DevicePose, RecentDevices
from arcloud.service.schemas import PROBLEM_RESPONSES, object_out

log = logging.getLogger(__name__)

DEVICE_RECENT_S = 120.0  # a device drawn is one heard from this recently
MIN_ACCESS_RECHECK_S = 1.0  # an open stream's key is looked at again every key_cache_s, at most this often
RETRY_MS = 2000  # what the stream tells clients to wait before reconnecting
REFUSED_RETRY_AFTER_S = 5  # a stream refused for a limit: ask again in this many seconds

Event = tuple[str, dict[str, Any]]  # (name, data)


# --- pure: what changed, and what one stream is told -------------------------------------------------
def diff_objects(before: Mapping[int, ObjectMeta], after: Iterable[ObjectMeta]) -> tuple[list[ObjectMeta], list[int]]:
    """(objects new or changed in ``after``, ids gone from it): a change is a new version or status."""
    now = {o.id: o for o in after}
    changed = [
        o for o in now.values() if (old := before.get(o.id)) is None or old.version != o.version or old.confirmed != o.confirmed
    ]
    return changed, sorted(set(before) - set(now))


def diff_devices(before: Mapping[str, DevicePose], after: Iterable[DevicePose]) -> tuple[list[DevicePose], list[str]]:
    """(devices with a new last frame, device ids no longer recent)."""
    now = {d.device_id: d for d in after}
    changed = [d for d in now.values() if before.get(d.device_id) != d]
    return changed, sorted(set(before) - set(now))


def device_out(pose: DevicePose) -> dict[str, Any]:
    """JSON of a device's last frame: the pose row-major, the intrinsics in pixels of a ``width`` x ``height`` image."""
    fx, fy, cx, cy = pose.intrinsics
    return {
        "device_id": pose.device_id,
        "frame_id": pose.frame_id,
        "cam2world": list(pose.cam2world),
        "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy},
        "width": pose.width,
        "height": pose.height,
        "received_at_s": pose.received_at_s,
    }


def object_event(object_id: int, meta: ObjectMeta | None, shown: set[int], include_tentative: bool) -> Event | None:
    """What a stream that has told its client about ``shown`` says of an object now ``meta`` (None: gone):
    ``upsert`` when the stream shows it, ``removed`` when it showed it and no longer does, else nothing.
    Updates ``shown``."""
    if meta is not None and (include_tentative or meta.confirmed):
        shown.add(object_id)
        return "upsert", object_out(meta)
    if object_id in shown:
        shown.discard(object_id)
        return "removed", {"id": object_id}
    return None


def sse(name: str, data: Mapping[str, Any]) -> str:
    """One server-sent event (the JSON holds no newline, so one ``data:`` line)."""
    return f"event: {name}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


# --- one stream, one watched map, every stream of the process ----------------------------------------
@dataclass(eq=False)
class Subscriber:
    """One open stream: what it still has to tell its client (coalesced per object and device)."""

    include_tentative: bool
    key: str = ""  # whose stream it is (``Caller.bucket``): the per-key limit counts it
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    needs_snapshot: bool = True
    shown: set[int] = field(default_factory=set)
    pending: dict[int, ObjectMeta | None] = field(default_factory=dict)  # object id -> latest state (None: gone)
    pending_devices: dict[str, DevicePose | None] = field(default_factory=dict)
    closed: bool = False

    def offer(
        self, changed: Sequence[ObjectMeta], removed: Sequence[int], devices: Sequence[DevicePose], gone: Sequence[str]
    ) -> None:
        if self.needs_snapshot:
            return  # its snapshot will be the map as it is then
        self.pending.update({o.id: o for o in changed})
        self.pending.update(dict.fromkeys(removed))
        self.pending_devices.update({d.device_id: d for d in devices})
        self.pending_devices.update(dict.fromkeys(gone))
        if changed or removed or devices or gone:
            self.wake.set()

    def take(self, watch: MapWatch) -> list[Event]:
        """The events to send now: the snapshot first (once the map was read), then what changed."""
        if self.needs_snapshot:
            if not watch.ready:
                return []
            self.needs_snapshot = False
            shown = [o for o in watch.objects.values() if self.include_tentative or o.confirmed]
            self.shown = {o.id for o in shown}
            objects = [object_out(o) for o in sorted(shown, key=lambda o: o.id)]
            devices = [device_out(d) for d in watch.devices.values()]
            return [("snapshot", {"objects": objects, "devices": devices, "world2gravity": list(watch.world2gravity)})]
        events = [
            e for i, meta in sorted(self.pending.items()) if (e := object_event(i, meta, self.shown, self.include_tentative))
        ]
        for device_id, pose in sorted(self.pending_devices.items()):
            events.append(("device", device_out(pose)) if pose is not None else ("device_removed", {"device_id": device_id}))
        self.pending.clear()
        self.pending_devices.clear()
        return events


@dataclass(eq=False)
class MapWatch:
    """One map's poller and its streams: reads the map every ``poll_s`` while it has streams."""

    map_id: str
    store: ObjectStore
    devices_of: RecentDevices
    poll_s: float
    world2gravity: tuple[float, ...]  # 9 numbers, row-major: the map's up to +z
    subscribers: set[Subscriber] = field(default_factory=set)
    objects: dict[int, ObjectMeta] = field(default_factory=dict)
    devices: dict[str, DevicePose] = field(default_factory=dict)
    ready: bool = False  # the map was read once
    read_at_mark: float | None = None  # the map's ``map_updated_at`` before the last read of its objects
    task: asyncio.Task[None] | None = None

    async def run(self, on_idle: Callable[[MapWatch], None]) -> None:
        """Poll until no stream is left (then ``on_idle(self)``, in the same step as the check)."""
        failing = False
        try:
            while self.subscribers:
                try:
                    metas = await run_in_threadpool(self.read_if_changed)
                except ArcloudError as exc:  # the store is down: streams stay open, quiet, until it answers
                    if not failing:
                        log.warning("event stream of map %s: reading its objects failed: %s", self.map_id, exc)
                    failing = True
                else:
                    if failing:
                        log.info("event stream of map %s: reading its objects again", self.map_id)
                    failing = False
                    self.apply(metas, self.devices_of.of_map(self.map_id, within_s=DEVICE_RECENT_S))
                if self.subscribers:
                    await asyncio.sleep(self.poll_s)
        except Exception:
            log.exception("event stream of map %s: the watch failed; closing its streams", self.map_id)
            for sub in self.subscribers:
                sub.closed = True
                sub.wake.set()
        finally:
            on_idle(self)

    def read_if_changed(self) -> list[ObjectMeta] | None:
        """The map's objects, or None when it did not change since they were last read (blocking)."""
        mark = self.store.map_updated_at(self.map_id)
        if self.ready and mark is not None and mark == self.read_at_mark:
            return None
        metas = self.store.list_meta(self.map_id)
        self.read_at_mark = mark
        return metas

    def apply(self, metas: Sequence[ObjectMeta] | None, devices: Sequence[DevicePose]) -> None:
        """Take a new read of the map (None: unchanged) and of its devices: tell every stream what changed."""
        changed, removed = diff_objects(self.objects, metas) if metas is not None else ([], [])
        moved, gone = diff_devices(self.devices, devices)
        if metas is not None:
            self.objects = {o.id: o for o in metas}
        self.devices = {d.device_id: d for d in devices}
        first = not self.ready
        self.ready = True
        for sub in self.subscribers:
            if first:
                sub.wake.set()  # its snapshot can go now
            sub.offer(changed, removed, moved, gone)


class EventStreams:
    """Every event stream of one app (one per process): the watched maps, the limits (in all, per map, per key),
    the shutdown. Used on the event loop only (no locks)."""

    def __init__(
        self,
        max_streams: int,
        poll_s: float,
        heartbeat_s: float,
        *,
        max_per_map: int | None = None,
        max_per_key: int | None = None,
    ) -> None:
        self.max_streams = max_streams
        self.max_per_map = max_per_map or max_streams
        self.max_per_key = max_per_key or max_streams
        self.poll_s = poll_s
        self.heartbeat_s = heartbeat_s
        self.watches: dict[str, MapWatch] = {}
        self.open_streams = 0
        self.by_key: Counter[str] = Counter()  # open streams per key (``Caller.bucket``)
        self.closing = False

    def subscribe(
        self,
        map_id: str,
        store: ObjectStore,
        devices: RecentDevices,
        params: Params,
        *,
        include_tentative: bool,
        key: str = "",
    ) -> tuple[MapWatch, Subscriber]:
        """A new stream of ``map_id`` for ``key``; ``HTTPException`` 503 when the process has its maximum open or
        stops, 429 when the map or the key has its maximum open (each naming the limit, with Retry-After)."""
        retry = {"Retry-After": str(REFUSED_RETRY_AFTER_S)}
        if self.closing:
            raise HTTPException(503, "event streams: the service is shutting down", headers=retry)
        if self.open_streams >= self.max_streams:
            raise HTTPException(
                503, f"event streams: {self.max_streams} open in this process, the maximum (max_event_streams)", headers=retry
            )
        watch = self.watches.get(map_id)
        if watch is not None and len(watch.subscribers) >= self.max_per_map:
            raise HTTPException(
                429,
                f"event streams: map {map_id!r} has {len(watch.subscribers)} open in this process, the maximum "
                f"(max_event_streams_per_map {self.max_per_map})",
                headers=retry,
            )
        if self.by_key[key] >= self.max_per_key:
            who = f"key {key.removeprefix('key:')}" if key.startswith("key:") else f"client {key.removeprefix('ip:')}"
            raise HTTPException(
                429,
                f"event streams: {who} has {self.by_key[key]} open in this process, the maximum "
                f"(max_event_streams_per_key {self.max_per_key})",
                headers=retry,
            )
        if watch is None:
            world2gravity = tuple(float(v) for v in params.gravity.world2gravity.reshape(9))
            watch = self.watches[map_id] = MapWatch(map_id, store, devices, self.poll_s, world2gravity)
        sub = Subscriber(include_tentative, key)
        watch.subscribers.add(sub)
        self.by_key[key] += 1
        if watch.task is None:
            watch.task = asyncio.create_task(watch.run(self._forget), name=f"arcloud-events-{map_id}")
        elif watch.ready:
            sub.wake.set()
        self.open_streams += 1
        return watch, sub

    def unsubscribe(self, watch: MapWatch, sub: Subscriber) -> None:
        if sub in watch.subscribers:
            watch.subscribers.discard(sub)
            self.open_streams -= 1
            self.by_key[sub.key] -= 1
            if self.by_key[sub.key] <= 0:
                del self.by_key[sub.key]

    def _forget(self, watch: MapWatch) -> None:
        if self.watches.get(watch.map_id) is watch:
            del self.watches[watch.map_id]
        for sub in list(watch.subscribers):  # the watch failed: its streams end
            self.unsubscribe(watch, sub)

    def close(self) -> None:
        """End every stream now and refuse new ones (503)."""
        self.closing = True
        for watch in list(self.watches.values()):
            for sub in watch.subscribers:
                sub.closed = True
                sub.wake.set()
            if watch.task is not None:
                watch.task.cancel()


def close_event_streams(app: FastAPI) -> None:
    """End the app's open event streams (a server calls it as it begins to shut down)."""
    streams: EventStreams | None = getattr(app.state, "event_streams", None)
    if streams is not None:
        streams.close()


# --- the route ---------------------------------------------------------------------------------------
@contextlib.asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings = app.state.runtime.settings  # the app's own lifespan, run first, started the runtime
    app.state.event_streams = EventStreams(
        settings.max_event_streams,
        settings.event_poll_s,
        settings.event_heartbeat_s,
        max_per_map=settings.max_event_streams_per_map,
        max_per_key=settings.max_event_streams_per_key,
    )
    try:
        yield
    finally:
        app.state.event_streams.close()


router = APIRouter(lifespan=lifespan)


@router.get(
    "/v1/maps/{map_id}/events",
    response_class=StreamingResponse,
    responses={
        **PROBLEM_RESPONSES,
        200: {"content": {"text/event-stream": {}}, "description": "snapshot, then upsert / removed / device events"},
    },
    tags=["objects"],
    summary="The map's object events, live (server-sent events)",
    description="A `snapshot` of the map, then `upsert` and `removed` events as objects change (the fields of the "
    "objects listing), and `device` events with each device's last camera pose. Confirmed objects only, unless "
    "`include=tentative`. Needs the Authorization header, or a viewer session's cookie (POST "
    "/v1/maps/{map_id}/viewer-session): EventSource cannot send headers, and a key never goes in a URL.",
)
async def map_events(
    map_id: MapId,
    request: Request,
    runtime: RuntimeDep,
    caller: Annotated[Caller, Depends(require("read"))],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)],
    include: Annotated[
        Literal["tentative"] | None, Query(description="tentative: tentative objects too", examples=["tentative"])
    ] = None,
) -> StreamingResponse:
    await run_in_threadpool(known_map, runtime, map_id)
    streams: EventStreams = request.app.state.event_streams
    watch, sub = streams.subscribe(
        map_id,
        runtime.store,
        runtime.ingest.devices,
        runtime.params,
        include_tentative=include == "tentative",
        key=caller.bucket,
    )
    token = credentials.credentials if credentials is not None else None
    viewer_session = request.cookies.get(VIEWER_COOKIE)
    address = request.client.host if request.client is not None else "unknown"

    async def still_allowed() -> str | None:
        """None while the key may read the map, else why not."""
        try:
            caller = await run_in_threadpool(runtime.access.authenticate, token, address, viewer_session)
            runtime.access.authorize(caller, "read", map_id)
        except Refused as exc:
            return exc.detail
        except ArcloudError as exc:  # the key store is down: keep streaming, look again later
            log.warning("event stream of map %s: checking its key failed: %s", map_id, exc)
        return None

    async def events() -> AsyncIterator[str]:
        yield f"retry: {RETRY_MS}\n\n"
        last_sent = last_check = time.monotonic()
        checking = runtime.access.keys is not None
        recheck_s = max(MIN_ACCESS_RECHECK_S, runtime.settings.key_cache_s)
        while not sub.closed:
            due = last_sent + streams.heartbeat_s
            if checking:
                due = min(due, last_check + recheck_s)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(sub.wake.wait(), max(0.0, due - time.monotonic()))
            sub.wake.clear()
            if sub.closed:
                return
            now = time.monotonic()
            if checking and now >= last_check + recheck_s:
                last_check = now
                refused = await still_allowed()
                if refused is not None:
                    yield sse("refused", {"detail": refused})
                    return
            sent = sub.take(watch)
            for name, data in sent:
                yield sse(name, data)
            if sent:
                last_sent = now
            elif now - last_sent >= streams.heartbeat_s:
                yield ": keep-alive\n\n"
                last_sent = now

    return EventStreamResponse(events(), on_close=lambda: streams.unsubscribe(watch, sub))


class EventStreamResponse(StreamingResponse):
    """A ``text/event-stream`` response that calls ``on_close`` however it ends (also when its client
    goes before the first event: a generator never started runs no ``finally``)."""

    def __init__(self, content: AsyncIterator[str], *, on_close: Callable[[], None]) -> None:
        super().__init__(
            content, media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
        )
        self.on_close = on_close

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.on_close()


__all__ = [
    "EventStreamResponse",
    "EventStreams",
    "MapWatch",
    "Subscriber",
    "close_event_streams",
    "device_out",
    "diff_devices",
    "diff_objects",
    "object_event",
    "router",
    "sse",
]
