"""``GET /v1/maps/{map}/events`` over real HTTP: a real uvicorn server on 127.0.0.1 running the embedded service
with a keys file (frames processed by its worker thread), and, on a real redis-server, the API with the
workers in another process's place. Streams are read as a browser reads them: line by line, as they come."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from svc_helpers import LEFT, RIGHT, BlobDetector, UvicornThread, cube, free_port, make_test_frame, wait_until
from viewer_helpers import EventStream, bearer, make_keys, version_of

from arcloud.core.change import ChangesSince, MapChange
from arcloud.core.header import MapHeader
from arcloud.core.types import Params
from arcloud.ports import ObjectMeta
from arcloud.proto.convert import frame_to_proto
from arcloud.service.event_stream import EventStreams
from arcloud.service.settings import Settings
from arcloud.stores.file_api_keys import FileKeyStore
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
MAX_STREAMS = 4


class Service:
    def __init__(self, server: UvicornThread, app: Any, tokens: dict[str, str], keys_file: Path) -> None:
        self.server = server
        self.url = server.url
        self.app = app
        self.tokens = tokens
        self.keys_file = keys_file
        self.http = httpx.Client(base_url=server.url, timeout=10.0)

    @property
    def streams(self) -> EventStreams:
        return self.app.state.event_streams  # type: ignore[no-any-return]  # app.state is untyped

    def post(self, map_id: str, index: int, **frame: Any) -> None:
        body = frame_to_proto(make_test_frame(index, map_id=map_id, **frame)).SerializeToString()
        answer = self.http.post(f"/v1/maps/{map_id}/frames", content=body, headers={**PROTOBUF, **bearer(self.tokens["device"])})
        assert answer.status_code == 202, answer.text

    def wait_processed(self, map_id: str, n_frames: int) -> None:
        def done() -> bool:
            frames = self.http.get(f"/v1/maps/{map_id}/stats", headers=bearer(self.tokens["device"])).json()["frames"]
            return int(frames["processed"]) >= n_frames

        wait_until(done, 30, f"{n_frames} frames of map {map_id} processed", 0.05)

    def objects(self, map_id: str) -> list[dict[str, Any]]:
        answer = self.http.get(f"/v1/maps/{map_id}/objects", headers=bearer(self.tokens["device"]))
        return answer.json()["objects"]  # type: ignore[no-any-return]  # httpx's JSON is Any


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    keys_file = tmp_path_factory.mktemp("keys") / "keys.json"
    tokens = make_keys(
        keys_file,
        device=("device", "*"),
        admin=("admin", "*"),
        reader=("reader", "ev-a,ev-b,ev-c,ev-d"),
        stranger=("reader", "elsewhere"),
    )
    settings = Settings(
        detector="sim:0",
        workers=1,
        keys_file=str(keys_file),
        key_cache_s=0.2,
        key_rate_per_s=0,
        event_poll_s=0.1,
        event_heartbeat_s=0.5,
        max_event_streams=MAX_STREAMS,
    )
    app = create_app(settings, detector=BlobDetector())
    with UvicornThread(app) as server:
        service = Service(server, app, tokens, keys_file)
        yield service
        service.http.close()


def assert_problem(answer: httpx.Response, status: int, contains: str) -> None:
    assert answer.status_code == status, answer.text
    assert answer.headers["content-type"] == "application/problem+json"
    assert contains in answer.json()["detail"], answer.json()


def test_the_events_route_keeps_the_access_rules_of_the_api(service: Service) -> None:
    service.post("ev-a", 0)
    path = "/v1/maps/ev-a/events"
    assert_problem(service.http.get(path), 401, "Bearer")
    assert_problem(service.http.get(path, headers=bearer(service.tokens["stranger"])), 403, "not for map 'ev-a'")
    assert_problem(service.http.get("/v1/maps/never/events", headers=bearer(service.tokens["device"])), 404, "not found")
    assert_problem(service.http.get("/v1/maps/bad%20id/events", headers=bearer(service.tokens["device"])), 422, "map_id")
    assert service.streams.open_streams == 0


def test_a_stream_sends_the_map_then_each_change_as_frames_are_processed(service: Service) -> None:
    service.post("ev-b", 0, level=True)
    service.wait_processed("ev-b", 1)
    with (
        EventStream(service.url, "ev-b", service.tokens["reader"]) as served,
        EventStream(service.url, "ev-b", service.tokens["reader"], tentative=True) as every,
    ):
        assert served.response.headers["content-type"].startswith("text/event-stream")
        _, snapshot = served.next_event("snapshot")
        assert snapshot["objects"] == []  # one frame: the object is tentative, outside the served map
        assert [d["device_id"] for d in snapshot["devices"]] == ["d"]
        assert snapshot["devices"][0]["cam2world"][3] == 0.0 and snapshot["devices"][0]["width"] == 160
        assert snapshot["world2gravity"] == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        _, everything = every.next_event("snapshot")
        [tentative] = everything["objects"]
        assert tentative["status"] == "tentative" and tentative["label"] == "chair"

        for index in range(1, 5):
            service.post("ev-b", index, level=True)
        service.wait_processed("ev-b", 5)
        [listed] = service.objects("ev-b")
        served.read_until(
            lambda s: s.objects == {listed["id"]: listed} and s.devices["d"]["frame_id"] == "f000004", "the confirmed object"
        )
        assert listed["id"] == tentative["id"] and listed["status"] == "confirmed"
        versions = [data["version"] for name, data in served.log if name == "upsert"]
        assert versions == sorted(set(versions))  # coalesced per poll, never an older state after a newer one
        assert served.devices["d"]["cam2world"][3] == pytest.approx(0.04)  # the device's last pose

        before = max(version_of(served.last_id) or 0, version_of(every.last_id) or 0)
        deleted = service.http.delete("/v1/maps/ev-b", headers=bearer(service.tokens["admin"]))
        assert deleted.status_code == 200, deleted.text
        for stream in (served, every):  # the deletion empties the log and moves the version on: the streams start over
            _, reset = stream.next_event("reset")
            _, empty = stream.next_event("snapshot")
            assert empty["objects"] == [] and empty["version"] == reset["version"] > before and stream.objects == {}
    wait_until(lambda: service.streams.open_streams == 0, 5, "both streams closed once their client went")
    wait_until(lambda: not service.streams.watches, 5, "the map's poller stopped")


def test_an_idle_stream_sends_keep_alive_comments(service: Service) -> None:
    service.post("ev-c", 0)
    with EventStream(service.url, "ev-c", service.tokens["reader"]) as stream:
        stream.next_event("snapshot")
        started = time.monotonic()
        assert stream.next_event(":", timeout_s=3) == (":", "keep-alive")
        assert time.monotonic() - started < 2.0  # heartbeat 0.5 s


def test_streams_beyond_the_limit_are_refused_and_a_closed_one_frees_its_place(service: Service) -> None:
    service.post("ev-c", 1)
    streams = [EventStream(service.url, "ev-c", service.tokens["reader"]) for _ in range(MAX_STREAMS)]
    try:
        for stream in streams:
            stream.next_event("snapshot")
        refused = service.http.get("/v1/maps/ev-c/events", headers=bearer(service.tokens["reader"]))
        assert_problem(refused, 503, f"{MAX_STREAMS} open")
        assert refused.headers["retry-after"] == "5"
        assert len(service.streams.watches) == 1  # one poller for the map, however many streams
        streams.pop().close()
        wait_until(lambda: service.streams.open_streams == MAX_STREAMS - 1, 5, "the closed stream's place freed")
        with EventStream(service.url, "ev-c", service.tokens["reader"]) as again:
            assert again.next_event("snapshot")[0] == "snapshot"
    finally:
        for stream in streams:
            stream.close()
    wait_until(lambda: service.streams.open_streams == 0, 5, "every stream closed")


def test_a_revoked_key_ends_its_open_streams(service: Service) -> None:
    service.post("ev-d", 0)
    token = make_keys(service.keys_file, revocable=("reader", "ev-d"))["revocable"]
    with EventStream(service.url, "ev-d", token) as stream:
        stream.next_event("snapshot")
        keys = FileKeyStore(service.keys_file)
        assert keys.revoke(token.split("_")[1])
        keys.close()
        started = time.monotonic()
        _, data = stream.next_event("refused", timeout_s=5)
        assert "not a valid key" in data["detail"]
        assert time.monotonic() - started < 3.0  # key_cache_s 0.2: looked at again every second
        assert list(stream.events()) == []  # and the stream ended
    wait_until(lambda: service.streams.open_streams == 0, 5, "the refused stream closed")


def test_serve_ends_open_streams_when_it_stops(tmp_path: Path) -> None:
    """``arcloud serve``'s server ends the streams as it begins to stop: uvicorn would wait for them."""
    import uvicorn

    from arcloud.tools.http_server import StreamClosingServer

    app = create_app(Settings(detector="sim:0", workers=1, event_poll_s=0.1), detector=BlobDetector())
    port = free_port()
    server = StreamClosingServer(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", ws="none"), app)
    thread = threading.Thread(target=server.run, name="serve", daemon=True)
    thread.start()
    wait_until(lambda: server.started, 20, "the server to start")
    url = f"http://127.0.0.1:{port}"
    frame = frame_to_proto(make_test_frame(0, map_id="stop", boxes=(LEFT, RIGHT))).SerializeToString()
    assert httpx.post(f"{url}/v1/maps/stop/frames", content=frame, headers=PROTOBUF).status_code == 202
    with EventStream(url, "stop") as stream:
        stream.next_event("snapshot")
        server.should_exit = True
        thread.join(5)
        assert not thread.is_alive(), "the server still waits for the open stream"
        assert [name for name, _ in stream.events()] == []  # ended, nothing after


@pytest.mark.redis
def test_on_redis_a_stream_sees_what_workers_elsewhere_write() -> None:
    """The API on Redis with no worker of its own (Zenoh off); a worker with its own connections, as
    another process would have, processes the frames: the API's stream sees its objects."""
    from redis_server import RedisServer

    from arcloud.service.worker import FrameWorker
    from arcloud.stores.redis import RedisStore
    from arcloud.stores.redis_queue import RedisFrameQueue

    with RedisServer.start() as redis_server:
        settings = Settings(store=redis_server.url, auth="none", detector="sim:0", workers=0, event_poll_s=0.1)
        app = create_app(settings)
        store, queue = RedisStore(redis_server.url), RedisFrameQueue(redis_server.url)
        stop = threading.Event()
        worker = FrameWorker(queue, store, BlobDetector(), settings.make_params(), consumer="elsewhere-1", read_block_s=0.1)
        thread = threading.Thread(target=worker.run, args=(stop,), name="worker-elsewhere", daemon=True)
        try:
            with UvicornThread(app) as server, httpx.Client(base_url=server.url, timeout=10) as http:
                thread.start()

                def post(index: int) -> None:
                    body = frame_to_proto(make_test_frame(index, map_id="r", boxes=(LEFT, RIGHT), level=True))
                    assert http.post("/v1/maps/r/frames", content=body.SerializeToString(), headers=PROTOBUF).status_code == 202

                post(0)
                with EventStream(server.url, "r") as stream:
                    assert stream.next_event("snapshot")[1]["objects"] == []
                    for index in range(1, 5):
                        post(index)
                    seen: dict[int, dict[str, Any]] = {}
                    while len(seen) < 2:
                        _, obj = stream.next_event("upsert")
                        seen[obj["id"]] = obj
                    assert {o["status"] for o in seen.values()} == {"confirmed"}
        finally:
            stop.set()
            thread.join(10)
            queue.close()
            store.close()


class CountingStore(MemoryStore):
    """The embedded store, counting whole-map reads and reads of the change log."""

    def __init__(self, **options: Any) -> None:
        super().__init__(**options)
        self.whole_map_reads = 0
        self.log_reads = 0

    def list_meta(self, map_id: str) -> list[ObjectMeta]:
        self.whole_map_reads += 1
        return super().list_meta(map_id)

    def changes_since(self, map_id: str, after: int, limit: int) -> ChangesSince:
        self.log_reads += 1
        return super().changes_since(map_id, after, limit)


def quiet_map(store: MemoryStore, *ids: int) -> None:
    store.open_map("quiet", MapHeader.from_params(Params(), codec_version=store.codec_version, created_at_s=1.0))
    store.commit("quiet", [], MapChange.writing("quiet", [cube(i) for i in ids]))


def test_a_watched_map_is_read_whole_only_for_a_snapshot_then_its_change_log_is_tailed() -> None:
    store = CountingStore()
    quiet_map(store, 1)
    settings = Settings(detector="sim:0", workers=1, event_poll_s=0.02)
    with (
        UvicornThread(create_app(settings, store=store, detector=BlobDetector())) as server,
        EventStream(server.url, "quiet", tentative=True) as stream,
    ):
        assert [o["id"] for o in stream.next_event("snapshot")[1]["objects"]] == [1]
        assert version_of(stream.last_id) == 1
        wait_until(lambda: store.log_reads >= 10, 10, "ten reads of the log")
        assert store.whole_map_reads == 1  # the snapshot's read; the log had nothing new
        store.commit("quiet", [], MapChange.writing("quiet", [cube(2)]))
        assert stream.next_event("upsert")[1]["id"] == 2 and version_of(stream.last_id) == 2
        assert store.whole_map_reads == 1


def test_a_client_back_with_last_event_id_gets_what_it_missed_and_one_too_far_behind_a_reset() -> None:
    """The log keeps 3 entries: a client away for 2 commits resumes with no snapshot and no gap; one away for
    more is told ``reset`` and sent the map as it is; an id not of this map's log (ahead of it) too."""
    store = MemoryStore(change_log_entries=3)
    quiet_map(store, 1)
    settings = Settings(detector="sim:0", workers=1, event_poll_s=0.02)
    with UvicornThread(create_app(settings, store=store, detector=BlobDetector())) as server:
        with EventStream(server.url, "quiet", tentative=True) as first:
            first.next_event("snapshot")
            left_at = first.last_id
        assert version_of(left_at) == 1
        store.commit("quiet", [], MapChange.writing("quiet", [cube(2)]))  # versions 2 and 3, while it was away
        with store.lock("quiet", [1], ttl_s=5, timeout_s=1) as lease:
            store.commit("quiet", [lease], MapChange.writing("quiet", [], [cube(1)]))
        with EventStream(server.url, "quiet", tentative=True, last_event_id=left_at) as back:
            back.objects = {1: {"id": 1}}  # what it held
            back.read_until(lambda s: version_of(s.last_id) == 3, "the changes after version 1")
            assert [(name, data["id"]) for name, data in back.log] == [("removed", 1), ("upsert", 2)]  # by id, no snapshot
            assert set(back.objects) == {2}
        for i in range(3, 8):  # versions 4 to 8: the log keeps 6 to 8
            store.commit("quiet", [], MapChange.writing("quiet", [cube(i)]))
        for stale in ("3", "99"):
            with EventStream(server.url, "quiet", tentative=True, last_event_id=stale) as behind:
                _, reset = behind.next_event("reset")
                _, snapshot = behind.next_event("snapshot")
                assert reset["version"] == snapshot["version"] == 8 and version_of(behind.last_id) == 8
                assert sorted(o["id"] for o in snapshot["objects"]) == [2, 3, 4, 5, 6, 7]


@pytest.mark.parametrize("store_kind", ["memory", pytest.param("redis", marks=pytest.mark.redis)])
def test_a_client_back_with_an_id_from_before_the_map_was_deleted_is_reset_however_far_the_new_map_got(
    store_kind: str,
) -> None:
    """The map is deleted and made again while the client is away, and the new map's writers get past the client's
    ``Last-Event-ID``: the stream says ``reset`` and sends the new map. (Versions restarted at 1 with the new map, so
    that one at version 2 answered an id 2 with nothing: the client kept the deleted map's objects, silently.)"""
    from redis_server import RedisServer

    from arcloud.stores.redis import RedisStore

    with contextlib.ExitStack() as stack:
        if store_kind == "redis":
            redis_url = stack.enter_context(RedisServer.start()).url
            store: MemoryStore | RedisStore = RedisStore(redis_url)
            stack.callback(store.close)
            settings = Settings(store=redis_url, auth="none", detector="sim:0", workers=0, event_poll_s=0.02)
            app = create_app(settings)
        else:
            store = MemoryStore()
            settings = Settings(detector="sim:0", workers=1, auth="none", event_poll_s=0.02)
            app = create_app(settings, store=store, detector=BlobDetector())
        header = MapHeader.from_params(Params(), codec_version=store.codec_version, created_at_s=1.0)

        def made(*places: int) -> None:  # the map opened, each object (ids from the map's counter) one commit
            store.open_map("again", header)
            for place, object_id in zip(places, store.new_ids("again", len(places))):
                store.commit("again", [], MapChange.writing("again", [cube(place).replace(id=object_id)]))

        made(1, 2)
        server = stack.enter_context(UvicornThread(app))
        with EventStream(server.url, "again", tentative=True) as first:
            first.next_event("snapshot")
            left_at, held = first.last_id, dict(first.objects)
        assert version_of(left_at) == 2 and sorted(held) == [1, 2]
        assert httpx.delete(f"{server.url}/v1/maps/again", timeout=10).status_code == 200
        made(7, 8, 9)  # the new map, while the client is away: as many commits as the old one had, and one more
        with EventStream(server.url, "again", tentative=True, last_event_id=left_at) as back:
            back.objects = held
            _, reset = back.next_event("reset")
            _, snapshot = back.next_event("snapshot")
        listed = store.list_meta("again")
        assert reset["version"] == snapshot["version"] == 6  # 2 commits, the deletion, 3 commits
        assert {i: o["aabb"]["min"] for i, o in back.objects.items()} == {o.id: o.aabb.min.tolist() for o in listed}
        assert sorted(back.objects) == [3, 4, 5]  # ids the deleted map never gave


def test_a_client_back_after_the_store_lost_the_map_is_reset_though_the_new_map_got_past_its_version() -> None:
    """A review of a lost Redis: a client at version 29 came back after Redis restarted empty and the new map reached
    version 36: it was sent 30 to 36 as if they followed its 29, and kept objects that no longer existed. The log
    that began again begins at another time, which the id carries (``V@B``): the stream says ``reset``. Here the
    embedded service restarts (its store is the process's): the same."""
    port = free_port()
    lost = MemoryStore()
    quiet_map(lost, 1, 2)
    settings = Settings(detector="sim:0", workers=1, event_poll_s=0.02)
    with (
        UvicornThread(create_app(settings, store=lost, detector=BlobDetector()), port=port) as server,
        EventStream(server.url, "quiet", tentative=True) as first,
    ):
        first.next_event("snapshot")
        left_at, held = first.last_id, dict(first.objects)
    assert version_of(left_at) == 1 and "@" in (left_at or "") and sorted(held) == [1, 2]
    again = MemoryStore()  # what the map became after the loss: other objects, past the client's version
    quiet_map(again, 5)
    again.commit("quiet", [], MapChange.writing("quiet", [cube(6)]))
    with (
        UvicornThread(create_app(settings, store=again, detector=BlobDetector()), port=port) as server,
        EventStream(server.url, "quiet", tentative=True) as fresh,  # a viewer already on the new log (a review: the
    ):  # check was against every stream's log, so the one back below was neither reset nor sent anything)
        fresh.next_event("snapshot")
        with EventStream(server.url, "quiet", tentative=True, last_event_id=left_at) as back:
            back.objects = held
            _, reset = back.next_event("reset")
            _, snapshot = back.next_event("snapshot")
    assert reset["reason"].startswith("the map's change log began again") and reset["version"] == snapshot["version"] == 2
    assert sorted(back.objects) == [5, 6] and version_of(back.last_id) == 2 and back.last_id != left_at
