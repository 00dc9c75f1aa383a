import numpy as np
import pytest

from arcloud.core.checks import check_detections, check_pose, make_frame
from arcloud.core.types import Detection
from arcloud.errors import InvalidInput

RGB = np.zeros((4, 5, 3), np.uint8)
DEPTH = np.ones((4, 5), np.float32)
K = {"fx": 10.0, "fy": 10.0, "cx": 2.0, "cy": 2.0}


def frame(**changes):
    args = dict(rgb=RGB, depth=DEPTH, intrinsics=K, cam2world=np.eye(4))
    meta = dict(timestamp_s=1.0, map_id="m", device_id="d", frame_id="f")
    for key, value in changes.items():
        (args if key in args or key == "depth_scale" else meta)[key] = value
    return make_frame(args.pop("rgb"), args.pop("depth"), args.pop("intrinsics"), args.pop("cam2world"), **args, **meta)


def test_valid_frame_normalises_uint16_depth_to_metres():
    f = frame(depth=np.full((4, 5), 1500, np.uint16), depth_scale=1000)
    assert f.depth_m.dtype == np.float32
    assert np.allclose(f.depth_m, 1.5)
    assert f.key == "d/f"


@pytest.mark.parametrize(
    ("changes", "field", "fragment"),
    [
        ({"rgb": np.zeros((4, 5), np.uint8)}, "rgb", "(H, W, 3)"),
        ({"rgb": np.zeros((4, 5, 3), np.float32)}, "rgb", "uint8"),
        ({"depth": np.ones((4, 6), np.float32)}, "depth", "size"),
        ({"depth": np.ones((4, 5), np.uint16)}, "depth_scale", "units per metre"),
        ({"depth": np.ones((4, 5), np.int32)}, "depth", "uint16"),
        ({"depth": np.ones((4, 5), np.float32), "depth_scale": 1000}, "depth_scale", "float depth"),
        ({"intrinsics": {"fx": 1.0, "fy": 1.0, "cx": 0.0}}, "intrinsics", "missing cy"),
        ({"intrinsics": {"fx": -1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}}, "intrinsics.fx", "> 0"),
        ({"cam2world": np.eye(3)}, "cam2world", "(4, 4)"),
        ({"cam2world": np.full((4, 4), np.nan)}, "cam2world", "finite"),
        ({"cam2world": np.diag([2.0, 1.0, 1.0, 1.0])}, "cam2world", "orthonormal"),
        ({"cam2world": np.diag([-1.0, 1.0, 1.0, 1.0])}, "cam2world", "det +1"),
        ({"timestamp_s": float("inf")}, "timestamp_s", "finite"),
        ({"map_id": ""}, "map_id", "non-empty"),
        ({"device_id": "a/b"}, "device_id", "'/'"),
        ({"frame_id": 7}, "frame_id", "string"),
    ],
)
def test_invalid_frame_names_field_expected_and_got(changes, field, fragment):
    with pytest.raises(InvalidInput) as info:
        frame(**changes)
    assert info.value.field == field
    assert fragment in str(info.value)
    assert str(info.value).startswith(f"{field}: expected")


def test_float_depth_invalid_values_become_zero():
    depth = DEPTH.copy()
    depth[0, 0], depth[0, 1], depth[0, 2] = np.nan, -1.0, np.inf
    f = frame(depth=depth)
    assert f.depth_m[0, :3].tolist() == [0.0, 0.0, 0.0]
    assert DEPTH[0, 0] == 1.0 and depth[0, 1] == -1.0  # the caller's array is untouched


def test_pose_accepts_small_rotation_error_and_flat_lists():
    rng = np.random.default_rng(0)
    pose = np.eye(4)
    pose[:3, :3] += rng.normal(0, 1e-5, (3, 3))
    assert check_pose("p", pose.ravel().tolist()).shape == (4, 4)
    bottom = np.eye(4)
    bottom[3, 3] = 2  # no transform, read either way
    with pytest.raises(InvalidInput, match="last row") as wrong:
        check_pose("p", bottom)
    assert "column-major" not in str(wrong.value)
    moved = np.eye(4)
    moved[:3, 3] = (1.0, 2.0, 0.5)
    with pytest.raises(InvalidInput) as columns:  # as ARKit's simd_float4x4 lists it: columns first
        check_pose("p", moved.T)
    assert str(columns.value) == (
        "p: expected last row (0, 0, 0, 1), got [1.  2.  0.5 1. ] (its last column is (0, 0, 0, 1): column-major? send it "
        "row-major, transposed)"
    )


def test_detections_checked_against_frame():
    mask = np.zeros((4, 5), bool)
    assert check_detections([Detection("tv", 0.5, mask)], (4, 5))[0].label == "tv"
    with pytest.raises(InvalidInput, match=r"detections\[0\].label"):
        check_detections([Detection("bus", 0.5, mask)], (4, 5))
    with pytest.raises(InvalidInput, match=r"detections\[0\].score"):
        check_detections([Detection("tv", 1.5, mask)], (4, 5))
    with pytest.raises(InvalidInput, match=r"detections\[0\].mask"):
        check_detections([Detection("tv", 0.5, np.zeros((3, 5), bool))], (4, 5))


def test_plausible_cameras_have_a_field_of_view_of_20_to_160_degrees():
    from arcloud.core.checks import check_plausible_camera
    from arcloud.core.types import Intrinsics

    widest, narrowest = 640 / (2 * np.tan(np.radians(80))), 640 / (2 * np.tan(np.radians(10)))  # 56.4 and 1814.8 px
    for fx in (widest + 1e-6, 525.0, narrowest - 1e-6):
        check_plausible_camera("intrinsics", Intrinsics(fx, 525.0, 319.5, 239.5), 640, 480)
    for fx in (widest - 0.1, narrowest + 0.1, 5.0):
        with pytest.raises(InvalidInput, match=r"intrinsics\.fx: expected 56\.4 to 1814\.8 px"):
            check_plausible_camera("intrinsics", Intrinsics(fx, 525.0, 319.5, 239.5), 640, 480)
    with pytest.raises(InvalidInput, match=r"intrinsics\.cy"):
        check_plausible_camera("intrinsics", Intrinsics(525.0, 525.0, 319.5, 480.5), 640, 480)
