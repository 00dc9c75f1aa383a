"""The maps as things to list and page through: ``GET /v1/maps`` and cursor pages of ``GET .../objects``,
on the embedded service (a real app, the blob detector) and, filtered by key, on Redis."""

from __future__ import annotations

import pytest
from redis_server import RedisServer
from svc_helpers import LEFT, RIGHT, AppClient, BlobDetector, UvicornThread, make_test_frame, wait_until

from arcloud.access import new_key
from arcloud.client.http import ArcloudClient
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores.redis_api_keys import RedisKeyStore
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}


def post(client: AppClient, map_id: str, index: int, headers: dict[str, str] | None = None) -> None:
    body = frame_to_proto(make_test_frame(index, map_id=map_id, boxes=(LEFT, RIGHT), level=True)).SerializeToString()
    response = client.post(f"/v1/maps/{map_id}/frames", content=body, headers={**PROTOBUF, **(headers or {})})
    assert response.status_code == 202, response.text


def test_maps_are_listed_by_id_in_pages_with_their_counts() -> None:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as client:
        assert client.get("/v1/maps").json() == {"maps": [], "next_cursor": None}
        for map_id in ("c", "a", "b"):
            post(client, map_id, 0)
        wait_until(
            lambda: all(client.get(f"/v1/maps/{m}/stats").json()["frames"]["processed"] == 1 for m in "abc"),
            20,
            "frames processed",
        )
        first = client.get("/v1/maps", params={"limit": 2}).json()
        assert [m["map_id"] for m in first["maps"]] == ["a", "b"] and first["next_cursor"] == "b"
        second = client.get("/v1/maps", params={"limit": 2, "cursor": first["next_cursor"]}).json()
        assert [m["map_id"] for m in second["maps"]] == ["c"] and second["next_cursor"] is None
        summary = second["maps"][0]
        assert summary["objects"] == 2 and summary["frames"] == {"accepted": 1, "processed": 1, "failed": 0, "pending": 0}
        assert summary["updated_at"].endswith("Z")
        client.delete("/v1/maps/b")
        assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["a", "c"]
        for bad in ({"limit": 0}, {"limit": 1001}, {"cursor": "vic\\tim"}):
            response = client.get("/v1/maps", params=bad)
            assert response.status_code == 422 and response.json()["field"] in ("limit", "cursor"), response.text


def test_objects_come_in_cursor_pages_that_cover_the_list_once() -> None:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as client:
        for index in range(2):
            post(client, "m", index)
        wait_until(lambda: client.get("/v1/maps/m/stats").json()["frames"]["processed"] == 2, 20, "frames processed")
        everything = client.get("/v1/maps/m/objects", params={"include": "tentative"}).json()
        assert everything["next_cursor"] is None and len(everything["objects"]) == 2
        seen, cursor = [], None
        while True:
            params = {"include": "tentative", "limit": 1, **({"cursor": cursor} if cursor else {})}
            page = client.get("/v1/maps/m/objects", params=params).json()
            seen += [o["id"] for o in page["objects"]]
            cursor = page["next_cursor"]
            if cursor is None:
                break
        assert seen == [o["id"] for o in everything["objects"]]
        for bad in ("x", "-1", "9" * 30):
            response = client.get("/v1/maps/m/objects", params={"cursor": bad, "limit": 1})
            assert response.status_code == 422 and response.json()["field"] == "cursor", response.text


@pytest.mark.redis
def test_a_key_lists_only_its_own_maps() -> None:
    server = RedisServer.start()
    try:
        keys = RedisKeyStore(server.url)
        admin, admin_token = new_key("admin", ("*",), now_s=0.0)
        device, device_token = new_key("device", ("a",), now_s=0.0)
        keys.add(admin)
        keys.add(device)
        keys.close()
        with AppClient(create_app(Settings(store=server.url, detector="sim:0", workers=0))) as client:
            for map_id in ("a", "b"):
                post(client, map_id, 0, {"authorization": f"Bearer {admin_token}"})  # no workers: listed once accepted
            as_admin = client.get("/v1/maps", headers={"authorization": f"Bearer {admin_token}"}).json()
            as_device = client.get("/v1/maps", headers={"authorization": f"Bearer {device_token}"}).json()
            assert [m["map_id"] for m in as_admin["maps"]] == ["a", "b"]
            assert [m["map_id"] for m in as_device["maps"]] == ["a"]
            assert as_device["maps"][0]["frames"]["pending"] == 1
            assert client.get("/v1/maps").status_code == 401
        with UvicornThread(create_app(Settings(store=server.url, detector="sim:0", workers=0))) as http:
            with ArcloudClient(http.url, token=device_token) as sdk:
                assert [m.map_id for m in sdk.list_maps(page_size=1)] == ["a"]
            with ArcloudClient(http.url, token=admin_token) as sdk:
                assert [m.map_id for m in sdk.list_maps(page_size=1)] == ["a", "b"]  # two pages
    finally:
        server.stop()


def test_an_object_carried_away_leaves_the_listing_for_the_retired_history() -> None:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as client:
        for index in range(6):  # two chairs, seen upright: confirmed
            post(client, "r", index)
        wait_until(lambda: client.get("/v1/maps/r/stats").json()["frames"]["processed"] == 6, 20, "frames processed")
        before = {o["id"]: o for o in client.get("/v1/maps/r/objects").json()["objects"]}
        assert len(before) == 2 and client.get("/v1/maps/r/retired").json() == {"objects": []}
        for index in range(6, 12):  # the left chair is gone: its place shows the wall behind
            body = frame_to_proto(make_test_frame(index, map_id="r", boxes=(RIGHT,), level=True)).SerializeToString()
            assert client.post("/v1/maps/r/frames", content=body, headers=PROTOBUF).status_code == 202
        wait_until(lambda: client.get("/v1/maps/r/stats").json()["frames"]["processed"] == 12, 20, "frames processed")
        after = {o["id"] for o in client.get("/v1/maps/r/objects", params={"include": "tentative"}).json()["objects"]}
        retired = client.get("/v1/maps/r/retired").json()["objects"]
        assert len(after) == 1 and [r["id"] for r in retired] == sorted(set(before) - after)
        assert retired[0]["label"] == "chair" and retired[0]["retired_at"].endswith("Z")
        assert client.get("/v1/maps/nowhere/retired").status_code == 404
