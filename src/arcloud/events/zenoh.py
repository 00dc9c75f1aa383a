"""Object events over Zenoh, and the map's current objects on request.

Key expressions (``map_id`` is checked by ``check_id``; ids with Zenoh's reserved ``#`` or ``$`` cannot
be published and are logged):

    arcloud/<map_id>/objects/<object_id>   PUT      ``arcloud.v1.ObjectEvent`` (protobuf) for each change
    arcloud/<map_id>/objects               QUERY    answered with ``arcloud.v1.ObjectList`` (current objects)
    arcloud/<map_id>/frames/<device_id>    PUT      ``arcloud.v1.Frame`` (optional ingest path)

Sessions: the API's session runs in peer mode (``listen`` and/or ``connect`` endpoints, e.g.
``tcp/127.0.0.1:7447``) or connects to a router. Multicast scouting is off by default: a deployment
names its endpoints. Peers do not route for other peers, so worker processes open *client* sessions to the
API's (or a router's) endpoints; subscribers connect the same way (``subscribe_objects``).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Literal

from arcloud.core.types import ObjectEvent

if TYPE_CHECKING:
    import zenoh

    from arcloud.ports import ObjectStore
    from arcloud.proto.arcloud.v1 import arcloud_pb2

log = logging.getLogger(__name__)

KEY_ROOT = "arcloud"
SessionMode = Literal["peer", "client", "router"]
FrameHandler = Callable[[str, bytes], None]  # (map id from the key, payload)


def objects_key(map_id: str) -> str:
    """``arcloud/<map_id>/objects``: the queryable answering the map's objects."""
    return f"{KEY_ROOT}/{map_id}/objects"


def object_key(map_id: str, object_id: int) -> str:
    """``arcloud/<map_id>/objects/<object_id>``: where an object's events are published."""
    return f"{objects_key(map_id)}/{int(object_id)}"


def frames_key(map_id: str = "*", device_id: str = "*") -> str:
    """``arcloud/<map_id>/frames/<device_id>``: where devices may publish frames."""
    return f"{KEY_ROOT}/{map_id}/frames/{device_id}"


def zenoh_config(mode: SessionMode = "peer", *, listen: Sequence[str] = (), connect: Sequence[str] = (), multicast: bool = False) -> zenoh.Config:
    """A Zenoh session config: ``mode``, endpoints, multicast scouting off unless asked."""
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    if mode == "client":
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    else:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config


def open_session(mode: SessionMode = "peer", *, listen: Sequence[str] = (), connect: Sequence[str] = ()) -> zenoh.Session:
    import zenoh

    return zenoh.open(zenoh_config(mode, listen=listen, connect=connect))


def connectable(endpoints: Sequence[str]) -> list[str]:
    """Listen endpoints turned into endpoints to connect to (``0.0.0.0``/``[::]`` -> loopback)."""
    out = []
    for endpoint in endpoints:
        out.append(endpoint.replace("/0.0.0.0:", "/127.0.0.1:").replace("/[::]:", "/[::1]:"))
    return out


