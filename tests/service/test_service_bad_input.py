"""Implausible and hostile input through the real app: every case answers a 4xx problem (``detail``, ``field``)
naming the field at fault, never a 5xx, and queues nothing (issue 10, "plausible input only" and
"bounded state"). The Redis cases run against a real redis-server.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Iterator
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
import svc_helpers
from redis_server import RedisServer
from svc_helpers import AppClient, BlobDetector, make_test_frame, multipart_parts, wait_until

from arcloud.core.checks import make_frame
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.service.worker import FrameWorker
from arcloud.stores import keys
from arcloud.stores.redis import RedisStore
from arcloud.stores.redis_queue import RedisFrameQueue
from arcloud.tools.wiring import create_app

PROTOBUF = {"content-type": "application/x-protobuf"}


def proto_body(frame: Any, **changes: Any) -> bytes:
    msg = frame_to_proto(frame)
    for name, value in changes.items():
        setattr(msg, name, value)
    return msg.SerializeToString()


def assert_problem(response: httpx.Response, status: int, field: str | None) -> None:
    """A 4xx answered as a problem (``application/problem+json``) naming ``field``."""
    problem = svc_helpers.assert_problem(response, status, field)
    assert set(problem) == {"type", "title", "status", "detail", "field"}, problem


MAX_PIXELS = 640 * 480


def vga_frame(focal_px: float, depth_m: float = 4.9) -> Any:
    """A 640 x 480 frame of one wall ``depth_m`` away (the measured case: fx = fy = 5, 4.9 m)."""
    rgb = np.full((480, 640, 3), 90, np.uint8)
    depth = np.full((480, 640), depth_m, np.float32)
    intrinsics = (focal_px, focal_px, 319.5, 239.5)
    return make_frame(rgb, depth, intrinsics, np.eye(4), timestamp_s=0.0, map_id="m", device_id="d", frame_id="vga")


def png(image: np.ndarray) -> bytes:
    return bytes(cv2.imencode(".png", image)[1].tobytes())


def jpeg_with_a_stray_byte(jpeg: bytes) -> bytes:
    """The JPEG with one byte between its first segment (APP0) and the next marker: decoders skip it."""
    app0_end = 4 + int.from_bytes(jpeg[4:6], "big")
    return jpeg[:app0_end] + b"\x00" + jpeg[app0_end:]


def jpeg_carrying(jpeg: bytes, n_bytes: int) -> bytes:
    """The JPEG with ``n_bytes`` of comment segments (COM) after its start marker: decoders skip them."""
    segments = b""
    while n_bytes > 0:
        size = min(n_bytes, 65533)
        segments += b"\xff\xfe" + (size + 2).to_bytes(2, "big") + b"x" * size
        n_bytes -= size
    return jpeg[:2] + segments + jpeg[2:]


def png_carrying(data: bytes, n_bytes: int) -> bytes:
    """The PNG with a text chunk (tEXt) of ``n_bytes`` after its header chunk: decoders skip it."""
    import zlib

    body = b"tEXt" + b"comment\x00" + b"x" * n_bytes
    chunk = (len(body) - 4).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")
    ihdr_end = 8 + 4 + 4 + 13 + 4
    return data[:ihdr_end] + chunk + data[ihdr_end:]


@pytest.fixture(scope="module")
def client() -> Iterator[AppClient]:
    settings = Settings(detector="sim:0", workers=1, max_frame_bytes=2_000_000, max_frame_pixels=MAX_PIXELS)
    with AppClient(create_app(settings, detector=BlobDetector())) as test_client:
        assert test_client.post("/v1/maps/m/frames", content=proto_body(make_test_frame(0)), headers=PROTOBUF).status_code == 202
        yield test_client


def bad_requests() -> list[tuple[str, str, str, dict[str, Any], int, str | None]]:
    """(case, method, path, request kwargs, status, field)."""
    frame = make_test_frame(1)
    parts = multipart_parts(frame)
    intrinsics = {"fx": 130.0, "fy": 130.0, "cx": 79.5, "cy": 59.5}
    far = frame.cam2world.copy()
    far[0, 3] = 20_000.0
    sheared = frame.cam2world.copy()
    sheared[0, 1] = 0.1
    huge_png = png(np.zeros((4096, 4096, 3), np.uint8))  # about 100 kB: 16.8 M pixels once decoded
    bbox_edge = f"{-1e308},{-1e308},{-1e308},{1e308},{1e308},{1e308}"
    return [
        # plausible cameras: a field of view of 20 to 160 degrees, the principal point inside the image
        (
            "fx = fy = 5 at 640 x 480, 4.9 m away",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(vga_frame(5.0))},
            422,
            "intrinsics.fx",
        ),
        (
            "fx = fy = 5 by protobuf",
            "POST",
            "/v1/maps/m/frames",
            {"content": proto_body(vga_frame(5.0)), "headers": PROTOBUF},
            422,
            "intrinsics.fx",
        ),
        (
            "fx of a telescope",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, intrinsics={**intrinsics, "fx": 5000.0})},
            422,
            "intrinsics.fx",
        ),
        (
            "fy too short",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, intrinsics={**intrinsics, "fy": 5.0})},
            422,
            "intrinsics.fy",
        ),
        (
            "cx left of the image",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, intrinsics={**intrinsics, "cx": -1.0})},
            422,
            "intrinsics.cx",
        ),
        (
            "cy below the image",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, intrinsics={**intrinsics, "cy": 500.0})},
            422,
            "intrinsics.cy",
        ),
        # poses: at most 10 km from the origin, a rotation
        (
            "camera 20 km away",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, cam2world=far.reshape(16).tolist())},
            422,
            "cam2world",
        ),
        (
            "sheared rotation",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, cam2world=sheared.reshape(16).tolist())},
            422,
            "cam2world",
        ),
        # depth units: 1 to 100000 per metre
        (
            "depth scale below 1",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, depth_scale=0.5)},
            422,
            "depth_scale",
        ),
        (
            "depth scale above 1e5",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, depth_scale=1e6)},
            422,
            "depth_scale",
        ),
        (
            "depth scale 0 by protobuf",
            "POST",
            "/v1/maps/m/frames",
            {"content": proto_body(frame, depth_scale=0.0), "headers": PROTOBUF},
            422,
            "depth_scale",
        ),
        # meta JSON: small and shallow
        (
            "meta nested 100000 deep",
            "POST",
            "/v1/maps/m/frames",
            {"files": {**parts, "meta": ("meta.json", b"[" * 100_000 + b"]" * 100_000, "a/json")}},
            422,
            "meta",
        ),
        (
            "meta over 64 kB",
            "POST",
            "/v1/maps/m/frames",
            {"files": {**parts, "meta": ("meta.json", b" " * 70_000 + b"{}", "a/json")}},
            422,
            "meta",
        ),
        # images: the size comes from the header, before decoding, or the image is refused
        (
            "4096 x 4096 PNG of 100 kB",
            "POST",
            "/v1/maps/m/frames",
            {"files": {**parts, "rgb": ("rgb.png", huge_png, "image/png")}},
            422,
            "rgb",
        ),
        (
            "JPEG with a stray byte",
            "POST",
            "/v1/maps/m/frames",
            {"files": {**parts, "rgb": ("rgb.jpg", jpeg_with_a_stray_byte(parts["rgb"][1]), "image/jpeg")}},
            422,
            "rgb",
        ),
        (
            "160 x 120 JPEG carrying 200 kB of comments",
            "POST",
            "/v1/maps/m/frames",
            {"files": {**parts, "rgb": ("rgb.jpg", jpeg_carrying(parts["rgb"][1], 200_000), "image/jpeg")}},
            422,
            "rgb",
        ),
        (
            "160 x 120 depth PNG carrying 200 kB of text",
            "POST",
            "/v1/maps/m/frames",
            {"files": {**parts, "depth": ("depth.png", png_carrying(parts["depth"][1], 200_000), "image/png")}},
            422,
            "depth",
        ),
        (
            "PNG without IHDR",
            "POST",
            "/v1/maps/m/frames",
            {"files": {**parts, "depth": ("depth.png", parts["depth"][1][:16], "image/png")}},
            422,
            "depth",
        ),
        (
            "raw depth over the pixel limit",
            "POST",
            "/v1/maps/m/frames",
            {
                "content": proto_body(frame, width=4096, height=4096, depth_encoding=pb.DEPTH_ENCODING_RAW_UINT16),
                "headers": PROTOBUF,
            },
            422,
            "depth",
        ),
        # query boxes: finite, within 100 km
        ("bbox at +-1e308", "GET", "/v1/maps/m/objects", {"params": {"bbox": bbox_edge}}, 422, "bbox"),
        ("bbox 1000 km wide", "GET", "/v1/maps/m/objects", {"params": {"bbox": "-5e5,0,0,5e5,1,1"}}, 422, "bbox"),
        # map ids: letters, digits, '.', '_', '-' only
        ("map id with a backslash", "DELETE", "/v1/maps/vic%5Ctim", {}, 422, "map_id"),
        ("map id with a glob star", "GET", "/v1/maps/m%2A/stats", {}, 422, "map_id"),
        (
            "map id with a colon",
            "POST",
            "/v1/maps/a:b/frames",
            {"content": proto_body(frame), "headers": PROTOBUF},
            422,
            "map_id",
        ),
        ("map id too long", "GET", "/v1/maps/" + "a" * 129 + "/objects", {}, 422, "map_id"),
        (
            "device id with a backslash",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, device_id="a\\b")},
            422,
            "device_id",
        ),
        # the framework's own 4xx
        ("unknown route", "GET", "/v2/nothing", {}, 404, None),
        ("method not allowed", "PUT", "/v1/maps/m/frames", {}, 405, None),
        (
            "multipart without boundary",
            "POST",
            "/v1/maps/m/frames",
            {"content": b"x", "headers": {"content-type": "multipart/form-data"}},
            400,
            None,
        ),
        (
            "multipart cut short",
            "POST",
            "/v1/maps/m/frames",
            {
                "content": b'--b\r\nContent-Disposition: form-data; name="meta"\r\n\r\n{',
                "headers": {"content-type": "multipart/form-data; boundary=b"},
            },
            422,
            "meta",
        ),
        ("object id not a number", "GET", "/v1/maps/m/objects/abc", {}, 422, "object_id"),
        (
            "content-length not a number",
            "POST",
            "/v1/maps/m/frames",
            {"content": b"x", "headers": {**PROTOBUF, "content-length": "x1"}},
            400,
            "content-length",
        ),
        ("object id of 40 digits", "GET", "/v1/maps/m/objects/" + "9" * 40, {}, 404, None),
        ("min_score NaN", "GET", "/v1/maps/m/objects", {"params": {"min_score": "nan"}}, 422, "min_score"),
        ("map id not ASCII", "GET", "/v1/maps/%C3%A9/stats", {}, 422, "map_id"),
        (
            "timestamp NaN",
            "POST",
            "/v1/maps/m/frames",
            {"content": proto_body(frame, timestamp_s=float("nan")), "headers": PROTOBUF},
            422,
            "timestamp_s",
        ),
        (
            "unknown rgb encoding",
            "POST",
            "/v1/maps/m/frames",
            {"content": proto_body(frame, rgb_encoding=99), "headers": PROTOBUF},
            422,
            "rgb_encoding",
        ),
        # a new user's review: millimetres read as metres were accepted, processed, and made no object
        (
            "depth in mm with depth_scale 1",
            "POST",
            "/v1/maps/m/frames",
            {"files": multipart_parts(frame, depth_scale=1)},
            422,
            "depth",
        ),
        (
            "depth in mm with depth_scale 1e5",
            "POST",
            "/v1/maps/m/frames",
            {"content": proto_body(frame, depth_scale=1e5), "headers": PROTOBUF},
            422,
            "depth",
        ),
        (
            "frame id of 10000 characters",
            "POST",
            "/v1/maps/m/frames",
            {"content": proto_body(frame, frame_id="x" * 10_000), "headers": PROTOBUF},
            422,
            "frame_id",
        ),
    ]


BAD_REQUESTS = bad_requests()


@pytest.mark.parametrize(
    ("case", "method", "path", "request_kwargs", "status", "field"), BAD_REQUESTS, ids=[c[0] for c in BAD_REQUESTS]
)
def test_bad_input_answers_4xx_naming_the_field(
    client: AppClient, case: str, method: str, path: str, request_kwargs: dict[str, Any], status: int, field: str | None
) -> None:
    response = client.request(method, path, **request_kwargs)
    assert_problem(response, status, field)
    stats = client.get("/v1/maps/m/stats").json()
    assert stats["frames"]["accepted"] == 1, (case, stats)  # nothing else was queued


def test_a_missing_or_unknown_field_is_said_so_in_the_detail(client: AppClient) -> None:
    frame = make_test_frame(1)
    parts = multipart_parts(frame)
    meta = json.loads(parts["meta"][1])
    missing = {k: v for k, v in meta.items() if k != "frame_id"}
    answer = client.post(
        "/v1/maps/m/frames", files={**parts, "meta": ("meta.json", json.dumps(missing).encode(), "application/json")}
    )
    assert answer.status_code == 422
    assert answer.json()["detail"] == "meta.frame_id: expected a value (the field is required), got none"
    extra = {**meta, "colour": 1}
    answer = client.post(
        "/v1/maps/m/frames", files={**parts, "meta": ("meta.json", json.dumps(extra).encode(), "application/json")}
    )
    assert answer.json()["detail"] == "meta.colour: expected no such field, got 1"
    answer = client.get("/v1/maps/m/objects", params={"limit": "many"})
    assert (
        answer.status_code == 422
        and answer.json()["detail"] == "limit: expected a valid integer, unable to parse string as an integer, got 'many'"
    )


def test_depth_in_the_wrong_units_is_refused_saying_its_lower_quartile(client: AppClient) -> None:
    answer = client.post("/v1/maps/m/frames", files=multipart_parts(make_test_frame(3), depth_scale=1))
    assert answer.status_code == 422 and answer.json()["detail"].startswith(
        "depth: expected depth in metres whose lower quartile is 0.05 to 100 m, as a camera sees (its units: "
        "depth_scale, 1000 for millimetres; float depth is metres), got a lower quartile of "
    ), answer.text


def test_depth_a_camera_sees_passes_however_far_and_however_much_of_it_is_invalid(client: AppClient) -> None:
    """A review: the first bound (a median of 0.05 to 30 m) refused a street seen at 40 m, and a Kinect frame more than
    half of whose pixels hold 65535 (nothing measured): a median of 65.5 m."""
    far = make_test_frame(5)
    street = dataclasses.replace(far, depth_m=np.full_like(far.depth_m, 40.0))
    kinect = make_test_frame(6)
    saturated = kinect.depth_m.copy()
    saturated[: int(saturated.shape[0] * 0.6)] = 65.535  # 60 % of the rows: 65535 at depth_scale 1000
    for frame in (street, dataclasses.replace(kinect, depth_m=saturated)):
        answer = client.post("/v1/maps/m/frames", files=multipart_parts(frame))
        assert answer.status_code == 202, answer.text


@pytest.mark.parametrize(
    ("field", "value", "got"),
    [
        ("depth_scale", True, "True"),
        ("depth_scale", "5000", "'5000'"),
        ("timestamp", "1.5", "'1.5'"),
        ("world_up", [0, 0, "1"], "'1'"),
    ],
)
def test_a_number_must_be_a_json_number(client: AppClient, field: str, value: object, got: str) -> None:
    """pydantic's lax mode read ``depth_scale: true`` as 1 (depth in metres: every object 1000 times too far) and
    ``"5000"`` as 5000: a fuzzing review. The meta is read strictly now; arrays still read as tuples (world_up)."""
    parts = multipart_parts(make_test_frame(2))
    meta = {**json.loads(parts["meta"][1]), field: value}
    answer = client.post(
        "/v1/maps/m/frames", files={**parts, "meta": ("meta.json", json.dumps(meta).encode(), "application/json")}
    )
    where = f"meta.{field}.2" if field == "world_up" else f"meta.{field}"
    assert answer.status_code == 422 and answer.json()["detail"] == f"{where}: expected a valid number, got {got}", answer.text
    accepted = {**meta, field: [0, 0, 1] if field == "world_up" else 5000 if field == "depth_scale" else 1}
    answer = client.post(
        "/v1/maps/m/frames", files={**parts, "meta": ("meta.json", json.dumps(accepted).encode(), "application/json")}
    )
    assert answer.status_code == 202, answer.text  # integers for numbers, and an array for world_up, still read


# --- against a real redis-server -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def redis_app() -> Iterator[tuple[AppClient, RedisServer]]:
    server = RedisServer.start()
    try:
        with AppClient(create_app(Settings(store=server.url, auth="none", detector="sim:0", workers=0))) as api:
            yield api, server
    finally:
        server.stop()


@pytest.mark.redis
def test_deleting_a_map_id_with_glob_escapes_never_touches_another_map(redis_app: tuple[AppClient, RedisServer]) -> None:
    api, server = redis_app
    assert (
        api.post("/v1/maps/victim/frames", content=proto_body(make_test_frame(0, map_id="victim")), headers=PROTOBUF).status_code
        == 202
    )
    redis = server.client()
    try:
        redis.set(keys.ids_key("victim"), 7)
        before = sorted(redis.scan_iter(match=keys.map_pattern("victim")))
        assert len(before) >= 2
        for path in ("/v1/maps/vic%5Ctim", "/v1/maps/vic%5Ctim%2A", "/v1/maps/v%3Fctim", "/v1/maps/%5Bv%5Dictim"):
            assert_problem(api.delete(path), 422, "map_id")
        # Below the API (defence in depth): the store's SCAN pattern escapes the id, so nothing else matches.
        with RedisStore(server.url) as store:
            for hostile in ("vic\\tim", "vic*", "v?ctim", "[v]ictim"):
                assert store.delete_map(hostile) == 0
        assert sorted(redis.scan_iter(match=keys.map_pattern("victim"))) == before
        assert api.get("/v1/maps/victim/stats").status_code == 200
    finally:
        redis.close()


@pytest.mark.redis
def test_query_boxes_at_the_edge_of_floats_answer_422_on_redis_too(redis_app: tuple[AppClient, RedisServer]) -> None:
    api, server = redis_app
    assert api.post("/v1/maps/q/frames", content=proto_body(make_test_frame(0, map_id="q")), headers=PROTOBUF).status_code == 202
    assert_problem(api.get("/v1/maps/q/objects", params={"bbox": "-1e308,-1e308,-1e308,1e308,1e308,1e308"}), 422, "bbox")
    assert api.get("/v1/maps/q/objects", params={"bbox": "-1e5,-1e5,-1e5,1e5,1e5,1e5"}).status_code == 200
    with RedisStore(server.url) as store:  # below the API: an unbounded box reads the bounds, never overflows
        assert store.query_region("q", np.full(3, -1e308), np.full(3, 1e308)) == {}


def test_the_default_pixel_limit_bounds_a_queued_frame() -> None:
    huge_png = png(np.zeros((4096, 4096, 3), np.uint8))
    parts = multipart_parts(make_test_frame(0))
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as api:
        response = api.post("/v1/maps/m/frames", files={**parts, "rgb": ("rgb.png", huge_png, "image/png")})
    assert_problem(response, 422, "rgb")
    assert f"at most {1920 * 1440} pixels" in response.json()["detail"]


def test_a_jpeg_of_more_scans_than_an_encoder_writes_is_refused_before_it_is_decoded() -> None:
    """Each scan of a progressive JPEG is a pass of the decoder over the image: within the pixel and byte limits, a
    3.6 MB image of 300,000 tiny scans held a decoding thread for 14 s, and a worker's again (a fuzzing review). A
    progressive JPEG as libjpeg writes it (10 scans) is still taken."""
    frame = make_test_frame(3)
    ok, progressive = cv2.imencode(".jpg", frame.rgb[..., ::-1], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    progressive = progressive.tobytes()
    assert ok and 2 < progressive.count(b"\xff\xda") <= 64 and progressive.endswith(b"\xff\xd9")
    last_scan = progressive[progressive.rfind(b"\xff\xda") : -2]
    many = progressive[:-2] + last_scan * 100 + progressive[-2:]
    parts = multipart_parts(frame)
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as api:
        accepted = api.post("/v1/maps/m/frames", files={**parts, "rgb": ("rgb.jpg", progressive, "image/jpeg")})
        refused = api.post("/v1/maps/m/frames", files={**parts, "rgb": ("rgb.jpg", many, "image/jpeg")})
    assert accepted.status_code == 202, accepted.text
    assert_problem(refused, 422, "rgb")
    scans = many.count(b"\xff\xda")
    assert refused.json()["detail"] == f"rgb: expected a JPEG of at most 64 scans, got {scans} scans"


def test_images_with_what_real_cameras_add_are_accepted() -> None:
    """The bound on an image's bytes leaves room for real images: noise at JPEG quality 100 with full-resolution
    chroma (1.37x its pixels' size), and a camera's metadata (60 kB of comments, a 60 kB text chunk)."""
    frame = make_test_frame(2)
    noise = np.random.default_rng(2).integers(0, 256, frame.rgb.shape, dtype=np.uint8)
    ok, rgb = cv2.imencode(
        ".jpg", noise, [cv2.IMWRITE_JPEG_QUALITY, 100, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444]
    )
    assert ok and len(rgb) > noise.nbytes
    parts = multipart_parts(frame)
    uploads = [
        {**parts, "rgb": ("rgb.jpg", rgb.tobytes(), "image/jpeg")},
        {
            **parts,
            "rgb": ("rgb.jpg", jpeg_carrying(parts["rgb"][1], 60_000), "image/jpeg"),
            "depth": ("depth.png", png_carrying(parts["depth"][1], 60_000), "image/png"),
        },
    ]
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as api:
        for i, files in enumerate(uploads):
            meta = json.loads(files["meta"][1])
            files = {**files, "meta": ("meta.json", json.dumps({**meta, "frame_id": f"real-{i}"}).encode(), "application/json")}
            response = api.post("/v1/maps/m/frames", files=files)
            assert response.status_code == 202, response.text


def wide_tilted_frame(map_id: str) -> Any:
    """A plausible frame whose one detection spans more index cells than a claim takes: a 640 x 480 wall
    2.45 m away filling a 159 x 139 degree view (fx 57, fy 45: the widest accepted), the camera tilted
    45 degrees, so the wall's box is about 28 x 20 x 20 m (11 000 cells of 1 m)."""
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    tilted = np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 1.0], [0, 0, 0, 1]])
    rgb = np.full((480, 640, 3), 90, np.uint8)
    depth = np.full((480, 640), 2.45, np.float32)
    return make_frame(
        rgb, depth, (57.0, 45.0, 319.5, 239.5), tilted, timestamp_s=0.0, map_id=map_id, device_id="d", frame_id="wide"
    )


