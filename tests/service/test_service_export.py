"""Exports of a real map (the embedded service, the blob detector, six upright frames of two chairs): each
format opens in a standard reader (Open3D for PLY, trimesh's glTF loader for GLB, the project's evaluation
for the ScanNet files), through the API and through `arcloud export` with a token."""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from svc_helpers import LEFT, RIGHT, AppClient, BlobDetector, UvicornThread, free_port, make_test_frame, wait_until

from arcloud.access import new_key
from arcloud.cli import main as cli_main
from arcloud.client.http import ArcloudClient, ServiceError
from arcloud.core.types import LabelledBox
from arcloud.eval.metrics import evaluate
from arcloud.formats.colors import object_color
from arcloud.formats.scannet import read_boxes
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores.file_api_keys import FileKeyStore
from arcloud.tools.wiring import create_app


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str, list[dict[str, Any]]]]:
    """(service URL, reader token, every object of map "room") with two confirmed chairs."""
    keys_file = tmp_path_factory.mktemp("keys") / "keys.json"
    device, device_token = new_key("device", ("room",), now_s=0.0)
    reader, reader_token = new_key("reader", ("room",), now_s=0.0)
    FileKeyStore(keys_file).add(device)
    FileKeyStore(keys_file).add(reader)
    app = create_app(Settings(detector="sim:0", workers=1, keys_file=str(keys_file)), detector=BlobDetector())
    with UvicornThread(app) as server, ArcloudClient(server.url, token=device_token) as client:
        for index in range(6):
            client.send_frame(make_test_frame(index, map_id="room", boxes=(LEFT, RIGHT), level=True))
        wait_until(lambda: client.stats("room").frames.processed == 6, 30, "six frames processed")
        objects = [dataclasses.asdict(o) for o in client.list_objects("room", include_tentative=True)]  # as the export's JSON
        assert sum(o["status"] == "confirmed" for o in objects) == 2
        yield server.url, reader_token, objects


def test_ply_has_one_coloured_point_per_voxel_of_the_served_objects(
    served: tuple[str, str, list[dict[str, Any]]], tmp_path: Path
) -> None:
    import open3d as o3d

    url, token, objects = served
    confirmed = [o for o in objects if o["status"] == "confirmed"]
    with ArcloudClient(url, token=token) as client:
        path = tmp_path / "room.ply"
        path.write_bytes(client.export("room", "ply"))
        voxels = {
            o["id"]: dataclasses.asdict(client.get_object("room", o["id"], voxels=True))["voxels"]["centers"] for o in confirmed
        }
    cloud = o3d.io.read_point_cloud(path)
    points, colors = np.asarray(cloud.points), np.round(np.asarray(cloud.colors) * 255).astype(int)
    assert len(points) == sum(o["n_voxels"] for o in confirmed) == sum(len(v) for v in voxels.values())
    assert cloud.has_colors()
    np.testing.assert_allclose(np.sort(points, axis=0), np.sort(np.concatenate(list(voxels.values())), axis=0), atol=1e-5)
    assert {tuple(c) for c in colors} == {object_color(i) for i in voxels}  # one colour per object


def test_ply_in_voxel_colours_reads_back_in_the_colour_the_frames_showed(
    served: tuple[str, str, list[dict[str, Any]]], tmp_path: Path
) -> None:
    import open3d as o3d

    url, token, objects = served
    confirmed = [o for o in objects if o["status"] == "confirmed"]
    with ArcloudClient(url, token=token) as client:
        path = tmp_path / "room-rgb.ply"
        path.write_bytes(client.export("room", "ply", color="rgb"))
        voxels = [dataclasses.asdict(client.get_object("room", o["id"], voxels=True))["voxels"] for o in confirmed]
    cloud = o3d.io.read_point_cloud(path)
    points, colors = np.asarray(cloud.points), np.round(np.asarray(cloud.colors) * 255).astype(int)
    assert cloud.has_colors() and len(points) == sum(len(v["colors"]) for v in voxels)
    # The near boxes were (200, 60, 40) in every frame (sent as JPEG, so within a few levels).
    np.testing.assert_allclose(colors, np.tile([200, 60, 40], (len(colors), 1)), atol=12)
    # The API gives each voxel's colour beside its centre: the same as the PLY's point there.
    by_point = {tuple(np.round(p, 4)): tuple(c) for p, c in zip(points, colors)}
    for v in voxels:
        assert len(v["colors"]) == len(v["centers"]) == len(v["weights"])
        assert all(by_point[tuple(np.round(c, 4))] == tuple(rgb) for c, rgb in zip(v["centers"], v["colors"]))


