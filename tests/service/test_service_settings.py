"""Settings: read from ARCLOUD_* variables, checked up front, secrets never shown."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from arcloud.errors import InvalidInput
from arcloud.ports import LATENCY_BUCKETS_S, latency_bucket
from arcloud.service.settings import Settings, redact_url
from arcloud.stores.redis_queue import latency_field, parse_stats
from arcloud.tools.wiring import build_detector, check_detector_spec, create_app, threads_per_process


def test_environment_is_read_and_parsed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ARCLOUD_STORE", "redis://127.0.0.1:6379/3")
    monkeypatch.setenv("ARCLOUD_WORKERS", "4")
    monkeypatch.setenv("ARCLOUD_DETECTOR", "sim:5")
    monkeypatch.setenv("ARCLOUD_ZENOH_MODE", "peer")
    monkeypatch.setenv("ARCLOUD_ZENOH_LISTEN", "tcp/0.0.0.0:7447, tcp/0.0.0.0:7448")
    monkeypatch.setenv("ARCLOUD_ZENOH_CONNECT", '["tcp/zenoh:7447"]')
    monkeypatch.setenv("ARCLOUD_PARAMS", '{"voxel_size_m": 0.04, "class_aware": true, "up": [0, 1, 0]}')
    monkeypatch.setenv("ARCLOUD_LOG_LEVEL", "debug")
    monkeypatch.setenv("ARCLOUD_LOG_FORMAT", "JSON")
    monkeypatch.setenv("ARCLOUD_MODEL", "ignored.onnx")  # another component's variable: not a setting
    settings = Settings()
    assert settings.store == "redis://127.0.0.1:6379/3" and not settings.embedded and settings.workers == 4
    assert settings.zenoh_listen == ["tcp/0.0.0.0:7447", "tcp/0.0.0.0:7448"] and settings.zenoh_connect == ["tcp/zenoh:7447"]
    assert settings.log_level == "DEBUG" and settings.log_format == "json"
    params = settings.make_params()
    assert params.voxel_size_m == 0.04 and params.class_aware is True and params.up == (0.0, 1.0, 0.0)
    assert params.lock_ttl_s == settings.lock_ttl_s


@pytest.mark.parametrize(
    ("changes", "says"),
    [
        ({"store": "postgres://db"}, "expected `memory` or a URL"),
        ({"detector": ":x"}, "PREFIX"),
        ({"workers": 0}, "workers: expected >= 1 with the memory store"),
        ({"params": {"voxel": 0.1}}, r"params: expected fields of Params \(.*\), got 'voxel'"),
        ({"params": {"erode_px": 1.5}}, r"params.erode_px: expected an integer >= 0, got 1.5"),
        ({"params": {"lock_ttl_s": 3}}, "ARCLOUD_LOCK_TTL_S"),  # a setting of its own
        ({"zenoh_mode": "client"}, "needs at least one endpoint"),
        ({"zenoh_frames": True}, "needs zenoh_mode"),
        ({"max_frame_bytes": 10}, "max_frame_bytes"),
        ({"max_queued_bytes_per_map": 10**6}, "max_queued_bytes_per_map: expected at least the largest frame"),
        ({"max_queued_bytes": 4 * 10**7}, "max_queued_bytes_per_map: expected at least the largest frame"),  # its quarter
        ({"frame_record_retention_s": 0}, "frame_record_retention_s"),
        ({"retired_history_s": -1.0}, "retired_history_s"),
        ({"colour": "red"}, "colour"),
        ({"log_format": "xml"}, "log_format"),
    ],
)
def test_wrong_settings_fail_at_once_naming_the_field(changes: dict, says: str) -> None:
    with pytest.raises(ValidationError, match=says):
        Settings(**changes)


def test_the_largest_frame_on_redis_depends_on_how_its_images_are_queued() -> None:
    """At 1920 x 1440: decoded depth 2 bytes a pixel, depth as uploaded (the default) up to 4 (twice its
    pixels' size, the bound on an upload's bytes), colour up to 6, each with 64 KiB for metadata."""
    pixels = 1920 * 1440
    on_redis = {"store": "redis://127.0.0.1:6379/0", "max_queued_bytes_per_map": 25 * 10**6}
    assert Settings(**on_redis, queued_images="decoded").largest_queued_frame() == 8 * pixels + 64 * 1024 < 25 * 10**6
    with pytest.raises(ValidationError, match="max_queued_bytes_per_map: expected at least the largest frame"):
        Settings(**on_redis)
    roomy = {**on_redis, "max_queued_bytes_per_map": 3 * 10**7}
    assert Settings(**roomy).largest_queued_frame() == 10 * pixels + 128 * 1024 < 3 * 10**7
    assert Settings(store="memory").largest_queued_frame() == 7 * pixels
    # the API swaps PNGs for pixels only where a queue carries the message (embedded: the decoded frame)
    assert [Settings(**kw).queue_decoded_png for kw in ({}, {**on_redis, "queued_images": "decoded"}, roomy)] == [
        False,
        True,
        False,
    ]


def test_queue_limits_default_a_map_to_a_quarter_of_the_queue(monkeypatch: pytest.MonkeyPatch) -> None:
    limits = Settings().queue_limits()
    assert (limits.max_queued_frames, limits.max_queued_frames_per_map) == (1000, 250)
    assert (limits.max_queued_bytes, limits.max_queued_bytes_per_map) == (2**30, 2**28)
    monkeypatch.setenv("ARCLOUD_MAX_QUEUED_FRAMES", "100")
    monkeypatch.setenv("ARCLOUD_MAX_QUEUED_BYTES_PER_MAP", str(2**29))
    monkeypatch.setenv("ARCLOUD_FRAME_RECORD_RETENTION_S", "3600")
    limits = Settings().queue_limits()
    assert (limits.max_queued_frames_per_map, limits.max_queued_bytes_per_map, limits.frame_record_retention_s) == (
        25,
        2**29,
        3600.0,
    )


@pytest.mark.parametrize(("spec", "says"), [("yolo:x", "PREFIX one of"), ("sim:-1", "sim:SEED"), ("sim:x", "sim:SEED")])
def test_unknown_detectors_fail_before_anything_is_built(spec: str, says: str) -> None:
    settings = Settings(detector=spec)  # the service knows no detector; the composition root does
    with pytest.raises(InvalidInput, match=says):
        check_detector_spec(settings.detector)
    with pytest.raises(InvalidInput, match=says):
        create_app(settings)
    assert check_detector_spec(" sim:3 ") == "sim:3"


def test_secrets_are_masked() -> None:
    settings = Settings(store="redis://user:s3cret@redis.internal:6380/1", workers=0)
    for text in (repr(settings), str(settings), str(settings.redacted())):
        assert "s3cret" not in text and "user:***@redis.internal:6380" in text
    assert settings.store.endswith("s3cret@redis.internal:6380/1")  # the real value is still there to connect
    with pytest.raises(ValidationError) as error:
        Settings(store="mysql://root:s3cret@db")
    assert "s3cret" not in str(error.value)
    assert redact_url("redis://:pw@h:1/0") == "redis://:***@h:1/0" and redact_url("redis://h:1/0") == "redis://h:1/0"


def test_a_redis_cluster_is_named_by_its_nodes_and_its_secret_masked() -> None:
    settings = Settings(store="redis+cluster://app:s3cret@10.0.0.1:7000,10.0.0.2:7000", workers=0, ingest_shards=3)
    for text in (repr(settings), str(settings.redacted())):
        assert "s3cret" not in text and "redis+cluster://app:***@10.0.0.1:7000,10.0.0.2:7000" in text
    assert settings.ingest_shards == 3 and Settings(workers=0, store="redis://h:1/0").ingest_shards == 1
    with pytest.raises(ValidationError, match="ingest_shards"):
        Settings(store="redis://h:1/0", ingest_shards=0)


def test_latency_buckets_and_stats_parsing() -> None:
    assert latency_bucket(0.0) == 0 and latency_bucket(LATENCY_BUCKETS_S[0]) == 0  # upper bounds are inclusive
    assert latency_bucket(0.0051) == 1 and latency_bucket(1e9) == len(LATENCY_BUCKETS_S)
    raw = {
        b"processed": b"3",
        b"failed": b"1",
        latency_field(1): b"2",
        latency_field(len(LATENCY_BUCKETS_S)): b"1",
        b"latency_sum_s": b"99.5",
    }
    snap = parse_stats(raw)
    assert (snap.processed, snap.failed, snap.accepted, snap.redelivered, snap.latency_count, snap.latency_sum_s) == (
        3,
        1,
        0,
        0,
        3,
        99.5,
    )
    assert snap.latency_counts[1] == 2 and snap.latency_counts[-1] == 1


def test_worker_processes_share_the_cores_and_the_detector_gets_its_share(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1, 2, 3, 4, 5, 6, 7})
    assert [threads_per_process(n) for n in (0, 1, 2, 3, 8, 20)] == [8, 8, 4, 2, 1, 1]
    assert build_detector("sim:0", threads=2).threads == 2  # type: ignore[attr-defined]  # a SimulatedDetector behind the Detector port
    assert build_detector("sim:0").threads == 0  # type: ignore[attr-defined]  # Open3D's default: every core


def test_a_mistyped_arcloud_variable_is_warned_of_at_start_naming_the_setting_it_may_mean(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A new user's review: ``ARCLOUD_WORKER=3 arcloud serve`` started 2 workers, the variable read by nothing. A
    warning, not a refusal: Kubernetes gives every pod ``ARCLOUD_API_SERVICE_HOST`` and such for a Service named
    ``arcloud-api`` (deploy/k8s), and a refusal made the shipped deployment crash-loop (a review)."""
    import logging

    from arcloud.cli import build_parser
    from arcloud.tools.service_cli import settings_from_args

    args = build_parser().parse_args(["serve", "--detector", "sim:0"])
    monkeypatch.setenv("ARCLOUD_WORKER", "3")
    monkeypatch.setenv("ARCLOUD_NOTHING_LIKE_IT", "1")
    for link in ("ARCLOUD_API_SERVICE_HOST", "ARCLOUD_API_SERVICE_PORT", "ARCLOUD_API_SERVICE_PORT_HTTP", "ARCLOUD_API_PORT",
                 "ARCLOUD_API_PORT_8000_TCP", "ARCLOUD_API_PORT_8000_TCP_ADDR", "ARCLOUD_API_PORT_8000_TCP_PROTO"):  # fmt: skip
        monkeypatch.setenv(link, "10.0.0.1")
    for other in ("ARCLOUD_TOKEN", "ARCLOUD_MODELS", "ARCLOUD_MODEL", "ARCLOUD_SHARED"):
        monkeypatch.setenv(other, "x")  # read by the SDK, the model cache, ...
    with caplog.at_level(logging.WARNING, logger="arcloud.tools.service_cli"):
        assert settings_from_args(args).workers == 2
    assert [r.getMessage() for r in caplog.records] == [
        "ARCLOUD_NOTHING_LIKE_IT: no such setting, ignored",
        "ARCLOUD_WORKER: no such setting (did you mean ARCLOUD_WORKERS?), ignored",
    ]
