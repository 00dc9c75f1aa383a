"""TUM RGB-D recordings (and any folder in the same layout), parsed once into a dataclass.

A recording folder holds ``rgb.txt`` and ``depth.txt`` (lines ``timestamp path``, the path relative to
the folder; ``#`` starts a comment), the images they list (colour; depth as uint16 PNG, ``depth_factor``
units a metre: 5000 in TUM, 0 = invalid; registered to colour, pixel for pixel) and ``groundtruth.txt``
(lines ``timestamp tx ty tz qx qy qz qw``: camera-to-world, OpenCV camera axes, metres, seconds).

Frames are made as TUM's ``associate.py`` pairs images: every depth image with the colour image nearest
in time, within ``MAX_RGB_DEPTH_DIFFERENCE_S`` (closest pairs first, each image used once). A frame's
pose is the trajectory at its depth timestamp plus ``pose_time_offset_s``: interpolated between the two
poses around it (position linearly, rotation by slerp); where one of them lies more than
``MAX_POSE_GAP_S`` away (a gap in the tracking, the ends of the trajectory) the nearest pose within
``MAX_NEAREST_POSE_S`` is taken as it is, and a frame with none is dropped (logged with a count). Unless given,
the offset is the one of ``POSE_TIME_OFFSETS_S`` that the recording's depth and poses agree with best
(``pose_time_offset_by_depth``), or 0 where none agrees better by ``CHECK_MARGIN``: a trajectory whose clock
runs a few hundredths of a second off the camera's puts every frame where the camera was a moment before or
after, which fuses what one object's frames saw into a smear.

The colour image of a frame was taken up to ``MAX_RGB_DEPTH_DIFFERENCE_S`` before or after its depth (the
sensor's two streams are not synchronized), and a hand-held camera turns by a few pixels' worth in that time.
A frame whose camera moved between its two images carries the motion as ``Frame.depth2rgb`` (the depth camera
at its time to the colour camera at its own, from the trajectory at both timestamps), so its masks are looked
up where the colour camera saw each depth point; one without a pose at its colour time, or that did not move,
is registered pixel for pixel.

Intrinsics: given, else ``camera-intrinsics.txt`` or ``intrinsics.txt`` in the folder (4 numbers
``fx fy cx cy``, or a 3x3 or 4x4 camera matrix), else by the TUM camera (``tum_camera``: the folder's name, or
the bag file ``rgb.txt`` names) what TUM publishes for it that the recording's depth and poses agree with
(``camera_by_depth``): the 525, 525, 319.5, 239.5 TUM recommends for turning its registered depth into 3D (the
first for freiburg1 and 2), its calibrated colour camera (the first for freiburg3), that camera with its lens
undone; else the generic 525, 525, 319.5, 239.5 with a warning. The depth factor: given, else TUM's 5000 over
the scale the depth and poses agree with (``camera_by_depth`` decides it for each camera).

TUM's world is not known to be gravity-aligned: up in the pose frame is chosen by
``arcloud.datasets.gravity.choose_up`` (given, ``gravity-direction.txt``, the ground truth's, else
estimated from the depth), and with ``align_gravity`` the poses are turned into a world whose +z is up.
Optional ground truth (``gt-boxes.json`` or the file given) is ``arcloud.datasets.gt_boxes``'s, its
world the frame of ``groundtruth.txt``.
"""

from __future__ import annotations

import functools
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from arcloud.core.calibration import MAX_PAIRS, depth_disagreement, stepped_pairs, view_pairs
from arcloud.core.checks import make_frame
from arcloud.core.types import Frame, Intrinsics
from arcloud.datasets.files import map_id_of, read_png_u16, read_rgb
from arcloud.datasets.frames import GravityAlignedSequence, LazyFrames
from arcloud.datasets.gravity import GRAVITY_FILE, choose_up, estimate_up_from_frames, gravity_world2file
from arcloud.datasets.gt_boxes import GT_BOXES_FILE, GroundTruthBoxes, load_ground_truth
from arcloud.errors import DatasetError

logger = logging.getLogger(__name__)

