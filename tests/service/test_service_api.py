"""The HTTP API in embedded mode: httpx against the app (in process, lifespan run) and a real uvicorn.

Frames are 160x120 with a near rectangle that ``BlobDetector`` reports as a chair, so every assertion
about objects is exact geometry, not a model's opinion. Lying flat (the default frames) it is never
confirmed; standing upright (``level=True``) it is once seen in enough frames.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator

import cv2
import httpx
import numpy as np
import pytest
from svc_helpers import (
    HEIGHT,
    LEFT,
    RIGHT,
    WIDTH,
    AppClient,
    BlobDetector,
    UvicornThread,
    make_test_frame,
    multipart_parts,
    wait_until,
)

from arcloud.client.results import ObjectDetail, from_json
from arcloud.core.types import Detection, Frame
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores.memory import MemoryStore
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}
TENTATIVE = {"include": "tentative"}


def proto_body(frame: object, **changes: object) -> bytes:
    msg = frame_to_proto(frame)  # type: ignore[arg-type]  # frame: a core Frame typed as object
    for name, value in changes.items():
        setattr(msg, name, value)
    return msg.SerializeToString()


@pytest.fixture
def client() -> Iterator[AppClient]:
    settings = Settings(detector="sim:0", workers=2, max_frame_bytes=200_000)
    with AppClient(create_app(settings, detector=BlobDetector())) as test_client:
        yield test_client


def processed(client: AppClient, map_id: str) -> int:
    return int(client.get(f"/v1/maps/{map_id}/stats").json()["frames"]["processed"])


def test_frames_by_protobuf_and_multipart_become_one_object(client: AppClient) -> None:
    for i in range(4):
        response = client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(i)), headers=PROTOBUF)
        assert response.status_code == 202, response.text
        assert response.json() == {"map_id": "m", "device_id": "d", "frame_id": f"f{i:06d}", "status": "queued"}
    for i in range(4, 8):
        response = client.post("/v1/maps/m/frames", files=multipart_parts(make_test_frame(i)))
        assert response.status_code == 202, response.text
    wait_until(lambda: processed(client, "m") == 8, 20, "8 frames processed")

    stats = client.get("/v1/maps/m/stats").json()
    assert stats == {
        "map_id": "m",
        "frames": {"accepted": 8, "processed": 8, "failed": 0, "pending": 0},
        "objects": {"confirmed": 0, "tentative": 1, "total": 1, "truncated": False},
    }
    assert client.get("/v1/maps/m/objects").json()["objects"] == []  # lying flat: no chair has that box
    (obj,) = client.get("/v1/maps/m/objects", params=TENTATIVE).json()["objects"]
    assert obj["label"] == "chair" and obj["n_frames"] == 8 and obj["version"] >= 1 and obj["status"] == "tentative"
    # The near rectangle (rows 30:80, cols 20:70 at 2 m, fx 130) spans x in [-0.91, -0.15] + camera shift, z = 2 m.
    assert obj["aabb"]["min"][2] == pytest.approx(2.0, abs=0.06)
    assert obj["aabb"]["min"][0] == pytest.approx((20 - 79.5) * 2.0 / 130, abs=0.1)
    assert obj["aabb"]["max"][1] == pytest.approx((80 - 59.5) * 2.0 / 130, abs=0.1)
    assert obj["updated_at"].endswith("Z")

    detail = client.get(f"/v1/maps/m/objects/{obj['id']}", params={"voxels": "true"}).json()
    centers = np.array(detail["voxels"]["centers"])
    assert centers.shape == (obj["n_voxels"], 3) and len(detail["voxels"]["weights"]) == obj["n_voxels"]
    assert np.all(centers >= np.array(obj["aabb"]["min"]) - 0.05) and np.all(centers <= np.array(obj["aabb"]["max"]) + 0.05)
    assert client.get(f"/v1/maps/m/objects/{obj['id']}").json() == {**detail, "voxels": None}  # the same object, no voxels


class SometimesTable(BlobDetector):
    """``BlobDetector``'s chair, called a table in the frames of ``table_on``."""

    def __init__(self, table_on: set[str]) -> None:
        super().__init__()
        self.table_on = table_on

    def detect(self, frame: Frame) -> list[Detection]:
        found = super().detect(frame)
        return [Detection("table", d.score, d.mask) for d in found] if frame.frame_id in self.table_on else found


