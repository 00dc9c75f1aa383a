"""Hypothesis strategies for frame uploads: a valid frame (built as the bad-input battery builds one) with
bits flipped, bytes cut or spliced in its protobuf encoding and in its PNG/JPEG payloads, its fields replaced
by odd values, and its multipart meta JSON given huge, tiny, NaN-ish or nested values.
"""

from __future__ import annotations

import functools
import json
from typing import Any

from fuzz_helpers import ODD_STRINGS, SEEDED_MAP
from hypothesis import strategies as st
from svc_helpers import make_test_frame, multipart_parts

from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb
from arcloud.proto.convert import frame_to_proto

Parts = dict[str, tuple[str, bytes, str]]


@functools.cache
def _valid_message_bytes() -> bytes:
    return frame_to_proto(make_test_frame(1, map_id=SEEDED_MAP, level=True)).SerializeToString()


def valid_message(frame_id: str = "f000001") -> pb.Frame:
    """A valid protobuf frame of map ``SEEDED_MAP`` (JPEG rgb, 16-bit PNG depth, 160 x 120); a fresh copy."""
    msg = pb.Frame.FromString(_valid_message_bytes())
    msg.frame_id = frame_id
    return msg


@functools.cache
def _valid_parts() -> tuple[tuple[str, tuple[str, bytes, str]], ...]:
    return tuple(multipart_parts(make_test_frame(1, map_id=SEEDED_MAP, level=True)).items())


def valid_parts() -> Parts:
    """The multipart parts (meta JSON, JPEG rgb, 16-bit PNG depth) of the same frame."""
    return dict(_valid_parts())


@st.composite
def mutated_bytes(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` with a few bits flipped, cut short, with bytes spliced in or a run zeroed (one to three of these)."""
    out = bytearray(data)
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["flip", "truncate", "splice", "zero"]))
        at = draw(st.integers(0, max(0, len(out) - 1)))
        if kind == "flip" and out:
            out[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "truncate":
            del out[at:]
        elif kind == "splice":
            out[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif kind == "zero":
            out[at : at + draw(st.integers(1, 64))] = b"\x00" * min(64, len(out) - at)
    return bytes(out)


odd_text = st.one_of(
    st.sampled_from(ODD_STRINGS), st.text(st.characters(codec="utf-8"), max_size=40)
)  # no lone surrogates: UTF-8 cannot carry them
odd_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e300, 1.7976931348623157e308, 2.0**63, -(2.0**63)]),
)
json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    odd_floats,
    odd_text,
    st.sampled_from(["NaN", "Infinity", "-Infinity", "1e309", "0x10", "", "null"]),
)
json_values = st.recursive(
    json_scalars, lambda children: st.lists(children, max_size=4) | st.dictionaries(odd_text, children, max_size=4), max_leaves=12
)


@st.composite
def meta_json(draw: st.DrawFn) -> bytes:
    """The valid meta with some values (top level or in ``intrinsics``) replaced, removed or added, or its text mutated."""
    meta: dict[str, Any] = json.loads(valid_parts()["meta"][1])
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from([*meta, *(f"intrinsics.{k}" for k in ["fx", "fy", "cx", "cy"]), "map_id", "extra"]))
        target, name = (meta.get("intrinsics"), key.split(".")[1]) if key.startswith("intrinsics.") else (meta, key)
        if not isinstance(target, dict):
            continue
        if draw(st.booleans()) and name in target:
            del target[name]
        else:
            target[name] = draw(json_values)
    text = json.dumps(meta).encode()  # NaN and Infinity spelled as Python's json spells them
    return draw(st.one_of(st.just(text), mutated_bytes(text)))


def _image_bytes(valid: bytes) -> st.SearchStrategy[bytes]:
    return st.one_of(st.just(valid), mutated_bytes(valid), st.binary(max_size=64))


@st.composite
def multipart_frames(draw: st.DrawFn) -> Parts:
    """Multipart parts of the valid frame with the meta, the rgb or the depth changed (at least one)."""
    parts = valid_parts()
    meta, rgb, depth = parts["meta"][1], parts["rgb"][1], parts["depth"][1]
    changed = draw(st.sets(st.sampled_from(["meta", "rgb", "depth", "swap"]), min_size=1))
    if "meta" in changed:
        meta = draw(meta_json())
    if "rgb" in changed:
        rgb = draw(_image_bytes(rgb))
    if "depth" in changed:
        depth = draw(_image_bytes(depth))
    if "swap" in changed:
        rgb, depth = depth, rgb
    return {
        "meta": ("meta.json", meta, "application/json"),
        "rgb": ("rgb", rgb, draw(st.sampled_from(["image/jpeg", "image/png", "application/octet-stream"]))),
        "depth": ("depth.png", depth, "image/png"),
    }


_FIELDS: dict[str, st.SearchStrategy[Any]] = {
    "map_id": odd_text,
    "device_id": odd_text,
    "frame_id": odd_text,
    "timestamp_s": odd_floats,
    "depth_scale": odd_floats,
    "rgb_encoding": st.integers(-3, 8),
    "depth_encoding": st.integers(-3, 8),
    "width": st.integers(0, 2**32 - 1),
    "height": st.integers(0, 2**32 - 1),
}


@st.composite
def protobuf_frames(draw: st.DrawFn) -> bytes:
    """The valid frame's protobuf bytes mutated, or its fields (ids, numbers, encodings, sizes, pose, intrinsics,
    image payloads) replaced with odd values."""
    if draw(st.booleans()):
        return draw(mutated_bytes(valid_message().SerializeToString()))
    msg = valid_message(frame_id=f"p{draw(st.integers(0, 10**6)):07d}")
    for name in draw(st.sets(st.sampled_from([*_FIELDS, "intrinsics", "cam2world", "rgb", "depth"]), min_size=1, max_size=4)):
        if name in _FIELDS:
            setattr(msg, name, draw(_FIELDS[name]))
        elif name == "intrinsics":
            msg.intrinsics.fx, msg.intrinsics.cx = draw(odd_floats), draw(odd_floats)
        elif name == "cam2world":
            msg.ClearField("cam2world")
            msg.cam2world.extend(draw(st.lists(odd_floats, max_size=20)))
        else:
            setattr(msg, name, draw(_image_bytes(getattr(msg, name))))
    return msg.SerializeToString()