RGB_LIST, DEPTH_LIST, TRAJECTORY = "rgb.txt", "depth.txt", "groundtruth.txt"
INTRINSICS_FILES = ("camera-intrinsics.txt", "intrinsics.txt")
#: TUM's depth PNG units a metre.
DEPTH_FACTOR = 5000.0
#: Largest time between a depth image and the colour image it is paired with (TUM's associate.py).
MAX_RGB_DEPTH_DIFFERENCE_S = 0.02
#: Largest time between a frame and either of the two poses it is interpolated between.
MAX_POSE_GAP_S = 0.05
#: Largest time between a frame and the nearest pose it takes as it is, where no two lie around it (the ends of the
#: trajectory, a gap in the tracking): TUM's tools pair poses within 0.02 s; a freiburg1 camera moves 8 mm and turns
#: 0.6 degrees in that time.
MAX_NEAREST_POSE_S = 0.02
#: TUM's published colour intrinsics (depth is registered to colour) by camera.
PUBLISHED_INTRINSICS = {
    "freiburg1": Intrinsics(517.3, 516.5, 318.6, 255.3),
    "freiburg2": Intrinsics(520.9, 521.0, 325.1, 249.7),
    "freiburg3": Intrinsics(535.4, 539.2, 320.1, 247.6),
}
GENERIC_INTRINSICS = Intrinsics(525.0, 525.0, 319.5, 239.5)
#: TUM's published lens distortion of its colour cameras (OpenCV's k1, k2, p1, p2, k3) by camera; freiburg3's images
#: are published undistorted.
PUBLISHED_DISTORTION = {
    "freiburg1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "freiburg2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
}
#: A camera whose motion between a frame's two images moves no entry of the transform by more than this (a
#: micrometre, a microradian: a thousandth of a pixel) did not move: the frame is registered pixel for pixel.
STILL = 1e-6
#: Depth images ``camera_by_depth`` and ``pose_time_offset_by_depth`` read, spread over the recording.
CHECK_FRAMES = 150
#: The generic intrinsics replace the calibrated ones, a depth scale or a pose time offset replaces none, when the
#: depth disagrees with them less by this share.
CHECK_MARGIN = 0.02
#: The pose time offsets ``pose_time_offset_by_depth`` tries (seconds): +-50 ms in steps of 5 ms.
POSE_TIME_OFFSETS_S = tuple(round(0.005 * k, 3) for k in range(-10, 11))
#: The scales of the depth ``camera_by_depth`` tries: 0.95-1.05 in steps of 1 % (TUM's freiburg2 depth reads
#: about 4 % long at its factor of 5000: ORB-SLAM2's TUM2 settings take 5208). No wider: with intrinsics that are
#: all wrong (another camera's) the depth's scale makes up for them, and a least at the ends is not taken.
DEPTH_SCALES = tuple(round(0.95 + 0.01 * k, 2) for k in range(11))
#: The depth factor of millimetres, which many tools write in TUM's layout; a warning names it where the depth and poses
#: disagree less than ``MILLIMETRE_MARGIN`` as much with it as with the factor chosen (read at 5000, millimetres are 5
#: times short: every surface two frames see lands apart).
MILLIMETRES, MILLIMETRE_MARGIN = 1000.0, 0.5
GENERIC_SOURCE = "generic 525, 525, 319.5, 239.5"
#: A TUM camera in a folder's name (``rgbd_dataset_freiburg1_desk``, ``Freiburg2_xyz``, ``fr3_office``) or in the
#: ``# file: 'rgbd_dataset_freiburg1_desk.bag'`` line TUM's list files begin with.
_CAMERA_IN_NAME = re.compile(r"(?:^|[^a-z0-9])(?:rgbd_dataset_)?(?:freiburg|fr)([123])(?=_|\.|'|$)", re.IGNORECASE)