def test_one_object_shows_the_votes_for_each_label_behind_its_label() -> None:
    detector = SometimesTable({"f000006", "f000007"})
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=detector)) as client:
        for i in range(8):  # 6 frames call it a chair, 2 a table
            assert client.post("/v1/maps/v/frames", files=multipart_parts(make_test_frame(i, map_id="v"))).status_code == 202
        wait_until(lambda: processed(client, "v") == 8, 20, "8 frames processed")
        (obj,) = client.get("/v1/maps/v/objects", params=TENTATIVE).json()["objects"]
        assert obj["n_frames"] == 8 and "label_votes" not in obj  # a list's objects are read without their voxels
        detail = client.get(f"/v1/maps/v/objects/{obj['id']}").json()
    votes = detail["label_votes"]
    assert detail["label"] == "chair" and list(votes) == ["chair", "table"]  # most first; no other class voted
    assert 2 * votes["table"] < votes["chair"] < 4 * votes["table"]  # three times the frames, about the same voxels
    typed = from_json(ObjectDetail, detail)  # the SDK's result
    assert typed.label_votes == votes and typed.label == "chair"


def test_meta_may_be_a_text_field(client: AppClient) -> None:
    parts = multipart_parts(make_test_frame(0))
    response = client.post("/v1/maps/t/frames", data={"meta": parts.pop("meta")[1].decode()}, files=parts)
    assert response.status_code == 202, response.text
    as_text_rgb = client.post(
        "/v1/maps/t/frames",
        data={"rgb": "not a file"},
        files={k: v for k, v in multipart_parts(make_test_frame(1)).items() if k != "rgb"},
    )
    assert as_text_rgb.status_code == 422 and "rgb: expected a file part" in as_text_rgb.json()["detail"]


def test_filters_select_objects(client: AppClient) -> None:
    two_boxes = ((30, 80, 10, 50), (30, 80, 110, 150))
    client.post("/v1/maps/f/frames", content=proto_body(make_test_frame(0, map_id="f", boxes=two_boxes)), headers=PROTOBUF)
    wait_until(lambda: processed(client, "f") == 1, 20, "frame processed")
    objects = client.get("/v1/maps/f/objects", params=TENTATIVE).json()["objects"]
    assert len(objects) == 2
    left = min(objects, key=lambda o: o["aabb"]["min"][0])
    x0, y0, z0 = left["aabb"]["min"]
    x1, y1, z1 = left["aabb"]["max"]
    box = f"{x0},{y0},{z0},{x1},{y1},{z1}"
    inside = client.get("/v1/maps/f/objects", params={"bbox": box, **TENTATIVE}).json()["objects"]
    assert [o["id"] for o in inside] == [left["id"]]
    assert client.get("/v1/maps/f/objects", params={"bbox": box}).json()["objects"] == []  # tentative: not served
    assert client.get("/v1/maps/f/objects", params={"bbox": "10,10,10,11,11,11", **TENTATIVE}).json()["objects"] == []
    assert client.get("/v1/maps/f/objects", params={"label": "tv", **TENTATIVE}).json()["objects"] == []
    assert len(client.get("/v1/maps/f/objects", params={"label": "chair", **TENTATIVE}).json()["objects"]) == 2
    best = max(o["score"] for o in objects)
    assert client.get("/v1/maps/f/objects", params={"min_score": min(1.0, best + 1e-6), **TENTATIVE}).json()["objects"] == []


