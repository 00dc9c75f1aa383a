"""The composition root of the service: the only code that chooses adapters, from ``Settings``.

    create_app(settings)         the HTTP service (uvicorn: ``arcloud.tools.wiring:create_app --factory``)
    run_worker(settings)         one ingest worker in this process, until SIGTERM
    worker_pool(settings, n)     n worker processes, each running ``run_worker``

``settings.store`` picks the store and the queue: ``memory`` -> ``MemoryStore`` and ``MemoryFrameQueue``
(worker threads in the API process run the step); a Redis URL -> ``RedisStore`` and ``RedisFrameQueue``
(``ingest_shards`` streams; worker processes run it), on one Redis or, for a ``redis+cluster://`` URL, on a
Redis Cluster (``stores.redis.connect_redis``). ``settings.detector`` picks the detector: the specs of
``arcloud.detectors.factory`` plus ``sim:SEED``, the simulator's faulty detector on ``generate_room(SEED)``
(the one ``arcloud replay`` streams frames of), registered by ``register_sim_detector`` before any spec is
checked or built so that importing this module never loads Open3D. ``settings.zenoh_*`` picks the
publisher. The service (``arcloud.service``) sees only the ports.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any, TypeVar

from fastapi import FastAPI

from arcloud.errors import ArcloudError, InvalidInput, StoreUnavailable
from arcloud.ports import (
    DEFAULT_RETIRED_HISTORY_S,
    Detector,
    DeviceAlignments,
    FrameQueue,
    KeyStore,
    ObjectStore,
    RateLimiter,
    UpdatePublisher,
    ViewerPasses,
)
from arcloud.service import app as service_app
from arcloud.service.change_feed import ChangeFeed
from arcloud.service.logs import configure_logging
from arcloud.service.pool import WorkerPool
from arcloud.service.runtime import Adapters, Closeable, FrameHandler, close_all
from arcloud.service.settings import Settings
from arcloud.service.worker import FrameWorker

log = logging.getLogger(__name__)

SIM_PREFIX = "sim"

DetectorFactory = Callable[[], Detector]

if TYPE_CHECKING:
    from arcloud.stores.redis import RedisSideStore
Side = TypeVar("Side", bound="RedisSideStore")


# --- detectors ---------------------------------------------------------------------------------------
def _sim_detector(argument: str, *, threads: int = 0) -> Detector:
    """``sim:SEED`` -> ``SimulatedDetector(generate_room(SEED), seed=SEED)`` with the default faults."""
    from arcloud.sim.detector import SimulatedDetector
    from arcloud.sim.room import generate_room

    seed = _sim_seed(argument)
    return SimulatedDetector(generate_room(seed), seed=seed, threads=threads)


def _sim_seed(argument: str) -> int:
    try:
        seed = int(argument)
    except ValueError:
        raise InvalidInput("detector spec", "sim:SEED with SEED a non-negative integer", repr(f"sim:{argument}")) from None
    if seed < 0:
        raise InvalidInput("detector spec", "sim:SEED with SEED a non-negative integer", repr(f"sim:{argument}"))
    return seed


def register_sim_detector() -> dict[str, Any]:
    """Add ``sim:SEED`` to the detector registry (once); returns the registry."""
    from arcloud.detectors.factory import DETECTOR_FACTORIES, register_detector

    if SIM_PREFIX not in DETECTOR_FACTORIES:
        register_detector(SIM_PREFIX, _sim_detector)
    return DETECTOR_FACTORIES


def check_detector_spec(spec: str) -> str:
    """The spec, stripped, if its prefix names a known detector (and ``sim:`` has an integer seed);
    raises ``InvalidInput`` otherwise. Loads nothing."""
    if not isinstance(spec, str) or not spec.strip():
        raise InvalidInput("detector", "PREFIX[:ARGUMENT]", repr(spec))
    spec = spec.strip()
    prefix, _, argument = spec.partition(":")
    known = register_sim_detector()
    if prefix not in known:
        raise InvalidInput("detector", f"PREFIX[:ARGUMENT] with PREFIX one of {', '.join(sorted(known))}", repr(spec))
    if prefix == SIM_PREFIX:
        _sim_seed(argument)
    return spec


def check_model_file(spec: str) -> None:
    """``InvalidInput`` when the spec names a model file that is not there (before workers start)."""
    from arcloud.detectors.factory import check_model_file as check

    check(spec)


def check_redis_policy(settings: Settings) -> None:
    """``check_redis`` for a process that waits for its Redis (the containers' entry points: a pod may start before
    Redis does): a Redis that does not answer yet is a warning, one that may evict keys is refused (``StoreError``)."""
    try:
        check_redis(settings)
    except StoreUnavailable as exc:
        log.warning("%s; starting anyway, and waiting for it", exc)


def check_redis(settings: Settings) -> None:
    """``StoreUnavailable`` now, in one line naming where, when the service's Redis does not answer within 3 s (not
    a traceback from the API's start), and ``StoreError`` when it may evict keys (``check_memory_policy``); the keys'
    Redis too, when apart. Nothing for the embedded store."""
    from arcloud.stores.redis import check_memory_policy, connect_redis, memory_reports, where
    from arcloud.stores.redis_errors import redis_errors

    for url in dict.fromkeys(u for u in (None if settings.embedded else settings.store, settings.keys_store) if u):
        client = connect_redis(url, reply_timeout_s=3.0)
        try:
            with redis_errors("reach the store (start Redis, or give the URL it answers at)", partial(where, client)):
                client.ping()
                check_memory_policy(client)
                limits = [int(report.get("maxmemory", 0)) for report in memory_reports(client)]
            if url == settings.store and limits and all(limits) and settings.max_queued_bytes > sum(limits) // 2:
                log.warning(
                    "MAX_QUEUED_BYTES %d is over half of Redis's maxmemory (%d bytes): a backlog could fill it, and a full "
                    "Redis refuses the writes its workers need to drain the queue (docs/service.md, Redis's memory)",
                    settings.max_queued_bytes, sum(limits),
                )  # fmt: skip
        finally:
            client.close()


def check_zenoh_config(settings: Settings) -> None:
    """``InvalidInput`` naming ``zenoh_config`` now, when Zenoh cannot read it (not at the first session)."""
    if settings.zenoh_mode != "off" and settings.zenoh_config:
        from arcloud.events.zenoh import load_config_file

        load_config_file(settings.zenoh_config)


#: What sizes the thread pools of numpy's BLAS (the masks' matrix product) and of OpenMP; read once, when
#: the library loads, so a worker process must start with them (``worker_pool``).
LIBRARY_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def threads_per_process(processes: int) -> int:
    """This machine's cores (those this process may run on) shared among ``processes`` worker
    processes: at least one each, so that N workers do not each start a thread per core."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, cores // max(1, processes))


