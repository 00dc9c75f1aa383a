"""Frame uploads -> wire ``Frame`` messages -> validated core ``Frame`` objects.

Two bodies are accepted: a protobuf ``arcloud.v1.Frame`` (``application/x-protobuf``), or multipart
parts ``meta`` (JSON, see ``schemas.FrameMeta``), ``rgb`` (JPEG or PNG file) and ``depth`` (16-bit PNG
file). Both become one message. Everything is checked before the frame is queued: image kinds and
sizes (pixels are counted from the headers before decoding, so a small file cannot expand into a huge
image), decoding, dtypes, shapes, pose, ids, and the map id of the body against the path.

The pose is taken into the map's world with OpenCV camera axes here, at the edge (``proto.convert.to_map_world``:
the frame's declared ``pose_convention`` and ``world_up``, and its ``device_from_map`` or else the device's
stored alignment, ``ports.DeviceAlignments``): the queue, the workers and the core see only that pose.

The ingest queues the validated ``Frame`` with its message (a queue that serialises, such as the Redis
one, carries the message rather than encoding the frame again: its images as uploaded, or, when
``Settings.queued_images`` says ``decoded``, its PNG images replaced by the pixels decoded here).
"""

from __future__ import annotations

import contextlib
import json
import struct
from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import ValidationError

from arcloud.core.checks import check_depth_scale, check_id, check_map_id, check_plausible_frame, describe
from arcloud.core.types import Frame
from arcloud.errors import InvalidInput
from arcloud.ports import DeviceAlignments
from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import POSE_CONVENTIONS, frame_from_proto
from arcloud.service.problems import first_error, validation_location, validation_wording
from arcloud.service.schemas import FrameMeta

PROTOBUF_MEDIA_TYPES = ("application/x-protobuf", "application/protobuf", "application/vnd.google.protobuf")
MULTIPART_MEDIA_TYPE = "multipart/form-data"
JPEG_MAGIC = b"\xff\xd8\xff"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DEFAULT_MAX_PIXELS = 1920 * 1440  # Settings.max_frame_pixels
# An encoded image may take at most twice its pixels' raw bytes, plus room for its metadata: more is not an
# image but a carrier (metadata segments, chunks), and it would travel whole into the queue. JPEG of noise
# at quality 100 with full-resolution chroma takes 1.37x; a PNG of noise just over 1x.
#: Scans a JPEG may hold: a baseline JPEG has one, a progressive one about ten (libjpeg's script for colour), an
#: EXIF thumbnail one more. Each scan is a pass of the decoder over the image, so the pixel and byte limits alone
#: let a 3.6 MB progressive image of 300,000 tiny scans hold a decoding thread for 14 s.
MAX_JPEG_SCANS = 64
SCAN_MARKER = b"\xff\xda"  # start of scan; in entropy-coded data a 0xFF byte is followed by 0x00 or a restart marker
MAX_ENCODED_OVER_RAW = 2
ENCODED_SLACK_BYTES = 64 * 1024
MAX_META_BYTES = 64 * 1024  # the multipart meta JSON: a few hundred bytes in practice


def parse_message(body: bytes) -> pb.Frame:
    """A protobuf ``Frame`` from a request body."""
    from google.protobuf.message import DecodeError

    if not body:
        raise InvalidInput("body", "a protobuf arcloud.v1.Frame", "an empty body")
    try:
        return pb.Frame.FromString(body)
    except DecodeError as exc:
        raise InvalidInput("body", "a protobuf arcloud.v1.Frame", f"{len(body)} bytes that do not parse as one") from exc


def valid_ids(msg: pb.Frame) -> dict[str, str]:
    """The message's device and frame ids that are valid ids (``check_id``: safe in a log line), before the rest of
    it is checked."""
    ids = {}
    for name in ("device_id", "frame_id"):
        with contextlib.suppress(InvalidInput):
            ids[name] = check_id(name, getattr(msg, name))
    return ids