def test_glb_has_one_node_per_object_with_its_box_and_label(served: tuple[str, str, list[dict[str, Any]]]) -> None:
    import trimesh

    url, token, objects = served
    with ArcloudClient(url, token=token) as client:
        data = client.export("room", "glb", include="tentative")
    scene = trimesh.load(io.BytesIO(data), file_type="glb", force="scene")
    boxed = [o for o in objects if o["obb"] is not None]
    nodes = [n for n in scene.graph.nodes_geometry]
    assert len(nodes) == len(boxed) == len(objects)
    # Each node's box, back in the map's z-up world, has the object's oriented-box size and centre.
    by_name = {f"{o['label']} {o['id']}": o for o in boxed}
    for node in nodes:
        transform, geometry = scene.graph[node]
        corners = trimesh.transform_points(scene.geometry[geometry].vertices, transform)
        world = corners[:, [0, 2, 1]] * np.array([1, -1, 1])  # glTF (x, y, z) = world (x, z, -y)
        obb = by_name[node]["obb"]
        np.testing.assert_allclose(world.mean(axis=0), obb["center"], atol=1e-4)
        np.testing.assert_allclose(np.linalg.norm(corners[0] - corners, axis=1).max(), np.linalg.norm(obb["size"]), atol=1e-4)


def test_scannet_files_read_back_to_the_same_map(served: tuple[str, str, list[dict[str, Any]]]) -> None:
    url, token, objects = served
    with ArcloudClient(url, token=token) as client, zipfile.ZipFile(io.BytesIO(client.export("room", "scannet"))) as archive:
        boxes = read_boxes(archive.read("room_boxes.txt").decode())
        assert archive.read("room.txt") == b""  # no mesh, no masks
    confirmed = [o for o in objects if o["status"] == "confirmed"]
    direct = [LabelledBox(o["label"], np.array(o["aabb"]["min"]), np.array(o["aabb"]["max"]), o["score"]) for o in confirmed]
    assert len(boxes) == len(direct)
    truth = [LabelledBox(b.label, b.min + 0.02, b.max + 0.02) for b in direct]  # near the boxes: mAP between 0 and 1 at 0.9
    for thresholds in ((0.25, 0.5), (0.9, 0.95)):
        a = evaluate({"room": direct}, {"room": truth}, iou_thresholds=thresholds).to_dict()
        b = evaluate({"room": boxes}, {"room": truth}, iou_thresholds=thresholds).to_dict()
        assert a == b


