"""Python SDK of the service for devices and viewers: ``ArcloudClient`` (blocking) and
``AsyncArcloudClient`` (asyncio), both on httpx, with the same methods.

    with ArcloudClient("http://127.0.0.1:8000") as client:
        client.send_frame(frame)                       # a core Frame, or arrays (see send_frame)
        client.wait_until_processed("office", timeout_s=60)   # until this client's frames are done
        for obj in client.iter_objects("office", label="chair", min_score=0.5):   # a page at a time
            print(obj.id, obj.aabb)     # confirmed objects (ObjectOut); include_tentative=True for every object
        for event in client.events("office"):          # SnapshotEvent, then UpsertEvent, RemovedEvent, ...
            ...

Answers are typed (``arcloud.client.results``: frozen dataclasses named as the API's schemas, ``ObjectOut``,
``MapStats``, ...). ``events`` follows the map's server-sent event stream and connects again when the connection
drops or the service restarts, sending the id of the last event it had (``Last-Event-ID``: the map's version), so
the stream goes on from there with nothing missed; when the service can no longer resume it (its change log no
longer holds what followed), a ``ResetEvent`` and a new ``SnapshotEvent`` come, to replace what the caller held.

With API keys (``arcloud keys create``), give ``token=`` or set ``$ARCLOUD_TOKEN``: every request then
carries ``Authorization: Bearer TOKEN``.

Uploads are asynchronous: the service answers 202 and processes the frame later. Each client keeps the
frames it had accepted (``sent``), and ``wait_until_processed(map_id)`` waits until every one of them is
done (asking each frame's status), however many frames other clients sent to the map.

Frames travel as protobuf (``arcloud.v1.Frame``: JPEG colour, 16-bit PNG depth in millimetres by
default). An AR app's poses go as they come, with how to read them: ``send_frame(...,
pose_convention="arkit")`` (or ``"arcore"``; ``world_up=``, ``device_from_map=``: ``arcloud.core.conventions``,
docs/ar-apps.md); ``set_device_alignment`` stores a device's ``device_from_map`` (an admin key's).

Retries (``RetryPolicy``): a request that could not be sent or answered (connect or read error, a
dropped connection, a timeout) and a 429, 502, 503 or 504 answer are tried again, ``max_retries``
times, after an exponential backoff with jitter (``backoff_s`` doubling up to ``max_backoff_s``, times
0.5 to 1.5; ``seed`` makes it repeatable), and at least the server's Retry-After. Only requests safe to
send twice are: GET and DELETE, and frame uploads (the API answers ``duplicate`` for a frame (device,
frame id) it accepted before, and queues nothing). Other refusals raise ``ServiceError`` with the status
and the server's problem (RFC 9457: its ``type``, ``title``, ``detail`` and ``field``); a transport failure
after the last try is httpx's exception, with a note saying how many attempts were made over how long.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import random
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import httpx
import numpy as np

from arcloud.client.results import (
    AlignmentDeleted,
    DeviceAlignment,
    FrameAccepted,
    FrameCounts,
    FrameState,
    MapDeleted,
    MapEvent,
    MapRestored,
    MapStats,
    MapSummary,
    ObjectCounts,
    ObjectDetail,
    ObjectOut,
    from_json,
    map_event,
)
from arcloud.core.types import Frame, Intrinsics
from arcloud.errors import ArcloudError

if TYPE_CHECKING:
    from arcloud.core.conventions import PoseConvention
    from arcloud.events.zenoh import SessionMode, Subscription
    from arcloud.proto.arcloud.v1 import arcloud_pb2
    from arcloud.proto.convert import RgbEncodingName

log = logging.getLogger(__name__)

PROTOBUF = "application/x-protobuf"
TOKEN_ENV = "ARCLOUD_TOKEN"  # the API key token when none is given
DEFAULT_TIMEOUT_S = 30.0
MAPS_PAGE = 500  # maps a page of iter_maps asks for
OBJECTS_PAGE = 500  # objects a page of iter_objects asks for
STREAM_RETRY_S = 2.0  # an event stream connects again after this, until the service says otherwise (``retry:``)

#: Answers worth trying again: rate limited, or the service (or a proxy before it) unavailable for now.
RETRY_STATUSES = frozenset({429, 502, 503, 504})
#: Transport failures worth trying again: no connection, a dropped or reset one, a timeout.
RETRY_ERRORS = (httpx.TimeoutException, httpx.NetworkError, httpx.RemoteProtocolError)
#: Methods safe to send twice (a frame upload is too: ``idempotent=True``).
IDEMPOTENT_METHODS = frozenset({"GET", "HEAD", "OPTIONS", "DELETE"})


def auth_headers(token: str | None) -> dict[str, str]:
    """``Authorization: Bearer`` with ``token``, else ``$ARCLOUD_TOKEN``; none when neither is set."""
    token = token if token is not None else os.environ.get(TOKEN_ENV) or None
    return {"Authorization": f"Bearer {token}"} if token else {}


def alignment_path(map_id: str, device_id: str) -> str:
    """A device's alignment route, the ids percent-encoded."""
    return "/v1/maps/" + "/".join(quote(part, safe="") for part in (map_id, "devices", device_id, "alignment"))


def alignment_body(device_from_map: np.ndarray | Sequence[float] | Sequence[Sequence[float]]) -> dict[str, Any]:
    """The JSON body of a device's alignment: its 4 rows."""
    matrix = np.asarray(device_from_map, np.float64)
    if matrix.size != 16:
        raise ArcloudError(f"device_from_map: expected a 4x4 matrix (16 numbers), got {matrix.size} numbers")
    return {"device_from_map": matrix.reshape(4, 4).tolist()}