def parse_meta(raw: str | bytes) -> FrameMeta:
    """The multipart ``meta`` part (at most ``MAX_META_BYTES``); errors name the first wrong field (``meta.<field>``)."""
    if len(raw) > MAX_META_BYTES:
        raise InvalidInput("meta", f"a JSON object of at most {MAX_META_BYTES} bytes", f"{len(raw)} bytes")
    try:
        data = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as exc:
        raise InvalidInput("meta", "a JSON object", f"invalid JSON ({exc})") from exc
    except RecursionError:
        raise InvalidInput("meta", "a JSON object", "JSON nested deeper than the parser goes") from None
    if not isinstance(data, dict):
        raise InvalidInput("meta", "a JSON object", describe(data))
    try:
        # JSON's strict mode (arrays still read as tuples), on the JSON as parsed above: a UTF-8 BOM or UTF-16, which
        # json reads, stays accepted
        return FrameMeta.model_validate_json(json.dumps(data), strict=True)
    except ValidationError as exc:
        first = first_error(exc.errors())
        where = validation_location(first["loc"])
        got = "none" if first.get("type") == "missing" else describe(first.get("input"))
        raise InvalidInput(f"meta.{where}" if where else "meta", validation_wording(first), got) from exc


def message_from_parts(meta: FrameMeta, rgb: bytes, depth: bytes, map_id: str) -> pb.Frame:
    """A protobuf ``Frame`` from multipart parts (images kept as uploaded)."""
    pose = meta.flat_pose()
    if len(pose) != 16:
        raise InvalidInput("meta.cam2world", "16 numbers (row-major 4x4) or 4 rows of 4", f"{len(pose)} numbers")
    if rgb.startswith(JPEG_MAGIC):
        rgb_encoding = pb.RGB_ENCODING_JPEG
    elif rgb.startswith(PNG_MAGIC):
        rgb_encoding = pb.RGB_ENCODING_PNG
    else:
        raise InvalidInput("rgb", "a JPEG or PNG image", f"{len(rgb)} bytes starting with {rgb[:8]!r}")
    if not depth.startswith(PNG_MAGIC):
        raise InvalidInput("depth", "a 16-bit PNG image", f"{len(depth)} bytes starting with {depth[:8]!r}")
    i = meta.intrinsics
    msg = pb.Frame(
        map_id=meta.map_id or map_id,
        device_id=meta.device_id,
        frame_id=meta.frame_id,
        timestamp_s=meta.timestamp,
        intrinsics=pb.Intrinsics(fx=i.fx, fy=i.fy, cx=i.cx, cy=i.cy),
        cam2world=pose,
        rgb=rgb,
        rgb_encoding=rgb_encoding,
        depth=depth,
        depth_encoding=pb.DEPTH_ENCODING_PNG,
        depth_scale=meta.depth_scale,
    )
    if meta.pose_convention != "opencv":
        msg.pose_convention = POSE_CONVENTIONS[meta.pose_convention]
    if meta.world_up is not None:
        x, y, z = meta.world_up
        msg.world_up.CopyFrom(pb.Vec3(x=x, y=y, z=z))
    if meta.device_from_map is not None:
        msg.device_from_map.extend(meta.flat_device_from_map())
    return msg


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header without decoding; None when it cannot be read."""
    if data.startswith(PNG_MAGIC) and len(data) >= 24 and data[12:16] == b"IHDR":
        width, height = struct.unpack(">II", data[16:24])
        return int(width), int(height)
    if data.startswith(JPEG_MAGIC):
        pos = 2
        while pos + 4 <= len(data):
            if data[pos] != 0xFF:
                return None
            marker = data[pos + 1]
            if marker == 0xFF:  # fill byte
                pos += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
                pos += 2
                continue
            (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
            if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):  # start of frame
                if pos + 9 > len(data):
                    return None
                height, width = struct.unpack(">HH", data[pos + 5 : pos + 9])
                return int(width), int(height)
            pos += 2 + length
    return None


def max_encoded_bytes(width: int, height: int, bytes_per_pixel: int) -> int:
    """The most bytes an encoded image of ``width`` x ``height`` pixels of ``bytes_per_pixel`` may take."""
    return MAX_ENCODED_OVER_RAW * width * height * bytes_per_pixel + ENCODED_SLACK_BYTES


def check_pixels(msg: pb.Frame, max_pixels: int) -> None:
    """Refuse images whose header declares more than ``max_pixels`` pixels, whose size cannot be read
    from the header (never decode to find out), that take more bytes than ``max_encoded_bytes``, or JPEGs of
    more than ``MAX_JPEG_SCANS`` scans."""
    for field, data, encoded, bytes_per_pixel in (
        ("rgb", msg.rgb, msg.rgb_encoding in (pb.RGB_ENCODING_JPEG, pb.RGB_ENCODING_PNG), 3),
        ("depth", msg.depth, msg.depth_encoding == pb.DEPTH_ENCODING_PNG, 2),
    ):
        if encoded:
            size = image_size(data)
            if size is None:
                raise InvalidInput(
                    field, "a PNG or JPEG whose header gives its size (IHDR, or SOF before the scan)", f"{len(data)} bytes"
                )
        else:  # raw pixels: the declared size (``frame_from_proto`` checks the byte count against it)
            size = (msg.width, msg.height)
        if size[0] * size[1] > max_pixels:
            raise InvalidInput(field, f"at most {max_pixels} pixels", f"{size[0]} x {size[1]}")
        if encoded and len(data) > (most := max_encoded_bytes(size[0], size[1], bytes_per_pixel)):
            raise InvalidInput(
                field,
                f"at most {most} bytes for a {size[0]} x {size[1]} image (twice its pixels' size + 64 KiB)",
                f"{len(data)} bytes",
            )
        if encoded and data.startswith(JPEG_MAGIC) and (scans := data.count(SCAN_MARKER)) > MAX_JPEG_SCANS:
            raise InvalidInput(field, f"a JPEG of at most {MAX_JPEG_SCANS} scans", f"{scans} scans")


def validate_message(
    msg: pb.Frame,
    map_id: str,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    queue_decoded_png: bool = True,
    map_up: Sequence[float] = (0.0, 0.0, 1.0),
    alignments: DeviceAlignments | None = None,
) -> Frame:
    """The validated ``Frame`` of a message posted to ``map_id`` (the message's map id is set to the
    path's when empty, and must equal it otherwise). ``queue_decoded_png``: the message's PNG images become
    the pixels decoded here, for the queue to carry (``frame_from_proto(lossless_to_raw=True)``;
    ``Settings.queued_images``). The pose, in the message too, becomes the OpenCV camera's in the world of the
    map (whose up is ``map_up``), with the device's alignment from ``alignments`` when the frame brings none."""
    check_map_id("map_id", map_id)
    if msg.map_id and msg.map_id != map_id:
        raise InvalidInput("map_id", f"the map id of the path ({map_id!r}) or none", repr(msg.map_id))
    msg.map_id = map_id
    check_pixels(msg, max_pixels)
    if msg.depth_encoding != pb.DEPTH_ENCODING_RAW_FLOAT32:  # 16-bit depth: units per metre (float: metres)
        check_depth_scale(msg.depth_scale)
    stored = None
    if alignments is not None and not msg.device_from_map:
        stored = alignments.get(map_id, check_id("device_id", msg.device_id))
    frame = frame_from_proto(msg, lossless_to_raw=queue_decoded_png, map_up=map_up, device_from_map=stored)
    return check_plausible_frame(frame)


def form_bytes(form: Mapping[str, Any], name: str, what: str) -> bytes | None:
    """The bytes of a multipart part given as a file (``what`` says what it should be)."""
    part = form.get(name)
    if part is None:
        raise InvalidInput(name, f"a multipart part named {name!r} ({what})", "nothing")
    if isinstance(part, str):
        if name == "meta":
            return part.encode()
        raise InvalidInput(name, f"a file part ({what})", "a text field")
    return None  # a file: the caller reads it (async)
