"""Object events over Zenoh, and the map's current objects on request.

Key expressions (``map_id`` is checked by ``check_map_id``; ids with Zenoh's reserved ``#`` or ``$`` cannot
be published and are logged):

    arcloud/<map_id>/objects/<object_id>             PUT    ``arcloud.v1.ObjectEvent`` (protobuf): the served map
    arcloud/<map_id>/objects/tentative/<object_id>   PUT    ``arcloud.v1.ObjectEvent`` of objects outside it
    arcloud/<map_id>/objects                         QUERY  ``arcloud.v1.ObjectList``: confirmed objects; with
                                                            ``?include=tentative``, every object
    arcloud/<map_id>/frames/<device_id>              PUT    ``arcloud.v1.Frame`` (optional ingest path)

Each event goes to exactly one key. The served key space carries every state of a confirmed object
and every change that takes one out of the served map (its first tentative state: ``Object.status``
TENTATIVE; MERGED, DELETED or RETIRED of an object that was served: the step's events say whether the
object was confirmed before, ``ObjectEvent.was_confirmed``); the tentative key space carries the rest.
RETIRED: the object was seen to be gone (it left the room) (the store keeps it in the
map's history for a while). A viewer of the served map subscribes to ``arcloud/<map_id>/objects/*`` and
drops an object on a tentative state, MERGED, DELETED or RETIRED; one that wants every object
subscribes to ``arcloud/<map_id>/objects/**`` (one subscriber: events arrive in the order they were published).

Sessions: the API's session runs in peer mode (``listen`` and/or ``connect`` endpoints, e.g.
``tcp/127.0.0.1:7447``) or connects to a router. Multicast scouting is off by default: a deployment
names its endpoints. Peers do not route for other peers, so worker processes open *client* sessions to the
API's (or a router's) endpoints; subscribers connect the same way (``subscribe_objects``).

Access control is the router's (its ``access_control`` and ``transport/auth``: docs/service.md, "Zenoh"):
every function that opens a session takes ``config_file``, a Zenoh config file that session starts from
(credentials, TLS), with ``mode``, endpoints and multicast scouting set on top.
"""

from __future__ import annotations

import json
import logging
import os
import re
import sys
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal

from arcloud.core.types import ObjectEvent
from arcloud.errors import ArcloudError, InvalidInput

if TYPE_CHECKING:
    import zenoh

    from arcloud.ports import ObjectStore
    from arcloud.proto.arcloud.v1 import arcloud_pb2

log = logging.getLogger(__name__)

KEY_ROOT = "arcloud"
SessionMode = Literal["peer", "client", "router"]
FrameHandler = Callable[[str, bytes], None]  # (map id from the key, payload)
ConfigFile = str | os.PathLike[str]  # a Zenoh config file: .json5, .json or .yaml


def objects_key(map_id: str) -> str:
    """``arcloud/<map_id>/objects``: the queryable answering the map's objects."""
    return f"{KEY_ROOT}/{map_id}/objects"


def object_key(map_id: str, object_id: int) -> str:
    """``arcloud/<map_id>/objects/<object_id>``: where an object's events in the served map are published."""
    return f"{objects_key(map_id)}/{int(object_id)}"


def tentative_key(map_id: str, object_id: int) -> str:
    """``arcloud/<map_id>/objects/tentative/<object_id>``: where events of objects outside the served map go."""
    return f"{objects_key(map_id)}/tentative/{int(object_id)}"


def frames_key(map_id: str = "*", device_id: str = "*") -> str:
    """``arcloud/<map_id>/frames/<device_id>``: where devices may publish frames."""
    return f"{KEY_ROOT}/{map_id}/frames/{device_id}"


def load_config_file(path: ConfigFile) -> zenoh.Config:
    """The Zenoh config in ``path`` (``zenoh.Config.from_file``). Raises ``InvalidInput`` naming the
    ``zenoh_config`` setting, with Zenoh's reason on one line, when it cannot be read or is not a Zenoh config."""
    import zenoh

    try:
        return zenoh.Config.from_file(os.fspath(path))
    except zenoh.ZError as exc:
        raise InvalidInput("zenoh_config", "a Zenoh config file", f"{path}: {_reason(exc)}") from exc


