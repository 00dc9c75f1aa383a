"""The ingest stream's message: the upload as the API validated it (its PNG images as the pixels the API
decoded, or as uploaded), from which a worker decodes the same frame, bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from arcloud.core.types import Frame
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.service.frames import validate_message
from arcloud.stores.stream_frames import decode_frame, encode_frame

HEIGHT, WIDTH = 48, 64


def upload(rng: np.random.Generator, *, depth_scale: float, rgb_png: bool) -> pb.Frame:
    """A message as a device sends it: depth a camera could see (0.5 to 4 m, as far as ``depth_scale`` units go: the
    service refuses a frame whose depth's median is not one of a room), and on a quarter of the pixels any 16-bit
    value (0 = no depth, 1, up to 65535)."""
    rgb = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    units = np.clip(np.rint(rng.uniform(0.5, 4.0, (HEIGHT, WIDTH)) * depth_scale), 1, 65535).astype(np.uint16)
    anything = rng.random((HEIGHT, WIDTH)) < 0.25
    units[anything] = rng.integers(0, 65536, int(anything.sum()), dtype=np.uint16)
    units.flat[:3] = (0, 1, 65535)
    ok, depth_png = cv2.imencode(".png", units)
    assert ok
    ok, rgb_bytes = cv2.imencode(".png" if rgb_png else ".jpg", rgb[..., ::-1])
    assert ok
    return pb.Frame(
        device_id="d",
        frame_id="f",
        intrinsics=pb.Intrinsics(fx=50, fy=50, cx=31.5, cy=23.5),
        cam2world=np.eye(4).ravel().tolist(),
        rgb=rgb_bytes.tobytes(),
        rgb_encoding=pb.RGB_ENCODING_PNG if rgb_png else pb.RGB_ENCODING_JPEG,
        depth=depth_png.tobytes(),
        depth_encoding=pb.DEPTH_ENCODING_PNG,
        depth_scale=depth_scale,
    )


def assert_same_frame(a: Frame, b: Frame) -> None:
    np.testing.assert_array_equal(a.rgb, b.rgb)
    assert a.depth_m.dtype == b.depth_m.dtype == np.float32
    np.testing.assert_array_equal(a.depth_m.view(np.uint32), b.depth_m.view(np.uint32))  # bit for bit
    np.testing.assert_array_equal(a.cam2world, b.cam2world)
    assert (a.intrinsics, a.map_id, a.key, a.timestamp_s) == (b.intrinsics, b.map_id, b.key, b.timestamp_s)


@pytest.mark.parametrize("depth_scale", [1000.0, 5000.0, 4000.0, 10_000 / 3, 1.0, 100_000.0])
@pytest.mark.parametrize("rgb_png", [True, False])
def test_a_worker_decodes_the_frame_the_api_validated(depth_scale: float, rgb_png: bool) -> None:
    uploaded = upload(np.random.default_rng(7), depth_scale=depth_scale, rgb_png=rgb_png)
    msg = pb.Frame()
    msg.CopyFrom(uploaded)
    validated = validate_message(msg, "room")
    # the API decoded the PNGs once, and the message it queues carries their pixels on
    assert msg.depth_encoding == pb.DEPTH_ENCODING_RAW_UINT16 and (msg.width, msg.height) == (WIDTH, HEIGHT)
    if rgb_png:
        assert msg.rgb_encoding == pb.RGB_ENCODING_RAW_RGB8
    else:  # JPEG is lossy: carried as uploaded, never re-encoded
        assert msg.rgb_encoding == pb.RGB_ENCODING_JPEG and msg.rgb == uploaded.rgb
    assert_same_frame(decode_frame(encode_frame(validated, msg)), validated)


@pytest.mark.parametrize("rgb_png", [True, False])
def test_images_queued_as_uploaded_decode_to_the_same_frame(rgb_png: bool) -> None:
    uploaded = upload(np.random.default_rng(8), depth_scale=1000.0, rgb_png=rgb_png)
    msg = pb.Frame()
    msg.CopyFrom(uploaded)
    validated = validate_message(msg, "room", queue_decoded_png=False)
    uploaded.map_id = "room"
    assert msg == uploaded  # as it came (the path's map id set)
    decoded_png = pb.Frame()
    decoded_png.CopyFrom(uploaded)
    assert_same_frame(validate_message(decoded_png, "room"), validated)
    assert decoded_png.depth_encoding == pb.DEPTH_ENCODING_RAW_UINT16 and msg.depth_encoding == pb.DEPTH_ENCODING_PNG
    assert_same_frame(decode_frame(encode_frame(validated, msg)), validated)


def test_raw_uploads_are_carried_as_they_are() -> None:
    rng = np.random.default_rng(3)
    msg = pb.Frame(
        device_id="d",
        frame_id="f",
        intrinsics=pb.Intrinsics(fx=50, fy=50, cx=31.5, cy=23.5),
        cam2world=np.eye(4).ravel().tolist(),
        width=WIDTH,
        height=HEIGHT,
        rgb=rng.integers(0, 256, HEIGHT * WIDTH * 3, dtype=np.uint8).tobytes(),
        rgb_encoding=pb.RGB_ENCODING_RAW_RGB8,
        depth=rng.random((HEIGHT, WIDTH), dtype=np.float32).astype("<f4").tobytes(),
        depth_encoding=pb.DEPTH_ENCODING_RAW_FLOAT32,
    )
    rgb, depth = msg.rgb, msg.depth
    validated = validate_message(msg, "room")
    assert (msg.rgb, msg.depth) == (rgb, depth)
    assert_same_frame(decode_frame(encode_frame(validated, msg)), validated)


def test_a_frame_queued_without_its_upload_is_carried_losslessly() -> None:
    msg = upload(np.random.default_rng(5), depth_scale=1000.0, rgb_png=False)
    validated = validate_message(msg, "room")
    assert_same_frame(decode_frame(encode_frame(validated)), validated)
    assert_same_frame(decode_frame(encode_frame(validated, msg)), validated)