def frame_status_path(map_id: str, device_id: str, frame_id: str) -> str:
    """The frame status route, each id percent-encoded (device and frame ids may hold '%', '#', ...)."""
    return "/v1/maps/" + "/".join(quote(part, safe="") for part in (map_id, "frames", device_id, frame_id))


class ServiceError(ArcloudError):
    """The service refused a request: ``status`` (HTTP), ``detail`` (its message), ``field`` (the input
    at fault, when it names one), and from its RFC 9457 problem the ``type`` (a URI reference such as
    ``/problems/queue-full``: what kind of refusal, to branch on) and ``title``; ``problem``: the whole
    document (extension members too, e.g. ``checks`` of ``/readyz``), empty when the answer was not one."""

    def __init__(self, status: int, detail: str, field: str | None = None, *, problem: Mapping[str, Any] | None = None) -> None:
        self.status = status
        self.detail = detail
        self.field = field
        self.problem = dict(problem or {})
        self.type = str(self.problem.get("type") or "about:blank")
        self.title = str(self.problem.get("title") or "")
        super().__init__(f"HTTP {status}: {detail}")


def frame_body(
    frame: Frame | None = None,
    *,
    map_id: str | None = None,
    rgb: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    intrinsics: Intrinsics | Mapping[str, float] | Sequence[float] | None = None,
    cam2world: np.ndarray | None = None,
    timestamp_s: float = 0.0,
    device_id: str = "",
    frame_id: str = "",
    depth_scale: float = 1000.0,
    rgb_encoding: RgbEncodingName = "jpeg",
    pose_convention: PoseConvention = "opencv",
    world_up: Sequence[float] | None = None,
    device_from_map: np.ndarray | None = None,
) -> tuple[str, bytes]:
    """(map id, protobuf bytes) of a frame given as a ``Frame`` or as arrays (validated here first).
    ``pose_convention`` (``opencv``, ``arkit``, ``arcore``), ``world_up`` and ``device_from_map`` say how the
    service is to read the pose (``arcloud.core.conventions``)."""
    from arcloud.proto.convert import frame_to_proto

    if frame is not None:
        msg = frame_to_proto(
            frame,
            rgb_encoding=rgb_encoding,
            depth_scale=depth_scale,
            pose_convention=pose_convention,
            world_up=world_up,
            device_from_map=device_from_map,
        )
    else:
        msg = frame_to_proto(
            rgb=rgb,
            depth=depth,
            intrinsics=intrinsics,
            cam2world=cam2world,
            timestamp_s=timestamp_s,
            map_id=map_id or "",
            device_id=device_id,
            frame_id=frame_id,
            depth_scale=depth_scale,
            rgb_encoding=rgb_encoding,
            pose_convention=pose_convention,
            world_up=world_up,
            device_from_map=device_from_map,
        )
    target = map_id or msg.map_id
    if not target:
        raise ArcloudError("send_frame: no map id (give map_id or a frame with one)")
    return target, msg.SerializeToString()


def include_query(include_tentative: bool) -> dict[str, str]:
    return {"include": "tentative"} if include_tentative else {}


def object_query(
    label: str | None, min_score: float | None, bbox: Sequence[float] | None, include_tentative: bool = False
) -> dict[str, str]:
    params = include_query(include_tentative)
    if label is not None:
        params["label"] = label
    if min_score is not None:
        params["min_score"] = repr(float(min_score))
    if bbox is not None:
        if len(bbox) != 6:
            raise ArcloudError(f"bbox: expected 6 numbers x0,y0,z0,x1,y1,z1, got {len(bbox)}")
        params["bbox"] = ",".join(repr(float(v)) for v in bbox)
    return params


def export_query(fmt: str, options: Mapping[str, str | bool]) -> dict[str, str]:
    return {"format": fmt, **{k: (str(v).lower() if isinstance(v, bool) else v) for k, v in options.items()}}


def page_query(page_size: int, cursor: str | None) -> dict[str, str]:
    return {"limit": str(page_size), **({"cursor": cursor} if cursor is not None else {})}


def checked(response: httpx.Response) -> dict[str, Any]:
    """The JSON object of a 2xx response; ``ServiceError`` otherwise."""
    if response.is_success:
        body: dict[str, Any] = response.json()
        return body
    raise service_error(response)


def checked_content(response: httpx.Response) -> bytes:
    """The body of a 2xx response (a file); ``ServiceError`` otherwise."""
    if response.is_success:
        return response.content
    raise service_error(response)


def service_error(response: httpx.Response) -> ServiceError:
    """The ``ServiceError`` of a refusal: its problem (``application/problem+json``; the ``{"detail", "field"}``
    of services before problems, a JSON object all the same), or the start of its text (a proxy's page)."""
    try:
        body = response.json()
    except ValueError:
        body = None
    if not isinstance(body, dict):
        return ServiceError(response.status_code, response.text[:500])
    field = body.get("field")
    detail = body.get("detail") or body.get("title") or response.reason_phrase
    return ServiceError(response.status_code, str(detail), field if isinstance(field, str) else None, problem=body)


def retry_after_s(response: httpx.Response, default_s: float = 1.0) -> float:
    try:
        return max(0.0, float(response.headers.get("retry-after", default_s)))
    except ValueError:
        return default_s


def backoff_s(attempt: int, *, base_s: float, max_s: float, jitter: float) -> float:
    """The wait before retry ``attempt`` (0: the first): ``base_s * 2**attempt`` capped at ``max_s``,
    times ``0.5 + jitter`` (``jitter`` in [0, 1))."""
    return min(max_s, base_s * 2.0**attempt) * (0.5 + jitter)


