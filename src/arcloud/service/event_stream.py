"""A map's object events over HTTP: ``GET /v1/maps/{map_id}/events``, a server-sent event stream.

The stream tails the map's change log (``core.change``, the store's ``ChangeLog``): every commit appends its
events there in the same atomic write, numbered by the map's version, wherever the step runs (worker threads of
this process, worker processes elsewhere), so the stream needs nothing but the store. While a map has streams
open, one task of this process (``MapWatch``, shared by all of them) reads the log after the version its streams
have every ``event_poll_s`` (0.5 s): on Redis one GET and one XRANGE a tick, however many viewers, and nothing for
maps no one watches. A stream's events carry the map's version, and when its log began, as their SSE ``id``
(``V@B``, ``event_id``; the last event of each read; a bare ``id:`` when a read moved the version but showed this
stream nothing), so a client that connects again with ``Last-Event-ID`` resumes where it was: the entries after
that version, no snapshot, no gap. When the log no longer holds them (trimmed: the store keeps its latest
``change_log_entries``; emptied: the map was deleted, which moves its version on, ``ObjectStore.delete_map``; or
the id is ahead of the log, not of this map's), or the log began at another time than the id's (the store lost the
map: a new log counts from 1 again), the stream says ``reset`` and sends the map as it is. Changes within one tick
are coalesced per object (its latest state), and a state never older than one the stream sent goes out.

Events, each ``event: NAME`` and one line of JSON ``data:``:

    snapshot        {"objects": [...], "devices": [...], "world2gravity": [9 numbers], "version": V}: first (unless
                    resumed), the map as it is at version V (its id), and the rotation taking the map's up
                    (``Params.up``) to +z (row-major 3x3)
    reset           {"reason": ..., "version": V}: ``Last-Event-ID`` (or the stream) is behind what the log keeps,
                    or not of this map's log: drop what you hold; a ``snapshot`` follows
    upsert          an object, with the fields of ``GET /v1/maps/{map}/objects`` (``schemas.object_out``)
    removed         {"id": N}: the object left this stream's view: merged, deleted, retired, or (without
                    ``?include=tentative``) no longer confirmed
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

from arcloud.core.change import ChangesSince
from arcloud.core.types import ObjectMeta, Params
from arcloud.errors import ArcloudError
from arcloud.ports import ObjectStore
from arcloud.service.access import VIEWER_COOKIE, Caller, Refused, bearer_scheme, require
from arcloud.service.app import MapId, RuntimeDep, known_map
from arcloud.service.devices import DevicePose, RecentDevices
from arcloud.service.schemas import PROBLEM_RESPONSES, object_out

log = logging.getLogger(__name__)

DEVICE_RECENT_S = 120.0  # a device drawn is one heard from this recently
MIN_ACCESS_RECHECK_S = 1.0  # an open stream's key is looked at again every key_cache_s, at most this often
RETRY_MS = 2000  # what the stream tells clients to wait before reconnecting
REFUSED_RETRY_AFTER_S = 5  # a stream refused for a limit: ask again in this many seconds

#: Log entries one read of a map's change log takes (a stream further behind catches up over the next ticks).
ENTRIES_PER_READ = 1000

Event = tuple[str, dict[str, Any]]  # (name, data)


# --- pure: what one stream is told -------------------------------------------------------------------
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


@dataclass(slots=True)
class Shown:
    """What a stream told its client of the objects: the version of each it shows, and whether it knows that
    (a stream resumed from ``Last-Event-ID`` does not: its client's view came from an earlier connection)."""

    versions: dict[int, int] = field(default_factory=dict)  # object id -> version shown
    known: bool = True
    hidden: set[int] = field(default_factory=set)  # not known: ids told removed since (told once)


def object_event(object_id: int, meta: ObjectMeta | None, shown: Shown, include_tentative: bool) -> Event | None:
    """What a stream that has told its client ``shown`` says of an object now ``meta`` (None: gone): ``upsert``
    when the stream shows it (a state newer than the one shown), ``removed`` when it may have shown it and no
    longer does, else nothing. Updates ``shown``."""
    if meta is not None and (include_tentative or meta.confirmed):
        if shown.versions.get(object_id, -1) >= meta.version:
            return None  # a state the stream sent already (a snapshot read after the entry)
        shown.versions[object_id] = meta.version
        shown.hidden.discard(object_id)
        return "upsert", object_out(meta)
    if shown.versions.pop(object_id, None) is not None or (not shown.known and object_id not in shown.hidden):
        if not shown.known:
            shown.hidden.add(object_id)
        return "removed", {"id": object_id}
    return None


def sse(name: str, data: Mapping[str, Any], event_id: str | None = None) -> str:
    """One server-sent event (the JSON holds no newline, so one ``data:`` line), with its ``id`` when given."""
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {name}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def event_id(version: int, began: str | None) -> str:
    """A stream's ``id``: the map's version, and the log it counts in (``ChangesSince.began``) when known: ``V@B``."""
    return f"{version}@{began}" if began else str(version)


#: The largest version a ``Last-Event-ID`` may name: versions are the first part of Redis stream ids, and the log is
#: read from the one after it (a larger one made every read of the map's log fail, for all its streams).
MAX_EVENT_ID = 2**63 - 2


def last_event_id(header: str | None) -> tuple[int, str | None] | None:
    """The version a client's ``Last-Event-ID`` names, and the log it counts in (None: an id without one); None when
    it names none (absent, or not one of ours: not ASCII digits, past ``MAX_EVENT_ID``, or a log's time that is not
    ``seconds.microseconds``). One past the map's version is answered by ``reset`` and a snapshot, and so is one of
    another log (the store lost the map since: a new log counts its versions from 1 again)."""
    text, _, began = ("" if header is None else header.strip()).partition("@")
    if not (text.isascii() and text.isdigit()) or len(text) > len(str(MAX_EVENT_ID)):
        return None
    seconds, dot, micro = began.partition(".")
    if began and not (len(began) <= 32 and seconds.isascii() and seconds.isdigit() and dot and micro.isdigit()):
        return None
    version = int(text)
    return (version, began or None) if version <= MAX_EVENT_ID else None


# --- one stream, one watched map, every stream of the process ----------------------------------------
@dataclass(frozen=True, slots=True)
class Snapshot:
    """The map as one read found it: its version (of the log that ``began`` then), then its objects (read after: they
    may hold later changes)."""

    version: int
    objects: dict[int, ObjectMeta]
    began: str = ""


@dataclass(eq=False)
class Subscriber:
    """One open stream: where its client is in the map's change log, and what it still has to tell it
    (coalesced per object and device)."""

    include_tentative: bool
    key: str = ""  # whose stream it is (``Caller.bucket``): the per-key limit counts it
    position: int | None = None  # the map's version its client has; None: it needs a snapshot
    began: str | None = None  # when the log its position counts in began (None or "": not known yet)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    shown: Shown = field(default_factory=Shown)
    reset: dict[str, Any] | None = None  # the ``reset`` to send before its next snapshot
    snapshot: Snapshot | None = None  # the snapshot to send (taken by ``take``)
    sent_id: int | None = None  # the last version sent as an id
    pending: dict[int, ObjectMeta | None] = field(default_factory=dict)  # object id -> latest state (None: gone)
    pending_devices: dict[str, DevicePose | None] = field(default_factory=dict)
    closed: bool = False

    def resume(self, version: int, began: str | None = None) -> None:
        """Its client has the map up to ``version`` of the log that ``began`` then (``Last-Event-ID``), from an
        earlier connection."""
        self.position = self.sent_id = version
        self.began = began
        self.shown = Shown(known=False)

    def other_log(self, got: ChangesSince) -> bool:
        """Whether ``got`` is of another log than the one its position counts in (both known)."""
        return bool(self.began) and bool(got.began) and got.began != self.began

    def start_over(self, snapshot: Snapshot, reason: str | None) -> None:
        """Send ``snapshot`` next (after a ``reset`` saying ``reason``, when one is given)."""
        if reason is not None:
            self.reset = {"reason": reason, "version": snapshot.version}
        self.snapshot = snapshot
        self.position = snapshot.version
        self.began = snapshot.began
        self.shown = Shown()
        self.pending.clear()
        self.pending_devices.clear()
        self.wake.set()

    def offer(self, got: ChangesSince, devices: Sequence[DevicePose], gone: Sequence[str]) -> None:
        """Take what the log holds after its position (its own log's), and what changed of the devices."""
        self.began = got.began or self.began
        for entry in got.entries:
            for event in entry.events:
                self.pending[event.object_id] = event.object if isinstance(event.object, ObjectMeta) else None
        if got.entries:
            self.position = got.entries[-1].version
        self.pending_devices.update({d.device_id: d for d in devices})
        self.pending_devices.update(dict.fromkeys(gone))
        if got.entries or devices or gone:
            self.wake.set()

    def take(self, watch: MapWatch) -> list[str]:
        """The server-sent events to send now: a reset and a snapshot when due, then what changed, the
        last object event carrying the map's version as its id."""
        out: list[str] = []
        if self.reset is not None:
            out.append(sse("reset", self.reset))
            self.reset = None
        if self.snapshot is not None:
            snapshot, self.snapshot = self.snapshot, None
            shown = [o for o in snapshot.objects.values() if self.include_tentative or o.confirmed]
            self.shown = Shown({o.id: o.version for o in shown})
            data = {
                "objects": [object_out(o) for o in sorted(shown, key=lambda o: o.id)],
                "devices": [device_out(d) for d in watch.devices.values()],
                "world2gravity": list(watch.world2gravity),
                "version": snapshot.version,
            }
            out.append(sse("snapshot", data, event_id(snapshot.version, self.began)))
            self.sent_id = snapshot.version
        events = [
            e for i, meta in sorted(self.pending.items()) if (e := object_event(i, meta, self.shown, self.include_tentative))
        ]
        self.pending.clear()
        if self.position is not None and self.position != self.sent_id:
            if events:
                out += [sse(name, data) for name, data in events[:-1]]
                out.append(sse(*events[-1], event_id(self.position, self.began)))
            else:
                out.append(f"id: {event_id(self.position, self.began)}\n\n")  # the client's place moves: nothing shows
            self.sent_id = self.position
        else:
            out += [sse(name, data) for name, data in events]
        for device_id, pose in sorted(self.pending_devices.items()):
            out.append(sse("device", device_out(pose)) if pose is not None else sse("device_removed", {"device_id": device_id}))
        self.pending_devices.clear()
        return out


@dataclass(frozen=True, slots=True)
class LogRead:
    """One tick's read of a map: the log after each position its streams are at, and the map itself when a
    stream needs a snapshot (a new one, or one the log cannot take further)."""

    logs: dict[int, ChangesSince]
    snapshot: Snapshot | None


@dataclass(eq=False)
class MapWatch:
    """One map's reader of its change log and its streams: reads every ``poll_s`` while it has streams."""

    map_id: str
    store: ObjectStore
    devices_of: RecentDevices
    poll_s: float
    world2gravity: tuple[float, ...]  # 9 numbers, row-major: the map's up to +z
    subscribers: set[Subscriber] = field(default_factory=set)
    devices: dict[str, DevicePose] = field(default_factory=dict)
    task: asyncio.Task[None] | None = None

    async def run(self, on_idle: Callable[[MapWatch], None]) -> None:
        """Read until no stream is left (then ``on_idle(self)``, in the same step as the check)."""
        failing = False
        try:
            while self.subscribers:
                places = {(sub.position, sub.began or None) for sub in self.subscribers}
                try:
                    read = await run_in_threadpool(self.read, places)
                except ArcloudError as exc:  # the store is down: streams stay open, quiet, until it answers
                    if not failing:
                        log.warning("event stream of map %s: reading its change log failed: %s", self.map_id, exc)
                    failing = True
                else:
                    if failing:
                        log.info("event stream of map %s: reading its change log again", self.map_id)
                    failing = False
                    self.apply(read, self.devices_of.of_map(self.map_id, within_s=DEVICE_RECENT_S))
                if self.subscribers:
                    await asyncio.sleep(self.poll_s)
        except Exception:
            log.exception("event stream of map %s: the watch failed; closing its streams", self.map_id)
            for sub in self.subscribers:
                sub.closed = True
                sub.wake.set()
        finally:
            on_idle(self)

    def read(self, places: set[tuple[int | None, str | None]]) -> LogRead:
        """The log after each of the streams' ``places`` (position, and when the log it counts in began: None when not
        known; a position None: a stream that needs a snapshot), and the map when a stream needs it (blocking): one
        the log cannot take further, or whose position counts in another log than the store's now."""
        positions = {position for position, _ in places}
        logs = {p: self.store.changes_since(self.map_id, p, ENTRIES_PER_READ) for p in positions if p is not None}
        other_log = any(p is not None and b and logs[p].began and logs[p].began != b for p, b in places)
        snapshot = None
        if None in positions or other_log or not all(got.complete for got in logs.values()):
            now = self.store.changes_since(self.map_id, 0, 0)  # first: the objects read after hold its version
            snapshot = Snapshot(now.version, {o.id: o for o in self.store.list_meta(self.map_id)}, now.began)
        return LogRead(logs, snapshot)

    def apply(self, read: LogRead, devices: Sequence[DevicePose]) -> None:
        """Take one tick's read: tell every stream what changed since its position (or start it over)."""
        moved, gone = diff_devices(self.devices, devices)
        self.devices = {d.device_id: d for d in devices}
        for sub in self.subscribers:
            got = read.logs.get(sub.position) if sub.position is not None else None
            if got is not None and got.complete and not sub.other_log(got):
                sub.offer(got, moved, gone)
            elif read.snapshot is not None and (sub.position is None or got is not None):  # not one that came since
                behind = "the change log no longer holds the changes after the stream's version"
                unknown = "the version is not of this map's change log (ahead of it)"
                again = "the map's change log began again (its store lost the map): the version is of the old one"
                reason = (
                    None
                    if sub.position is None
                    else again
                    if got is not None and sub.other_log(got)
                    else unknown
                    if sub.position > read.snapshot.version
                    else behind
                )
                sub.start_over(read.snapshot, reason)


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
        after: tuple[int, str | None] | None = None,
    ) -> tuple[MapWatch, Subscriber]:
        """A new stream of ``map_id`` for ``key`` (``after``: the map's version its client has, from
        ``Last-Event-ID``; None: it starts from a snapshot); ``HTTPException`` 503 when the process has its maximum open or
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
        if after is not None:
            sub.resume(*after)
        watch.subscribers.add(sub)
        self.by_key[key] += 1
        if watch.task is None:
            watch.task = asyncio.create_task(watch.run(self._forget), name=f"arcloud-events-{map_id}")
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
    "objects listing), and `device` events with each device's last camera pose. Events carry the map's version as "
    "their `id`: a client that connects again with `Last-Event-ID` resumes after it (or is sent `reset` and a new "
    "`snapshot` when the map's change log no longer holds what followed). Confirmed objects only, unless "
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
        after=last_event_id(request.headers.get("last-event-id")),
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
            for text in sent:
                yield text
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
    "Shown",
    "Snapshot",
    "Subscriber",
    "close_event_streams",
    "device_out",
    "diff_devices",
    "last_event_id",
    "object_event",
    "router",
    "sse",
]
