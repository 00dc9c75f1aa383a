"""``ARCLOUD_QUEUED_IMAGES``: what the Redis ingest stream carries of a frame's PNG images (a real redis-server,
the real app; no workers: the entry is read back as a worker reads it)."""

from __future__ import annotations

import numpy as np
import pytest
from redis_server import RedisServer
from svc_helpers import AppClient, make_test_frame

from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_to_proto
from arcloud.service.settings import Settings
from arcloud.stores import keys
from arcloud.stores.stream_frames import decode_frame
from arcloud.tools.wiring import create_app

pytestmark = [pytest.mark.redis]


@pytest.mark.parametrize(
    ("queued_images", "depth_encoding"), [("decoded", pb.DEPTH_ENCODING_RAW_UINT16), ("uploaded", pb.DEPTH_ENCODING_PNG)]
)
def test_the_stream_carries_png_depth_as_the_setting_says_and_a_worker_reads_the_same_frame(
    queued_images: str, depth_encoding: int
) -> None:
    frame = make_test_frame(3, map_id="room")
    upload = frame_to_proto(frame)
    assert upload.depth_encoding == pb.DEPTH_ENCODING_PNG and upload.rgb_encoding == pb.RGB_ENCODING_JPEG
    server = RedisServer.start()
    try:
        settings = Settings(store=server.url, auth="none", detector="sim:0", workers=0, queued_images=queued_images)
        with AppClient(create_app(settings)) as api:
            response = api.post(
                "/v1/maps/room/frames", content=upload.SerializeToString(), headers={"content-type": "application/x-protobuf"}
            )
            assert response.status_code == 202, response.text
        ((_, fields),) = server.client().xrange(keys.ingest_stream(keys.shard_tag(0, 1)))
        carried = pb.Frame.FromString(fields[b"frame"])
        assert carried.depth_encoding == depth_encoding
        assert carried.rgb == upload.rgb  # JPEG: as uploaded either way
        read = decode_frame(fields[b"frame"])
        expected = decode_frame(upload.SerializeToString())  # the upload decoded directly
        np.testing.assert_array_equal(read.rgb, expected.rgb)
        np.testing.assert_array_equal(read.depth_m.view(np.uint32), expected.depth_m.view(np.uint32))
        assert (read.map_id, read.key) == ("room", expected.key)
    finally:
        server.stop()