def zenoh_config(
    mode: SessionMode = "peer",
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool = False,
    config_file: ConfigFile | None = None,
) -> zenoh.Config:
    """A Zenoh session config: ``config_file``'s (credentials, TLS; default: Zenoh's defaults), with
    ``mode``, endpoints and multicast scouting (off unless asked) set on top."""
    import zenoh

    config = load_config_file(config_file) if config_file is not None else zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    if mode == "client":
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    else:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config


def open_session(
    mode: SessionMode = "peer",
    *,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: ConfigFile | None = None,
) -> zenoh.Session:
    """An open session (see ``zenoh_config``). Raises ``InvalidInput`` for a bad ``config_file`` and
    ``ArcloudError`` when Zenoh cannot open it: a client whose router is down or refuses it (a router
    that authenticates closes a session with a wrong or missing user or password), a port in use. A peer
    opens all the same and keeps trying its ``connect`` endpoints: a warning says when it reached none."""
    import zenoh

    config = zenoh_config(mode, listen=listen, connect=connect, config_file=config_file)
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        raise ArcloudError(
            f"zenoh: no {mode} session (listen {list(listen) or '-'}, connect {list(connect) or '-'}): {_reason(exc)} "
            "(is the router up? if it authenticates, does it accept our user and password?)"
        ) from exc
    if mode == "peer" and connect and not (list(session.info.routers_zid()) or list(session.info.peers_zid())):
        log.warning("zenoh peer session reached none of %s (down, or refusing our credentials?); it keeps trying", list(connect))
    return session


def _reason(exc: Exception) -> str:
    """Zenoh's error on one line: without its Rust source location, nor the lines of a config file it
    quotes (they may hold a password); where it says, ``line L, column C:`` first."""
    lines = [line.strip() for line in str(exc).splitlines()]
    text = " ".join(line for line in lines if line and not re.match(r"^\d*\s*\|", line))
    text = re.sub(r"\s+at \S+\.rs:\d+\.?$", "", text)
    text = re.sub(
        r'JSON error: Message \{ msg: "(.*)", location: Some\(Location \{ line: (\d+), column: (\d+) \}\) \}',
        r"-->\2:\3 \1",
        text,
    )
    text = re.sub(r"-->\s*(\d+):(\d+)\s*=?\s*", r"line \1, column \2: ", text)
    return text.strip()