def build_detector(spec: str, *, threads: int | None = None) -> Detector:
    """The detector a spec names, loaded now (models, rooms); ``threads``: its compute threads
    (onnxruntime's intra-op threads, the simulator's ray-casting threads; None: one per core)."""
    from arcloud.detectors.factory import make_detector

    check_detector_spec(spec)
    options: dict[str, Any] = {}
    if threads is not None:
        options["threads" if spec.startswith(SIM_PREFIX) else "intra_op_threads"] = threads
    detector = make_detector(spec, **options)
    log.info("detector %s loaded", spec)
    return detector


# --- store, queue, publisher -------------------------------------------------------------------------
def build_store(
    url: str,
    *,
    cell_m: float,
    frame_record_retention_s: float,
    reply_timeout_s: float = 30.0,
    retired_history_s: float = DEFAULT_RETIRED_HISTORY_S,
) -> ObjectStore:
    """``memory`` -> ``MemoryStore``; a Redis URL -> ``RedisStore`` waiting ``reply_timeout_s`` at most for
    a reply (workers: 30 s; the API: ``api_redis_timeout_s``, so that a hung Redis answers 503 within about that).
    Processed frames' marks are kept ``frame_record_retention_s``, retired objects ``retired_history_s`` (the
    settings')."""
    if url == "memory":
        from arcloud.stores.memory import MemoryStore

        return MemoryStore(cell_m=cell_m, frame_record_retention_s=frame_record_retention_s, retired_history_s=retired_history_s)
    from arcloud.stores.redis import RedisStore

    return RedisStore(
        url,
        cell_m=cell_m,
        reply_timeout_s=reply_timeout_s,
        frame_record_retention_s=frame_record_retention_s,
        retired_history_s=retired_history_s,
    )