class RetryPolicy:
    """When and how long the clients wait to try a request again (see the module's docstring).
    ``seed``: the jitter's generator, for repeatable waits (None: seeded from the OS)."""

    def __init__(
        self, max_retries: int = 5, *, backoff_s: float = 0.25, max_backoff_s: float = 10.0, seed: int | None = None
    ) -> None:
        if max_retries < 0 or backoff_s < 0 or max_backoff_s < 0:
            raise ArcloudError(
                f"retries: expected max_retries, backoff_s, max_backoff_s >= 0, got {max_retries}, {backoff_s}, {max_backoff_s}"
            )
        self.max_retries = max_retries
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self._rng = random.Random(seed)

    def wait_s(self, attempt: int, response: httpx.Response | None = None) -> float:
        """How long to wait before retry ``attempt`` (0: the first): the backoff, or the answer's
        Retry-After when longer."""
        wait = backoff_s(attempt, base_s=self.backoff_s, max_s=self.max_backoff_s, jitter=self._rng.random())
        if response is not None and "retry-after" in response.headers:
            wait = max(wait, retry_after_s(response))
        return wait

    def retryable(self, method: str, idempotent: bool) -> bool:
        return self.max_retries > 0 and (idempotent or method.upper() in IDEMPOTENT_METHODS)


def _next_wait_s(
    retry: RetryPolicy, method: str, path: str, outcome: httpx.Response | Exception, attempt: int, retries: int, started: float
) -> float | None:
    """After attempt ``attempt`` (0-based) of ``retries + 1``: the seconds to wait before the next one, or None
    when ``outcome`` (a response) is final. A transport error on the last attempt is raised, with a note
    saying how many attempts over how long. Shared by the blocking and the async client."""
    if isinstance(outcome, Exception):
        if attempt == retries:
            outcome.add_note(
                f"arcloud: {method} {path}: no answer after {attempt + 1} attempts over {time.monotonic() - started:.1f} s"
            )
            raise outcome
        wait_s = retry.wait_s(attempt)
        what = type(outcome).__name__
    else:
        if outcome.status_code not in RETRY_STATUSES or attempt == retries:
            return None
        wait_s = retry.wait_s(attempt, outcome)
        what = f"HTTP {outcome.status_code}"
    log.info("%s %s: %s; trying again in %.2f s (%d/%d)", method, path, what, wait_s, attempt + 1, retries)
    return wait_s


class EventStream:
    """One map's event stream across its connections, shared by the blocking and the async client: reads the
    server-sent events of each connection's lines (``feed``) and says how long to wait before the next
    connection (``wait_s``). A connection that gave an event resets the count of failures; ``max_retries``
    failures in a row (refusals 429, 502, 503, 504, transport errors, streams ended before an event) raise."""

    def __init__(self, retry: RetryPolicy, path: str, *, wait_for_map: bool = False) -> None:
        self.retry = retry
        self.path = path
        self.wait_for_map = wait_for_map  # a 404 (no such map yet): look again every retry_s, without end
        self.retry_s = STREAM_RETRY_S
        self.failures = 0
        self.started = time.monotonic()
        self.last_event_id: str | None = None  # the id of the last event taken: where a new connection resumes
        self.connected()

    def connected(self) -> None:
        """A new connection: what the last one left half-read is dropped."""
        self.name = ""
        self.data: list[str] = []
        self.event_id: str | None = None

    def resume_headers(self) -> dict[str, str]:
        """``Last-Event-ID`` of the last event taken, when there is one."""
        return {"Last-Event-ID": self.last_event_id} if self.last_event_id is not None else {}

    def feed(self, line: str) -> MapEvent | None:
        """Take one line of the stream; the event a blank line completes. A ``refused`` event (the key lost the
        map) raises ``ServiceError`` 403."""
        if line.startswith(":"):  # a comment: ``: keep-alive``
            return None
        if line:
            field, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if field == "event":
                self.name = value
            elif field == "data":
                self.data.append(value)
            elif field == "id" and "\0" not in value:
                self.event_id = value
            elif field == "retry" and value.isdigit():
                self.retry_s = int(value) / 1000
            return None
        name, text = self.name, "\n".join(self.data)
        if self.event_id is not None:  # taken with its event (a bare id too: the client's place moved)
            self.last_event_id = self.event_id
        self.connected()
        if not text:
            return None
        data = json.loads(text)
        if name == "refused":
            raise ServiceError(403, str(data.get("detail")), problem={"status": 403, **data})
        event = map_event(name, data)
        if event is not None:
            self.failures = 0
        return event

    def wait_s(self, outcome: httpx.Response | Exception | None) -> float:
        """Seconds to wait before connecting again after a connection ended with ``outcome``: a refusal (its
        response), a transport error, or None (the service ended the stream: it restarts, or dropped us). Raises
        ``ServiceError`` for a refusal not worth trying again, and the error after ``max_retries`` failures."""
        if isinstance(outcome, httpx.Response) and outcome.status_code == 404 and self.wait_for_map and _no_map_yet(outcome):
            self.failures = 0
            log.info("GET %s: no such map yet; looking again in %.2f s", self.path, self.retry_s)
            return self.retry_s
        attempt = self.failures
        self.failures += 1
        if isinstance(outcome, httpx.Response):
            if outcome.status_code not in RETRY_STATUSES or attempt >= self.retry.max_retries:
                raise service_error(outcome)
            wait_s = self.retry.wait_s(attempt, outcome)
        else:
            if attempt >= self.retry.max_retries:
                if outcome is not None:
                    outcome.add_note(f"arcloud: GET {self.path}: {attempt + 1} connections failed in a row")
                    raise outcome
                raise ArcloudError(f"GET {self.path}: the service ended the stream {attempt + 1} times in a row")
            wait_s = max(self.retry_s, self.retry.wait_s(attempt))
        what = f"HTTP {outcome.status_code}" if isinstance(outcome, httpx.Response) else type(outcome).__name__
        log.info("GET %s: the stream ended (%s); connecting again in %.2f s", self.path, what, wait_s)
        return wait_s


