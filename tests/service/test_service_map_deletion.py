"""Deleting a large map (issue 22: big jobs run in bounded chunks and report progress): ``DELETE /v1/maps/{map}``
records the deletion and goes on in steps; another client follows it with ``GET .../deletion`` (admin, as the
DELETE); the map's frames and reads answer 409 ``/problems/map-deleting`` until it is done, never a 500; Redis
answers another client's PING within the bound throughout. Real app, real redis-server (and the embedded store)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from ping_watch import PING_BOUND_S, PingWatch
from redis_server import RedisServer
from svc_helpers import AppClient, BlobDetector, UvicornThread, assert_problem, cube, make_test_frame, wait_until

from arcloud.access import new_key
from arcloud.core.change import MapChange
from arcloud.core.types import Params
from arcloud.errors import StoreUnavailable
from arcloud.proto.convert import frame_to_proto
from arcloud.service import app as app_module
from arcloud.service.settings import Settings
from arcloud.service.worker import FrameWorker
from arcloud.stores import keys
from arcloud.stores import redis as redis_store_module
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_api_keys import RedisKeyStore
from arcloud.stores.redis_queue import RedisFrameQueue
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
N_OBJECTS = 600
STEP_OBJECTS = 4  # objects a deletion step here (64 in service): many steps for the reader to see


@pytest.fixture(scope="module")
def redis_server() -> Iterator[RedisServer]:
    with RedisServer.start() as server:
        yield server


def dying_after_one_step() -> Any:
    """A ``RedisStore._delete_objects`` that deletes one step's objects, then fails as a dying process would."""
    delete_objects = RedisStore._delete_objects
    steps = 0

    def dying(self: RedisStore, going: Any, ids: list[bytes]) -> Any:
        nonlocal steps
        steps += 1
        if steps > 1:
            raise StoreUnavailable("the process died here")
        return delete_objects(self, going, ids)

    return dying


def frame_body(map_id: str, index: int = 0) -> bytes:
    return frame_to_proto(make_test_frame(index, map_id=map_id)).SerializeToString()


