"""Queue wait and lock wait: the worker times them (``LockTimer``, the delivery's ``accepted_at_s``), the queue
counts them, and ``/metrics`` serves them as histograms that count every processed frame."""

from __future__ import annotations

import threading
import time

from prometheus_client.parser import text_string_to_metric_families
from svc_helpers import AppClient, make_blob_detector, make_test_frame, wait_until

from arcloud.ports import WAIT_BUCKETS_S
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.service.worker import LockTimer
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
WAITS = ("arcloud_queue_wait_seconds", "arcloud_lock_wait_seconds")


def histograms(text: str) -> dict[str, dict[str, float]]:
    """Each histogram of a /metrics text: sample name (and ``le`` for buckets) -> value."""
    found: dict[str, dict[str, float]] = {}
    for family in text_string_to_metric_families(text):
        if family.type == "histogram":
            found[family.name] = {
                sample.name + (f"[{sample.labels['le']}]" if "le" in sample.labels else ""): sample.value
                for sample in family.samples
            }
    return found


def test_the_wait_histograms_count_every_processed_frame() -> None:
    frames = [make_test_frame(i, map_id="waits", device_id=f"d{i % 2}") for i in range(6)]
    with AppClient(create_app(Settings(workers=2), detector=make_blob_detector(delay_s=0.05))) as client:
        before = histograms(client.get("/metrics").text)
        for name in WAITS:  # served from the start, empty
            assert before[name][f"{name}_count"] == 0 and before[name][f"{name}_bucket[+Inf]"] == 0
        for frame in frames:
            body = frame_to_proto(frame).SerializeToString()
            assert client.post("/v1/maps/waits/frames", content=body, headers=PROTOBUF).status_code == 202
        wait_until(lambda: client.get("/v1/maps/waits/stats").json()["frames"]["processed"] == 6, 60, "6 frames processed")
        after = histograms(client.get("/metrics").text)
    for name in WAITS:
        samples = after[name]
        buckets = [samples[f"{name}_bucket[{bound!r}]"] for bound in WAIT_BUCKETS_S] + [samples[f"{name}_bucket[+Inf]"]]
        assert buckets == sorted(buckets) and buckets[-1] == samples[f"{name}_count"] == 6, (name, buckets)
        assert samples[f"{name}_sum"] > 0, name
    # 2 workers, 6 frames posted at once, each detection 50 ms: the last frames waited for a worker.
    assert after["arcloud_queue_wait_seconds"]["arcloud_queue_wait_seconds_sum"] >= 0.05
    assert after["arcloud_step_latency_seconds"]["arcloud_step_latency_seconds_count"] == 6


def test_the_lock_timer_counts_the_time_another_holder_kept_the_objects() -> None:
    store = MemoryStore(cell_m=1.0)
    timer = LockTimer(store)
    held = store.lock("m", [1, 2], ttl_s=10, timeout_s=0)
    # Held 0.3 s from before the timed call: at least 0.2 s of it is waited inside the call, unless the waiting
    # thread is held back over 0.1 s before it starts (the 0.2 s hold it had measured 0.196 s on a loaded machine).
    releaser = threading.Timer(0.3, held.release)
    releaser.start()
    started = time.perf_counter()
    with timer.lock("m", [2, 3], ttl_s=10, timeout_s=5):
        waited_s = time.perf_counter() - started
    releaser.join()
    assert 0.2 <= timer.lock_wait_s <= waited_s  # the call's time, within what the test saw
    locked_s = timer.lock_wait_s
    started = time.perf_counter()
    with timer.claim("m", [(0, 0, 0)], ttl_s=10, timeout_s=0):  # free cells: added, taken at once
        claimed_s = time.perf_counter() - started
    assert 0 < timer.lock_wait_s - locked_s <= claimed_s
