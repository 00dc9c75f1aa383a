"""The service as ``serve --redis URL --workers 2`` runs it (uvicorn, two worker processes) while its Redis
fails: restarted without its data, then hung (SIGSTOP). The tests share one deployment (worker processes
take seconds to start) and print what they measured.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import httpx
import pytest
from chaos_helpers import frozen, restart_empty
from prometheus_client.parser import text_string_to_metric_families
from redis_server import RedisServer
from svc_helpers import UvicornThread, make_blob_detector, make_test_frame, wait_until

from arcloud.client import ArcloudClient
from arcloud.service import app as service_app
from arcloud.service.runtime import Adapters, FrameHandler
from arcloud.service.settings import Settings
from arcloud.stores.keys import ingest_counts_key, shard_tag
from arcloud.tools import wiring

pytestmark = [pytest.mark.redis, pytest.mark.slow]

RECOVERY_BOUND_S = 30.0  # a new frame is processed this soon after Redis is back empty
UNAVAILABLE_BOUND_S = 5.0  # a request answers 503 this soon while Redis hangs
HEALTHZ_BOUND_S = 1.0


def connect_blob_workers(settings: Settings, on_frame: FrameHandler) -> Adapters:
    """``wiring.connect`` with the pool's workers running the blob detector (no model to load)."""
    adapters = wiring.connect(settings.model_copy(update={"workers": 0}), on_frame)
    adapters.pool = wiring.worker_pool(settings, settings.workers, detector_factory=make_blob_detector)
    return adapters


@dataclass
class Serving:
    redis: RedisServer
    url: str
    app: Any = None

    def in_flight(self) -> float:
        """HTTP requests the API has taken and not yet answered (its gauge alone: the whole registry reads Redis)."""
        (gauge,) = self.app.state.metrics_registry.restricted_registry(["http_requests_in_flight"]).collect()
        return float(gauge.samples[0].value)

    def client(self) -> ArcloudClient:
        return ArcloudClient(self.url, max_retries=10, backoff_s=0.1, max_backoff_s=1.0, seed=0)

    def ready(self) -> bool:
        return httpx.get(f"{self.url}/readyz", timeout=10).status_code == 200


@pytest.fixture(scope="module")
def serving() -> Iterator[Serving]:
    server = RedisServer.start()
    settings = Settings(store=server.url, auth="none", workers=2, read_block_s=0.2, claim_interval_s=0.5)
    deployment = Serving(server, "")
    try:
        deployment.app = service_app.create_app(settings, connect_blob_workers)
        with UvicornThread(deployment.app) as api:
            deployment.url = api.url
            wait_until(deployment.ready, 90, "the service ready (2 workers reading)", 0.2)
            yield deployment
    finally:
        deployment.redis.stop()