def test_a_frame_over_the_claim_cap_fails_at_once_embedded() -> None:
    with AppClient(create_app(Settings(detector="sim:0", workers=1), detector=BlobDetector())) as api:
        assert (
            api.post("/v1/maps/wide/frames", content=proto_body(wide_tilted_frame("wide")), headers=PROTOBUF).status_code == 202
        )
        wait_until(lambda: api.get("/v1/maps/wide/stats").json()["frames"]["failed"] == 1, 60, "the frame failed")
        assert api.get("/v1/maps/wide/objects", params={"include": "tentative"}).json()["objects"] == []


@pytest.mark.redis
def test_a_frame_over_the_claim_cap_is_dead_lettered_at_its_first_delivery(redis_app: tuple[AppClient, RedisServer]) -> None:
    api, server = redis_app
    assert api.post("/v1/maps/wide/frames", content=proto_body(wide_tilted_frame("wide")), headers=PROTOBUF).status_code == 202
    redis = server.client()
    queue, store = RedisFrameQueue(server.url), RedisStore(server.url)
    worker = FrameWorker(
        queue, store, BlobDetector(), Settings().make_params(), heartbeat_s=None, read_block_s=0.2, max_deliveries=5
    )
    try:
        started = time.perf_counter()
        deadline = started + 60
        while not redis.xlen(keys.ingest_dead_letter_stream(keys.shard_tag(0, 1))) and time.perf_counter() < deadline:
            worker.poll_once()
        elapsed_s = time.perf_counter() - started
        [(_, dead)] = redis.xrange(keys.ingest_dead_letter_stream(keys.shard_tag(0, 1)))
        assert dead[b"deliveries"] == b"1" and dead[b"reason"].startswith(
            b"TooManyCells: detections: expected at most 4096 index cells"
        ), dead
        assert elapsed_s < 30, elapsed_s  # one delivery, no claim on Redis (9.4 M cells once blocked it 72 s)
        assert not list(redis.scan_iter(match=keys.map_pattern("wide").replace(":*", ":claim:*")))
        stats = api.get("/v1/maps/wide/stats").json()["frames"]
        assert stats["failed"] == 1 and stats["pending"] == 0, stats
    finally:
        queue.close()
        store.close()
        redis.close()