def build_queue(settings: Settings, *, store: ObjectStore | None = None, read_block_s: float = 0.0) -> FrameQueue:
    """``memory`` -> ``MemoryFrameQueue``; a Redis URL -> ``RedisFrameQueue`` of ``ingest_shards`` shards (on ``store``'s connections
    when it is a ``RedisStore``, else its own, whose reads may block ``read_block_s``)."""
    if settings.embedded:
        from arcloud.stores.memory_queue import MemoryFrameQueue

        return MemoryFrameQueue(limits=settings.queue_limits())
    from arcloud.stores.redis import RedisStore
    from arcloud.stores.redis_queue import RedisFrameQueue

    client = store.client if isinstance(store, RedisStore) else None
    return RedisFrameQueue(
        settings.store,
        client=client,
        group=settings.consumer_group,
        limits=settings.queue_limits(),
        shards=settings.ingest_shards,
        socket_timeout_s=max(30.0, 2 * read_block_s + 5),
    )


def on_redis(kind: type[Side], settings: Settings, store: ObjectStore | None, url: str | None = None) -> Side:
    """A side store of ``kind`` on its own Redis ``url`` when given, else on ``store``'s connections when it is a
    ``RedisStore``, else on the settings' store URL (connections of its own: the API's reply timeout)."""
    from arcloud.stores.redis import RedisStore

    if not url and isinstance(store, RedisStore):
        return kind(client=store.client)
    return kind(url or settings.store, reply_timeout_s=settings.api_redis_timeout_s)


def build_key_store(settings: Settings, store: ObjectStore | None = None) -> KeyStore | None:
    """The API keys: ``keys_file``, else ``keys_store``'s Redis, else the store's (on ``store``'s connections
    when it is a ``RedisStore``); None with auth none."""
    if settings.auth_mode == "none":
        return None
    if settings.keys_file:
        from arcloud.stores.file_api_keys import FileKeyStore

        return FileKeyStore(settings.keys_file)
    from arcloud.stores.redis_api_keys import RedisKeyStore

    return on_redis(RedisKeyStore, settings, store, settings.keys_store)


def build_viewer_passes(settings: Settings, store: ObjectStore | None = None) -> ViewerPasses | None:
    """The viewer's tickets and sessions: in memory (embedded), else beside the keys in Redis (``keys_store``'s, or
    the store's, on ``store``'s connections when it is a ``RedisStore``), shared by every API process; None with
    auth none (the viewer needs no pass)."""
    if settings.auth_mode == "none":
        return None
    if settings.embedded:
        from arcloud.stores.memory_viewer_passes import MemoryViewerPasses

        return MemoryViewerPasses()
    from arcloud.stores.redis_viewer_passes import RedisViewerPasses

    return on_redis(RedisViewerPasses, settings, store, settings.keys_store)


def build_rate_limiter(settings: Settings, store: ObjectStore | None = None) -> RateLimiter | None:
    """In memory (embedded) or on Redis (shared by every API process); None when every limit is off."""
    failures_limited = settings.auth_mode == "keys" and settings.auth_failure_rate_per_s > 0
    if settings.key_rate_per_s <= 0 and settings.map_frame_rate_per_s <= 0 and not failures_limited:
        return None
    if settings.embedded:
        from arcloud.stores.memory_rate import MemoryRateLimiter

        return MemoryRateLimiter()
    from arcloud.stores.redis_rate import RedisRateLimiter

    return on_redis(RedisRateLimiter, settings, store)


def build_alignments(settings: Settings, store: ObjectStore | None = None) -> DeviceAlignments:
    """The devices' alignments: in memory (embedded), else in the store's Redis (on ``store``'s connections when
    it is a ``RedisStore``), shared by every API process."""
    if settings.embedded:
        from arcloud.stores.memory_alignments import MemoryDeviceAlignments

        return MemoryDeviceAlignments()
    from arcloud.stores.redis_alignments import RedisDeviceAlignments

    return on_redis(RedisDeviceAlignments, settings, store)


def build_publisher(settings: Settings, store: ObjectStore, on_frame: FrameHandler | None) -> UpdatePublisher | None:
    """The API's Zenoh session (from ``zenoh_config``'s file, if any; answering map queries from ``store``;
    taking published frames when ``zenoh_frames``), or None when Zenoh is off."""
    if settings.zenoh_mode == "off":
        return None
    from arcloud.events.zenoh import ZenohPublisher

    return ZenohPublisher(
        mode=settings.zenoh_mode,
        listen=settings.zenoh_listen,
        connect=settings.zenoh_connect,
        store=store,
        on_frame=on_frame if settings.zenoh_frames else None,
        config_file=settings.zenoh_config,
    )