class ReadyWatch:
    """``/readyz`` polled every 50 ms in a thread: (seconds since start, status, checks) each time."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.seen: list[tuple[float, int, dict[str, Any]]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._started = time.monotonic()

    def _watch(self) -> None:
        with httpx.Client(timeout=10) as http:
            while not self._stop.wait(0.05):
                try:
                    response = http.get(f"{self.url}/readyz")
                    self.seen.append((time.monotonic() - self._started, response.status_code, response.json()["checks"]))
                except httpx.HTTPError as exc:
                    self.seen.append((time.monotonic() - self._started, 0, {"error": repr(exc)}))

    def __enter__(self) -> ReadyWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(15)


def test_redis_restarted_empty_the_service_recovers_without_a_restart(serving: Serving) -> None:
    with serving.client() as client:
        client.send_frame(make_test_frame(0, map_id="a"))
        client.wait_until_processed("a", 1, 30)
        with ReadyWatch(serving.url) as watch:
            time.sleep(0.3)
            serving.redis = restart_empty(serving.redis)
            back_at = time.monotonic()
            answer = client.send_frame(make_test_frame(1, map_id="a"))
            client.wait_until_processed("a", 1, RECOVERY_BOUND_S)
            processed_s = time.monotonic() - back_at
            stats = client.stats("a")
            wait_until(serving.ready, RECOVERY_BOUND_S, "/readyz ready again", 0.1)
            ready_s = time.monotonic() - back_at
    print(f"\nRedis back empty: new frame processed after {processed_s:.2f} s, /readyz ready after {ready_s:.2f} s")
    assert answer.status == "queued" and (
        stats.frames.accepted,
        stats.frames.processed,
        stats.frames.failed,
        stats.frames.pending,
    ) == (1, 1, 0, 0)
    assert processed_s <= RECOVERY_BOUND_S
    statuses = [status for _, status, _ in watch.seen]
    assert statuses[0] == 200 and 503 in statuses, statuses
    first_down = statuses.index(503)
    assert 200 in statuses[first_down:] or serving.ready()
    reasons = {key: value for _, status, checks in watch.seen if status == 503 for key, value in checks.items() if value != "ok"}
    print(f"/readyz while down: {reasons}")


def test_a_hung_redis_gives_503_quickly_and_healthz_answers(serving: Serving) -> None:
    with serving.client() as client:
        client.send_frame(make_test_frame(2, map_id="b"))
        client.wait_until_processed("b", 1, 30)
    objects = f"{serving.url}/v1/maps/b/objects"
    with frozen(serving.redis), httpx.Client(timeout=30) as http:
        started = time.monotonic()
        refused = http.get(objects)
        refused_s = time.monotonic() - started
        with ThreadPoolExecutor(60) as pool:  # more than the API's worker threads (40): every one waits on Redis
            flood = [pool.submit(http.get, objects) for _ in range(60)]
            wait_until(lambda: serving.in_flight() >= 60, 10, "the 60 requests taken by the API", 0.01)
            started = time.monotonic()
            health = http.get(f"{serving.url}/healthz")
            healthz_s = time.monotonic() - started
            flooded = [f.result() for f in flood]
        started = time.monotonic()
        not_ready = http.get(f"{serving.url}/readyz")
        readyz_s = time.monotonic() - started
        started = time.monotonic()
        scrape = http.get(f"{serving.url}/metrics")
        scrape_s = time.monotonic() - started
        started = time.monotonic()
        worker_healthy = wiring.healthy(Settings(store=serving.redis.url))  # the containers' healthcheck
        healthcheck_s = time.monotonic() - started
    print(
        f"\nRedis hung: objects 503 in {refused_s:.2f} s, /healthz 200 in {healthz_s:.3f} s under 60 waiting requests, "
        f"/readyz 503 in {readyz_s:.2f} s, /metrics 200 in {scrape_s:.2f} s, worker healthcheck false in {healthcheck_s:.2f} s"
    )
    assert refused.status_code == 503 and refused.headers["retry-after"] == "5", refused.text
    assert refused_s <= UNAVAILABLE_BOUND_S
    assert health.status_code == 200 and healthz_s <= HEALTHZ_BOUND_S
    assert {r.status_code for r in flooded} == {503}
    assert not_ready.status_code == 503 and not_ready.json()["checks"]["store"].startswith("unreachable")
    assert not worker_healthy and healthcheck_s <= UNAVAILABLE_BOUND_S
    # /metrics still answers (a new user's review: a 503, and the scrape of the process and HTTP series lost with it)
    assert scrape.status_code == 200 and scrape_s <= UNAVAILABLE_BOUND_S, scrape.text
    scraped = {s.name: s.value for family in text_string_to_metric_families(scrape.text) for s in family.samples}
    assert scraped["arcloud_frame_counters_up"] == 0 and scraped["arcloud_workers_up"] == 0
    assert "process_resident_memory_bytes" in scraped and "arcloud_frames_processed_total" not in scraped
    # Redis answers again: all is well, without a restart.
    wait_until(lambda: httpx.get(objects, timeout=10).status_code == 200, 10, "objects served again", 0.1)
    wait_until(serving.ready, 30, "/readyz ready again", 0.1)
    with serving.client() as client:
        client.send_frame(make_test_frame(3, map_id="b"))
        client.wait_until_processed("b", 2, 30)
    scraped = {
        s.name: s.value for f in text_string_to_metric_families(httpx.get(f"{serving.url}/metrics").text) for s in f.samples
    }
    assert scraped["arcloud_frame_counters_up"] == 1 and scraped["arcloud_frames_processed_total"] >= 2


def test_replay_survives_a_redis_restart_mid_run(serving: Serving) -> None:
    from arcloud.tools.replay import replay

    def accepted() -> int:
        with serving.redis.client() as client:
            return int(client.hget(ingest_counts_key(shard_tag(0, 1), "walk"), "accepted") or 0)  # one shard (the default)

    started = time.monotonic()
    with ThreadPoolExecutor(1) as pool:
        running = pool.submit(
            replay, serving.url, "walk", 2, 0, None, n_frames=40, width=160, height=120, timeout_s=60, show_progress=False
        )
        wait_until(lambda: accepted() >= 5, 60, "replay's first frames accepted", 0.01)
        serving.redis = restart_empty(serving.redis)
        results = running.result(timeout=120)
    elapsed_s = time.monotonic() - started
    frames = results["frames"]
    print(f"\nreplay through a Redis restart: {frames} in {elapsed_s:.1f} s")
    assert frames["sent"] == 40 and frames["accepted"] + frames["duplicate"] == 40 and frames["lost"] >= 5
    assert frames["processed"] + frames["failed"] <= 40 - frames["lost"] + 2  # + the frames in workers' hands at the restart
