"""Prometheus metrics of the service: the frame queue's counters (``QueueStats``) read at scrape time, the
HTTP requests this process answered (``HttpMetrics``), and the process itself (prometheus-client's process,
platform and garbage collector collectors: ``process_*``, ``python_*``).

One registry per app (several apps in one process never clash). With a shared queue (Redis) the frame
counters are every worker's, so any API replica reports the whole deployment's frames, per map and per worker
too; the HTTP and process metrics are this process's.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable, Iterator, MutableMapping
from dataclasses import dataclass
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Gauge
from prometheus_client import Histogram as PromHistogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector
from prometheus_client.registry import Collector

from arcloud.errors import StoreError
from arcloud.ports import LATENCY_BUCKETS_S, SETTLED_OUTCOMES, Histogram
from arcloud.service.ingest import Ingest
from arcloud.service.worker import LIVE_WORKER_S

#: At most this many maps get series of their own (those with the most frames settled, and every map with frames
#: queued among them first): a label value per map, and maps are made by clients.
MAX_MAP_SERIES = 500
#: Upper bounds (seconds) of the HTTP request duration histogram's buckets: a probe's millisecond to a slow export.
HTTP_BUCKETS_S: tuple[float, ...] = (0.001, 0.0025, *LATENCY_BUCKETS_S)
#: The methods counted as themselves; any other is counted as ``other`` (a label value per method sent: unbounded).
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "DELETE", "PATCH", "OPTIONS"})
UNMATCHED_ROUTE = "unmatched"  # the route label of a request no route took (a 404): paths are the client's

log = logging.getLogger(__name__)


class IngestCollector(Collector):
    """Frames accepted/processed/failed, queue depth (frames and bytes), live workers, and the histograms of
    the step latency, the queue wait and the lock wait."""

    def __init__(self, ingest: Callable[[], Ingest | None]) -> None:
        self._ingest = ingest
        self._unread = False  # the last scrape could not read the counters (logged once an outage)

    def collect(self) -> Iterator[Metric]:
        ingest = self._ingest()
        if ingest is None:  # before start-up
            return
        try:
            snap, live, workers_ok = ingest.stats(), ingest.live_workers(), ingest.workers_health().ok
        except StoreError as exc:  # the queue's store unreachable: its counters are left out, the rest is served
            if not self._unread:
                log.warning("metrics: the frame counters are left out while the queue's store is unreachable (%s)", exc)
            self._unread = True
            yield counters_up(0.0)
            yield workers_up(0.0)
            return
        self._unread = False
        yield counters_up(1.0)
        for name, value, text in (
            ("arcloud_frames_accepted", snap.accepted, "Frames validated and queued"),
            ("arcloud_frames_duplicate", snap.duplicates, "Frames posted again after being accepted (not queued)"),
            ("arcloud_frames_processed", snap.processed, "Frames whose step committed"),
            (
                "arcloud_frames_redelivered",
                snap.redelivered,
                "Frames delivered again after their commit (not processed again: idempotent)",
            ),
            ("arcloud_frames_failed", snap.failed, "Frames given up on (dead-lettered)"),
            ("arcloud_frames_claimed", snap.claimed, "Frames taken over from a worker that stopped"),
            ("arcloud_step_retries", snap.retried, "Steps tried again after a lock timeout or a stale lease"),
        ):
            yield CounterMetricFamily(name, text, value=value)
        yield GaugeMetricFamily("arcloud_queue_depth", "Frames queued or in progress", value=snap.queue_depth)
        yield GaugeMetricFamily(
            "arcloud_queue_bytes", "Bytes the queue holds of the frames queued or in progress", value=snap.queued_bytes
        )
        yield GaugeMetricFamily(
            "arcloud_live_workers",
            f"Workers taking frames: worker threads alive (embedded), else workers with a heartbeat in the last "
            f"{LIVE_WORKER_S:.0f} s",
            value=live,
        )
        cumulative, buckets = 0, []
        for bound, count in zip((*LATENCY_BUCKETS_S, float("inf")), snap.latency_counts):
            cumulative += count
            buckets.append(("+Inf" if bound == float("inf") else repr(bound), cumulative))
        yield HistogramMetricFamily(
            "arcloud_step_latency_seconds",
            "Time of the per-frame step (detect to commit)",
            buckets=buckets,
            sum_value=snap.latency_sum_s,
        )
        yield from settled_families(snap.maps, snap.map_depth, snap.workers)
        yield workers_up(1.0 if workers_ok else 0.0)
        for name, histogram, text in (
            (
                "arcloud_queue_wait_seconds",
                snap.queue_wait,
                "Time a frame waited in the queue, from its acceptance until a worker took it",
            ),
            ("arcloud_lock_wait_seconds", snap.lock_wait, "Time a frame's step spent taking object locks and space claims"),
        ):
            yield HistogramMetricFamily(name, text, buckets=cumulative_buckets(histogram), sum_value=histogram.sum_s)


def counters_up(value: float) -> Metric:
    return GaugeMetricFamily(
        "arcloud_frame_counters_up",
        "1 when this scrape read the frame queue's counters, else 0 (its store unreachable: the arcloud_frames_*, "
        "queue, latency and per-map series are left out, and arcloud_workers_up is 0)",
        value=value,
    )


def workers_up(value: float) -> Metric:
    return GaugeMetricFamily(
        "arcloud_workers_up",
        "1 when the workers take the frames accepted (GET /healthz/workers answers 200), else 0",
        value=value,
    )


def cumulative_buckets(histogram: Histogram) -> list[tuple[str, float]]:
    """A ``Histogram``'s counts as Prometheus's cumulative (le, count) pairs, +Inf last."""
    cumulative, buckets = 0, list[tuple[str, float]]()
    for bound, count in zip((*histogram.bounds_s, float("inf")), histogram.counts):
        cumulative += count
        buckets.append(("+Inf" if bound == float("inf") else repr(bound), cumulative))
    return buckets


def settled_families(
    maps: dict[str, dict[str, int]], map_depth: dict[str, int], workers: dict[str, dict[str, int]]
) -> Iterator[Metric]:
    """The frames settled per map (``map_id``: at most ``MAX_MAP_SERIES`` maps) and per worker (``worker``: its
    consumer name, as in the logs), by outcome, and each map's frames queued or in progress."""
    ranked = sorted(set(maps) | set(map_depth), key=lambda m: (-map_depth.get(m, 0), -sum(maps.get(m, {}).values()), m))
    shown = ranked[:MAX_MAP_SERIES]
    for kind, label, names, counts in (("map", "map_id", shown, maps), ("worker", "worker", sorted(workers), workers)):
        for outcome in SETTLED_OUTCOMES:
            family = CounterMetricFamily(
                f"arcloud_{kind}_frames_{outcome}",
                f"Frames {outcome} ({'dead-lettered' if outcome == 'failed' else 'settled'}), by {kind}",
                labels=[label],
            )
            for name in names:
                family.add_metric([name], counts.get(name, {}).get(outcome, 0))
            yield family
    depth = GaugeMetricFamily("arcloud_map_queue_depth", "Frames of the map queued or in progress", labels=["map_id"])
    for name in shown:
        depth.add_metric([name], map_depth.get(name, 0))
    yield depth