def worker_publisher(settings: Settings) -> UpdatePublisher | None:
    """A Zenoh client session for a worker process: to ``zenoh_connect`` (a router), else to the API's
    listen endpoints, from ``zenoh_config``'s file (its credentials), if any. None when Zenoh is off."""
    if settings.zenoh_mode == "off":
        return None
    from arcloud.events.zenoh import ZenohPublisher, connectable

    endpoints = settings.zenoh_connect or connectable(settings.zenoh_listen)
    if not endpoints:
        log.warning("zenoh is on but no endpoint to connect to: this worker publishes no events")
        return None
    return ZenohPublisher(mode="client", connect=endpoints, config_file=settings.zenoh_config)


# --- the app -----------------------------------------------------------------------------------------
def connect(
    settings: Settings,
    on_frame: FrameHandler,
    *,
    store: ObjectStore | None = None,
    queue: FrameQueue | None = None,
    detector: Detector | None = None,
    publisher: UpdatePublisher | None = None,
    host_workers: int = 0,
) -> Adapters:
    """The adapters of one app: those given, and the ones the settings name for the rest (owned by the
    app: closed on shutdown). Embedded: the detector, run by ``settings.workers`` threads. Redis:
    ``settings.workers`` worker processes (none: they run elsewhere, ``host_workers`` of them in another process
    of this host); a detector cannot be given."""
    owned: list[Closeable] = []
    try:
        if not settings.embedded and detector is not None:
            raise InvalidInput(
                "detector",
                "none with a Redis store (worker processes build theirs from settings.detector)",
                type(detector).__name__,
            )
        params = settings.make_params()
        if store is None:
            store = build_store(
                settings.store,
                cell_m=params.index_cell_m,
                reply_timeout_s=settings.api_redis_timeout_s,
                frame_record_retention_s=settings.frame_record_retention_s,
                retired_history_s=settings.retired_history_s,
            )
            _own(owned, store)
        if publisher is None:
            publisher = build_publisher(settings, store, on_frame)
            _own(owned, publisher)
        if queue is None:
            queue = build_queue(settings, store=store)
            _own(owned, queue)
        keys = build_key_store(settings, store)
        _own(owned, keys)
        limiter = build_rate_limiter(settings, store)
        _own(owned, limiter)
        viewer_passes = build_viewer_passes(settings, store)
        _own(owned, viewer_passes)
        alignments = build_alignments(settings, store)
        _own(owned, alignments)
        pool = None
        if settings.embedded:
            if detector is None:
                detector = build_detector(settings.detector, threads=settings.detector_threads)
        elif settings.workers > 0:
            pool = worker_pool(settings, settings.workers)
    except BaseException:
        close_all(owned)
        raise
    from arcloud.stores.snapshot import ZipMapArchive

    return Adapters(
        store, queue, detector, publisher, pool, keys, limiter, ZipMapArchive(), owned, alignments, viewer_passes, host_workers
    )


def _own(owned: list[Closeable], thing: Any) -> None:
    """Keep ``thing`` (an adapter built here, or None) to close on shutdown."""
    if thing is not None:
        owned.append(thing)


def create_app(
    settings: Settings | None = None,
    *,
    store: ObjectStore | None = None,
    queue: FrameQueue | None = None,
    detector: Detector | None = None,
    publisher: UpdatePublisher | None = None,
    host_workers: int = 0,
) -> FastAPI:
    """The service on the adapters the settings name. Not given, they are read from ``ARCLOUD_*`` and, as
    this is then the process's entry point (``uvicorn --factory``), configure its logging too
    (``log_level``, ``log_format``) and check its Redis (``check_redis_policy``: exit 2 with one line when it evicts).
    ``store``, ``queue``, ``detector``, ``publisher``: adapters to use instead (tests, embedding); the caller keeps
    ownership of what it passes. ``host_workers``: worker processes another process of this host runs for it
    (``serve --api-processes``), expected by ``/healthz/workers``. Checks the detector spec now; builds nothing until
    the app starts."""
    if settings is None:
        settings = Settings()
        configure_logging(settings.log_level, settings.log_format)
        try:
            check_redis_policy(settings)  # the image's API (uvicorn --factory) starts here: refused on an evicting Redis
        except ArcloudError as exc:
            log.error("%s", exc)  # one line in the container's log, and no API on a Redis that would lose its data
            raise SystemExit(2) from exc
    check_detector_spec(settings.detector)
    return service_app.create_app(
        settings, partial(connect, store=store, queue=queue, detector=detector, publisher=publisher, host_workers=host_workers)
    )