def test_export_command_writes_each_format_and_masks_over_a_mesh(
    served: tuple[str, str, list[dict[str, Any]]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import open3d as o3d

    url, token, objects = served
    common = ["export", "--url", url, "--token", token, "--map", "room"]
    for fmt in ("json", "ply", "glb"):
        assert cli_main([*common, "--format", fmt, "--out", str(tmp_path / f"room.{fmt}")]) == 0
    assert cli_main([*common, "--format", "ply", "--color", "rgb", "--out", str(tmp_path / "rgb.ply")]) == 0
    rgb = np.round(np.asarray(o3d.io.read_point_cloud(tmp_path / "rgb.ply").colors) * 255)
    assert len(rgb) and np.abs(rgb - [200, 60, 40]).max() <= 12
    listed = json.loads((tmp_path / "room.json").read_text())
    assert listed["world_from_export"] == np.eye(4).tolist() and len(listed["objects"]) == 2
    # A mesh of points: one inside each object's voxels, one far away.
    inside = [np.array(o["obb"]["center"]) for o in objects if o["status"] == "confirmed"]
    mesh = o3d.geometry.TriangleMesh()
    mesh.vertices = o3d.utility.Vector3dVector(np.array([*inside, [50.0, 50.0, 50.0]]))
    o3d.io.write_triangle_mesh(tmp_path / "mesh.ply", mesh)
    assert cli_main([*common, "--format", "scannet", "--out", str(tmp_path / "pred"), "--mesh", str(tmp_path / "mesh.ply")]) == 0
    listing = (tmp_path / "pred" / "room.txt").read_text().splitlines()
    assert len(listing) == 2
    for line in listing:
        mask_file, label_id, _score = line.split()
        assert label_id == "5"  # chair
        mask = (tmp_path / "pred" / mask_file).read_text().split()
        assert len(mask) == 3 and mask[2] == "0" and mask.count("1") >= 1
    assert cli_main([*common, "--format", "scannet", "--out", str(tmp_path / "pred.zip")]) == 0
    assert zipfile.is_zipfile(tmp_path / "pred.zip")
    assert cli_main(["export", "--url", url, "--token", "arc_nope", "--map", "room", "--out", str(tmp_path / "x.json")]) == 2
    assert "401" in capsys.readouterr().err


def test_export_refusals(served: tuple[str, str, list[dict[str, Any]]]) -> None:
    url, token, _ = served
    with ArcloudClient(url, token=token, max_retries=0) as client:
        for fmt, status in (("obj", 422), ("json", 200)):
            if status == 200:
                assert json.loads(client.export("room", fmt))["map_id"] == "room"
                continue
            with pytest.raises(ServiceError) as refused:
                client.export("room", fmt)
            assert refused.value.status == status and refused.value.field == "format"
        with pytest.raises(ServiceError) as unknown:
            client.export("nowhere", "json")
        assert unknown.value.status == 403  # not the reader's map: refused before anything is looked up


def test_exports_snapshots_and_restores_beyond_those_under_way_are_refused_with_retry_after() -> None:
    """Each holds a map's file in memory. Snapshots and restores took no place (a review: three 1 MB restores that
    unpack to 1 GB at once took the process to 4.3 GB)."""
    app = create_app(Settings(detector="sim:0", workers=1, max_exports=1), detector=BlobDetector())
    with AppClient(app) as api:
        frame = make_test_frame(0, map_id="room", boxes=(LEFT, RIGHT), level=True)
        assert api.post("/v1/maps/room/frames", content=frame_to_proto(frame).SerializeToString(),
                        headers={"content-type": "application/x-protobuf"}).status_code == 202  # fmt: skip
        snapshot = api.get("/v1/maps/room/snapshot")
        assert snapshot.status_code == 200, snapshot.text
        building = app.state.runtime.exports
        assert building.take(None) is None  # an export being built: the process's one place taken
        try:
            refused = {
                "export": api.get("/v1/maps/room/export", params={"format": "json"}),
                "snapshot": api.get("/v1/maps/room/snapshot"),
                "restore": api.request(
                    "PUT", "/v1/maps/copy/snapshot", content=snapshot.content, headers={"content-type": "application/zip"}
                ),
            }
        finally:
            building.give_back(None)
        for what, answer in refused.items():
            assert answer.status_code == 429 and answer.headers["retry-after"] == "2", (what, answer.text)
            assert answer.json()["detail"].startswith(
                f"{what}: 1 exports, snapshots or restores are under way in this API process, the most it runs at once "
                "(max_exports)"
            )
        assert api.get("/v1/maps/room/export", params={"format": "json"}).status_code == 200  # its place back
        restored = api.request(
            "PUT", "/v1/maps/copy/snapshot", content=snapshot.content, headers={"content-type": "application/zip"}
        )
        assert restored.status_code == 200, restored.text


def test_one_key_holds_at_most_all_but_one_export_place(tmp_path: Path) -> None:
    """A review: one reader key asking again and again held both of a process's places, and every other key's exports
    and its admin's snapshots were refused. Now that key's next export is refused, naming the key, while another
    key still gets its export; with the place back, the first key's export goes through."""
    keys_file = tmp_path / "keys.json"
    admin, admin_token = new_key("admin", ("room",), now_s=0.0)
    hoarder, hoarder_token = new_key("reader", ("room",), now_s=0.0)
    for key in (admin, hoarder):
        FileKeyStore(keys_file).add(key)
    settings = Settings(detector="sim:0", workers=1, keys_file=str(keys_file), max_exports=2)
    app = create_app(settings, detector=BlobDetector())
    with AppClient(app) as api:
        frame = make_test_frame(0, map_id="room", boxes=(LEFT, RIGHT), level=True)
        assert api.post("/v1/maps/room/frames", content=frame_to_proto(frame).SerializeToString(),
                        headers={"content-type": "application/x-protobuf", "authorization": f"Bearer {admin_token}"}).status_code == 202  # fmt: skip
        places = app.state.runtime.exports
        assert places.take(hoarder.id) is None  # the reader's first export, under way
        try:
            as_hoarder = {"authorization": f"Bearer {hoarder_token}"}
            refused = api.get("/v1/maps/room/export", params={"format": "json"}, headers=as_hoarder)
            other = api.get("/v1/maps/room/snapshot", headers={"authorization": f"Bearer {admin_token}"})
        finally:
            places.give_back(hoarder.id)
        assert refused.status_code == 429 and refused.headers["retry-after"] == "2", refused.text
        assert refused.json()["detail"].startswith(
            f"export: key {hoarder.id} has 1 of this API process's 2 exports, snapshots or restores under way, the most "
            "one key may (all but one: max_exports)"
        )
        assert other.status_code == 200, other.text  # the other place, another key's
        assert api.get("/v1/maps/room/export", params={"format": "json"}, headers=as_hoarder).status_code == 200
        assert places.taken == 0 and not places.by_key


def test_a_service_that_is_not_there_is_one_line_not_a_traceback(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A new user's review: `arcloud export`, `maps list` and `replay` printed httpx's 75-line traceback."""
    port = free_port()  # nothing listens there
    out = tmp_path / "room.json"
    argv = [
        "export",
        "--map",
        "room",
        "--format",
        "json",
        "--out",
        str(out),
        "--url",
        f"http://127.0.0.1:{port}",
        "--retries",
        "0",
    ]
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"arcloud: error: could not reach the service at http://127.0.0.1:{port}/v1/maps/room/export: ")
    assert err.count("\n") == 1 and "Traceback" not in err and not out.exists()