def test_the_served_map_holds_confirmed_objects_and_loses_those_that_turn_tentative() -> None:
    detector = BlobDetector()
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=detector)) as client:

        def send(index: int, boxes: tuple = (LEFT,)) -> None:
            response = client.post(
                "/v1/maps/s/frames",
                content=proto_body(make_test_frame(index, map_id="s", boxes=boxes, level=True)),
                headers=PROTOBUF,
            )
            assert response.status_code == 202, response.text
            wait_until(lambda: processed(client, "s") == index + 1, 20, f"frame {index} processed")

        def listed(**params: str) -> dict[int, str]:
            return {o["id"]: o["status"] for o in client.get("/v1/maps/s/objects", params=params).json()["objects"]}

        send(0)  # one frame: a faint, half-formed object
        ((chair, status),) = listed(**TENTATIVE).items()
        assert status == "tentative" and listed() == {}
        assert client.get(f"/v1/maps/s/objects/{chair}").json()["status"] == "tentative"
        assert client.get("/v1/maps/s/stats").json()["objects"] == {
            "confirmed": 0,
            "tentative": 1,
            "total": 1,
            "truncated": False,
        }

        for i in range(1, 6):  # seen upright in six frames: confirmed, served
            send(i)
        assert listed() == listed(**TENTATIVE) == {chair: "confirmed"}
        assert client.get(f"/v1/maps/s/objects/{chair}").json()["status"] == "confirmed"
        assert client.get("/v1/maps/s/stats").json()["objects"] == {
            "confirmed": 1,
            "tentative": 0,
            "total": 1,
            "truncated": False,
        }

        # The chair stays in view but the detector stops finding it: misses count until it is tentative again.
        detector.miss_left_on.update(f"f{i:06d}" for i in range(6, 60))
        index = 6
        while client.get(f"/v1/maps/s/objects/{chair}").json()["status"] == "confirmed":
            assert index < 60, "the missed chair stayed confirmed"
            send(index, (LEFT, RIGHT))
            index += 1
        assert chair not in listed() and listed(**TENTATIVE)[chair] == "tentative"
        detail = client.get(f"/v1/maps/s/objects/{chair}", params={"voxels": "true"})
        assert detail.status_code == 200 and detail.json()["status"] == "tentative" and detail.json()["voxels"]["centers"]
        everything = listed(**TENTATIVE)
        counts = client.get("/v1/maps/s/stats").json()["objects"]
        assert counts == {
            "confirmed": sum(s == "confirmed" for s in everything.values()),
            "tentative": sum(s == "tentative" for s in everything.values()),
            "total": len(everything),
            "truncated": False,
        }
        assert listed() == {i: s for i, s in everything.items() if s == "confirmed"}


def _jpeg(rgb: np.ndarray) -> bytes:
    return cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]))[1].tobytes()