@dataclass(frozen=True, eq=False)
class TumSequence(GravityAlignedSequence):
    """A parsed recording. ``frame_names``: the depth timestamps as written in ``depth.txt``; ``depth_indices``: each
    frame's place among ``depth.txt``'s images, from 0 (its number in a ground truth's ``visible_frames``).
    ``cam2world``: (N, 4, 4) their poses in the output world (the pose frame, or the gravity-aligned
    one when ``world2file`` is not the identity). ``timestamps_s``: (N,) depth timestamps;
    ``rgb_paths``/``depth_paths``: the images of each frame. ``dropped_frames``: depth images without a
    colour image or a pose.

    up_file: (3,) unit up in the pose frame, None when unknown; ``up_source`` says where it came from.
    world2file: (4, 4) maps output-world points to the pose frame (identity unless gravity-aligned).
    ground_truth: ``gt-boxes.json`` parsed (the folder's, or the one given), or None.
    depth2rgb: (N, 4, 4) each frame's camera motion from its depth image to its colour image (identity: none known).
    ``pose_time_offset_s``, ``depth_factor`` and ``intrinsics`` come with a ``*_source`` saying what decided them.
    distortion: the lens distortion (OpenCV's k1, k2, p1, p2, k3) of both images, which ``load_frame`` undoes
    (``undistort``) so that frames are pinhole images with ``intrinsics``; None: they are already."""

    name: str
    root: Path
    intrinsics: Intrinsics
    intrinsics_source: str
    frame_names: tuple[str, ...]
    timestamps_s: np.ndarray
    rgb_paths: tuple[Path, ...]
    depth_paths: tuple[Path, ...]
    cam2world: np.ndarray
    dropped_frames: tuple[str, ...]
    up_file: np.ndarray | None
    world2file: np.ndarray
    depth_factor: float = DEPTH_FACTOR
    ground_truth: GroundTruthBoxes | None = None
    up_source: str = "none"
    device_id: str = "user-0"
    depth2rgb: np.ndarray | None = None
    pose_time_offset_s: float = 0.0
    pose_time_offset_source: str = "given"
    depth_factor_source: str = "given"
    distortion: tuple[float, ...] | None = None
    depth_indices: tuple[int, ...] = ()  # each frame's place among depth.txt's images, from 0: its frame number

    def colour_turn_deg(self) -> dict[str, float]:
        """How far the camera turned between a frame's depth and colour images (median and largest, degrees):
        the motion ``load_frame`` undoes (a degree is 9 px at 525 px focal length)."""
        if self.depth2rgb is None:
            return {"median": 0.0, "max": 0.0}
        cosines = (np.trace(self.depth2rgb[:, :3, :3], axis1=1, axis2=2) - 1) / 2
        degrees = np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))
        return {"median": round(float(np.median(degrees)), 3), "max": round(float(degrees.max()), 3)}

    def load_frame(self, name: str, *, device_id: str | None = None) -> Frame:
        """The frame ``name`` (a depth timestamp): colour resized to the depth size if they differ."""
        if name not in self._index:
            raise DatasetError(f"{self.root}: expected a frame named {name!r} with a colour image and a pose, got none")
        index = self._index[name]
        depth = read_png_u16(self.depth_paths[index])
        rgb = read_rgb(self.rgb_paths[index], (depth.shape[1], depth.shape[0]))
        if self.distortion is not None:
            depth, rgb = undistort(depth, self.intrinsics, self.distortion), undistort(rgb, self.intrinsics, self.distortion)
        moved = None if self.depth2rgb is None else self.depth2rgb[index]
        return make_frame(
            rgb,
            depth,
            self.intrinsics,
            self.cam2world[index],
            depth2rgb=None if moved is None or np.allclose(moved, np.eye(4), rtol=0, atol=STILL) else moved,
            timestamp_s=float(self.timestamps_s[index] - self.timestamps_s[0]),
            map_id=self.name,
            device_id=device_id or self.device_id,
            frame_id=name,
            depth_scale=self.depth_factor,
        )


@dataclass(frozen=True)
class _Listing:
    """A parsed list file: ``texts`` as written, ``times_s`` (N,), the other ``fields`` of each line, and its
    ``line_numbers`` (from 1, for errors)."""

    texts: tuple[str, ...]
    times_s: np.ndarray
    fields: tuple[tuple[str, ...], ...]
    line_numbers: tuple[int, ...] = ()