class ZenohPublisher:
    """``UpdatePublisher`` over Zenoh. With a ``store`` it also answers queries for a map's objects;
    with ``on_frame`` it hands the payloads published on ``arcloud/<map_id>/frames/*`` to
    ``on_frame(map_id, payload)`` (called on a Zenoh thread; it must be quick; what it raises is logged).

    ``session``: an open session to use (not closed by ``close``), else one is opened with ``mode``,
    ``listen`` and ``connect``."""

    def __init__(
        self,
        session: zenoh.Session | None = None,
        *,
        mode: SessionMode = "peer",
        listen: Sequence[str] = (),
        connect: Sequence[str] = (),
        store: ObjectStore | None = None,
        on_frame: FrameHandler | None = None,
    ) -> None:
        self._owns_session = session is None
        self.session = session if session is not None else open_session(mode, listen=listen, connect=connect)
        self.store = store
        self._declared: list[Any] = []
        self._closed = threading.Event()
        if store is not None:
            self._declared.append(self.session.declare_queryable(f"{KEY_ROOT}/*/objects", self._answer_objects))
        if on_frame is not None:
            self._declared.append(self.session.declare_subscriber(frames_key(), lambda sample: _call_frame(on_frame, sample)))
        log.info("zenoh %s session open (listen %s, connect %s)", mode, list(listen) or "-", list(connect) or "-")

    def publish(self, events: Sequence[ObjectEvent]) -> None:
        """Put each event on its object's key. Never raises: a lost event is logged (viewers can
        always re-read the map with a query)."""
        if self._closed.is_set():
            return
        from arcloud.proto.convert import event_to_proto

        for event in events:
            try:
                self.session.put(object_key(event.map_id, event.object_id), event_to_proto(event).SerializeToString())
            except Exception:  # noqa: BLE001 - publishing must not fail the step
                log.warning("map %s: event %s of object %d not published", event.map_id, event.kind, event.object_id, exc_info=True)

    def _answer_objects(self, query: Any) -> None:
        key = str(query.key_expr)
        parts = key.split("/")
        if len(parts) != 3 or any(c in parts[1] for c in "*$#"):
            query.reply_err(f"ask for one map: {KEY_ROOT}/<map_id>/objects, got {key}".encode())
            return
        map_id = parts[1]
        try:
            objects = _list_objects(self.store, map_id)  # type: ignore[arg-type]
            from arcloud.proto.convert import objects_to_proto

            query.reply(key, objects_to_proto(objects, map_id).SerializeToString())
        except Exception as exc:  # noqa: BLE001 - answer with the error instead of leaving the query hanging
            log.warning("map %s: objects query failed", map_id, exc_info=True)
            query.reply_err(f"{type(exc).__name__}: {exc}".encode())

    def close(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        for entity in self._declared:
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001
                log.debug("undeclare failed", exc_info=True)
        if self._owns_session:
            self.session.close()


def _list_objects(store: ObjectStore, map_id: str) -> list[Any]:
    """Objects without voxels when the store offers that (``list_meta``), else full objects."""
    list_meta = getattr(store, "list_meta", None)
    return list_meta(map_id) if list_meta is not None else store.list_objects(map_id)


def _call_frame(handler: FrameHandler, sample: Any) -> None:
    try:
        handler(str(sample.key_expr).split("/")[1], sample.payload.to_bytes())
    except Exception:  # noqa: BLE001 - a bad frame must not kill the Zenoh thread
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
) -> Subscription:
    """Call ``callback(ObjectEvent message)`` for every event of ``map_id`` (on a Zenoh thread)."""
    from arcloud.proto.arcloud.v1 import arcloud_pb2

    def on_sample(sample: Any) -> None:
        try:
            callback(arcloud_pb2.ObjectEvent.FromString(sample.payload.to_bytes()))
        except Exception:  # noqa: BLE001 - keep the subscription alive
            log.warning("event on %s not handled", sample.key_expr, exc_info=True)

    owns = session is None
    session = session if session is not None else open_session(mode, connect=connect)
    subscriber = session.declare_subscriber(f"{objects_key(map_id)}/*", on_sample)
    return Subscription(session, subscriber, owns)


def query_objects(
    map_id: str,
    *,
    connect: Sequence[str] = (),
    mode: SessionMode = "peer",
    session: zenoh.Session | None = None,
    timeout_s: float = 5.0,
) -> arcloud_pb2.ObjectList:
    """The map's current objects, asked of whoever answers ``arcloud/<map_id>/objects``.
    Raises ``LookupError`` when nobody answers in time, ``RuntimeError`` with the answerer's error."""
    from arcloud.proto.arcloud.v1 import arcloud_pb2

    owns = session is None
    session = session if session is not None else open_session(mode, connect=connect)
    try:
        for reply in session.get(objects_key(map_id), timeout=timeout_s):
            if reply.ok is not None:
                return arcloud_pb2.ObjectList.FromString(reply.ok.payload.to_bytes())
            raise RuntimeError(f"objects of map {map_id}: {reply.err.payload.to_bytes().decode(errors='replace')}")
        raise LookupError(f"objects of map {map_id}: no answer within {timeout_s} s")
    finally:
        if owns:
            session.close()


__all__ = [
    "Subscription",
    "ZenohPublisher",
    "connectable",
    "frames_key",
    "object_key",
    "objects_key",
    "open_session",
    "query_objects",
    "subscribe_objects",
    "zenoh_config",
]