def _png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def bad_uploads() -> list[tuple[str, dict[str, object], int, str]]:
    """(case, request kwargs, status, text the message must contain)."""
    frame = make_test_frame(0)
    parts = multipart_parts(frame)
    reflected = frame.cam2world.copy()
    reflected[0, 0] = -1.0
    jpeg = parts["rgb"][1]
    depth8 = _png(np.full((HEIGHT, WIDTH), 200, np.uint8))
    small_depth = _png(np.full((HEIGHT // 2, WIDTH // 2), 2000, np.uint16))
    return [
        ("wrong content type", {"content": b"{}", "headers": {"content-type": "application/json"}}, 415, "content-type"),
        ("no content type", {"content": b"abc"}, 415, "content-type"),
        ("not protobuf", {"content": b"\xff\xff\xff\xff", "headers": PROTOBUF}, 422, "body"),
        ("empty protobuf", {"content": b"", "headers": PROTOBUF}, 422, "body"),
        ("truncated jpeg", {"files": {**parts, "rgb": ("rgb.jpg", jpeg[: len(jpeg) // 2], "image/jpeg")}}, 422, "rgb"),
        ("not an image", {"files": {**parts, "rgb": ("rgb.gif", b"GIF89a....", "image/gif")}}, 422, "rgb"),
        ("8-bit depth", {"files": {**parts, "depth": ("depth.png", depth8, "image/png")}}, 422, "16-bit"),
        ("depth size", {"files": {**parts, "depth": ("depth.png", small_depth, "image/png")}}, 422, "depth"),
        ("reflected pose", {"files": multipart_parts(frame, cam2world=reflected.reshape(16).tolist())}, 422, "cam2world"),
        ("pose not 4x4", {"files": multipart_parts(frame, cam2world=[1, 0, 0])}, 422, "cam2world"),
        ("missing depth", {"files": {k: v for k, v in parts.items() if k != "depth"}}, 422, "depth"),
        ("missing meta", {"files": {k: v for k, v in parts.items() if k != "meta"}}, 422, "meta"),
        ("meta not json", {"files": {**parts, "meta": ("meta.json", b"{oops", "application/json")}}, 422, "meta"),
        ("meta missing intrinsics", {"files": multipart_parts(frame, intrinsics=None)}, 422, "meta.intrinsics"),
        ("meta unknown field", {"files": multipart_parts(frame, colour="red")}, 422, "meta.colour"),
        ("bad frame id", {"files": multipart_parts(frame, frame_id="a/b")}, 422, "frame_id"),
        ("map id mismatch", {"files": multipart_parts(frame, map_id="other")}, 422, "map_id"),
        ("map id mismatch (protobuf)", {"content": proto_body(frame, map_id="other"), "headers": PROTOBUF}, 422, "map_id"),
        ("no intrinsics (protobuf)", {"content": _without_intrinsics(frame), "headers": PROTOBUF}, 422, "intrinsics"),
        ("too large", {"content": b"\0" * 200_001, "headers": PROTOBUF}, 413, "200000 bytes"),
        (
            "too large multipart",
            {
                "files": {
                    **parts,
                    "rgb": ("rgb.jpg", _jpeg(np.random.default_rng(0).integers(0, 255, (600, 600, 3), np.uint8)), "image/jpeg"),
                }
            },
            413,
            "bytes",
        ),
    ]


def _without_intrinsics(frame: object) -> bytes:
    msg = frame_to_proto(frame)  # type: ignore[arg-type]  # frame: a core Frame typed as object
    msg.ClearField("intrinsics")
    return msg.SerializeToString()


BAD_UPLOADS = bad_uploads()


@pytest.mark.parametrize(("case", "request_kwargs", "status", "says"), BAD_UPLOADS, ids=[c[0] for c in BAD_UPLOADS])
def test_bad_uploads_are_refused_with_a_reason(
    client: AppClient, case: str, request_kwargs: dict, status: int, says: str
) -> None:
    response = client.post("/v1/maps/m/frames", **request_kwargs)
    assert response.status_code == status, (case, response.text)
    body = response.json()
    assert says in body["detail"], (case, body)
    assert client.get("/v1/maps/m/stats").status_code == 404  # nothing was accepted


def test_a_large_body_without_content_length_is_cut_off(client: AppClient) -> None:
    async def chunks():
        for _ in range(5):
            yield b"\0" * 60_000  # 300 kB in all, streamed (chunked): no Content-Length to refuse early

    response = client.post("/v1/maps/m/frames", content=chunks(), headers=PROTOBUF)
    assert response.status_code == 413 and "at most 200000 bytes" in response.json()["detail"]


def test_unknown_maps_objects_and_bad_queries(client: AppClient) -> None:
    assert client.get("/v1/maps/nope/objects").status_code == 404
    assert client.get("/v1/maps/nope/stats").status_code == 404
    assert client.delete("/v1/maps/nope").status_code == 404
    assert client.post("/v1/maps/a{b}/frames", content=proto_body(make_test_frame(0)), headers=PROTOBUF).status_code == 422
    client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(0)), headers=PROTOBUF)
    wait_until(lambda: processed(client, "m") == 1, 20, "frame processed")
    missing = client.get("/v1/maps/m/objects/999")
    assert missing.status_code == 404 and "999" in missing.json()["detail"]
    for params, field in (
        ({"label": "dog"}, "label"),
        ({"min_score": "2"}, "min_score"),
        ({"bbox": "1,2,3"}, "bbox"),
        ({"bbox": "1,1,1,0,0,0"}, "bbox"),
        ({"include": "all"}, "include"),
        ({"include": "confirmed"}, "include"),
    ):
        response = client.get("/v1/maps/m/objects", params=params)
        assert response.status_code == 422 and field in response.json()["detail"] and response.json()["field"] == field, (
            response.text
        )
    assert "tentative" in client.get("/v1/maps/m/objects", params={"include": "all"}).json()["detail"]  # says what it takes
    assert client.get("/v1/maps/m/objects/-1").status_code == 422


def test_duplicates_delete_and_counts(client: AppClient) -> None:
    body = proto_body(make_test_frame(0))
    assert client.post("/v1/maps/m/frames", content=body, headers=PROTOBUF).json()["status"] == "queued"
    assert client.post("/v1/maps/m/frames", content=body, headers=PROTOBUF).json()["status"] == "duplicate"
    wait_until(lambda: processed(client, "m") == 1, 20, "frame processed")
    assert client.get("/v1/maps/m/stats").json()["frames"]["accepted"] == 1
    deleted = client.delete("/v1/maps/m")
    assert deleted.json() == {"map_id": "m", "deleted_objects": 1}
    assert client.get("/v1/maps/m/objects").status_code == 404
    assert client.post("/v1/maps/m/frames", content=body, headers=PROTOBUF).json()["status"] == "queued"  # a new map


def test_failed_frame_is_counted_and_can_be_sent_again() -> None:
    detector = BlobDetector(crash_on=["f000001"])
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=detector)) as client:
        for i in range(3):
            client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(i)), headers=PROTOBUF)
        wait_until(lambda: client.get("/v1/maps/m/stats").json()["frames"]["pending"] == 0, 20, "frames done")
        assert client.get("/v1/maps/m/stats").json()["frames"] == {"accepted": 3, "processed": 2, "failed": 1, "pending": 0}
        detector.crash_on.clear()
        again = client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(1)), headers=PROTOBUF)
        assert again.json()["status"] == "queued"
        wait_until(lambda: processed(client, "m") == 3, 20, "frame processed again")
        assert client.get("/v1/maps/m/stats").json()["frames"] == {"accepted": 3, "processed": 3, "failed": 0, "pending": 0}
        metrics = client.get("/metrics").text
        assert "arcloud_frames_failed_total 1.0" in metrics and "arcloud_frames_processed_total 3.0" in metrics


