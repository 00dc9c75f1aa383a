"""The committed generated code is what ``make proto`` makes from ``proto/``, and the wire numbers stay put."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from arcloud.proto.arcloud.v1 import arcloud_pb2 as pb

ROOT = Path(__file__).resolve().parents[2]
GENERATED = ("arcloud/v1/arcloud_pb2.py", "arcloud/v1/arcloud_pb2.pyi")


def test_generated_code_matches_the_proto(tmp_path: Path) -> None:
    pytest.importorskip("grpc_tools", reason="grpcio-tools (a dev dependency) regenerates the code")
    # the command of `make proto`, writing into a temporary folder
    subprocess.run(
        [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            "-Iproto",
            f"--python_out={tmp_path}",
            f"--pyi_out={tmp_path}",
            *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "proto/arcloud/v1").glob("*.proto")),
        ],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    for relative in GENERATED:
        fresh = (tmp_path / relative).read_text()
        committed = (ROOT / "src/arcloud/proto" / relative).read_text()
        assert fresh == committed, f"src/arcloud/proto/{relative} is out of date: run `make proto`"


def numbers(message) -> dict[str, int]:
    return {field.name: field.number for field in message.DESCRIPTOR.fields}


def test_field_numbers_never_change() -> None:
    # Renumbering a field breaks every client in the field: add new numbers instead.
    assert pb.DESCRIPTOR.package == "arcloud.v1"
    assert numbers(pb.Frame) == {
        "map_id": 1,
        "device_id": 2,
        "frame_id": 3,
        "timestamp_s": 4,
        "intrinsics": 5,
        "cam2world": 6,
        "rgb": 7,
        "rgb_encoding": 8,
        "depth": 9,
        "depth_encoding": 10,
        "depth_scale": 11,
        "width": 12,
        "height": 13,
        "pose_convention": 14,
        "world_up": 15,
        "device_from_map": 16,
    }
    assert numbers(pb.Intrinsics) == {"fx": 1, "fy": 2, "cx": 3, "cy": 4}
    assert numbers(pb.Object) == {
        "id": 1,
        "map_id": 2,
        "label": 3,
        "score": 4,
        "aabb": 5,
        "obb": 6,
        "version": 7,
        "created_at_s": 8,
        "updated_at_s": 9,
        "n_voxels": 10,
        "n_frames": 11,
        "n_devices": 12,
        "status": 13,
    }
    assert dict(pb.Object.Status.items()) == {"STATUS_UNSPECIFIED": 0, "STATUS_CONFIRMED": 1, "STATUS_TENTATIVE": 2}
    assert numbers(pb.ObjectEvent) == {"kind": 1, "map_id": 2, "object_id": 3, "object": 4, "merged_into": 5, "time_s": 6}
    assert numbers(pb.Box3) == {"min": 1, "max": 2}
    assert numbers(pb.OrientedBox) == {"center": 1, "size": 2, "yaw_rad": 3, "rotation": 4}
    assert numbers(pb.ObjectList) == {"map_id": 1, "objects": 2}
    assert dict(pb.RgbEncoding.items()) == {
        "RGB_ENCODING_UNSPECIFIED": 0,
        "RGB_ENCODING_JPEG": 1,
        "RGB_ENCODING_PNG": 2,
        "RGB_ENCODING_RAW_RGB8": 3,
    }
    assert dict(pb.DepthEncoding.items()) == {
        "DEPTH_ENCODING_UNSPECIFIED": 0,
        "DEPTH_ENCODING_PNG": 1,
        "DEPTH_ENCODING_RAW_UINT16": 2,
        "DEPTH_ENCODING_RAW_FLOAT32": 3,
    }
    assert dict(pb.PoseConvention.items()) == {
        "POSE_CONVENTION_UNSPECIFIED": 0,
        "POSE_CONVENTION_OPENCV": 1,
        "POSE_CONVENTION_ARKIT": 2,
        "POSE_CONVENTION_ARCORE": 3,
    }
    assert dict(pb.ObjectEvent.Kind.items()) == {
        "KIND_UNSPECIFIED": 0,
        "KIND_CREATED": 1,
        "KIND_UPDATED": 2,
        "KIND_MERGED": 3,
        "KIND_DELETED": 4,
        "KIND_RETIRED": 5,
    }


def test_a_known_frame_encodes_to_known_bytes() -> None:
    # A golden encoding: what a client library in any language must produce for these values.
    msg = pb.Frame(map_id="m", frame_id="1", timestamp_s=0.5, rgb_encoding=pb.RGB_ENCODING_PNG, width=2)
    assert msg.SerializeToString() == bytes.fromhex("0a016d1a013121000000000000e03f40026002")