def connectable(endpoints: Sequence[str]) -> list[str]:
    """Listen endpoints turned into endpoints to connect to (``0.0.0.0``/``[::]`` -> loopback)."""
    out = []
    for endpoint in endpoints:
        out.append(endpoint.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:"))
    return out


Route = Literal["served", "tentative"]
_GONE = sys.maxsize  # the version remembered for a merged, deleted or retired object: nothing of it is newer


class ServedRouter:
    """Decides where each event goes (see the module docstring), and drops a state that is not newer
    than one already published of its object (two worker threads' events of one object can come out
    of order: the older is dropped, so that a viewer never goes back). Remembers the versions of the
    ``max_objects`` objects published most recently. A ``created`` object is new whatever was published under its id
    before: a map restored from a snapshot keeps its ids and starts their versions at 1 again, and so does one made
    again after its store lost it (their states were dropped until they passed the old versions). Not thread-safe:
    the publisher routes and puts under one lock, so that events leave in the order they were routed.

    ``route(event)``: ``"served"``, ``"tentative"``, or None for a state to drop."""

    def __init__(self, max_objects: int = 100_000) -> None:
        self.max_objects = max_objects
        self._last: OrderedDict[tuple[str, int], int] = OrderedDict()  # -> version last published

    def route(self, event: ObjectEvent) -> Route | None:
        key = (event.map_id, int(event.object_id))
        if event.object is None:  # merged, deleted or retired: whoever had it is told
            self._remember(key, _GONE)
            return "served" if event.was_confirmed else "tentative"
        version = int(event.object.version)
        last = self._last.get(key)
        if last is not None and version <= last and event.kind != "created":
            return None
        self._remember(key, version)
        return "served" if event.object.confirmed or event.was_confirmed else "tentative"

    def _remember(self, key: tuple[str, int], value: int) -> None:
        self._last[key] = value
        self._last.move_to_end(key)
        while len(self._last) > self.max_objects:
            self._last.popitem(last=False)


class ZenohPublisher:
    """``UpdatePublisher`` over Zenoh: each event on the served or the tentative key space
    (``ServedRouter``). With a ``store`` it also answers queries for a map's objects;
    with ``on_frame`` it hands the payloads published on ``arcloud/<map_id>/frames/*`` to
    ``on_frame(map_id, payload)`` (called on a Zenoh thread; it must be quick; what it raises is logged).

    ``session``: an open session to use (not closed by ``close``), else one is opened with ``mode``,
    ``listen``, ``connect`` and ``config_file`` (``open_session``)."""

    def __init__(
        self,
        session: zenoh.Session | None = None,
        *,
        mode: SessionMode = "peer",
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        store: ObjectStore | None = None,
        on_frame: FrameHandler | None = None,
        config_file: ConfigFile | None = None,
    ) -> None:
        self._owns_session = session is None
        if session is None:
            session = open_session(mode, listen=listen, connect=connect, config_file=config_file)
        self.session = session
        self.store = store
        self.router = ServedRouter()
        self._publishing = threading.Lock()  # routing and putting: worker threads publish at once
        self._declared: list[Any] = []
        self._closed = threading.Event()
        if store is not None:
            self._declared.append(self.session.declare_queryable(f"{KEY_ROOT}/*/objects", self._answer_objects))
        if on_frame is not None:
            self._declared.append(self.session.declare_subscriber(frames_key(), lambda sample: _call_frame(on_frame, sample)))
        log.info(
            "zenoh %s session open (listen %s, connect %s, config %s)",
            mode,
            list(listen) or "-",
            list(connect) or "-",
            config_file or "-",
        )

    def publish(self, events: Sequence[ObjectEvent]) -> None:
        """Put each event on its key space's key for its object. Never raises: a lost event is logged
        (viewers can always re-read the map with a query)."""
        if self._closed.is_set():
            return
        with self._publishing:
            for event in events:
                self._put(event)

    def _put(self, event: ObjectEvent) -> None:
        from arcloud.proto.convert import event_to_proto

        route = self.router.route(event)
        if route is None:
            log.debug("map %s: object %d: a state older than one published, not published", event.map_id, event.object_id)
            return
        key = object_key(event.map_id, event.object_id) if route == "served" else tentative_key(event.map_id, event.object_id)
        try:
            self.session.put(key, event_to_proto(event).SerializeToString())
        except Exception:  # publishing must not fail the step
            log.warning("map %s: event %s of object %d not published", event.map_id, event.kind, event.object_id, exc_info=True)

    def _answer_objects(self, query: Any) -> None:
        key = str(query.key_expr)
        parts = key.split("/")
        if len(parts) != 3 or any(c in parts[1] for c in "*$#"):
            query.reply_err(f"ask for one map: {KEY_ROOT}/<map_id>/objects, got {key}".encode())
            return
        map_id = parts[1]
        include = query.parameters.get("include")
        if include not in (None, "tentative"):
            query.reply_err(f"include: expected tentative (or nothing: confirmed objects only), got {include!r}".encode())
            return
        try:
            objects = [o for o in self.store.list_meta(map_id) if include == "tentative" or o.confirmed]  # type: ignore[union-attr]  # declared only with a store
            from arcloud.proto.convert import objects_to_proto

            query.reply(key, objects_to_proto(objects, map_id).SerializeToString())
        except Exception as exc:  # answer with the error instead of leaving the query hanging
            log.warning("map %s: objects query failed", map_id, exc_info=True)
            query.reply_err(f"{type(exc).__name__}: {exc}".encode())

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        for entity in self._declared:
            try:
                entity.undeclare()
            except Exception:  # closing goes on: undeclaring is best effort
                log.debug("undeclare failed", exc_info=True)
        if self._owns_session:
            self.session.close()


def _call_frame(handler: FrameHandler, sample: Any) -> None:
    try:
        handler(str(sample.key_expr).split("/")[1], sample.payload.to_bytes())
    except Exception:  # a bad frame must not kill the Zenoh thread
        log.warning("frame from %s dropped", sample.key_expr, exc_info=True)


class Subscription:
    """A live subscription to a map's object events; ``close()`` ends it (also a context manager)."""

    def __init__(self, session: zenoh.Session, subscriber: Any, owns_session: bool) -> None:
        self.session = session
        self.subscriber = subscriber
        self._owns_session = owns_session

    def close(self) -> None:
        self.subscriber.undeclare()
        if self._owns_session:
            self.session.close()

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def subscribe_objects(
    map_id: str,
    callback: Callable[[arcloud_pb2.ObjectEvent], None],
    *,
    connect: Sequence[str] = (),
    mode: SessionMode = "peer",
    session: zenoh.Session | None = None,
    include_tentative: bool = False,
    config_file: ConfigFile | None = None,
) -> Subscription:
    """Call ``callback(ObjectEvent message)`` for every event of ``map_id``'s served map (on a Zenoh
    thread): states of confirmed objects, and the event that takes one out (a tentative state, MERGED,
    DELETED or REMOVED). ``include_tentative``: the events of tentative objects too. Without ``session``, opens one
    (``open_session``: ``mode``, ``connect``, ``config_file`` with the device's credentials)."""
    from arcloud.proto.arcloud.v1 import arcloud_pb2

    def on_sample(sample: Any) -> None:
        try:
            callback(arcloud_pb2.ObjectEvent.FromString(sample.payload.to_bytes()))
        except Exception:  # keep the subscription alive
            log.warning("event on %s not handled", sample.key_expr, exc_info=True)

    owns = session is None
    session = session if session is not None else open_session(mode, connect=connect, config_file=config_file)
    subscriber = session.declare_subscriber(f"{objects_key(map_id)}/{'**' if include_tentative else '*'}", on_sample)
    return Subscription(session, subscriber, owns)


def query_objects(
    map_id: str,
    *,
    connect: Sequence[str] = (),
    mode: SessionMode = "peer",
    session: zenoh.Session | None = None,
    timeout_s: float = 5.0,
    include_tentative: bool = False,
    config_file: ConfigFile | None = None,
) -> arcloud_pb2.ObjectList:
    """The map's confirmed objects (``include_tentative``: every object), asked of whoever answers
    ``arcloud/<map_id>/objects`` (without ``session``: on one opened as ``subscribe_objects`` does).
    Raises ``LookupError`` when nobody answers in time, ``RuntimeError`` with the answerer's error."""
    from arcloud.proto.arcloud.v1 import arcloud_pb2

    owns = session is None
    session = session if session is not None else open_session(mode, connect=connect, config_file=config_file)
    try:
        selector = f"{objects_key(map_id)}?include=tentative" if include_tentative else objects_key(map_id)
        for reply in session.get(selector, timeout=timeout_s):
            if reply.ok is not None:
                return arcloud_pb2.ObjectList.FromString(reply.ok.payload.to_bytes())
            raise RuntimeError(f"objects of map {map_id}: {reply.err.payload.to_bytes().decode(errors='replace')}")  # type: ignore[union-attr]  # not ok: err
        raise LookupError(f"objects of map {map_id}: no answer within {timeout_s} s")
    finally:
        if owns:
            session.close()


__all__ = [
    "ConfigFile",
    "ServedRouter",
    "Subscription",
    "ZenohPublisher",
    "connectable",
    "frames_key",
    "load_config_file",
    "object_key",
    "objects_key",
    "open_session",
    "query_objects",
    "subscribe_objects",
    "tentative_key",
    "zenoh_config",
]
