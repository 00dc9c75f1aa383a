"""Start and stop of the service: the adapters the composition root connects, the ingest on them.

The service never builds an adapter. ``create_app`` takes a ``Connect`` callable (the composition root's,
``arcloud.tools.wiring``) that the lifespan calls once with the settings and the handler of frames
published over Zenoh; it returns ``Adapters``: the ports, the worker processes to start (if any) and
what to close on shutdown. A detector among them means the step runs in threads of this process.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from arcloud.core.types import Params
from arcloud.errors import InvalidInput
from arcloud.ports import (
    Detector,
    DeviceAlignments,
    FrameQueue,
    KeyStore,
    MapArchive,
    ObjectStore,
    RateLimiter,
    UpdatePublisher,
    ViewerPasses,
)
from arcloud.service import frames as frames_in
from arcloud.service.access import Access, KeyCache
from arcloud.service.change_feed import ChangeFeed
from arcloud.service.exports import ExportPlaces
from arcloud.service.ingest import Ingest
from arcloud.service.pool import WorkerPool
from arcloud.service.settings import Settings
from arcloud.service.worker import FrameWorker, consumer_name

log = logging.getLogger(__name__)

#: How long an idle worker thread of the API waits for a frame before it looks at its stop flag.
IN_PROCESS_READ_BLOCK_S = 0.1
#: How often the API publishes the change log entries no worker published (``service.change_feed``).
FEED_SWEEP_S = 2.0

FrameHandler = Callable[[str, bytes], None]  # (map id, protobuf Frame bytes) published by a device


class Closeable(Protocol):
    """What the runtime closes on shutdown (connections, sessions)."""

    def close(self) -> None: ...


@dataclass(eq=False)
class Adapters:
    """What the composition root connected for one app. ``detector``: run the step in ``settings.workers``
    threads of this process (None: workers run elsewhere); ``pool``: worker processes to start and stop
    with the app; ``keys``: the API keys (None: auth none); ``limiter``: the rate limits (None: none);
    ``archive``: map snapshots (None: no snapshot routes); ``owned``: closed on shutdown, last first;
    ``alignments``: the devices' stored alignments (None: no alignment routes, frames bring their own);
    ``viewer_passes``: the viewer's tickets and sessions (None: no viewer passes, as with auth none);
    ``host_workers``: worker processes that another process of this host runs for this service (``serve
    --api-processes``: its pool), which ``/healthz/workers`` expects to beat (0: none expected by count)."""

    store: ObjectStore
    queue: FrameQueue
    detector: Detector | None = None
    publisher: UpdatePublisher | None = None
    pool: WorkerPool | None = None
    keys: KeyStore | None = None
    limiter: RateLimiter | None = None
    archive: MapArchive | None = None
    owned: list[Closeable] = field(default_factory=list)
    alignments: DeviceAlignments | None = None
    viewer_passes: ViewerPasses | None = None
    host_workers: int = 0


Connect = Callable[[Settings, FrameHandler], Adapters]


@dataclass(eq=False)
class Runtime:
    """What the lifespan started; routes reach it through the app's ``RuntimeDep`` dependency."""

    settings: Settings
    params: Params
    store: ObjectStore
    ingest: Ingest
    access: Access
    detector: Detector | None = None
    publisher: UpdatePublisher | None = None
    archive: MapArchive | None = None
    owned: list[Closeable] = field(default_factory=list)  # closed on shutdown, last first
    alignments: DeviceAlignments | None = None
    feed_stop: threading.Event = field(default_factory=threading.Event)  # ends the feed's sweeps (with a publisher)
    exports: ExportPlaces = field(init=False)  # places for exports, snapshots and restores (``max_exports``)

    def __post_init__(self) -> None:
        self.exports = ExportPlaces(self.settings.max_exports)