def test_glob_characters_in_map_patterns_are_escaped() -> None:
    assert keys.map_pattern("vic\\tim") == "arcloud:{vic\\\\tim}:*"
    assert keys.map_pattern("a*b?[c]") == "arcloud:{a\\*b\\?\\[c\\]}:*"
    assert np.all([keys.map_pattern(m).startswith(keys.map_prefix(m)) for m in ("office", "a.b_c-d")])


def test_a_wrong_number_in_the_pose_is_named_by_its_place(client: AppClient) -> None:
    """A new user's review: a null in cam2world was named ``meta.cam2world.list[float].3`` (the union's branch); in
    4 rows, a wrong number was named by the flat list's branch, the whole first row (a review)."""
    parts = multipart_parts(make_test_frame(4))
    meta = json.loads(parts["meta"][1])

    def post(changed: dict) -> dict:
        files = {**parts, "meta": ("meta.json", json.dumps(changed).encode(), "application/json")}
        answer = client.post("/v1/maps/m/frames", files=files)
        assert answer.status_code == 422, answer.text
        return answer.json()

    flat = {**meta, "cam2world": [*meta["cam2world"][:3], None, *meta["cam2world"][4:]]}
    assert post(flat)["field"] == "meta.cam2world.3"
    assert post(flat)["detail"] == "meta.cam2world.3: expected a valid number, got None"
    rows = [meta["cam2world"][i : i + 4] for i in range(0, 16, 4)]
    rows[2][3] = "2"
    assert post({**meta, "cam2world": rows})["detail"] == "meta.cam2world.2.3: expected a valid number, got '2'"