def test_full_queue_answers_503_with_retry_after() -> None:
    release = threading.Event()

    class Blocking(BlobDetector):
        def detect(self, frame):
            release.wait(10)
            return super().detect(frame)

    settings = Settings(detector="sim:0", workers=1, max_queued_frames=1)
    with AppClient(create_app(settings, detector=Blocking())) as client:
        codes = [
            client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(i)), headers=PROTOBUF).status_code
            for i in range(4)
        ]
        release.set()
        assert 503 in codes and codes[0] == 202 and codes.count(202) <= 2, codes
        refused = client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(9)), headers=PROTOBUF)
        if refused.status_code == 503:
            assert refused.headers["retry-after"] == "1" and "queue full" in refused.json()["detail"]
        wait_until(lambda: client.get("/v1/maps/m/stats").json()["frames"]["pending"] == 0, 20, "queue drained")


@pytest.mark.parametrize("store", ["memory", pytest.param("redis", marks=pytest.mark.redis)])
def test_a_map_at_its_queue_limit_gets_503_while_another_map_still_gets_202(store: str) -> None:
    """Embedded: one worker thread holds a's first frame (in hand: still counted). Redis: no worker."""
    from redis_server import RedisServer

    release = threading.Event()

    class Blocking(BlobDetector):
        def detect(self, frame):
            release.wait(10)
            return super().detect(frame)

    def post(map_id: str, index: int) -> httpx.Response:
        body = proto_body(make_test_frame(index, map_id=map_id))
        return client.post(f"/v1/maps/{map_id}/frames", content=body, headers=PROTOBUF)  # type: ignore[no-any-return]  # AppClient's portal call is Any

    server = RedisServer.start() if store == "redis" else None
    limits = {"max_queued_frames": 8, "max_queued_frames_per_map": 2}
    if server is None:
        app = create_app(Settings(detector="sim:0", workers=1, **limits), detector=Blocking())
    else:
        app = create_app(Settings(store=server.url, auth="none", detector="sim:0", workers=0, **limits))
    try:
        with AppClient(app) as client:
            assert [post("a", i).status_code for i in range(2)] == [202, 202]
            refused = post("a", 2)
            assert refused.status_code == 503 and refused.headers["retry-after"] == "1", refused.text
            assert "queue full: map a has 2 frames queued (max_queued_frames_per_map 2)" in refused.json()["detail"]
            assert post("b", 0).status_code == 202  # another map still gets in
            assert client.get("/v1/maps/a/stats").json()["frames"]["accepted"] == 2
            gauges = dict(line.split() for line in client.get("/metrics").text.splitlines() if line.startswith("arcloud_queue_"))
            assert float(gauges["arcloud_queue_depth"]) == 3
            queued_bytes, pixels = float(gauges["arcloud_queue_bytes"]), 3 * HEIGHT * WIDTH
            if server is None:
                assert queued_bytes >= pixels * 2  # the arrays: depth alone 4 bytes a pixel
            else:
                assert 3000 < queued_bytes < pixels * 2  # the images as uploaded (JPEG, PNG), not their pixels
            if server is None:
                release.set()
                wait_until(lambda: processed(client, "a") + processed(client, "b") == 3, 20, "the three frames processed")
                assert "arcloud_queue_bytes 0.0" in client.get("/metrics").text
                assert post("a", 2).status_code == 202  # room again
    finally:
        release.set()
        if server is not None:
            server.stop()


