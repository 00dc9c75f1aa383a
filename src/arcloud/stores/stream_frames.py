"""How the Redis ingest stream carries a frame: the protobuf ``arcloud.v1.Frame`` as the API validated it.
With ``ARCLOUD_QUEUED_IMAGES=uploaded`` (the default) its images travel as they came; with ``decoded`` the
API replaced its PNG images by the pixels it decoded to validate them (``frame_from_proto(lossless_to_raw=True)``),
so that no worker decodes them again (a VGA PNG depth image: 2.7 ms; its pixels: 614 kB in the stream against
~120 kB). JPEG always travels as uploaded (lossy: never re-encoded). ``decode_frame`` turns the bytes back
into the same ``Frame``, bit for bit.
"""

from __future__ import annotations

from arcloud.core.types import Frame
from arcloud.errors import InvalidInput
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_from_proto


def decode_frame(payload: bytes) -> Frame:
    """A validated ``Frame`` from protobuf bytes; ``InvalidInput`` when they are not one."""
    from google.protobuf.message import DecodeError

    try:
        message = pb.Frame.FromString(payload)
    except DecodeError as exc:
        raise InvalidInput("frame", "a protobuf arcloud.v1.Frame", f"{len(payload)} undecodable bytes") from exc
    return frame_from_proto(message)


def encode_frame(frame: Frame, message: pb.Frame | None = None) -> bytes:
    """The bytes a stream entry carries: ``message``, the frame's upload as validated, or without one the
    frame's pixels and float depth as they are (lossless either way)."""
    from arcloud.proto.convert import frame_to_proto

    if message is None:
        message = frame_to_proto(frame, rgb_encoding="raw", depth_encoding="raw_float32")
    return bytes(message.SerializeToString())