def _no_map_yet(response: httpx.Response) -> bool:
    """Whether a 404 says the map has no frame yet (``map 'M' not found``), not that no route is there (a wrong base
    URL: a review saw ``wait_for_map`` wait for ever on one)."""
    try:
        detail = str(response.json().get("detail", ""))
    except ValueError:
        return False
    return detail.startswith("map ") and " not found" in detail


def unknown_map_stats(map_id: str) -> MapStats:
    """The stats of a map the service does not know: nothing counted."""
    return MapStats(
        map_id,
        FrameCounts(accepted=0, processed=0, failed=0, pending=0),
        ObjectCounts(confirmed=0, tentative=0, total=0, truncated=False),
    )


def _map_done(stats: MapStats, n_frames: int) -> bool:
    return stats.frames.processed + stats.frames.failed >= n_frames


#: A frame status (``GET .../frames/{device}/{frame}``) -> its outcome for ``wait_until_processed``; None: not done.
OUTCOMES: dict[str, str | None] = {
    "queued": None,
    "processing": None,
    "processed": "processed",
    "failed": "failed",
    "unknown": "lost",
}


class SentFrames:
    """The frames a client had accepted (202), by map, until it sees each done: ``processed``, ``failed`` or
    ``lost`` (the service no longer knows it: 404 or ``unknown``, e.g. a Redis that lost its data). Counts are
    of uploads answered 202 (``duplicate`` too: a frame sent again counts again), from the client's start or
    from ``delete_map`` through it."""

    def __init__(self) -> None:
        self._pending: dict[str, dict[tuple[str, str], None]] = {}  # map -> (device, frame), in send order
        self._counts: dict[str, dict[str, int]] = {}
        self._lock = threading.Lock()  # the blocking client may be shared by threads

    def add(self, answer: FrameAccepted) -> None:
        """Record an upload's answer (``queued`` or ``duplicate``: both are the service's to process)."""
        key = (answer.device_id, answer.frame_id)
        with self._lock:
            pending = self._pending.setdefault(answer.map_id, {})
            if key not in pending:
                pending[key] = None
                self._counts_of(answer.map_id)["sent"] += 1

    def pending(self, map_id: str) -> list[tuple[str, str]]:
        with self._lock:
            return list(self._pending.get(map_id, ()))

    def settle(self, map_id: str, key: tuple[str, str], outcome: str) -> None:
        with self._lock:
            pending = self._pending.get(map_id, {})
            if key in pending:
                del pending[key]
                self._counts_of(map_id)[outcome] += 1

    def forget(self, map_id: str) -> None:
        with self._lock:
            self._pending.pop(map_id, None)
            self._counts.pop(map_id, None)

    def summary(self, map_id: str) -> dict[str, Any]:
        """``{"map_id", "frames": {"sent", "processed", "failed", "lost"}}``: this client's frames of the map."""
        with self._lock:
            return {"map_id": map_id, "frames": dict(self._counts_of(map_id))}

    def _counts_of(self, map_id: str) -> dict[str, int]:
        return self._counts.setdefault(map_id, {"sent": 0, "processed": 0, "failed": 0, "lost": 0})


def frame_outcome(response: httpx.Response) -> tuple[str | None, str]:
    """(outcome or None when not done yet, status) of a frame status answer; 404 (never accepted, or no
    longer known: the map deleted, the store's data lost) is ``lost``; other refusals raise ``ServiceError``."""
    if response.status_code == 404:
        return "lost", "not found"
    status = str(checked(response)["status"])
    return OUTCOMES.get(status), status


def not_processed(
    map_id: str,
    sent: SentFrames,
    last: tuple[str, str, str] | None,
    n_frames: int | None,
    stats: MapStats | None,
    timeout_s: float,
) -> TimeoutError:
    """The ``TimeoutError`` of ``wait_until_processed``: what it was waiting for, and what it last saw."""
    pending = sent.pending(map_id)
    what = []
    if pending:
        first = f" ({last[0]}/{last[1]}: {last[2]})" if last is not None else ""
        what.append(f"{len(pending)} of the {sent.summary(map_id)['frames']['sent']} frames this client sent{first}")
    if n_frames is not None:
        frames = stats.frames if stats else None
        what.append(f"{n_frames} frames of the map in all (last: {frames})")
    return TimeoutError(f"map {map_id}: not processed within {timeout_s} s: {'; '.join(what)}")


def subscribe(
    map_id: str,
    callback: Callable[[arcloud_pb2.ObjectEvent], None],
    endpoints: Sequence[str],
    *,
    mode: SessionMode = "peer",
    include_tentative: bool = False,
    config_file: str | os.PathLike[str] | None = None,
) -> Subscription:
    """Receive the map's object events (``arcloud.v1.ObjectEvent``) over Zenoh from ``endpoints``
    (the service's or a router's, e.g. ``["tcp/127.0.0.1:7447"]``); ``close()`` the result to stop.
    By default the served map's: confirmed objects, and an event when one leaves it (a tentative
    state, MERGED, DELETED or RETIRED); ``include_tentative``: tentative objects' events too. ``config_file``: a
    Zenoh config file the session starts from, e.g. this device's user and password for a router with
    access control (``transport/auth/usrpwd``). Needs Zenoh: ``pip install 'arcloud[events]'`` (the
    base install has no Zenoh)."""
    try:
        import zenoh  # noqa: F401 - loaded here so that a light install fails with what to install
    except ImportError as exc:
        raise ImportError("subscribe needs Zenoh (eclipse-zenoh): pip install 'arcloud[events]'", name="zenoh") from exc
    from arcloud.events.zenoh import subscribe_objects

    return subscribe_objects(
        map_id, callback, connect=endpoints, mode=mode, include_tentative=include_tentative, config_file=config_file
    )


