"""Starting without the Redis a process needs says so in one line: `serve` with a Redis that does not answer stops
before uvicorn starts (not three tracebacks of the API's start-up), a container's worker healthcheck without a Redis
URL answers unhealthy (not a traceback)."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from arcloud.cli import main as cli_main


@pytest.fixture
def own_logging() -> Iterator[None]:
    """For a test whose entry point sets the process's logging up (``configure_logging``): pytest's handlers and the
    level put back after it, so later tests' lines are captured as before."""
    root, ours = logging.getLogger(), logging.getLogger("arcloud")
    handlers, level = root.handlers[:], ours.level
    yield
    root.handlers[:] = handlers
    ours.setLevel(level)


def test_serve_with_redis_down_stops_with_one_line(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("ARCLOUD_DETECTOR", "sim:0")
    assert cli_main(["serve", "--redis", "redis://127.0.0.1:1/0", "--port", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("arcloud: error: reach the store (start Redis, or give the URL it answers at): redis at 127.0.0.1:1")
    assert "unreachable" in err


def test_a_worker_healthcheck_without_a_redis_url_says_unhealthy_in_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from arcloud.tools.worker import main as container_worker_main

    monkeypatch.delenv("ARCLOUD_STORE", raising=False)
    assert container_worker_main(["--healthcheck"]) == 1
    printed = capsys.readouterr()
    assert printed.out == "unhealthy: ARCLOUD_STORE is no Redis URL (workers take frames from Redis)\n"
    assert printed.err == ""


@pytest.mark.redis
def test_a_redis_that_evicts_keys_is_refused_at_start_and_a_full_one_is_not_ready(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """A review of a lost Redis: with maxmemory-policy allkeys-lru, Redis deleted 154 of 200 queued frames, a map and
    half of another's object without an error, /readyz 200; with noeviction and full, every request answered 503 for
    minutes while /readyz said 200 (a PING passes)."""
    import redis
    from redis_server import RedisServer
    from svc_helpers import AppClient

    from arcloud.errors import StoreUnavailable
    from arcloud.service.settings import Settings
    from arcloud.stores.redis import RedisStore
    from arcloud.tools.wiring import check_redis, create_app

    monkeypatch.setenv("ARCLOUD_DETECTOR", "sim:0")
    with RedisServer.start() as server:
        config = redis.Redis.from_url(server.url)
        config.config_set("maxmemory", 64 * 2**20)
        with caplog.at_level(logging.WARNING, logger="arcloud.tools.wiring"):  # before serve sets its own logging up
            check_redis(Settings(store=server.url))  # noeviction: the one policy that keeps every key
            assert "MAX_QUEUED_BYTES 1073741824 is over half of Redis's maxmemory (67108864 bytes)" in caplog.text
            caplog.clear()
            check_redis(Settings(store=server.url, max_queued_bytes=2**25, max_queued_bytes_per_map=2**25))  # half of it
            assert not caplog.text
        config.config_set("maxmemory-policy", "allkeys-lru")
        capsys.readouterr()  # what was logged so far (an earlier serve's handler writes to stderr)
        for command in (["serve", "--redis", server.url, "--port", "1"], ["worker", "--redis", server.url]):
            assert cli_main(command) == 2
            err = capsys.readouterr().err.strip()
            assert err.startswith(
                f"arcloud: error: Redis at 127.0.0.1:{server.port}/0 evicts keys when full (maxmemory-policy allkeys-lru, "
                "maxmemory 67108864 bytes): it would delete maps, queued frames and locks without an error; set "
                "maxmemory-policy noeviction"
            ), err
        config.config_set("maxmemory-policy", "noeviction")
        with AppClient(create_app(Settings(store=server.url, auth="none", detector="sim:0", workers=0))) as api:
            assert api.get("/readyz").status_code == 200
            config.config_set("maxmemory", 1)  # less than it holds: full, refusing writes
            with pytest.raises(StoreUnavailable, match=r"is full: \d+ bytes used of its maxmemory 1: writes are refused"):
                RedisStore(server.url).ping()
            not_ready = api.get("/readyz")
            assert not_ready.status_code == 503 and "is full" in not_ready.json()["checks"]["store"], not_ready.text
            config.config_set("maxmemory", 0)
            assert api.get("/readyz").status_code == 200


@pytest.mark.redis
def test_the_containers_entry_points_refuse_a_redis_that_evicts_keys(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], own_logging: None
) -> None:
    """A review of workers failing: `python -m arcloud.tools.worker` (docker-compose, the k8s worker) took frames from
    a Redis with maxmemory-policy allkeys-lru, and the image's API (`uvicorn --factory ...:create_app`) started on it,
    where `arcloud serve` and `arcloud worker` refuse."""
    import redis
    from redis_server import RedisServer

    from arcloud.tools.wiring import create_app
    from arcloud.tools.worker import main as container_worker_main

    monkeypatch.setenv("ARCLOUD_DETECTOR", "sim:0")
    with RedisServer.start() as server:
        config = redis.Redis.from_url(server.url)
        config.config_set("maxmemory", 64 * 2**20)
        config.config_set("maxmemory-policy", "allkeys-lru")
        monkeypatch.setenv("ARCLOUD_STORE", server.url)
        capsys.readouterr()
        assert container_worker_main([]) == 2
        with pytest.raises(SystemExit) as exited:
            create_app()  # each entry point sets the process's logging up: its lines go to stderr
        assert exited.value.code == 2
        err = capsys.readouterr().err
        refusals = [line for line in err.splitlines() if "evicts keys when full (maxmemory-policy allkeys-lru" in line]
        assert len(refusals) == 2 and "Traceback" not in err, err
        config.config_set("maxmemory-policy", "noeviction")
        create_app()  # the same Redis, keeping its keys: the API is made


def test_the_containers_entry_points_wait_for_a_redis_that_does_not_answer_yet(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], own_logging: None
) -> None:
    """A review of the check above: its first version made the image's API and worker exit 2 while Redis was still
    starting (a fresh `kubectl apply`, a failover), where they used to wait for it: pods crash-looped."""
    from arcloud.service.settings import Settings
    from arcloud.tools.wiring import check_redis_policy, create_app

    monkeypatch.setenv("ARCLOUD_DETECTOR", "sim:0")
    monkeypatch.setenv("ARCLOUD_STORE", "redis://127.0.0.1:1/0")
    check_redis_policy(Settings())  # no answer: a warning, not a refusal
    assert create_app() is not None  # the API is made; its /readyz says 503 until Redis answers
    err = capsys.readouterr().err
    assert "reach the store" in err and "starting anyway, and waiting for it" in err, err