@pytest.mark.redis
@pytest.mark.slow
def test_a_large_maps_deletion_is_followed_by_another_client_and_refuses_the_maps_frames(
    redis_server: RedisServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """600 objects deleted 4 at a time while a second client polls the deletion, posts a frame to the map and reads
    it. A loaded machine can hold a process back 100 ms by itself: the whole is tried again once when a PING went over."""
    monkeypatch.setattr(redis_store_module, "DELETE_OBJECTS", STEP_OBJECTS)
    now = time.time()
    admin_key, admin = new_key("admin", ("*",), now_s=now)
    reader_key, reader = new_key("reader", ("*",), now_s=now)
    key_store = RedisKeyStore(redis_server.url)
    key_store.add(admin_key)
    key_store.add(reader_key)
    key_store.close()
    as_admin = {"authorization": f"Bearer {admin}"}
    settings = Settings(store=redis_server.url, detector="sim:0", workers=0, key_cache_s=0.0, key_rate_per_s=0)
    store = RedisStore(redis_server.url)
    try:
        with UvicornThread(create_app(settings)) as server, httpx.Client(base_url=server.url, timeout=30) as http:
            for attempt in range(2):
                big = f"big{attempt}"
                posted = http.post(f"/v1/maps/{big}/frames", content=frame_body(big), headers={**PROTOBUF, **as_admin})
                assert posted.status_code == 202, posted.text
                for start in range(1, N_OBJECTS + 1, 100):
                    store.commit(big, [], MapChange.writing(big, [cube(i) for i in range(start, start + 100)]))
                assert store.count_objects(big) == N_OBJECTS
                answers: dict[str, httpx.Response] = {}

                def delete(map_id: str = big, answers: dict[str, httpx.Response] = answers) -> None:
                    with httpx.Client(base_url=server.url, timeout=60) as deleter:
                        answers["delete"] = deleter.delete(f"/v1/maps/{map_id}", headers=as_admin)

                seen: list[dict[str, Any]] = []
                refusals: list[httpx.Response] = []
                with PingWatch(redis_server.url) as watch:
                    deleter = threading.Thread(target=delete)
                    deleter.start()
                    deadline = time.monotonic() + 60
                    while (not seen or seen[-1]["state"] != "deleted") and time.monotonic() < deadline:
                        progress = http.get(f"/v1/maps/{big}/deletion", headers=as_admin)
                        if progress.status_code == 404:  # not begun yet
                            continue
                        assert progress.status_code == 200, progress.text
                        seen.append(progress.json())
                        if seen[-1]["state"] == "deleting" and not refusals:
                            refusals = [
                                http.post(f"/v1/maps/{big}/frames", content=frame_body(big, 1), headers={**PROTOBUF, **as_admin}),
                                http.get(f"/v1/maps/{big}/objects", headers=as_admin),
                                http.delete(f"/v1/maps/{big}", headers=as_admin),
                            ]
                    deleter.join(60)
                if watch.max_s < PING_BOUND_S:
                    break
            print(
                f"{len(seen)} progress reads, {sum(s['state'] == 'deleting' for s in seen)} mid-deletion; PING max "
                f"{1000 * watch.max_s:.1f} ms of {len(watch.times_s)}, longest command {1000 * watch.longest_command_s:.1f} ms"
            )
            assert answers["delete"].status_code == 200, answers["delete"].text
            assert answers["delete"].json() == {"map_id": big, "deleted_objects": N_OBJECTS}
            removed = [s["objects_removed"] for s in seen]
            assert removed == sorted(removed) and any(0 < r < N_OBJECTS for r in removed), removed
            done = seen[-1]
            assert done["state"] == "deleted" and done["objects"] == done["objects_removed"] == N_OBJECTS
            assert done["keys_removed"] > N_OBJECTS and done["started_at"] <= done["finished_at"]
            assert all(s["finished_at"] is None for s in seen[:-1])
            assert len(refusals) == 3, "no progress read found the deletion going on"
            for refused in refusals:
                problem = assert_problem(refused, 409, "map_id")
                assert problem["type"] == "/problems/map-deleting" and "is being deleted" in problem["detail"], problem
            assert watch.max_s < PING_BOUND_S, f"a PING waited {watch.max_s:.3f} s while the map was deleted"
            # Access as the DELETE's: admin; the map takes frames again once its deletion is done (a new map).
            assert http.get(f"/v1/maps/{big}/deletion", headers={"authorization": f"Bearer {reader}"}).status_code == 403
            assert http.get(f"/v1/maps/{big}/objects", headers=as_admin).status_code == 404
            again = http.post(f"/v1/maps/{big}/frames", content=frame_body(big, 2), headers={**PROTOBUF, **as_admin})
            assert again.status_code == 202, again.text
            assert http.get("/v1/maps/other/deletion", headers=as_admin).status_code == 404
    finally:
        store.close()


def test_the_embedded_store_deletes_at_once_and_says_so() -> None:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as api:
        assert api.post("/v1/maps/m/frames", content=frame_body("m"), headers=PROTOBUF).status_code == 202
        wait_until(lambda: api.get("/v1/maps/m/stats").json()["frames"]["processed"] == 1, 20, "the frame processed")
        n_objects = api.get("/v1/maps/m/stats").json()["objects"]["total"]
        assert n_objects > 0
        assert_problem(api.get("/v1/maps/m/deletion"), 404, None)
        assert api.delete("/v1/maps/m").json() == {"map_id": "m", "deleted_objects": n_objects}
        done = api.get("/v1/maps/m/deletion").json()
        assert done["state"] == "deleted" and done["objects"] == done["objects_removed"] == n_objects
        assert done["keys_removed"] == 0 and done["finished_at"] == done["updated_at"]
        assert api.get("/v1/maps/m/stats").status_code == 404  # done: the map is simply gone


@pytest.mark.redis
def test_a_deletion_whose_process_died_refuses_the_map_until_a_delete_goes_on_with_it(
    redis_server: RedisServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A deletion stopped after its first step (here: the store failing under it) keeps the map refused (409), and a
    second DELETE answers 409 while the deletion is fresh; once it made no progress for ``DELETION_STALE_S`` a
    DELETE goes on from what is left and ends it."""
    monkeypatch.setattr(redis_store_module, "DELETE_OBJECTS", STEP_OBJECTS)
    settings = Settings(store=redis_server.url, detector="sim:0", workers=0, auth="none")
    store = RedisStore(redis_server.url)
    delete_objects = RedisStore._delete_objects
    dying = dying_after_one_step()

    try:
        with AppClient(create_app(settings)) as api:
            assert api.post("/v1/maps/died/frames", content=frame_body("died"), headers=PROTOBUF).status_code == 202
            store.commit("died", [], MapChange.writing("died", [cube(i) for i in range(1, 21)]))
            monkeypatch.setattr(RedisStore, "_delete_objects", dying)
            assert api.delete("/v1/maps/died").status_code == 503
            monkeypatch.setattr(RedisStore, "_delete_objects", delete_objects)
            stopped = api.get("/v1/maps/died/deletion").json()
            assert stopped["state"] == "deleting" and (stopped["objects"], stopped["objects_removed"]) == (20, STEP_OBJECTS)
            for refused in (
                api.post("/v1/maps/died/frames", content=frame_body("died", 1), headers=PROTOBUF),
                api.get("/v1/maps/died/stats"),
                api.delete("/v1/maps/died"),  # fresh: another process may be deleting it
            ):
                assert assert_problem(refused, 409, "map_id")["type"] == "/problems/map-deleting"
            monkeypatch.setattr(app_module, "DELETION_STALE_S", 0.0)
            assert api.delete("/v1/maps/died").json() == {"map_id": "died", "deleted_objects": 20 - STEP_OBJECTS}
            done = api.get("/v1/maps/died/deletion").json()
            assert done["state"] == "deleted" and done["objects"] == done["objects_removed"] == 20 - STEP_OBJECTS
            left = {k.decode() for k in store.client.scan_iter(match="arcloud:{died}:*")}
            assert store.count_objects("died") == 0 and left <= {
                keys.version_key("died"),
                keys.began_key("died"),
                keys.published_key("died"),
            }
            assert api.post("/v1/maps/died/frames", content=frame_body("died", 2), headers=PROTOBUF).status_code == 202
    finally:
        store.close()


@pytest.mark.redis
def test_a_frame_queued_before_its_maps_deletion_is_dead_lettered_and_does_not_bring_the_map_back(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A worker takes a frame of a map whose deletion is under way (here stopped after its first step): the frame
    is dead-lettered with the reason, and the map gets no header or object back."""
    monkeypatch.setattr(redis_store_module, "DELETE_OBJECTS", STEP_OBJECTS)
    redis_server = RedisServer.start()  # its own: the module's server holds other tests' queued frames
    store = RedisStore(redis_server.url)
    queue = RedisFrameQueue(redis_server.url)
    worker = FrameWorker(queue, store, BlobDetector(), Params(voxel_size_m=0.04), consumer="late", read_block_s=0.1)
    delete_objects = RedisStore._delete_objects
    dying = dying_after_one_step()

    try:
        store.commit("late", [], MapChange.writing("late", [cube(i) for i in range(1, 21)]))
        dead_letters = keys.ingest_dead_letter_stream(keys.shard_tag(0, 1))
        before = redis_server.client().xlen(dead_letters)
        assert queue.put(make_test_frame(0, map_id="late"))
        monkeypatch.setattr(RedisStore, "_delete_objects", dying)
        with pytest.raises(StoreUnavailable):
            store.delete_map("late")
        monkeypatch.setattr(RedisStore, "_delete_objects", delete_objects)
        deletion = store.map_deletion("late")
        assert deletion is not None and not deletion.done
        remaining = store.count_objects("late")
        assert worker.poll_once() == 1
        assert redis_server.client().xlen(dead_letters) == before + 1
        [(_, dead)] = redis_server.client().xrevrange(dead_letters, count=1)
        assert dead[b"reason"].startswith(b"MapBeingDeleted: map late is being deleted"), dead
        assert store.map_header("late") is None and store.count_objects("late") == remaining
    finally:
        queue.close()
        store.close()
        redis_server.stop()