class _Client:
    """What both clients hold: the service's ``url``, the retry policy, the auth headers and the frames sent."""

    def __init__(
        self, url: str, *, max_retries: int, backoff_s: float, max_backoff_s: float, seed: int | None, token: str | None
    ) -> None:
        self.url = url.rstrip("/")
        self.retry = RetryPolicy(max_retries, backoff_s=backoff_s, max_backoff_s=max_backoff_s, seed=seed)
        self.headers = auth_headers(token)
        self.sent = SentFrames()

    def subscribe(
        self,
        map_id: str,
        callback: Callable[[arcloud_pb2.ObjectEvent], None],
        endpoints: Sequence[str],
        *,
        include_tentative: bool = False,
        config_file: str | os.PathLike[str] | None = None,
    ) -> Subscription:
        """As the module's ``subscribe`` (the callback runs on a Zenoh thread)."""
        return subscribe(map_id, callback, endpoints, include_tentative=include_tentative, config_file=config_file)


class ArcloudClient(_Client):
    """Blocking client of one service at ``url``."""

    def __init__(
        self,
        url: str,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        max_retries: int = 5,
        backoff_s: float = 0.25,
        max_backoff_s: float = 10.0,
        seed: int | None = None,
        token: str | None = None,
        http: httpx.Client | None = None,
    ) -> None:
        super().__init__(url, max_retries=max_retries, backoff_s=backoff_s, max_backoff_s=max_backoff_s, seed=seed, token=token)
        self._owns = http is None
        self.http = http if http is not None else httpx.Client(base_url=self.url, timeout=timeout_s)

    def close(self) -> None:
        if self._owns:
            self.http.close()

    def __enter__(self) -> ArcloudClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _request(self, method: str, path: str, *, idempotent: bool = False, **kwargs: Any) -> dict[str, Any]:
        return checked(self._send(method, path, idempotent=idempotent, **kwargs))

    def _send(self, method: str, path: str, *, idempotent: bool = False, **kwargs: Any) -> httpx.Response:
        """The final response (after retries), whatever its status."""
        retries = self.retry.max_retries if self.retry.retryable(method, idempotent) else 0
        headers = {**self.headers, **kwargs.pop("headers", {})}
        started = time.monotonic()
        for attempt in range(retries + 1):
            outcome: httpx.Response | Exception
            try:
                outcome = self.http.request(method, path, headers=headers, **kwargs)
            except RETRY_ERRORS as exc:
                outcome = exc
            wait_s = _next_wait_s(self.retry, method, path, outcome, attempt, retries, started)
            if wait_s is None:
                assert isinstance(outcome, httpx.Response)  # only a response is final
                return outcome
            time.sleep(wait_s)
        raise AssertionError("unreachable")

    def send_frame(self, frame: Frame | None = None, **arrays: Any) -> FrameAccepted:
        """Upload one frame: ``send_frame(frame)`` or ``send_frame(map_id=, rgb=, depth=, intrinsics=,
        cam2world=, timestamp_s=, device_id=, frame_id=, depth_scale=)`` (rgb (H, W, 3) uint8, depth
        (H, W) float32 metres or uint16 units), with ``pose_convention=``, ``world_up=``, ``device_from_map=``
        for an AR app's pose (``frame_body``)."""
        map_id, body = frame_body(frame, **arrays)
        return self.send_encoded(map_id, body)

    def send_encoded(self, map_id: str, body: bytes) -> FrameAccepted:
        """Upload protobuf ``Frame`` bytes made beforehand (``frame_body``)."""
        answer = from_json(
            FrameAccepted,
            self._request("POST", f"/v1/maps/{map_id}/frames", idempotent=True, content=body, headers={"content-type": PROTOBUF}),
        )
        self.sent.add(answer)
        return answer

    def list_objects(
        self,
        map_id: str,
        *,
        include_tentative: bool = False,
        label: str | None = None,
        min_score: float | None = None,
        bbox: Sequence[float] | None = None,
    ) -> list[ObjectOut]:
        """The map's confirmed objects (``include_tentative``: tentative ones too), each with its ``status``, in
        one answer (``iter_objects``: a page at a time)."""
        params = object_query(label, min_score, bbox, include_tentative)
        answer = self._request("GET", f"/v1/maps/{map_id}/objects", params=params)
        return [from_json(ObjectOut, o) for o in answer["objects"]]

    def iter_objects(
        self,
        map_id: str,
        *,
        include_tentative: bool = False,
        label: str | None = None,
        min_score: float | None = None,
        bbox: Sequence[float] | None = None,
        page_size: int = OBJECTS_PAGE,
    ) -> Iterator[ObjectOut]:
        """The objects of ``list_objects``, in id order, ``page_size`` a request: each page is asked for when the
        one before is used up (the service reads about what a page returns)."""
        params = object_query(label, min_score, bbox, include_tentative)
        cursor: str | None = None
        while True:
            page = self._request("GET", f"/v1/maps/{map_id}/objects", params={**params, **page_query(page_size, cursor)})
            yield from (from_json(ObjectOut, o) for o in page["objects"])
            if (cursor := page["next_cursor"]) is None:
                return

    def get_object(self, map_id: str, object_id: int, *, voxels: bool = False) -> ObjectDetail:
        """Any object of the map, confirmed or tentative (its ``status`` says)."""
        answer = self._request("GET", f"/v1/maps/{map_id}/objects/{int(object_id)}", params={"voxels": "true"} if voxels else {})
        return from_json(ObjectDetail, answer)

    def events(self, map_id: str, *, include_tentative: bool = False, wait_for_map: bool = False) -> Iterator[MapEvent]:
        """The map's events as they come (``GET /v1/maps/{map}/events``): a ``SnapshotEvent``, then ``UpsertEvent``,
        ``RemovedEvent``, ``DeviceEvent``, ``DeviceRemovedEvent``; confirmed objects unless ``include_tentative``.
        Never ends by itself: connects again when the connection drops, the service restarts or a read waits
        longer than the client's timeout (the service sends a keep-alive every 15 s), resuming after the last
        event it had (``Last-Event-ID``; a ``ResetEvent`` and a ``SnapshotEvent`` when it cannot: the module's docstring); ``ServiceError`` when refused (403 when the key loses the map
        during the stream), and after ``max_retries`` failed connections in a row. Leave the loop (or ``close()``
        the iterator) to close the stream. ``wait_for_map``: a map that does not exist yet (404: no frame of it
        accepted) is looked for again every 2 s until it does, as the viewer does, rather than raising: an app may
        subscribe before its first upload."""
        path = f"/v1/maps/{map_id}/events"
        stream = EventStream(self.retry, path, wait_for_map=wait_for_map)
        while True:
            outcome: httpx.Response | Exception | None = None
            try:
                with self.http.stream(
                    "GET", path, params=include_query(include_tentative), headers={**self.headers, **stream.resume_headers()}
                ) as response:
                    stream.connected()
                    if not response.is_success:
                        response.read()
                        outcome = response
                    else:
                        for line in response.iter_lines():
                            if (event := stream.feed(line)) is not None:
                                yield event
            except RETRY_ERRORS as exc:
                outcome = exc
            time.sleep(stream.wait_s(outcome))

    def delete_map(self, map_id: str) -> MapDeleted:
        answer = from_json(MapDeleted, self._request("DELETE", f"/v1/maps/{map_id}"))
        self.sent.forget(map_id)
        return answer

    def frame_status(self, map_id: str, device_id: str, frame_id: str) -> FrameState:
        """Where an accepted frame is: ``status`` queued, processing, processed, failed (with ``reason``) or
        unknown (posting it again queues it); ``ServiceError`` 404 for a frame never accepted."""
        return from_json(FrameState, self._request("GET", frame_status_path(map_id, device_id, frame_id)))

    def stats(self, map_id: str) -> MapStats:
        return from_json(MapStats, self._request("GET", f"/v1/maps/{map_id}/stats"))

    def export(self, map_id: str, fmt: str = "json", **options: str | bool) -> bytes:
        """The map as a file's bytes (``GET /v1/maps/{map}/export``): ``fmt`` json, ply, glb or scannet (a zip);
        ``options``: include="tentative", color="class", voxels=True."""
        return checked_content(self._send("GET", f"/v1/maps/{map_id}/export", params=export_query(fmt, options)))

    def set_device_alignment(
        self, map_id: str, device_id: str, device_from_map: np.ndarray | Sequence[float] | Sequence[Sequence[float]]
    ) -> DeviceAlignment:
        """Store where the device's session world stands in the map (an admin key's): ``device_from_map``, a rigid
        4x4 mapping map points to the device's world (``arcloud.core.conventions``), applied to every frame the
        device sends from now on without one of its own."""
        answer = self._request("PUT", alignment_path(map_id, device_id), idempotent=True, json=alignment_body(device_from_map))
        return from_json(DeviceAlignment, answer)

    def device_alignment(self, map_id: str, device_id: str) -> DeviceAlignment:
        """The device's stored alignment; ``ServiceError`` 404 when it has none."""
        return from_json(DeviceAlignment, self._request("GET", alignment_path(map_id, device_id)))

    def delete_device_alignment(self, map_id: str, device_id: str) -> AlignmentDeleted:
        """Remove the device's alignment (an admin key's)."""
        return from_json(AlignmentDeleted, self._request("DELETE", alignment_path(map_id, device_id)))

    def device_alignments(self, map_id: str) -> list[DeviceAlignment]:
        """Every stored alignment of the map, by device id."""
        answer = self._request("GET", f"/v1/maps/{map_id}/alignments")
        return [from_json(DeviceAlignment, a) for a in answer["alignments"]]

    def snapshot(self, map_id: str) -> bytes:
        """The whole map as one file (an admin key's; ``GET /v1/maps/{map}/snapshot``)."""
        return checked_content(self._send("GET", f"/v1/maps/{map_id}/snapshot"))

    def restore(self, map_id: str, snapshot: bytes, *, replace: bool = False) -> MapRestored:
        """Restore a snapshot into the map (empty, or deleted first with ``replace``); an admin key's."""
        answer = self._request(
            "PUT",
            f"/v1/maps/{map_id}/snapshot",
            idempotent=replace,  # into an empty map, a second try would find it full
            params={"replace": str(replace).lower()},
            content=snapshot,
            headers={"content-type": "application/zip"},
        )
        return from_json(MapRestored, answer)

    def list_maps(self, *, page_size: int = MAPS_PAGE) -> list[MapSummary]:
        """Every map the token may read, by id (``GET /v1/maps``, page after page)."""
        return list(self.iter_maps(page_size=page_size))

    def iter_maps(self, *, page_size: int = MAPS_PAGE) -> Iterator[MapSummary]:
        """The maps of ``list_maps``, each page asked for when the one before is used up."""
        cursor: str | None = None
        while True:
            page = self._request("GET", "/v1/maps", params=page_query(page_size, cursor))
            yield from (from_json(MapSummary, m) for m in page["maps"])
            if (cursor := page["next_cursor"]) is None:
                return

    def wait_until_processed(
        self, map_id: str, n_frames: int | None = None, timeout_s: float = 60.0, *, poll_s: float = 0.1
    ) -> dict[str, Any]:
        """Wait until every frame this client sent to the map (each upload answered 202) is done: processed,
        failed, or lost (the service no longer knows it); asks each frame's status, in send order. Returns
        ``{"map_id", "frames": {"sent", "processed", "failed", "lost"}}`` (this client's frames of the map).
        ``n_frames``: wait also until the map counts that many frames done in all, every client's (for a
        client waiting on others' frames). Raises ``TimeoutError`` saying what is still waited for."""
        deadline = time.monotonic() + timeout_s
        last: tuple[str, str, str] | None = None
        stats: MapStats | None = None
        while True:
            for device_id, frame_id in self.sent.pending(map_id):
                outcome, status = frame_outcome(self._send("GET", frame_status_path(map_id, device_id, frame_id)))
                last = (device_id, frame_id, status)
                if outcome is None:
                    break  # still queued or processing: the later ones most likely too
                self.sent.settle(map_id, (device_id, frame_id), outcome)
            else:
                if n_frames is None or _map_done(stats := self._map_stats(map_id), n_frames):
                    return self.sent.summary(map_id)
            if time.monotonic() >= deadline:
                raise not_processed(map_id, self.sent, last, n_frames, stats, timeout_s)
            time.sleep(poll_s)

    def _map_stats(self, map_id: str) -> MapStats:
        """The map's stats; no frame counted for a map the service does not know (404)."""
        try:
            return self.stats(map_id)
        except ServiceError as exc:
            if exc.status != 404:
                raise
            return unknown_map_stats(map_id)


