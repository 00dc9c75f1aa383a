"""Workers of one queue map with one set of settings: a worker started beside live workers of other map settings
refuses to start (it would fail every frame of their maps, and a review of workers failing saw good frames
dead-lettered as it kept claiming them), one of other --params is warned of, and /healthz/workers says when the live
workers' settings differ (a map they share mixes them: the review saw it happen in silence)."""

from __future__ import annotations

import dataclasses
import logging
import socket
import threading

import pytest
from redis_server import RedisServer
from svc_helpers import BlobDetector, wait_until

from arcloud.core.types import Params
from arcloud.errors import ArcloudError
from arcloud.service.ingest import Ingest
from arcloud.service.map_header import settings_differences, worker_settings
from arcloud.service.worker import FrameWorker
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue


def test_two_workers_settings_differ_by_the_map_settings_they_name() -> None:
    ours = worker_settings(Params(), 3)
    assert settings_differences(ours, worker_settings(Params(), 3)) == []
    assert settings_differences(worker_settings(Params(voxel_size_m=0.04), 3), ours) == ["voxel_size_m: theirs 0.04, ours 0.05"]
    other_params = worker_settings(Params(min_voxels_per_detection=1000), 3)
    assert settings_differences(other_params, ours) == [] and other_params["params"] != ours["params"]


@pytest.mark.redis
def test_a_worker_beside_live_workers_of_other_settings(caplog: pytest.LogCaptureFixture) -> None:
    with RedisServer.start() as server:
        queue, store = RedisFrameQueue(server.url), RedisStore(server.url)
        ingest = Ingest(queue, store)
        try:
            queue.prepare()

            def worker(params: Params, name: str) -> FrameWorker:
                return FrameWorker(queue, store, BlobDetector(), params, consumer=name, read_block_s=0.1, monitor=queue)

            first = worker(Params(), "host-1")
            stop = threading.Event()
            running = threading.Thread(target=first.run, args=(stop,))
            running.start()
            try:
                wait_until(lambda: "host-1" in queue.live_settings(10.0), 10, "the first worker beats")
                assert ingest.workers_health().checks["settings"] == "ok"
                wider = worker(Params(voxel_size_m=0.04), "host-2")
                with pytest.raises(ArcloudError, match=r"worker host-1 maps with other map settings \(voxel_size_m: "):
                    wider.check_peers()
                stopped = threading.Event()
                stopped.set()  # were it not refused, it would stop at once rather than hang the test
                with pytest.raises(ArcloudError, match="start it with the same --params"):
                    wider.run(stopped)  # refused before it takes a frame or beats
                assert sorted(queue.live_settings(10.0)) == ["host-1"]
                other = worker(dataclasses.replace(Params(), min_voxels_per_detection=1000), "host-3")
                with caplog.at_level(logging.WARNING, logger="arcloud.service.worker"):
                    other.check_peers()  # the same map settings: it may run, warned
                assert "host-1 map with other --params" in caplog.text
                queue.heartbeat("host-3", (), other.settings)
                assert ingest.workers_health().checks["settings"] == "ok"  # other Params alone: logged, not failed
                queue.heartbeat("host-2", (), wider.settings)  # started together, say: both passed the check
                health = ingest.workers_health()
                assert not health.ok and health.checks["settings"].startswith(
                    "the live workers map with 2 different map settings (host-1, host-3; host-2)"
                ), health
                queue.leave("host-2")
                assert ingest.workers_health().checks["settings"] == "ok"
                # a worker of this host killed a moment ago (its heartbeat fresh, its process gone) is no peer
                from arcloud.service.worker import consumer_name

                dead = consumer_name(2**22 + 12345)  # above the kernel's pid_max default: no such process
                queue.heartbeat(dead, (), worker(Params(), "x").settings | {"map": wider.settings["map"]})
                again = worker(Params(), consumer_name())
                again.check_peers()  # host-1's settings are ours; the dead one's are not counted
            finally:
                stop.set()
                running.join(10)
        finally:
            queue.close()
            store.close()


@pytest.mark.redis
def test_an_api_process_of_serve_api_processes_expects_its_hosts_worker_processes() -> None:
    """A review of workers failing: with `serve --api-processes 2 --workers 2`, one of the two workers hung (SIGSTOP)
    and /healthz/workers still answered 200 (any heartbeat would do): the API processes did not know the pool."""
    from svc_helpers import AppClient

    from arcloud.service.settings import Settings
    from arcloud.service.worker import consumer_name
    from arcloud.tools.wiring import create_app

    with RedisServer.start() as server:
        queue = RedisFrameQueue(server.url)
        try:
            queue.prepare()
            settings = Settings(store=server.url, auth="none", detector="sim:0", workers=0)
            with AppClient(create_app(settings, host_workers=2)) as api:
                queue.heartbeat(consumer_name(101), ())
                queue.heartbeat("elsewhere-7", ())  # another host's worker is not one of ours...
                queue.heartbeat(f"{socket.gethostname()}-2-555", ())  # ...nor one of a host named as ours with "-2"
                hung = api.get("/healthz/workers")
                assert hung.status_code == 503, hung.text
                body = hung.json()
                assert (
                    body["checks"]["workers"].startswith("1 of 2 worker processes of this host reading") and body["expected"] == 2
                )
                queue.heartbeat(consumer_name(102), ())
                assert api.get("/healthz/workers").status_code == 200
            with AppClient(create_app(settings)) as api:  # workers elsewhere: any live one will do
                queue.leave(consumer_name(102))
                assert api.get("/healthz/workers").json()["expected"] is None
                assert api.get("/healthz/workers").status_code == 200
        finally:
            queue.close()
