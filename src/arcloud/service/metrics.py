"""Prometheus metrics of the service, read from the frame queue's counters (``QueueStats``) at scrape time.

One collector per app on the app's own registry (several apps in one process never clash). With a
shared queue (Redis) the counters are every worker's, so any API replica reports the whole deployment's
frames and step latencies.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Counter
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from arcloud.ports import LATENCY_BUCKETS_S, Histogram
from arcloud.service.ingest import Ingest
from arcloud.service.worker import LIVE_WORKER_S


class IngestCollector(Collector):
    """Frames accepted/processed/failed, queue depth (frames and bytes), live workers, and the histograms of
    the step latency, the queue wait and the lock wait."""

    def __init__(self, ingest: Callable[[], Ingest | None]) -> None:
        self._ingest = ingest

    def collect(self) -> Iterator[Metric]:
        ingest = self._ingest()
        if ingest is None:  # before start-up
            return
        snap = ingest.stats()
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
            value=ingest.live_workers(),
        )
        cumulative, buckets = 0, []
        for bound, count in zip((*LATENCY_BUCKETS_S, float("inf")), snap.latency_counts):
            cumulative += count
            buckets.append(("+Inf" if bound == float("inf") else repr(bound), cumulative))
        yield HistogramMetricFamily(
            "arcloud_step_latency_seconds",
            "Time of the per-frame step (detect to publish)",
            buckets=buckets,
            sum_value=snap.latency_sum_s,
        )
        for name, histogram, text in (
            (
                "arcloud_queue_wait_seconds",
                snap.queue_wait,
                "Time a frame waited in the queue, from its acceptance until a worker took it",
            ),
            ("arcloud_lock_wait_seconds", snap.lock_wait, "Time a frame's step spent taking object locks and space claims"),
        ):
            yield HistogramMetricFamily(name, text, buckets=cumulative_buckets(histogram), sum_value=histogram.sum_s)


def cumulative_buckets(histogram: Histogram) -> list[tuple[str, float]]:
    """A ``Histogram``'s counts as Prometheus's cumulative (le, count) pairs, +Inf last."""
    cumulative, buckets = 0, list[tuple[str, float]]()
    for bound, count in zip((*histogram.bounds_s, float("inf")), histogram.counts):
        cumulative += count
        buckets.append(("+Inf" if bound == float("inf") else repr(bound), cumulative))
    return buckets


def make_registry(ingest: Callable[[], Ingest | None]) -> tuple[CollectorRegistry, Counter]:
    """A registry with the ingest collector, and the counter of rejected frame uploads (by status)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(IngestCollector(ingest))
    rejected = Counter("arcloud_frames_rejected", "Frame uploads refused, by HTTP status", ["status"], registry=registry)
    return registry, rejected
