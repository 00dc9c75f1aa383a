"""Checks at the edges: normalise dtypes and say what was expected and what came."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from arcloud.core.errors import InvalidInput
from arcloud.core.types import CLASSES, Detection, Frame, Intrinsics

ROTATION_TOLERANCE = 1e-3
MAX_ID_LENGTH = 128
# Map ids name Redis keys, SCAN patterns and Zenoh key expressions: letters, digits, '.', '_', '-' only.
MAP_ID_CHARACTERS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-")

# What a real camera sends (checked at the service's edge by ``check_plausible_frame``; ``make_frame``
# takes any finite values). Each bound keeps the state one frame makes small: a focal length of a few
# pixels spreads a VGA frame's pixels over hundreds of metres, and so over millions of index cells.
MIN_FOV_DEG = 20.0  # field of view along each image axis: fx <= width / (2 tan(10°)), about 2.84 width
MAX_FOV_DEG = 160.0  # fx >= width / (2 tan(80°)), about 0.088 width
MAX_TRANSLATION_M = 10_000.0  # each coordinate of a camera's position, metres from the map's origin
MAX_COORDINATE_M = 100_000.0  # each coordinate of a query box: beyond every camera and what it sees
MIN_DEPTH_SCALE, MAX_DEPTH_SCALE = 1.0, 100_000.0  # units per metre of 16-bit depth: 1 m to 10 µm a unit
# The lower quartile of a frame's valid depth as a real camera sees a room, a street or a table close up (metres):
# beyond, its units are wrong (millimetres sent as metres, or with depth_scale 1: about 1000 m). A quartile, not the
# median: a Kinect writes 65535 where it measured nothing, and half a frame of it is a median of 65.5 m.
MIN_DEPTH_QUARTILE_M, MAX_DEPTH_QUARTILE_M = 0.05, 100.0  # no camera measures a quarter of a frame under 5 cm


def describe(value: object) -> str:
    """A short description of a value for error messages: shape and dtype for arrays."""
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape} and dtype {value.dtype}"
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def check_id(field: str, value: object) -> str:
    """A device or frame id: a non-empty printable string without whitespace, '/', '\\', braces or glob
    characters."""
    if not isinstance(value, str) or not value or len(value) > MAX_ID_LENGTH:
        raise InvalidInput(field, f"a non-empty string of at most {MAX_ID_LENGTH} characters", describe(value))
    if not value.isprintable() or any(c.isspace() or c in "/\\{}*?[]" for c in value):
        raise InvalidInput(field, "no whitespace, '/', '\\', braces or glob characters", describe(value))
    return value


def check_map_id(field: str, value: object) -> str:
    """A map id: 1 to ``MAX_ID_LENGTH`` letters, digits, '.', '_' or '-' (``MAP_ID_CHARACTERS``, ASCII only)."""
    if not isinstance(value, str) or not 0 < len(value) <= MAX_ID_LENGTH or not MAP_ID_CHARACTERS.issuperset(value):
        raise InvalidInput(
            field, f"a non-empty string of at most {MAX_ID_LENGTH} letters, digits, '.', '_' or '-'", describe(value)
        )
    return value


def check_finite_number(field: str, value: object, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInput(field, "a number", describe(value))
    try:
        number = float(value)
    except OverflowError:  # an integer past the largest float (10**400): no finite number either
        raise InvalidInput(field, "a finite number", describe(value)) from None
    if not math.isfinite(number):
        raise InvalidInput(field, "a finite number", describe(value))
    if positive and number <= 0:
        raise InvalidInput(field, "a number > 0", describe(value))
    return number


def check_intrinsics(value: Intrinsics | Mapping[str, float] | Sequence[float]) -> Intrinsics:
    """Intrinsics from an ``Intrinsics``, a mapping with fx, fy, cx, cy, or a 4-sequence."""
    if isinstance(value, Intrinsics):
        values: tuple[float, ...] = (value.fx, value.fy, value.cx, value.cy)
    elif isinstance(value, Mapping):
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in value]
        if missing:
            raise InvalidInput("intrinsics", "keys fx, fy, cx, cy", f"missing {', '.join(missing)}")
        values = (value["fx"], value["fy"], value["cx"], value["cy"])
    elif isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 4:
        values = tuple(value)
    else:
        raise InvalidInput("intrinsics", "fx, fy, cx, cy", describe(value))
    fx, fy = (check_finite_number(f"intrinsics.f{k}", v, positive=True) for k, v in zip("xy", values[:2]))
    cx, cy = (check_finite_number(f"intrinsics.c{k}", v) for k, v in zip("xy", values[2:]))
    return Intrinsics(fx, fy, cx, cy)


def check_pose(field: str, value: object) -> np.ndarray:
    """A rigid 4x4 transform: finite, last row (0, 0, 0, 1), rotation orthonormal with det +1."""
    try:
        pose = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(field, "a 4x4 matrix of numbers", describe(value)) from exc
    if pose.shape == (16,):
        pose = pose.reshape(4, 4)
    if pose.shape != (4, 4):
        raise InvalidInput(field, "shape (4, 4)", f"shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise InvalidInput(field, "finite values", "NaN or infinity")
    if not np.allclose(pose[3], (0, 0, 0, 1), atol=1e-6):
        transposed = np.allclose(pose[:, 3], (0, 0, 0, 1), atol=1e-6)  # ARKit's simd and OpenGL store columns first
        got = np.array2string(pose[3], precision=4) + (
            " (its last column is (0, 0, 0, 1): column-major? send it row-major, transposed)" if transposed else ""
        )
        raise InvalidInput(field, "last row (0, 0, 0, 1)", got)
    rotation = pose[:3, :3]
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if error > ROTATION_TOLERANCE:
        raise InvalidInput(field, f"an orthonormal rotation (tolerance {ROTATION_TOLERANCE})", f"error {error:.3g}")
    if np.linalg.det(rotation) < 0:
        raise InvalidInput(field, "a proper rotation (det +1)", "a reflection (det -1)")
    return pose


def check_plausible_camera(field: str, intrinsics: Intrinsics, width: int, height: int) -> Intrinsics:
    """Intrinsics of a real camera for a ``width`` x ``height`` image: a field of view of ``MIN_FOV_DEG``
    to ``MAX_FOV_DEG`` along each axis, the principal point inside the image."""
    for axis, focal_px, size in (("x", intrinsics.fx, width), ("y", intrinsics.fy, height)):
        lo = size / (2 * math.tan(math.radians(MAX_FOV_DEG / 2)))
        hi = size / (2 * math.tan(math.radians(MIN_FOV_DEG / 2)))
        if not lo <= focal_px <= hi:
            raise InvalidInput(
                f"{field}.f{axis}",
                f"{lo:.1f} to {hi:.1f} px for an image {size} px {'wide' if axis == 'x' else 'high'} "
                f"(a field of view of {MIN_FOV_DEG:g} to {MAX_FOV_DEG:g} degrees)",
                focal_px,
            )
    for axis, centre_px, size in (("x", intrinsics.cx, width), ("y", intrinsics.cy, height)):
        if not 0 <= centre_px <= size:
            raise InvalidInput(f"{field}.c{axis}", f"a principal point inside the image (0 to {size} px)", centre_px)
    return intrinsics


def check_plausible_position(field: str, pose: np.ndarray) -> np.ndarray:
    """A (4, 4) pose whose translation stays within ``MAX_TRANSLATION_M`` of the origin on every axis."""
    translation = np.asarray(pose, np.float64)[:3, 3]
    if np.any(np.abs(translation) > MAX_TRANSLATION_M):
        raise InvalidInput(
            field, f"a translation of at most {MAX_TRANSLATION_M:g} m on each axis", np.array2string(translation, precision=1)
        )
    return pose


def check_depth_scale(value: object) -> float:
    """Units per metre of 16-bit depth, ``MIN_DEPTH_SCALE`` to ``MAX_DEPTH_SCALE``."""
    scale = check_finite_number("depth_scale", value)
    if not MIN_DEPTH_SCALE <= scale <= MAX_DEPTH_SCALE:
        raise InvalidInput(
            "depth_scale", f"{MIN_DEPTH_SCALE:g} to {MAX_DEPTH_SCALE:g} units per metre (1000: millimetres)", scale
        )
    return scale


def check_plausible_frame(frame: Frame) -> Frame:
    """A frame a real camera could have taken (``check_plausible_camera`` for the depth camera and, when
    given, the colour camera; ``check_plausible_position``): what the service accepts."""
    height, width = frame.shape
    check_plausible_camera("intrinsics", frame.intrinsics, width, height)
    if frame.rgb_intrinsics is not None:
        check_plausible_camera("rgb_intrinsics", frame.rgb_intrinsics, frame.rgb.shape[1], frame.rgb.shape[0])
    check_plausible_position("cam2world", frame.cam2world)
    check_plausible_depth(frame.depth_m)
    return frame


def check_plausible_depth(depth_m: np.ndarray) -> np.ndarray:
    """Depth in metres whose valid pixels' lower quartile (every 8th row and column) is ``MIN_DEPTH_QUARTILE_M`` to
    ``MAX_DEPTH_QUARTILE_M``; a frame of almost no valid depth (the sky, a lens covered) passes: it adds nothing."""
    sample = depth_m[::8, ::8]
    valid = sample[sample > 0]
    if valid.size < 16:
        return depth_m
    quartile = float(np.quantile(valid, 0.25))
    if not MIN_DEPTH_QUARTILE_M <= quartile <= MAX_DEPTH_QUARTILE_M:
        raise InvalidInput(
            "depth",
            f"depth in metres whose lower quartile is {MIN_DEPTH_QUARTILE_M:g} to {MAX_DEPTH_QUARTILE_M:g} m, as a camera "
            "sees (its units: depth_scale, 1000 for millimetres; float depth is metres)",
            f"a lower quartile of {quartile:.4g} m",
        )
    return depth_m


def check_rgb(value: object) -> np.ndarray:
    rgb = np.asarray(value)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise InvalidInput("rgb", "shape (H, W, 3)", f"shape {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise InvalidInput("rgb", "dtype uint8", f"dtype {rgb.dtype}")
    return rgb


def check_depth(value: object, depth_scale: float | None) -> np.ndarray:
    """Depth in metres as float32, 0 where invalid. uint16 needs ``depth_scale`` (units per metre,
    e.g. 1000 for millimetres); float input is metres and must not come with a scale."""
    depth = np.asarray(value)
    if depth.ndim != 2 or depth.shape[0] < 1 or depth.shape[1] < 1:
        raise InvalidInput("depth", "shape (H, W)", f"shape {depth.shape}")
    if depth.dtype == np.uint16:
        if depth_scale is None:
            raise InvalidInput("depth_scale", "units per metre for uint16 depth (e.g. 1000)", None)
        scale = check_finite_number("depth_scale", depth_scale, positive=True)
        return depth.astype(np.float32) / np.float32(scale)
    if depth.dtype in (np.float32, np.float64):
        if depth_scale not in (None, 1, 1.0):
            raise InvalidInput("depth_scale", "none (or 1) for float depth in metres", describe(depth_scale))
        metres = depth.astype(np.float32, copy=True)
        bad = ~np.isfinite(metres) | (metres < 0)
        metres[bad] = 0.0
        return metres
    raise InvalidInput("depth", "dtype uint16 (with depth_scale) or float32 metres", f"dtype {depth.dtype}")


def make_frame(
    rgb: object,
    depth: object,
    intrinsics: Intrinsics | Mapping[str, float] | Sequence[float],
    cam2world: object,
    *,
    timestamp_s: float,
    map_id: str,
    device_id: str,
    frame_id: str,
    depth_scale: float | None = None,
    rgb_intrinsics: Intrinsics | Mapping[str, float] | Sequence[float] | None = None,
    depth2rgb: object = None,
) -> Frame:
    """A validated ``Frame``; raises ``InvalidInput`` naming the first wrong field. ``rgb_intrinsics``
    and ``depth2rgb`` describe an unregistered colour camera (see ``Frame``)."""
    rgb_array = check_rgb(rgb)
    depth_m = check_depth(depth, depth_scale)
    if rgb_array.shape[:2] != depth_m.shape:
        raise InvalidInput("depth", f"the rgb's size {rgb_array.shape[:2]}", f"size {depth_m.shape}")
    return Frame(
        rgb=rgb_array,
        depth_m=depth_m,
        intrinsics=check_intrinsics(intrinsics),
        cam2world=check_pose("cam2world", cam2world),
        timestamp_s=check_finite_number("timestamp_s", timestamp_s),
        map_id=check_map_id("map_id", map_id),
        device_id=check_id("device_id", device_id),
        frame_id=check_id("frame_id", frame_id),
        rgb_intrinsics=None if rgb_intrinsics is None else check_intrinsics(rgb_intrinsics),
        depth2rgb=None if depth2rgb is None else check_pose("depth2rgb", depth2rgb),
    )


def check_detections(detections: Sequence[Detection], shape: tuple[int, int]) -> list[Detection]:
    """Detections that fit a frame of ``shape``: a known class, a score in [0, 1], an (H, W) mask."""
    checked = []
    for i, det in enumerate(detections):
        if det.label not in CLASSES:
            raise InvalidInput(f"detections[{i}].label", f"one of {CLASSES}", describe(det.label))
        score = check_finite_number(f"detections[{i}].score", det.score)
        if not 0.0 <= score <= 1.0:
            raise InvalidInput(f"detections[{i}].score", "a score in [0, 1]", score)
        mask = np.asarray(det.mask)
        if mask.shape != shape:
            raise InvalidInput(f"detections[{i}].mask", f"shape {shape}", f"shape {mask.shape}")
        checked.append(Detection(det.label, score, mask.astype(bool, copy=False)))
    return checked