def test_health_readiness_metrics_and_docs(client: AppClient) -> None:
    from arcloud import __version__

    index = client.get("/")  # a new user's first request: it answered 404
    assert index.status_code == 200 and index.json() == {
        "service": "arcloud", "version": __version__, "docs": "/docs", "openapi": "/openapi.json", "viewer": "/viewer",
        "health": "/healthz", "ready": "/readyz",
    }  # fmt: skip
    assert all(client.get(page).status_code == 200 for page in ("/docs", "/openapi.json", "/viewer"))
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json() == {"status": "ready", "checks": {"store": "ok"}}
    workers = client.get("/healthz/workers").json()
    assert workers["checks"] == {"detector": "ok", "workers": "ok"} and len(workers["live"]) == workers["expected"] == 2
    client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(0)), headers=PROTOBUF)
    client.post("/v1/maps/m/frames", content=b"x", headers={"content-type": "text/plain"})
    wait_until(lambda: processed(client, "m") == 1, 20, "frame processed")
    metrics = client.get("/metrics")
    assert metrics.headers["content-type"].startswith("text/plain")
    text = metrics.text
    for line in (
        "arcloud_frames_accepted_total 1.0",
        "arcloud_frames_processed_total 1.0",
        "arcloud_queue_depth 0.0",
        "arcloud_live_workers 2.0",
        'arcloud_frames_rejected_total{status="415"} 1.0',
        "arcloud_step_latency_seconds_count 1.0",
        'arcloud_step_latency_seconds_bucket{le="+Inf"} 1.0',
    ):
        assert line in text, line
    spec = client.get("/openapi.json").json()
    upload = spec["paths"]["/v1/maps/{map_id}/frames"]["post"]
    assert set(upload["requestBody"]["content"]) == {"application/x-protobuf", "multipart/form-data"}
    assert json.loads(upload["requestBody"]["content"]["multipart/form-data"]["schema"]["properties"]["meta"]["example"])[
        "frame_id"
    ]
    assert {"202", "413", "415", "422"} <= set(upload["responses"])
    for path in (
        "/v1/maps/{map_id}/objects",
        "/v1/maps/{map_id}/objects/{object_id}",
        "/v1/maps/{map_id}",
        "/v1/maps/{map_id}/stats",
        "/healthz",
        "/readyz",
        "/metrics",
    ):
        assert path in spec["paths"], path
    listing = {p["name"]: p for p in spec["paths"]["/v1/maps/{map_id}/objects"]["get"]["parameters"]}
    assert listing["include"]["schema"]["anyOf"][0]["const"] == "tentative" and "tentative" in listing["include"]["description"]
    schemas = spec["components"]["schemas"]
    assert (
        schemas["ObjectOut"]["properties"]["status"]["enum"] == ["confirmed", "tentative"]
        and "status" in schemas["ObjectOut"]["required"]
    )
    assert schemas["ObjectOut"]["examples"][0]["status"] == "confirmed"
    assert schemas["MapStats"]["examples"][0]["objects"] == {"confirmed": 14, "tentative": 31, "total": 45, "truncated": False}


def test_real_uvicorn_server_and_shared_store() -> None:
    store = MemoryStore()
    app = create_app(Settings(detector="sim:0", workers=2), store=store, detector=BlobDetector())
    with UvicornThread(app) as server, httpx.Client(base_url=server.url, timeout=10) as http:
        for i in range(6):
            response = http.post("/v1/maps/u/frames", files=multipart_parts(make_test_frame(i, map_id="u")))
            assert response.status_code == 202, response.text
        wait_until(lambda: http.get("/v1/maps/u/stats").json()["frames"]["processed"] == 6, 20, "6 frames processed")
        assert http.post("/v1/maps/u/frames", content=b"x", headers={"content-type": "image/png"}).status_code == 415
        objects = http.get("/v1/maps/u/objects", params=TENTATIVE).json()["objects"]
        served = http.get("/v1/maps/u/objects").json()["objects"]
    assert [o["id"] for o in objects] == [o.id for o in store.list_objects("u")]
    assert [o["id"] for o in served] == [o.id for o in store.list_objects("u") if o.confirmed]
    assert store.count_frames("u") == 6
    assert not server.thread.is_alive()