def start_runtime(settings: Settings, connect: Connect) -> Runtime:
    """Connect the adapters, start the ingest. Blocking: loads models and connects."""
    params = settings.make_params()
    holder: dict[str, Ingest] = {}
    adapters = connect(
        settings,
        lambda map_id, payload: ingest_published_frame(
            holder["ingest"], map_id, payload, settings, map_up=params.up, alignments=adapters.alignments
        ),
    )
    if settings.auth_mode == "keys" and adapters.keys is None:
        close_all(adapters.owned)
        raise InvalidInput("auth", "a key store with auth keys (a Redis store or keys_file)", "none connected")
    access = Access(
        settings,
        KeyCache(adapters.keys, settings.key_cache_s) if settings.auth_mode == "keys" and adapters.keys else None,
        adapters.limiter,
        adapters.viewer_passes,
    )
    if access.keys is None:
        log.warning("auth none: anyone who reaches this service may read, write and delete every map")
    else:
        access.keys_health()  # counts the keys there are now: losing them later is then seen
    feed = ChangeFeed(adapters.store, adapters.publisher) if adapters.publisher is not None else None
    threads = []
    if adapters.detector is not None:
        threads = [
            FrameWorker(
                adapters.queue,
                adapters.store,
                adapters.detector,
                params,
                feed,
                consumer=f"{consumer_name()}-{i}",
                read_block_s=IN_PROCESS_READ_BLOCK_S,
                attempts=settings.max_deliveries,
                claim_min_idle_s=settings.claim_min_idle_s,
                claim_interval_s=settings.claim_interval_s,
                max_deliveries=settings.max_deliveries,
                heartbeat_s=None,
                warm_up=True,
                prefetch=settings.worker_prefetch,
            )
            for i in range(settings.workers)
        ]
    ingest = holder["ingest"] = Ingest(
        adapters.queue, adapters.store, threads=threads, pool=adapters.pool, host_workers=adapters.host_workers
    )
    try:
        ingest.start()
    except BaseException:
        close_all(adapters.owned)
        raise
    log.info("arcloud service started: %s", json.dumps(settings.redacted(), default=str))
    runtime = Runtime(
        settings,
        params,
        adapters.store,
        ingest,
        access,
        adapters.detector,
        adapters.publisher,
        adapters.archive,
        adapters.owned,
        adapters.alignments,
    )
    if feed is not None:  # publishes what workers committed and did not publish (they died, or failed to)
        threading.Thread(
            target=feed.run,
            args=(runtime.feed_stop, lambda: list(adapters.store.list_maps()), FEED_SWEEP_S),
            name="arcloud-change-feed",
            daemon=True,
        ).start()
    return runtime


def stop_runtime(runtime: Runtime) -> None:
    runtime.feed_stop.set()
    runtime.ingest.stop()
    close_all(runtime.owned)
    log.info("arcloud service stopped")


def ingest_published_frame(
    ingest: Ingest,
    map_id: str,
    payload: bytes,
    settings: Settings,
    *,
    map_up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    alignments: DeviceAlignments | None = None,
) -> None:
    """A frame published on ``arcloud/<map_id>/frames/<device>``: validated and queued like an upload
    (the map id of the key plays the part of the path's; its pose taken into the map's world the same way)."""
    msg = frames_in.parse_message(payload)
    frame = frames_in.validate_message(
        msg,
        map_id,
        max_pixels=settings.max_frame_pixels,
        queue_decoded_png=settings.queue_decoded_png,
        map_up=map_up,
        alignments=alignments,
    )
    ingest.submit(frame, msg)


def close_all(things: list[Closeable]) -> None:
    """``close_quietly`` each, last first."""
    for thing in reversed(things):
        close_quietly(thing)


def close_quietly(thing: Closeable | None) -> None:
    """``thing.close()``, logging (not raising) what goes wrong."""
    if thing is None:
        return
    try:
        thing.close()
    except Exception:  # shutdown must go on
        log.warning("closing %s failed", type(thing).__name__, exc_info=True)


__all__ = ["Adapters", "Closeable", "Connect", "FrameHandler", "Runtime", "close_quietly", "start_runtime", "stop_runtime"]
