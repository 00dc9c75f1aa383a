"""The operator's dashboard (services/grafana) is a Grafana dashboard whose every query names metrics a real
app's /metrics exposes, and the compose file's ``monitoring`` profile wires Prometheus and Grafana to it."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families
from svc_helpers import AppClient, make_test_frame, wait_until

from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

ROOT = Path(__file__).resolve().parents[2]
DASHBOARD = ROOT / "services" / "grafana" / "arcloud-dashboard.json"
COMPOSE = ROOT / "docker-compose.yml"
PROTOBUF = {"content-type": "application/x-protobuf"}

#: PromQL words that are not metric names: aggregation modifiers, set operators, number literals.
PROMQL_WORDS = {"by", "without", "on", "ignoring", "group_left", "group_right", "offset", "bool", "and", "or", "unless"}
PROMQL_WORDS |= {"inf", "nan"}


def metric_names(expr: str) -> set[str]:
    """The metric names a PromQL expression reads: identifiers left once strings, label matchers
    ``{...}``, ranges ``[...]`` and ``by (...)``-style label lists are removed, that are not calls
    (followed by ``(``) nor keywords."""
    text = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)
    text = re.sub(r"\{[^}]*\}", " ", text)
    text = re.sub(r"\[[^\]]*\]", " ", text)
    text = re.sub(r"\b(?:by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", text)
    names = set()
    for match in re.finditer(r"(?<![\w$.])[A-Za-z_:][A-Za-z0-9_:]*", text):
        if text[match.end() :].lstrip().startswith("(") or match.group().lower() in PROMQL_WORDS:
            continue
        names.add(match.group())
    return names


def test_metric_names_reads_names_and_skips_functions_labels_and_ranges() -> None:
    expr = 'histogram_quantile(0.95, sum by (le) (rate(a_bucket{job="x", le!="1e3"}[$__rate_interval]))) / on (job) b_total'
    assert metric_names(expr) == {"a_bucket", "b_total"}
    assert metric_names("sum without (instance) (c) > bool 2e-3 or vector(1)") == {"c"}


def panels_of(dashboard: dict[str, Any]) -> list[dict[str, Any]]:
    """Every panel, those inside collapsed rows too."""
    found = []
    for panel in dashboard["panels"]:
        found.append(panel)
        found += panel.get("panels", [])
    return found


def exprs_of(dashboard: dict[str, Any]) -> list[str]:
    return [target["expr"] for panel in panels_of(dashboard) for target in panel.get("targets", [])]


def test_the_dashboard_is_a_grafana_dashboard_on_a_prometheus_datasource_variable() -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    assert isinstance(dashboard["schemaVersion"], int) and dashboard["schemaVersion"] >= 36
    assert dashboard["uid"] and dashboard["title"] and dashboard.get("id") is None  # provisioned: Grafana gives the id
    (variable,) = [v for v in dashboard["templating"]["list"] if v["type"] == "datasource"]
    assert variable["query"] == "prometheus"
    uses = {"type": "prometheus", "uid": f"${{{variable['name']}}}"}
    panels = [p for p in panels_of(dashboard) if p["type"] != "row"]
    assert len({p["id"] for p in panels_of(dashboard)}) == len(panels_of(dashboard))
    for panel in panels:
        assert panel["title"] and panel["datasource"] == uses, panel["title"]
        assert panel["targets"] and {"h", "w", "x", "y"} <= set(panel["gridPos"]), panel["title"]
        assert panel["gridPos"]["x"] + panel["gridPos"]["w"] <= 24, panel["title"]
        for target in panel["targets"]:
            assert target["expr"].strip() and target["refId"] and target["datasource"] == uses, panel["title"]
    titles = " / ".join(p["title"].lower() for p in panels)
    for topic in ("queue depth (frames)", "queue depth (bytes)", "frames per second", "refused", "latency", "failures"):
        assert topic in titles, topic
    assert "live workers" in titles and "retries and claims" in titles


def scraped_sample_names(client: AppClient) -> set[str]:
    text = client.get("/metrics").text
    return {sample.name for family in text_string_to_metric_families(text) for sample in family.samples}


def test_every_metric_the_dashboard_queries_is_on_a_real_apps_metrics() -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    queried = set().union(*(metric_names(expr) for expr in exprs_of(dashboard)))
    wanted = {
        "arcloud_queue_depth",
        "arcloud_queue_bytes",
        "arcloud_frames_accepted_total",
        "arcloud_frames_processed_total",
        "arcloud_frames_failed_total",
        "arcloud_frames_rejected_total",
        "arcloud_step_latency_seconds_bucket",
        "arcloud_step_retries_total",
        "arcloud_frames_claimed_total",
        "arcloud_live_workers",
        "arcloud_queue_wait_seconds_bucket",
        "arcloud_lock_wait_seconds_bucket",
    }
    assert wanted <= queried, wanted - queried
    assert any(e.startswith("histogram_quantile(0.99,") for e in exprs_of(dashboard))

    with AppClient(create_app(Settings(detector="sim:0", workers=1))) as client:
        body = frame_to_proto(make_test_frame(0, map_id="dash")).SerializeToString()
        assert client.post("/v1/maps/dash/frames", content=body, headers=PROTOBUF).status_code == 202
        assert client.post("/v1/maps/dash/frames", content=b"x", headers={"content-type": "text/plain"}).status_code == 415
        wait_until(lambda: client.get("/v1/maps/dash/stats").json()["frames"]["processed"] == 1, 30, "the frame processed")
        exposed = scraped_sample_names(client)
    assert queried <= exposed, f"queried but not exposed: {sorted(queried - exposed)}"


@pytest.fixture
def compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())


def test_the_monitoring_profile_scrapes_the_api_and_provisions_the_dashboard(compose: dict[str, Any]) -> None:
    services = compose["services"]
    monitoring = {name for name, service in services.items() if "monitoring" in service.get("profiles", [])}
    assert monitoring == {"prometheus", "grafana"}
    cluster = {name for name, service in services.items() if "cluster" in service.get("profiles", [])}  # tests/test_deploy.py
    assert all(not service.get("profiles") for name, service in services.items() if name not in monitoring | cluster)
    for name in monitoring:
        image = services[name]["image"]
        assert re.fullmatch(r"[\w./-]+:v?\d+\.\d+\.\d+", image), f"{name}: pin the image's version, got {image}"
        for port in services[name]["ports"]:
            assert port.startswith("127.0.0.1:"), f"{name} publishes {port} beyond loopback"
        for volume in services[name]["volumes"]:
            source = volume.split(":")[0]
            if source.startswith("./"):
                assert (ROOT / source).exists(), f"{name} mounts {source}, which is not in the repository"

    (prometheus_config,) = [v.split(":")[0] for v in services["prometheus"]["volumes"] if v.endswith("prometheus.yml:ro")]
    scrape = yaml.safe_load((ROOT / prometheus_config).read_text())["scrape_configs"]
    api_port = services["api"]["ports"][0].split(":")[-1]
    assert [(job["metrics_path"], job["static_configs"][0]["targets"]) for job in scrape] == [("/metrics", [f"api:{api_port}"])]

    grafana_mounts = dict(v.split(":")[:2] for v in services["grafana"]["volumes"])  # source -> target
    assert grafana_mounts["./services/grafana/arcloud-dashboard.json"].startswith("/var/lib/grafana/dashboards/")
    provisioning = ROOT / "services" / "grafana" / "provisioning"
    assert grafana_mounts["./services/grafana/provisioning"] == "/etc/grafana/provisioning"
    (provider,) = yaml.safe_load((provisioning / "dashboards" / "arcloud.yml").read_text())["providers"]
    assert provider["options"]["path"] == "/var/lib/grafana/dashboards"
    (source,) = yaml.safe_load((provisioning / "datasources" / "prometheus.yml").read_text())["datasources"]
    assert source["type"] == "prometheus" and source["url"] == "http://prometheus:9090"


def test_the_services_log_json_in_compose(compose: dict[str, Any]) -> None:
    assert compose["x-arcloud"]["environment"]["ARCLOUD_LOG_FORMAT"] == "${ARCLOUD_LOG_FORMAT:-json}"
    for name in ("api", "worker"):
        assert compose["services"][name]["environment"]["ARCLOUD_LOG_FORMAT"].endswith("json}")