def _read_listing(path: Path, n_fields: int, form: str) -> _Listing:
    """Lines of ``n_fields`` whitespace-separated fields, the first a timestamp in seconds; ``#`` comments."""
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f"{path}: expected a readable {path.name} ({exc})") from exc
    texts, times, fields, numbers = [], [], [], []
    for number, line in enumerate(lines, 1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        if len(words) != n_fields:
            raise DatasetError(f"{path}:{number}: expected '{form}' ({n_fields} fields), got {line.strip()!r}")
        try:
            time_s = float(words[0])
        except ValueError:
            time_s = float("nan")
        if not np.isfinite(time_s):
            raise DatasetError(f"{path}:{number}: expected a timestamp in seconds first, got {words[0]!r}")
        texts.append(words[0])
        times.append(time_s)
        fields.append(tuple(words[1:]))
        numbers.append(number)
    if not texts:
        raise DatasetError(f"{path}: expected lines '{form}', got none")
    return _Listing(tuple(texts), np.asarray(times), tuple(fields), tuple(numbers))


def associate(
    first_s: Sequence[float] | np.ndarray,
    second_s: Sequence[float] | np.ndarray,
    *,
    max_difference_s: float = MAX_RGB_DEPTH_DIFFERENCE_S,
) -> list[tuple[int, int]]:
    """Pairs (i, j) of timestamps ``first_s[i]`` and ``second_s[j]`` less than ``max_difference_s``
    apart, as TUM's ``associate.py`` makes them: closest pairs first, each timestamp used once. Sorted by i."""
    first, second = np.asarray(first_s, np.float64), np.asarray(second_s, np.float64)
    order = np.argsort(second, kind="stable")
    ordered = second[order]
    lo = np.searchsorted(ordered, first - max_difference_s, side="left")
    hi = np.searchsorted(ordered, first + max_difference_s, side="right")
    candidates = [
        (abs(first[i] - ordered[k]), i, int(order[k]))
        for i in range(len(first))
        for k in range(lo[i], hi[i])
        if abs(first[i] - ordered[k]) < max_difference_s
    ]
    used_first: set[int] = set()
    used_second: set[int] = set()
    pairs = []
    for _, i, j in sorted(candidates):
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def interpolate_poses(
    times_s: np.ndarray,
    positions: np.ndarray,
    quaternions_xyzw: np.ndarray,
    query_s: np.ndarray,
    *,
    max_gap_s: float = MAX_POSE_GAP_S,
    max_nearest_s: float = MAX_NEAREST_POSE_S,
    interpolated_only: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query_s`` (M,) from a trajectory: ``times_s`` (N,) increasing, ``positions`` (N, 3),
    unit ``quaternions_xyzw`` (N, 4). Between two poses both within ``max_gap_s``: position linear,
    rotation slerp; else the nearest pose within ``max_nearest_s`` (with ``interpolated_only``: none). Returns
    (M, 4, 4) poses and (M,) bool, False where no pose was found (those poses are NaN)."""
    from scipy.spatial.transform import Rotation

    times, query = np.asarray(times_s, np.float64), np.asarray(query_s, np.float64)
    if len(query) == 0 or len(times) == 0:
        return np.full((len(query), 4, 4), np.nan), np.zeros(len(query), bool)
    rotations = Rotation.from_quat(np.asarray(quaternions_xyzw, np.float64))
    after = np.clip(np.searchsorted(times, query, side="right"), 1, max(len(times) - 1, 1))
    before = after - 1
    if len(times) == 1:
        before = after = np.zeros(len(query), int)
    gap_before, gap_after = np.abs(query - times[before]), np.abs(times[after] - query)
    between = (times[before] <= query) & (query <= times[after]) & (gap_before <= max_gap_s) & (gap_after <= max_gap_s)
    span = times[after] - times[before]
    alpha = np.where(between & (span > 0), (query - times[before]) / np.where(span > 0, span, 1.0), 0.0)
    nearest = np.where(gap_after < gap_before, after, before)
    valid = between if interpolated_only else between | (np.minimum(gap_before, gap_after) <= max_nearest_s)
    start = np.where(between, before, nearest)
    end = np.where(between, after, nearest)
    alpha = np.where(between, alpha, 0.0)
    turn = (rotations[start].inv() * rotations[end]).as_rotvec()
    rotation = rotations[start] * Rotation.from_rotvec(alpha[:, None] * turn)
    poses = np.tile(np.eye(4), (len(query), 1, 1))
    poses[:, :3, :3] = rotation.as_matrix()
    poses[:, :3, 3] = (1 - alpha[:, None]) * positions[start] + alpha[:, None] * positions[end]
    poses[~valid] = np.nan
    return poses, valid


def _read_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``groundtruth.txt`` -> times (N,) increasing, positions (N, 3), unit quaternions xyzw (N, 4)."""
    listing = _read_listing(path, 8, "timestamp tx ty tz qx qy qz qw")
    try:
        values = np.asarray(listing.fields, dtype=np.float64)
    except ValueError:
        values = np.array([[_number_or_nan(word) for word in row] for row in listing.fields])
        first = int(np.flatnonzero(np.isnan(values).any(axis=1))[0])
        raise DatasetError(
            f"{path}:{listing.line_numbers[first]}: expected numbers 'timestamp tx ty tz qx qy qz qw', got "
            f"{' '.join((listing.texts[first], *listing.fields[first]))!r}"
        ) from None
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if len(bad):
        raise DatasetError(
            f"{path}:{listing.line_numbers[bad[0]]}: expected finite poses, got {listing.fields[bad[0]]} at time "
            f"{listing.texts[bad[0]]}"
        )
    norms = np.linalg.norm(values[:, 3:], axis=1)
    off = np.flatnonzero(np.abs(norms - 1.0) > 0.01)
    if len(off):
        raise DatasetError(
            f"{path}:{listing.line_numbers[off[0]]}: expected unit quaternions qx qy qz qw, got norm {norms[off[0]]:.4f} "
            f"at time {listing.texts[off[0]]}"
        )
    order = np.argsort(listing.times_s, kind="stable")
    times = listing.times_s[order]
    repeated = np.flatnonzero(np.diff(times) == 0)
    if len(repeated):
        raise DatasetError(f"{path}: expected one pose per timestamp, got two at {listing.texts[order[repeated[0]]]}")
    return times, values[order, :3], values[order, 3:] / norms[order, None]


def _number_or_nan(word: str) -> float:
    try:
        return float(word)
    except ValueError:
        return float("nan")


def read_intrinsics_file(path: Path) -> Intrinsics:
    """``fx fy cx cy`` (4 numbers), or a 3x3 or 4x4 camera matrix (row-major), whitespace-separated."""
    try:
        values = np.array(path.read_text().replace(",", " ").split(), dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: expected 4, 9 or 16 numbers (fx fy cx cy, or a camera matrix), got {exc}") from exc
    if values.size == 4:
        fx, fy, cx, cy = values
    elif values.size in (9, 16):
        k = values.reshape(3, 3) if values.size == 9 else values.reshape(4, 4)[:3, :3]
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    else:
        raise DatasetError(f"{path}: expected 4, 9 or 16 numbers (fx fy cx cy, or a camera matrix), got {values.size}")
    if not np.all(np.isfinite([fx, fy, cx, cy])) or fx <= 0 or fy <= 0:
        raise DatasetError(f"{path}: expected finite intrinsics with positive focal lengths, got {[fx, fy, cx, cy]}")
    return Intrinsics(float(fx), float(fy), float(cx), float(cy))


def tum_camera(root: Path) -> tuple[str, str] | None:
    """The TUM camera (``freiburg1``, ``2`` or ``3``) a recording was taken with and what says so: its folder's name
    (as resolved: ``.`` names the folder it is), else the bag file its ``rgb.txt`` says it came from; None when
    neither does."""
    named = _CAMERA_IN_NAME.search(root.resolve().name)
    if named is not None:
        return f"freiburg{named.group(1)}", "by the folder's name"
    try:
        with open(root / RGB_LIST, errors="replace") as listing:
            header = [line for line, _ in zip(listing, range(5)) if line.startswith("#")]
    except OSError:
        return None
    named = next((found for line in header if (found := _CAMERA_IN_NAME.search(line)) is not None), None)
    return None if named is None else (f"freiburg{named.group(1)}", f"by the bag file {RGB_LIST} names")


def choose_intrinsics(root: Path, given: Intrinsics | None = None) -> tuple[Intrinsics, str, str | None]:
    """The recording's intrinsics, where they came from and the TUM camera they stand for (None: none; see the module
    docstring): for a TUM camera whose colour images are the sensor's own (freiburg1 and 2, whose lens TUM
    publishes), the 525, 525, 319.5, 239.5 TUM recommends for turning their registered depth into 3D; for freiburg3
    (published undistorted) its calibration."""
    if given is not None:
        return given, "given (--intrinsics)", None
    for name in INTRINSICS_FILES:
        if (root / name).is_file():
            return read_intrinsics_file(root / name), str(root / name), None
    found = tum_camera(root)
    if found is None:
        logger.warning(
            "%s: no intrinsics file and no freiburg1/2/3 in the folder's name or %s; using the generic %s", root, RGB_LIST,
            GENERIC_INTRINSICS,
        )  # fmt: skip
        return GENERIC_INTRINSICS, GENERIC_SOURCE, None
    camera, where = found
    if camera in PUBLISHED_DISTORTION:
        return GENERIC_INTRINSICS, f"TUM's 525, 525, 319.5, 239.5 for {camera}'s registered depth ({camera} {where})", camera
    return PUBLISHED_INTRINSICS[camera], f"TUM {camera}'s calibrated colour camera ({camera} {where})", camera


def check_pairs(cam2world: np.ndarray) -> list[tuple[int, int]]:
    """The pairs of frames the depth checks compare: frames turned apart (``core.calibration.view_pairs``), and
    when those are fewer than a quarter of ``MAX_PAIRS`` (a path that steps more than it turns), frames stepped
    apart besides (``stepped_pairs``), which tell the depth's scale and the clock."""
    pairs = view_pairs(cam2world)
    if len(pairs) < MAX_PAIRS // 4:
        pairs = sorted(set(pairs) | set(stepped_pairs(cam2world)[: MAX_PAIRS - len(pairs)]))
    return pairs


def undistort(image: np.ndarray, intrinsics: Intrinsics, distortion: Sequence[float]) -> np.ndarray:
    """The pinhole image with ``intrinsics`` of an ``image`` (H, W) or (H, W, 3) taken through a lens with
    ``distortion`` (OpenCV's k1, k2, p1, p2, k3) and the same intrinsics: depth and labels by the nearest pixel
    (never a depth between two surfaces), colour bilinearly."""
    import cv2

    height, width = image.shape[:2]
    x_map, y_map = _undistortion_maps(intrinsics, tuple(distortion), width, height)
    nearest = image.ndim == 2 or image.dtype != np.uint8
    return cv2.remap(image, x_map, y_map, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR)


@functools.lru_cache(maxsize=4)
def _undistortion_maps(
    intrinsics: Intrinsics, distortion: tuple[float, ...], width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    matrix = np.array([[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]], np.float64)
    return cv2.initUndistortRectifyMap(matrix, np.asarray(distortion, np.float64), None, matrix, (width, height), cv2.CV_32FC1)


def camera_by_depth(sequence: TumSequence, *, camera: str | None, scales: Sequence[float]) -> TumSequence:
    """The sequence with the intrinsics and depth factor its depth and poses agree with best (``core.calibration``;
    up to ``CHECK_FRAMES`` depth images), each taken only where the depth disagrees with it by ``CHECK_MARGIN``
    less; their sources say what decided. Each candidate camera at the depth's scale it agrees with (one of
    ``scales``, over 1 only by the margin and never at an end of them: depth a few per cent long puts what two
    frames seen from places apart measured of one surface centimetres apart); then a camera other than the
    sequence's own by the margin over that one at its scale. For a TUM ``camera`` (``tum_camera``) the
    candidates are the generic 525, 525, 319.5, 239.5, which TUM gives for turning its depth, registered to
    colour by the sensor's factory calibration, into 3D, and its calibrated colour camera (16 px apart in cy on
    freiburg1, which turns every frame's rays by 1.8 degrees), and where TUM publishes that camera's lens
    distortion (``PUBLISHED_DISTORTION``) its calibration with the lens undone too (TUM registers depth to colour
    pixel for pixel, so a lens that bends the colour image may bend the depth image alike). Each camera at its own
    scale, since each stands in for the other a little: 7-Scenes' depth 3 % short agrees better with a focal
    length 1.5 % short than with its own at the depth's own scale."""
    own = (sequence.intrinsics, sequence.intrinsics_source, None)
    cameras: list[tuple[Intrinsics, str, tuple[float, ...] | None]] = [own]
    if camera is not None:
        calibrated, lens = PUBLISHED_INTRINSICS[camera], PUBLISHED_DISTORTION.get(camera)
        cameras += [
            other
            for other in (
                (GENERIC_INTRINSICS, GENERIC_SOURCE, None),
                (calibrated, f"TUM {camera}'s calibrated colour camera", None),
            )
            if other[0] != own[0]
        ]
        if lens is not None:
            cameras.append((calibrated, f"TUM {camera}'s calibrated colour camera with its lens distortion {lens}", lens))
    picked = list(range(0, sequence.n_frames, max(1, -(-sequence.n_frames // CHECK_FRAMES))))
    cam2world = sequence.cam2world[picked]
    pairs = check_pairs(cam2world)
    if not pairs or (len(cameras) == 1 and list(scales) == [1.0]):
        unchecked = "; no frames seen from places turned or stepped apart to check it on" if not pairs else ""
        factor_source = sequence.depth_factor_source if list(scales) == [1.0] else f"{sequence.depth_factor:g}{unchecked}"
        return replace(sequence, intrinsics_source=sequence.intrinsics_source + unchecked, depth_factor_source=factor_source)
    images = [read_png_u16(sequence.depth_paths[i]) for i in picked]
    gaps = {}
    for k, (intrinsics, _, distortion) in enumerate(cameras):
        raw = [
            (undistort(d, intrinsics, distortion) if distortion else d).astype(np.float32) / sequence.depth_factor for d in images
        ]
        for scale in scales:
            gaps[(k, scale)] = depth_disagreement([d * scale for d in raw] if scale != 1.0 else raw, cam2world, intrinsics, pairs)

    def own_scale(k: int) -> float:  # a least at an end of the scales is a climb, not a minimum
        scale = min(scales, key=lambda s: (gaps[(k, s)], abs(s - 1.0)))
        inside = min(scales) < scale < max(scales)
        return scale if inside and gaps[(k, scale)] < (1 - CHECK_MARGIN) * gaps[(k, 1.0)] else 1.0

    best = [(k, own_scale(k)) for k in range(len(cameras))]
    chosen = min(best, key=lambda key: (gaps[key], key[0]))
    if gaps[chosen] >= (1 - CHECK_MARGIN) * gaps[best[0]]:
        chosen = best[0]
    (k, scale), nominal, start = chosen, sequence.depth_factor, (0, 1.0)
    figures = f"the depth and poses disagree by {gaps[chosen] * 1000:.1f} mm with it, {gaps[start] * 1000:.1f} mm with {own[1]} at {nominal:g}"
    if chosen != start:
        logger.warning("%s: %s; using %s and a depth factor of %.6g", sequence.root, figures, cameras[k][1], nominal / scale)
    if len(list(scales)) > 1 and nominal != MILLIMETRES:  # the factor not given: depth in millimetres, as many tools write?
        intrinsics, _, distortion = cameras[k]
        as_mm = [(undistort(d, intrinsics, distortion) if distortion else d).astype(np.float32) / MILLIMETRES for d in images]
        gap_mm = depth_disagreement(as_mm, cam2world, intrinsics, pairs)
        if gap_mm < MILLIMETRE_MARGIN * gaps[chosen]:
            logger.warning(
                "%s: the depth and poses agree far better at a depth factor of %g (millimetres): they disagree by %.1f mm "
                "there, %.1f mm at %.6g; give --depth-factor %g if its depth is in millimetres",
                sequence.root, MILLIMETRES, gap_mm * 1000, gaps[chosen] * 1000, nominal / scale, MILLIMETRES,
            )  # fmt: skip
    intrinsics_source = own[1] if k == 0 else f"{cameras[k][1]}, not {own[1]}"
    return replace(
        sequence,
        intrinsics=cameras[k][0],
        intrinsics_source=f"{intrinsics_source}: {figures}",
        distortion=cameras[k][2],
        depth_factor=nominal / scale,
        depth_factor_source=f"{nominal / scale:.6g}"
        + (f" (the depth x{scale:.2f})" if scale != 1.0 else "")
        + f" by the depth: {figures}",
    )


def is_tum_recording(root: Path) -> bool:
    return (root / RGB_LIST).is_file() and (root / DEPTH_LIST).is_file()


def load_tum(
    root: str | Path,
    *,
    align_gravity: bool = True,
    name: str | None = None,
    intrinsics: Intrinsics | None = None,
    depth_factor: float | None = None,
    pose_time_offset_s: float | None = None,
    gt_boxes: str | Path | None = None,
    up: object = None,
    estimate_up: bool = True,
) -> TumSequence:
    """Parse a TUM RGB-D recording (see the module docstring), with ``gt_boxes`` (a ground-truth file)
    or else the folder's ``gt-boxes.json`` when it has one. ``name`` (default: the folder's name, as a
    map id) names the maps. ``pose_time_offset_s`` and ``depth_factor``: None (default) for the ones the depth
    agrees with (``pose_time_offset_by_depth``, ``camera_by_depth``). Up in
    the pose frame: ``up`` (3 numbers), else ``gravity-direction.txt``, else the ground truth's, else (with
    ``estimate_up``) an estimate from the depth."""
    base = Path(root)
    if not base.is_dir():
        raise DatasetError(f"{base}: expected a TUM RGB-D folder, got no such folder")
    for listed in (RGB_LIST, DEPTH_LIST, TRAJECTORY):
        if not (base / listed).is_file():
            raise DatasetError(f"{base}: expected {listed} (TUM RGB-D layout), got no such file")
    if depth_factor is not None and not (np.isfinite(depth_factor) and depth_factor > 0):
        raise DatasetError(f"depth factor: expected a positive number of depth units a metre, got {depth_factor}")
    if pose_time_offset_s is not None and not np.isfinite(pose_time_offset_s):
        raise DatasetError(f"pose time offset: expected a finite number of seconds, got {pose_time_offset_s}")
    chosen_intrinsics, intrinsics_source, camera = choose_intrinsics(base, intrinsics)
    rgb = _read_listing(base / RGB_LIST, 2, "timestamp path")
    depth = _read_listing(base / DEPTH_LIST, 2, "timestamp path")
    if len(set(depth.texts)) != len(depth.texts):
        raise DatasetError(f"{base / DEPTH_LIST}: expected one image per timestamp, got repeated timestamps")
    trajectory = _read_trajectory(base / TRAJECTORY)

    pairs = sorted(associate(depth.times_s, rgb.times_s), key=lambda pair: depth.times_s[pair[0]])
    if pose_time_offset_s is None:
        paired = [i for i, _ in pairs]
        offset_s, offset_source = pose_time_offset_by_depth(
            trajectory, depth.times_s[paired], [base / depth.fields[i][0] for i in paired], chosen_intrinsics,
            DEPTH_FACTOR if depth_factor is None else depth_factor,
        )  # fmt: skip
    else:
        offset_s, offset_source = float(pose_time_offset_s), "given"
    cam2file, posed = interpolate_poses(*trajectory, depth.times_s[[i for i, _ in pairs]] + offset_s)
    kept = [(i, j) for (i, j), ok in zip(pairs, posed, strict=True) if ok]
    without_rgb, without_pose = len(depth.texts) - len(pairs), int(np.sum(~posed))
    if without_rgb or without_pose:
        logger.warning("%s: dropped %d of %d depth images: %d without a colour image within %g s, %d without a pose "
                       "(two around it within %g s, or one within %g s)", base, without_rgb + without_pose, len(depth.texts),
                       without_rgb, MAX_RGB_DEPTH_DIFFERENCE_S, without_pose, MAX_POSE_GAP_S, MAX_NEAREST_POSE_S)  # fmt: skip
    if not kept:
        raise DatasetError(f"{base}: expected depth images with a colour image and a pose, got none of {len(depth.texts)}")
    kept_depth = {i for i, _ in kept}
    # the camera's motion from each depth image to its colour image, where the trajectory holds poses around both
    # times (not a nearest pose taken as it is: two of those may lie a tracking gap apart)
    depth_s, colour_s = depth.times_s[[i for i, _ in kept]] + offset_s, rgb.times_s[[j for _, j in kept]] + offset_s
    depth_pose, depth_between = interpolate_poses(*trajectory, depth_s, interpolated_only=True)
    colour_pose, colour_between = interpolate_poses(*trajectory, colour_s, interpolated_only=True)
    moved = depth_between & colour_between
    depth2rgb = np.tile(np.eye(4), (len(kept), 1, 1))
    depth2rgb[moved] = np.linalg.inv(colour_pose[moved]) @ depth_pose[moved]
    gt_path = Path(gt_boxes) if gt_boxes is not None else base / GT_BOXES_FILE
    ground_truth = load_ground_truth(gt_path) if gt_boxes is not None or gt_path.is_file() else None
    in_file_world = TumSequence(
        name=name or map_id_of(base.name),
        root=base,
        intrinsics=chosen_intrinsics,
        intrinsics_source=intrinsics_source,
        frame_names=tuple(depth.texts[i] for i, _ in kept),
        timestamps_s=depth.times_s[[i for i, _ in kept]],
        rgb_paths=tuple(base / rgb.fields[j][0] for _, j in kept),
        depth_paths=tuple(base / depth.fields[i][0] for i, _ in kept),
        cam2world=cam2file[posed],
        dropped_frames=tuple(text for i, text in enumerate(depth.texts) if i not in kept_depth),
        depth_indices=tuple(i for i, _ in kept),
        up_file=None,
        world2file=np.eye(4),
        depth_factor=DEPTH_FACTOR if depth_factor is None else float(depth_factor),
        ground_truth=ground_truth,
        depth2rgb=depth2rgb,
        pose_time_offset_s=offset_s,
        pose_time_offset_source=offset_source,
    )
    in_file_world = camera_by_depth(
        in_file_world,
        camera=camera,
        scales=DEPTH_SCALES if depth_factor is None else [1.0],
    )
    choice = choose_up(
        given=up,
        gravity_file=base / GRAVITY_FILE,
        ground_truth=ground_truth,
        estimate=(lambda: estimate_up_from_frames(LazyFrames(in_file_world.frame_names, in_file_world.load_frame, cache=False)))
        if estimate_up else None,
        where=base,
    )  # fmt: skip
    world2file = gravity_world2file(choice.up_file) if align_gravity else np.eye(4)
    logger.info("%s: %d frames, intrinsics %s, depth factor %s, pose time offset %s", base, in_file_world.n_frames,
                in_file_world.intrinsics_source, in_file_world.depth_factor_source, offset_source)  # fmt: skip
    return replace(
        in_file_world,
        cam2world=np.einsum("ij,njk->nik", np.linalg.inv(world2file), in_file_world.cam2world),
        up_file=choice.up_file,
        up_source=choice.source,
        world2file=world2file,
    )


def pose_time_offset_by_depth(
    trajectory: tuple[np.ndarray, np.ndarray, np.ndarray],
    times_s: np.ndarray,
    depth_paths: Sequence[Path],
    intrinsics: Intrinsics,
    depth_factor: float,
) -> tuple[float, str]:
    """The pose time offset (seconds) and what decided it: the one of ``POSE_TIME_OFFSETS_S`` at which up to
    ``CHECK_FRAMES`` depth images (taken at ``times_s``, of ``depth_paths``) agree best with the poses of
    ``trajectory`` (times, positions, quaternions xyzw) there (``core.calibration``), when they disagree with it
    by ``CHECK_MARGIN`` less than with none and it is not at an end of them; else 0. Frames without a pose at some
    offset are left out."""
    picked = np.arange(0, len(times_s), max(1, -(-len(times_s) // CHECK_FRAMES)))
    tried = [interpolate_poses(*trajectory, times_s[picked] + offset) for offset in POSE_TIME_OFFSETS_S]
    always = np.logical_and.reduce([posed for _, posed in tried])
    poses = {offset: cam2world[always] for offset, (cam2world, _) in zip(POSE_TIME_OFFSETS_S, tried, strict=True)}
    pairs = check_pairs(poses[0.0])
    if not pairs:
        return 0.0, "0 s: no frames with poses seen from places turned or stepped apart to check it on"
    depths = [read_png_u16(depth_paths[i]).astype(np.float32) / depth_factor for i in picked[always]]
    gaps = {offset: depth_disagreement(depths, cam2world, intrinsics, pairs) for offset, cam2world in poses.items()}
    best = min(gaps, key=lambda offset: (gaps[offset], abs(offset)))
    figures = f"the depth and poses disagree by {gaps[best] * 1000:.1f} mm at {best:+.3f} s, {gaps[0.0] * 1000:.1f} mm at 0"
    inside = min(POSE_TIME_OFFSETS_S) < best < max(POSE_TIME_OFFSETS_S)  # a least at an end is a climb, not a minimum
    if best != 0.0 and inside and gaps[best] < (1 - CHECK_MARGIN) * gaps[0.0]:
        logger.warning("pose time offset: %s; using %+.3f s", figures, best)
        return best, f"{best:+.3f} s by the depth: {figures}"
    return 0.0, f"0 s by the depth: {figures}"


__all__ = [
    "DEPTH_FACTOR",
    "DEPTH_SCALES",
    "GENERIC_INTRINSICS",
    "MAX_NEAREST_POSE_S",
    "MAX_POSE_GAP_S",
    "MAX_RGB_DEPTH_DIFFERENCE_S",
    "POSE_TIME_OFFSETS_S",
    "PUBLISHED_DISTORTION",
    "PUBLISHED_INTRINSICS",
    "TumSequence",
    "associate",
    "camera_by_depth",
    "check_pairs",
    "choose_intrinsics",
    "interpolate_poses",
    "is_tum_recording",
    "load_tum",
    "pose_time_offset_by_depth",
    "read_intrinsics_file",
    "tum_camera",
    "undistort",
]