@pytest.mark.parametrize(
    "rows", [[[1, 0, 0, 0, 0], [1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], [[], list(range(16))]], ids=["5, 3, 4, 4", "0, 16"]
)
def test_a_pose_in_rows_of_other_lengths_is_refused_not_flattened(client: AppClient, rows: list) -> None:
    """A hostile client's review: ragged rows of 16 numbers in all were flattened into some other matrix (202)."""
    parts = multipart_parts(make_test_frame(5))
    meta = json.loads(parts["meta"][1])
    for field in ("cam2world", "device_from_map"):
        files = {**parts, "meta": ("meta.json", json.dumps({**meta, field: rows}).encode(), "application/json")}
        answer = client.post("/v1/maps/m/frames", files=files)
        assert answer.status_code == 422 and answer.json()["field"] == f"meta.{field}", answer.text
        assert "4 rows of 4" in answer.json()["detail"] and "rows of [" in answer.json()["detail"]


def test_a_meta_with_a_byte_order_mark_is_read_as_before(client: AppClient) -> None:
    """A review: the strict reading refused a meta starting with a UTF-8 BOM (``json.loads`` reads it), with a garbled
    detail."""
    parts = multipart_parts(make_test_frame(7))
    meta = ("meta.json", b"\xef\xbb\xbf" + parts["meta"][1], "application/json")
    answer = client.post("/v1/maps/m/frames", files={**parts, "meta": meta})
    assert answer.status_code == 202, answer.text