class AsyncArcloudClient(_Client):
    """asyncio client of one service at ``url`` (same methods as ``ArcloudClient``, awaitable)."""

    def __init__(
        self,
        url: str,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        max_retries: int = 5,
        backoff_s: float = 0.25,
        max_backoff_s: float = 10.0,
        seed: int | None = None,
        token: str | None = None,
        http: httpx.AsyncClient | None = None,
    ) -> None:
        super().__init__(url, max_retries=max_retries, backoff_s=backoff_s, max_backoff_s=max_backoff_s, seed=seed, token=token)
        self._owns = http is None
        self.http = http if http is not None else httpx.AsyncClient(base_url=self.url, timeout=timeout_s)

    async def aclose(self) -> None:
        if self._owns:
            await self.http.aclose()

    async def __aenter__(self) -> AsyncArcloudClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _request(self, method: str, path: str, *, idempotent: bool = False, **kwargs: Any) -> dict[str, Any]:
        return checked(await self._send(method, path, idempotent=idempotent, **kwargs))

    async def _send(self, method: str, path: str, *, idempotent: bool = False, **kwargs: Any) -> httpx.Response:
        retries = self.retry.max_retries if self.retry.retryable(method, idempotent) else 0
        headers = {**self.headers, **kwargs.pop("headers", {})}
        started = time.monotonic()
        for attempt in range(retries + 1):
            outcome: httpx.Response | Exception
            try:
                outcome = await self.http.request(method, path, headers=headers, **kwargs)
            except RETRY_ERRORS as exc:
                outcome = exc
            wait_s = _next_wait_s(self.retry, method, path, outcome, attempt, retries, started)
            if wait_s is None:
                assert isinstance(outcome, httpx.Response)  # only a response is final
                return outcome
            await asyncio.sleep(wait_s)
        raise AssertionError("unreachable")

    async def send_frame(self, frame: Frame | None = None, **arrays: Any) -> FrameAccepted:
        """As ``ArcloudClient.send_frame``; the encoding runs in a thread."""
        map_id, body = await asyncio.to_thread(frame_body, frame, **arrays)
        return await self.send_encoded(map_id, body)

    async def send_encoded(self, map_id: str, body: bytes) -> FrameAccepted:
        """Upload protobuf ``Frame`` bytes made beforehand (``frame_body``)."""
        answer = from_json(
            FrameAccepted,
            await self._request(
                "POST", f"/v1/maps/{map_id}/frames", idempotent=True, content=body, headers={"content-type": PROTOBUF}
            ),
        )
        self.sent.add(answer)
        return answer

    async def list_objects(
        self,
        map_id: str,
        *,
        include_tentative: bool = False,
        label: str | None = None,
        min_score: float | None = None,
        bbox: Sequence[float] | None = None,
    ) -> list[ObjectOut]:
        params = object_query(label, min_score, bbox, include_tentative)
        answer = await self._request("GET", f"/v1/maps/{map_id}/objects", params=params)
        return [from_json(ObjectOut, o) for o in answer["objects"]]

    async def iter_objects(
        self,
        map_id: str,
        *,
        include_tentative: bool = False,
        label: str | None = None,
        min_score: float | None = None,
        bbox: Sequence[float] | None = None,
        page_size: int = OBJECTS_PAGE,
    ) -> AsyncIterator[ObjectOut]:
        """As ``ArcloudClient.iter_objects``: ``async for obj in client.iter_objects(map_id)``."""
        params = object_query(label, min_score, bbox, include_tentative)
        cursor: str | None = None
        while True:
            page = await self._request("GET", f"/v1/maps/{map_id}/objects", params={**params, **page_query(page_size, cursor)})
            for o in page["objects"]:
                yield from_json(ObjectOut, o)
            if (cursor := page["next_cursor"]) is None:
                return

    async def get_object(self, map_id: str, object_id: int, *, voxels: bool = False) -> ObjectDetail:
        answer = await self._request(
            "GET", f"/v1/maps/{map_id}/objects/{int(object_id)}", params={"voxels": "true"} if voxels else {}
        )
        return from_json(ObjectDetail, answer)

    async def events(
        self, map_id: str, *, include_tentative: bool = False, wait_for_map: bool = False
    ) -> AsyncIterator[MapEvent]:
        """As ``ArcloudClient.events``: ``async for event in client.events(map_id)``."""
        path = f"/v1/maps/{map_id}/events"
        stream = EventStream(self.retry, path, wait_for_map=wait_for_map)
        while True:
            outcome: httpx.Response | Exception | None = None
            try:
                async with self.http.stream(
                    "GET", path, params=include_query(include_tentative), headers={**self.headers, **stream.resume_headers()}
                ) as response:
                    stream.connected()
                    if not response.is_success:
                        await response.aread()
                        outcome = response
                    else:
                        async for line in response.aiter_lines():
                            if (event := stream.feed(line)) is not None:
                                yield event
            except RETRY_ERRORS as exc:
                outcome = exc
            await asyncio.sleep(stream.wait_s(outcome))

    async def delete_map(self, map_id: str) -> MapDeleted:
        answer = from_json(MapDeleted, await self._request("DELETE", f"/v1/maps/{map_id}"))
        self.sent.forget(map_id)
        return answer

    async def frame_status(self, map_id: str, device_id: str, frame_id: str) -> FrameState:
        return from_json(FrameState, await self._request("GET", frame_status_path(map_id, device_id, frame_id)))

    async def stats(self, map_id: str) -> MapStats:
        return from_json(MapStats, await self._request("GET", f"/v1/maps/{map_id}/stats"))

    async def export(self, map_id: str, fmt: str = "json", **options: str | bool) -> bytes:
        return checked_content(await self._send("GET", f"/v1/maps/{map_id}/export", params=export_query(fmt, options)))

    async def set_device_alignment(
        self, map_id: str, device_id: str, device_from_map: np.ndarray | Sequence[float] | Sequence[Sequence[float]]
    ) -> DeviceAlignment:
        answer = await self._request(
            "PUT", alignment_path(map_id, device_id), idempotent=True, json=alignment_body(device_from_map)
        )
        return from_json(DeviceAlignment, answer)

    async def device_alignment(self, map_id: str, device_id: str) -> DeviceAlignment:
        return from_json(DeviceAlignment, await self._request("GET", alignment_path(map_id, device_id)))

    async def delete_device_alignment(self, map_id: str, device_id: str) -> AlignmentDeleted:
        return from_json(AlignmentDeleted, await self._request("DELETE", alignment_path(map_id, device_id)))

    async def device_alignments(self, map_id: str) -> list[DeviceAlignment]:
        answer = await self._request("GET", f"/v1/maps/{map_id}/alignments")
        return [from_json(DeviceAlignment, a) for a in answer["alignments"]]

    async def snapshot(self, map_id: str) -> bytes:
        return checked_content(await self._send("GET", f"/v1/maps/{map_id}/snapshot"))

    async def restore(self, map_id: str, snapshot: bytes, *, replace: bool = False) -> MapRestored:
        answer = await self._request(
            "PUT",
            f"/v1/maps/{map_id}/snapshot",
            idempotent=replace,
            params={"replace": str(replace).lower()},
            content=snapshot,
            headers={"content-type": "application/zip"},
        )
        return from_json(MapRestored, answer)

    async def list_maps(self, *, page_size: int = MAPS_PAGE) -> list[MapSummary]:
        return [m async for m in self.iter_maps(page_size=page_size)]

    async def iter_maps(self, *, page_size: int = MAPS_PAGE) -> AsyncIterator[MapSummary]:
        cursor: str | None = None
        while True:
            page = await self._request("GET", "/v1/maps", params=page_query(page_size, cursor))
            for m in page["maps"]:
                yield from_json(MapSummary, m)
            if (cursor := page["next_cursor"]) is None:
                return

    async def wait_until_processed(
        self, map_id: str, n_frames: int | None = None, timeout_s: float = 60.0, *, poll_s: float = 0.1
    ) -> dict[str, Any]:
        """As ``ArcloudClient.wait_until_processed``."""
        deadline = time.monotonic() + timeout_s
        last: tuple[str, str, str] | None = None
        stats: MapStats | None = None
        while True:
            for device_id, frame_id in self.sent.pending(map_id):
                outcome, status = frame_outcome(await self._send("GET", frame_status_path(map_id, device_id, frame_id)))
                last = (device_id, frame_id, status)
                if outcome is None:
                    break
                self.sent.settle(map_id, (device_id, frame_id), outcome)
            else:
                if n_frames is None or _map_done(stats := await self._map_stats(map_id), n_frames):
                    return self.sent.summary(map_id)
            if time.monotonic() >= deadline:
                raise not_processed(map_id, self.sent, last, n_frames, stats, timeout_s)
            await asyncio.sleep(poll_s)

    async def _map_stats(self, map_id: str) -> MapStats:
        try:
            return await self.stats(map_id)
        except ServiceError as exc:
            if exc.status != 404:
                raise
            return unknown_map_stats(map_id)