def test_a_service_with_other_settings_refuses_the_map_and_its_workers_leave_it_alone(caplog: pytest.LogCaptureFixture) -> None:
    from arcloud.core.types import Params
    from arcloud.service.worker import FrameWorker
    from arcloud.stores.memory_queue import MemoryFrameQueue

    store = MemoryStore()
    with AppClient(create_app(Settings(detector="sim:0", workers=1), store=store, detector=BlobDetector())) as first:
        for i in range(3):
            assert (
                first.post("/v1/maps/h/frames", content=proto_body(make_test_frame(i, map_id="h")), headers=PROTOBUF).status_code
                == 202
            )
        wait_until(lambda: processed(first, "h") == 3, 20, "3 frames processed")
    before = store.list_objects("h")
    assert before and store.map_header("h").voxel_size_m == 0.05  # the first writer stored its settings
    other = Settings(detector="sim:0", workers=1, params={"voxel_size_m": 0.04})
    with AppClient(create_app(other, store=store, detector=BlobDetector())) as second:
        refused = second.post("/v1/maps/h/frames", content=proto_body(make_test_frame(3, map_id="h")), headers=PROTOBUF)
        assert refused.status_code == 409, refused.text
        assert refused.json() == {
            "type": "/problems/map-mismatch",
            "title": "Map of other settings",
            "status": 409,
            "detail": "map h was built with other settings: voxel_size_m: map 0.05, ours 0.04",
            "field": "map_id",
        }
        second.post("/v1/maps/fresh/frames", content=proto_body(make_test_frame(0, map_id="fresh")), headers=PROTOBUF)
        wait_until(lambda: processed(second, "fresh") == 1, 20, "a new map takes the second service's settings")
        assert store.map_header("fresh").voxel_size_m == 0.04
    # A worker started with other settings takes a frame of the map and refuses it, writing nothing.
    queue = MemoryFrameQueue()
    queue.put(make_test_frame(4, map_id="h"))
    worker = FrameWorker(queue, store, BlobDetector(), Params(voxel_size_m=0.04), heartbeat_s=None)
    item = queue.take("w", block_s=1.0)
    assert item is not None and worker.handle(item) == "failed"
    assert "map h was built with other settings: voxel_size_m: map 0.05, ours 0.04" in caplog.text
    assert [(o.id, o.version) for o in store.list_objects("h")] == [(o.id, o.version) for o in before]
    assert not store.is_frame_done("h", "d/f000004")


def test_a_frame_status_says_where_it_is_and_why_it_failed() -> None:
    settings = Settings(detector="sim:0", workers=1)
    with AppClient(create_app(settings, detector=BlobDetector(refuse_on=["f000001"]))) as client:
        for i in (0, 1):
            assert (
                client.post(
                    "/v1/maps/fs/frames", content=proto_body(make_test_frame(i, map_id="fs")), headers=PROTOBUF
                ).status_code
                == 202
            )
        wait_until(lambda: client.get("/v1/maps/fs/stats").json()["frames"]["pending"] == 0, 20, "both frames done")
        done = client.get("/v1/maps/fs/frames/d/f000000").json()
        assert done == {"map_id": "fs", "device_id": "d", "frame_id": "f000000", "status": "processed"}
        refused = client.get("/v1/maps/fs/frames/d/f000001").json()  # InvalidInput from the step: failed at once
        assert refused["status"] == "failed" and refused["reason"].startswith("InvalidInput: detections[0].label")
        missing = client.get("/v1/maps/fs/frames/d/f000099")
        assert missing.status_code == 404 and "never accepted" in missing.json()["detail"]
        assert client.get("/v1/maps/nomap/frames/d/f000000").status_code == 404
        bad_id = client.get("/v1/maps/fs/frames/d/f%2A")
        assert bad_id.status_code == 422 and bad_id.json()["field"] == "frame_id"
        assert client.get("/v1/maps/f%20s/frames/d/f000000").json()["field"] == "map_id"