# --- workers -----------------------------------------------------------------------------------------
def run_worker(
    settings: Settings,
    *,
    detector_factory: DetectorFactory | None = None,
    stop: threading.Event | None = None,
    processes: int = 1,
) -> None:
    """One worker in this process until SIGTERM/SIGINT (or ``stop``). ``processes``: how many worker
    processes share this machine's cores (the detector's threads default to this one's share)."""
    from arcloud.allocator import keep_freed_memory

    if settings.embedded:
        raise InvalidInput("store", "a Redis URL for stream workers", "memory")
    keep_freed_memory()
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, lambda *_: stop.set())
    params = settings.make_params()
    owned: list[Closeable] = []
    try:
        store = build_store(
            settings.store,
            cell_m=params.index_cell_m,
            frame_record_retention_s=settings.frame_record_retention_s,
            retired_history_s=settings.retired_history_s,
        )
        _own(owned, store)
        threads = settings.detector_threads or threads_per_process(processes)
        import cv2

        cv2.setNumThreads(threads)  # its resizes and colour conversions: this process's share of the cores, as the rest
        if detector_factory is not None:
            detector = detector_factory()
        else:
            detector = build_detector(settings.detector, threads=threads)
        publisher = worker_publisher(settings)
        _own(owned, publisher)
        queue = build_queue(settings, read_block_s=settings.read_block_s)
        _own(owned, queue)
        FrameWorker(
            queue,
            store,
            detector,
            params,
            ChangeFeed(store, publisher) if publisher is not None else None,
            claim_min_idle_s=settings.claim_min_idle_s,
            claim_interval_s=settings.claim_interval_s,
            max_deliveries=settings.max_deliveries,
            read_block_s=settings.read_block_s,
            warm_up=True,
            prefetch=settings.worker_prefetch,
            monitor=queue,
        ).run(stop)
    finally:
        close_all(owned)


def worker_process(settings: Settings, detector_factory: DetectorFactory | None, processes: int) -> None:
    """The body of a worker process of a ``WorkerPool`` (spawned: it configures its own logging); a refusal
    (``ArcloudError``: another live worker maps with other settings) is one line logged, and exit status 2."""
    configure_logging(settings.log_level, settings.log_format)
    try:
        run_worker(settings, detector_factory=detector_factory, processes=processes)
    except ArcloudError as exc:
        log.error("%s", exc)
        raise SystemExit(2) from exc


def worker_pool(
    settings: Settings, size: int, *, detector_factory: DetectorFactory | None = None, restart: bool = True
) -> WorkerPool:
    """``size`` worker processes on the settings' queue. ``detector_factory``: a picklable callable
    building each worker's detector (default: the settings' spec)."""
    threads = str(settings.detector_threads or threads_per_process(size))
    return WorkerPool(
        size,
        worker_process,
        (settings, detector_factory, size),
        claim_after_s=settings.claim_min_idle_s,
        restart=restart,
        env=dict.fromkeys(LIBRARY_THREAD_VARIABLES, threads),
    )


def healthy(settings: Settings, host: str | None = None, max_age_s: float = 10.0) -> bool:
    """Whether a worker on ``host`` (default: this one) wrote a heartbeat in the last ``max_age_s`` (False
    when Redis does not answer within 3 s)."""
    from arcloud.service.worker import of_host
    from arcloud.stores.redis import connect_redis
    from arcloud.stores.redis_queue import RedisFrameQueue

    try:
        client = connect_redis(settings.store, reply_timeout_s=3.0)  # a hung Redis: unhealthy in 3 s
    except StoreUnavailable:  # a cluster's client reads its slot map at once
        return False
    try:
        queue = RedisFrameQueue(client=client, group=settings.consumer_group)
        return any(of_host(name, host) for name in queue.live_consumers(max_age_s))
    except StoreUnavailable:
        return False
    finally:
        client.close()


__all__ = [
    "build_alignments",
    "build_detector",
    "build_key_store",
    "build_publisher",
    "build_queue",
    "build_rate_limiter",
    "build_store",
    "check_detector_spec",
    "check_model_file",
    "check_redis",
    "check_redis_policy",
    "check_zenoh_config",
    "connect",
    "create_app",
    "healthy",
    "register_sim_detector",
    "run_worker",
    "threads_per_process",
    "worker_pool",
    "worker_process",
    "worker_publisher",
]
