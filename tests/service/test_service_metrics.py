"""``/metrics`` of a real app: prometheus-client's process, platform and GC collectors; HTTP requests counted by
method, route template and status, timed, and in flight; frames settled per map and per worker; the workers' health
as a gauge."""

from __future__ import annotations

import re
from pathlib import Path

from prometheus_client.parser import text_string_to_metric_families
from svc_helpers import AppClient, BlobDetector, make_test_frame, wait_until

from arcloud.proto.convert import frame_to_proto
from arcloud.service.metrics import MAX_MAP_SERIES, settled_families
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
SERVICE_DOCS = Path(__file__).resolve().parents[2] / "docs" / "service.md"


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """(sample name, sorted labels) -> value of every sample of a scrape."""
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def test_metrics_has_process_http_per_map_and_per_worker_series() -> None:
    settings = Settings(detector="sim:0", workers=1, auth="none", max_frame_bytes=100_000)
    with AppClient(create_app(settings, detector=BlobDetector())) as api:
        for index, map_id in ((0, "ma"), (1, "ma"), (2, "mb")):
            body = frame_to_proto(make_test_frame(index, map_id=map_id)).SerializeToString()
            assert api.post(f"/v1/maps/{map_id}/frames", content=body, headers=PROTOBUF).status_code == 202
        wait_until(lambda: api.get("/v1/maps/ma/stats").json()["frames"]["processed"] == 2, 30, "ma's frames processed")
        wait_until(lambda: api.get("/v1/maps/mb/stats").json()["frames"]["processed"] == 1, 30, "mb's frame processed")
        assert api.get("/no/such/route").status_code == 404
        assert api.request("BREW", "/v1/maps/ma/stats").status_code == 405
        too_big = {**PROTOBUF, "content-length": "200000"}  # the body limit answers before any route runs
        assert api.post("/v1/maps/ma/frames", content=b"", headers=too_big).status_code == 413
        worker = api.get("/healthz/workers").json()["live"][0]
        scrape = api.get("/metrics")
    assert scrape.status_code == 200
    seen = samples(scrape.text)
    names = {name for name, _ in seen}
    assert {
        "process_cpu_seconds_total",
        "process_resident_memory_bytes",
        "python_info",
        "python_gc_objects_collected_total",
    } <= names
    frames = ("method", "POST"), ("route", "/v1/maps/{map_id}/frames")
    assert seen["http_requests_total", (*frames, ("status", "202"))] == 3
    assert seen["http_requests_total", (*frames, ("status", "413"))] == 1  # counted with its route
    assert seen["http_requests_total", (("method", "GET"), ("route", "unmatched"), ("status", "404"))] == 1
    assert seen["http_requests_total", (("method", "other"), ("route", "/v1/maps/{map_id}/stats"), ("status", "405"))] == 1
    assert seen["http_request_duration_seconds_count", frames] == 4
    assert seen["http_request_duration_seconds_bucket", (("le", "+Inf"), *frames)] == 4
    assert seen["http_requests_in_flight", ()] == 1  # the scrape itself
    assert seen["arcloud_map_frames_processed_total", (("map_id", "ma"),)] == 2
    assert seen["arcloud_map_frames_processed_total", (("map_id", "mb"),)] == 1
    assert seen["arcloud_map_frames_failed_total", (("map_id", "mb"),)] == 0
    assert seen["arcloud_map_queue_depth", (("map_id", "ma"),)] == 0
    assert seen["arcloud_worker_frames_processed_total", (("worker", worker),)] == 3
    assert seen["arcloud_workers_up", ()] == 1


def test_map_series_are_bounded_queued_maps_first() -> None:
    maps = {f"m{i:04d}": {"processed": i} for i in range(MAX_MAP_SERIES + 50)}
    families = {f.name: f for f in settled_families(maps, {"m0000": 3}, {})}
    shown = [s.labels["map_id"] for s in families["arcloud_map_frames_processed"].samples if s.name.endswith("_total")]
    assert len(shown) == MAX_MAP_SERIES and shown[0] == "m0000"  # queued frames first, then the busiest maps
    assert shown[1] == f"m{MAX_MAP_SERIES + 49:04d}"


def documented_metric_names(row: str) -> set[str]:
    """The metric names a table row gives in backticks, brace groups inside a name expanded
    (``a_{b,c}_total``: ``a_b_total``, ``a_c_total``) and a label list at its end dropped (``name{method,route}``)."""
    names = set()
    for token in re.findall(r"`([a-z_{},]+)`", row):
        token = re.sub(r"\{[a-z_,]+\}$", "", token)  # labels
        group = re.search(r"\{([a-z_,]+)\}", token)
        options = group.group(1).split(",") if group else [""]
        names |= {token[: group.start()] + o + token[group.end() :] if group else token for o in options}
    return names


def test_the_service_docs_list_every_metric_the_app_exposes_and_no_other() -> None:
    row = next(line for line in SERVICE_DOCS.read_text().splitlines() if line.startswith("| `GET /metrics` |"))
    documented = {name for name in documented_metric_names(row) if name.startswith(("arcloud_", "http_"))}
    settings = Settings(detector="sim:0", workers=1, auth="none")
    with AppClient(create_app(settings, detector=BlobDetector())) as api:
        body = frame_to_proto(make_test_frame(0, map_id="docs")).SerializeToString()
        assert api.post("/v1/maps/docs/frames", content=body, headers=PROTOBUF).status_code == 202
        assert api.post("/v1/maps/docs/frames", content=b"x", headers={"content-type": "text/plain"}).status_code == 415
        wait_until(lambda: api.get("/v1/maps/docs/stats").json()["frames"]["processed"] == 1, 30, "the frame processed")
        families = list(text_string_to_metric_families(api.get("/metrics").text))
    # prometheus-client's own ``<counter or histogram>_created`` series (when each began) are not ours to list.
    ours = [f for f in families if f.name.startswith(("arcloud_", "http_")) and not f.name.endswith("_created")]
    exposed = {f.name + ("_total" if f.type == "counter" else "") for f in ours}
    assert documented == exposed, f"undocumented: {sorted(exposed - documented)}; not exposed: {sorted(documented - exposed)}"