@dataclass(frozen=True, eq=False)
class ServiceMetrics:
    """An app's metrics: its ``registry`` (what ``/metrics`` serves), the counter of refused frame uploads (by
    status), and the HTTP request metrics ``HttpMetrics`` records."""

    registry: CollectorRegistry
    rejected: Counter
    requests: Counter
    duration: PromHistogram
    in_flight: Gauge


def make_registry(ingest: Callable[[], Ingest | None]) -> ServiceMetrics:
    """A registry with the ingest collector, the process, platform and GC collectors, the counter of rejected
    frame uploads and the HTTP request metrics."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(IngestCollector(ingest))
    ProcessCollector(registry=registry)
    PlatformCollector(registry=registry)
    GCCollector(registry=registry)
    rejected = Counter("arcloud_frames_rejected", "Frame uploads refused, by HTTP status", ["status"], registry=registry)
    requests = Counter(
        "http_requests",
        "HTTP requests answered, by method, route template (unmatched: no route) and status",
        ["method", "route", "status"],
        registry=registry,
    )
    duration = PromHistogram(
        "http_request_duration_seconds",
        "Time from a request's arrival to the end of its answer, by method and route template (an event stream: while open)",
        ["method", "route"],
        buckets=HTTP_BUCKETS_S,
        registry=registry,
    )
    in_flight = Gauge("http_requests_in_flight", "HTTP requests being answered (event streams while open)", registry=registry)
    return ServiceMetrics(registry, rejected, requests, duration, in_flight)


class HttpMetrics:
    """ASGI middleware counting each HTTP request by method, route template and status, timing it to the end of
    its answer, and counting the requests in flight. The route is the one the router took (``scope["route"]``),
    else the first of ``routes(scope)`` (the templates whose path matches: a refusal before routing, the body
    limit's 413), else ``unmatched``; a request whose exception escaped the app counts as 500 (the answer the
    app's last handler gives)."""

    def __init__(
        self,
        app: Callable[..., Awaitable[None]],
        metrics: ServiceMetrics,
        routes: Callable[[MutableMapping[str, Any]], list[str]] = lambda scope: [],
    ) -> None:
        self.app = app
        self.metrics = metrics
        self.routes = routes

    async def __call__(
        self,
        scope: MutableMapping[str, Any],
        receive: Callable[[], Awaitable[dict[str, Any]]],
        send: Callable[[dict[str, Any]], Awaitable[None]],
    ) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500

        async def counted(message: dict[str, Any]) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        self.metrics.in_flight.inc()
        try:
            await self.app(scope, receive, counted)
        finally:
            self.metrics.in_flight.dec()
            method = scope.get("method", "")
            method = method if method in HTTP_METHODS else "other"
            route = route_template(scope, self.routes)
            self.metrics.requests.labels(method, route, str(status)).inc()
            self.metrics.duration.labels(method, route).observe(time.perf_counter() - started)


def route_template(scope: MutableMapping[str, Any], routes: Callable[[MutableMapping[str, Any]], list[str]]) -> str:
    """The path template of the route that took the request (``/v1/maps/{map_id}/objects``), else the first of
    ``routes(scope)``, else ``UNMATCHED_ROUTE``."""
    path = getattr(scope.get("route"), "path", None)  # a Route's or a Mount's (a BaseRoute may have none)
    return path if isinstance(path, str) and path else next(iter(routes(scope)), UNMATCHED_ROUTE)


__all__ = ["HttpMetrics", "IngestCollector", "ServiceMetrics", "make_registry", "route_template"]
