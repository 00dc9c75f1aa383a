"""Maps that last and move: Redis with its append-only file keeps every map across a restart; a
snapshot taken through the API restores the same objects into an empty Redis and into the embedded
service; `arcloud maps` lists, snapshots, restores and copies. Real redis-servers, real apps."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from redis_server import RedisServer
from snapshot_edits import first_object_id, with_object_changed, with_object_renamed
from svc_helpers import LEFT, RIGHT, AppClient, BlobDetector, UvicornThread, make_test_frame

from arcloud.cli import main as cli_main
from arcloud.core.types import AABB
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.service.worker import FrameWorker
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue
from arcloud.tools.wiring import create_app

pytestmark = [pytest.mark.redis, pytest.mark.slow]
PROTOBUF = {"content-type": "application/x-protobuf"}
TENTATIVE = {"include": "tentative"}
#: What a restore keeps of an object: everything but the version (the stores' write fence starts again at 1).
KEPT = ("id", "label", "score", "aabb", "obb", "n_voxels", "n_frames", "n_devices", "status", "updated_at")


def redis_app(url: str) -> Any:
    return create_app(Settings(store=url, auth="none", detector="sim:0", workers=0))


def fill(api: AppClient, url: str, maps: dict[str, int]) -> None:
    """Post frames of two chairs to each map and process them with one worker here."""
    for map_id, n in maps.items():
        for index in range(n):
            body = frame_to_proto(make_test_frame(index, map_id=map_id, boxes=(LEFT, RIGHT), level=True)).SerializeToString()
            assert api.post(f"/v1/maps/{map_id}/frames", content=body, headers=PROTOBUF).status_code == 202
    queue, store = RedisFrameQueue(url), RedisStore(url)
    worker = FrameWorker(queue, store, BlobDetector(), Settings().make_params(), heartbeat_s=None, read_block_s=0.1)
    try:
        deadline = time.monotonic() + 60
        while any(api.get(f"/v1/maps/{m}/stats").json()["frames"]["processed"] < n for m, n in maps.items()):
            assert time.monotonic() < deadline, "frames not processed in 60 s"
            worker.poll_once()
    finally:
        queue.close()
        store.close()


def objects(api: AppClient, map_id: str) -> list[dict[str, Any]]:
    return [{k: o[k] for k in KEPT} for o in api.get(f"/v1/maps/{map_id}/objects", params=TENTATIVE).json()["objects"]]


def voxels(api: AppClient, map_id: str) -> dict[int, Any]:
    return {
        o["id"]: api.get(f"/v1/maps/{map_id}/objects/{o['id']}", params={"voxels": "true"}).json()["voxels"]
        for o in objects(api, map_id)
    }


class Filled:
    """A Redis with its AOF in a folder (``server`` is the one running now), and the objects of its maps."""

    def __init__(self, server: RedisServer, aof: Path, before: dict[str, list[dict[str, Any]]]) -> None:
        self.server, self.aof, self.before = server, aof, before


@pytest.fixture(scope="module")
def filled(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Filled]:
    """Maps a (6 frames) and b (3 frames) made through the API on a Redis with its AOF on."""
    aof = tmp_path_factory.mktemp("aof")
    server = RedisServer.start(aof_dir=str(aof))
    with AppClient(redis_app(server.url)) as api:
        fill(api, server.url, {"a": 6, "b": 3})
        before = {m: objects(api, m) for m in ("a", "b")}
    assert before["a"] and before["b"]
    state = Filled(server, aof, before)
    yield state
    state.server.stop()


def test_a_redis_restart_with_its_aof_keeps_every_map(filled: Filled) -> None:
    old = filled.server
    old.client().shutdown()  # graceful; with fsync always a kill -9 would lose nothing either
    old.process.wait(10)
    old.stop()
    filled.server = RedisServer.start(port=old.port, aof_dir=str(filled.aof))
    with AppClient(redis_app(filled.server.url)) as api:
        assert [m["map_id"] for m in api.get("/v1/maps").json()["maps"]] == ["a", "b"]
        assert {m: objects(api, m) for m in ("a", "b")} == filled.before


def test_a_snapshot_restores_the_same_objects_into_an_empty_redis_and_the_embedded_service(filled: Filled) -> None:
    server, before = filled.server, filled.before
    with AppClient(redis_app(server.url)) as source:
        snapshot = source.get("/v1/maps/a/snapshot")
        assert snapshot.status_code == 200 and snapshot.headers["content-type"] == "application/zip"
        source_voxels = voxels(source, "a")
    with RedisServer.start() as empty, AppClient(redis_app(empty.url)) as target:
        assert target.get("/v1/maps/a/objects").status_code == 404
        put = target.request("PUT", "/v1/maps/a/snapshot", content=snapshot.content, headers={"content-type": "application/zip"})
        assert put.json() == {"map_id": "a", "restored_objects": len(before["a"])}
        assert objects(target, "a") == before["a"] and voxels(target, "a") == source_voxels
        again = target.request("PUT", "/v1/maps/a/snapshot", content=snapshot.content)
        assert again.status_code == 422 and again.json()["field"] == "map_id"  # not into a map with objects
        replaced = target.request("PUT", "/v1/maps/a/snapshot", params={"replace": "true"}, content=snapshot.content)
        assert replaced.status_code == 200 and objects(target, "a") == before["a"]
        # New objects of the restored map get new ids: the id counter moved past the restored ones.
        assert [m["map_id"] for m in target.get("/v1/maps").json()["maps"]] == ["a"]
        bad = target.request("PUT", "/v1/maps/c/snapshot", content=b"not a zip")
        assert bad.status_code == 422 and bad.json()["field"] == "snapshot"
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as embedded:
        assert embedded.request("PUT", "/v1/maps/moved/snapshot", content=snapshot.content).status_code == 200
        assert objects(embedded, "moved") == before["a"] and voxels(embedded, "moved") == source_voxels
    other = create_app(Settings(detector="sim:0", workers=1, params={"voxel_size_m": 0.04}), detector=BlobDetector())
    with AppClient(other) as mismatched:
        refused = mismatched.request("PUT", "/v1/maps/a/snapshot", content=snapshot.content)
        assert refused.status_code == 409 and "voxel_size_m" in refused.json()["detail"]


def test_a_snapshot_holding_what_no_frame_could_make_is_refused_422_naming_the_object(filled: Filled) -> None:
    """Issue 22: an HTML label was stored and served, a NaN box served as null, an id >= 2**63 answered 500."""
    with AppClient(redis_app(filled.server.url)) as source:
        valid = source.get("/v1/maps/a/snapshot").content
    first = first_object_id(valid)
    bad = {
        f"objects/{first}.label": with_object_changed(valid, first, label="<script>alert(1)</script>\nchair"),
        f"objects/{first}.aabb": with_object_changed(valid, first, aabb=AABB(np.array([np.nan, 0.0, 0.0]), np.ones(3))),
        f"objects/{2**63}.id": with_object_renamed(valid, first, str(2**63)),
    }
    embedded = create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())
    with RedisServer.start() as empty, AppClient(redis_app(empty.url)) as on_redis, AppClient(embedded) as in_memory:
        for api in (on_redis, in_memory):
            for field, body in bad.items():
                answer = api.request("PUT", "/v1/maps/r/snapshot", content=body, headers={"content-type": "application/zip"})
                assert answer.status_code == 422 and answer.json()["field"] == field, answer.text
                assert answer.json()["detail"].startswith(f"{field}: expected ")
            assert api.get("/v1/maps/r/objects").status_code == 404  # nothing restored
            assert api.request("PUT", "/v1/maps/r/snapshot", content=valid).status_code == 200


def test_maps_commands_list_snapshot_restore_and_copy(filled: Filled, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    server, before = filled.server, filled.before
    capsys.readouterr()
    assert cli_main(["maps", "list", "--redis", server.url]) == 0
    listing = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in listing[1:]] == ["a", "b"] and listing[1].split()[1] == str(len(before["a"]))
    assert cli_main(["maps", "snapshot", "--redis", server.url, "--map", "b", "--out", str(tmp_path / "b.zip")]) == 0
    with RedisServer.start() as empty:
        assert cli_main(["maps", "restore", "--redis", empty.url, "--map", "b2", "--in", str(tmp_path / "b.zip")]) == 0
        embedded = create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())
        with UvicornThread(embedded) as http:
            assert cli_main(["maps", "copy", "--map", "b2", "--from", empty.url, "--to", http.url]) == 0
            with AppClient(redis_app(empty.url)) as check:
                assert objects(check, "b2") == before["b"]
            capsys.readouterr()
            assert cli_main(["maps", "list", "--url", http.url]) == 0
            assert capsys.readouterr().out.splitlines()[1].split()[:2] == ["b2", str(len(before["b"]))]
    assert cli_main(["maps", "copy", "--map", "b", "--from", "ftp://x", "--to", server.url]) == 2


def test_a_map_replaced_from_a_snapshot_forgets_its_frames_as_a_delete_does() -> None:
    """A review of a lost Redis: ``replace=true`` deleted the objects but kept the frames' records and counts, so the
    stats read processed 0, pending 3 for ever, and a frame sent again answered ``duplicate``: what the frames since
    the snapshot added could not be sent back. A refused file forgets nothing."""
    with RedisServer.start() as server, AppClient(redis_app(server.url)) as api:
        fill(api, server.url, {"r": 3})
        snapshot = api.get("/v1/maps/r/snapshot").content
        frames = lambda: api.get("/v1/maps/r/stats").json()["frames"]  # noqa: E731 - read again after each change
        refused = api.request("PUT", "/v1/maps/r/snapshot", params={"replace": "true"}, content=b"not a zip")
        assert refused.status_code == 422 and frames() == {"accepted": 3, "processed": 3, "failed": 0, "pending": 0}
        put = api.request("PUT", "/v1/maps/r/snapshot", params={"replace": "true"}, content=snapshot)
        assert put.status_code == 200, put.text
        assert frames() == {"accepted": 0, "processed": 0, "failed": 0, "pending": 0}
        body = frame_to_proto(make_test_frame(2, map_id="r", boxes=(LEFT, RIGHT), level=True)).SerializeToString()
        assert api.post("/v1/maps/r/frames", content=body, headers=PROTOBUF).json()["status"] == "queued"
