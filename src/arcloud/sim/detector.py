"""A simulated 2D instance detector with realistic, seeded faults, and the sensor faults of frames.

``SimulatedDetector.detect(frame)`` renders the room's instance image at the frame's true pose and
turns every visible object into a detection, then applies the faults of ``DetectorFaults``: misses
(more for small, truncated and occluded instances), label confusions between similar classes, mask
borders that are eroded, dilated and jittered by a few pixels, occasional split masks, and spurious
detections on background clutter or surfaces. The same ``DetectorFaults`` also describe the sensor:
Kinect-like depth noise with dropouts and flying pixels at depth edges, and a small pose error.

Determinism: every random draw of a frame comes from a generator seeded by ``(seed, crc32(frame_id),
stream)`` (``frame_rng``), never by device id, process or call order, so the same frame gives the same
detections whichever user it is assigned to. The reported pose of a frame is its true pose times a
noise transform drawn the same way: ``reported = true @ noise``, so ``true = reported @ inv(noise)``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import zlib
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from arcloud.core.checks import describe
from arcloud.core.types import CLASSES, Detection, Frame, Intrinsics
from arcloud.errors import InvalidInput
from arcloud.sim.room import Room, room_renderer
from arcloud.virtual_camera.render import MeshRenderer

log = logging.getLogger(__name__)

# Random streams of a frame (the third seed word).
STREAM_POSE = 1
STREAM_DEPTH = 2
STREAM_INSTANCE = 3
STREAM_SPURIOUS = 4
STREAM_OBJECT = 5  # per object, not per frame: which objects are hard

#: Labels a detector confuses a class with (COCO detectors on indoor frames).
CONFUSIONS: dict[str, tuple[str, ...]] = {
    "chair": ("couch",),
    "couch": ("chair", "table"),
    "table": ("couch",),
    "tv": ("laptop",),
    "laptop": ("tv",),
}
#: Labels given to spurious detections on background clutter, by clutter kind.
CLUTTER_LOOKALIKES: dict[str, tuple[str, ...]] = {
    "cabinet": ("table", "tv"),
    "tv cabinet": ("table",),
    "bookshelf": ("tv", "table"),
    "plant": ("chair",),
    "boxes": ("table", "laptop", "tv"),
    "lamp": ("chair",),
    "door": ("tv",),
    "window": ("tv",),
    "picture": ("tv", "laptop"),
}


@dataclass(frozen=True)
class DetectorFaults:
    """Faults of the simulated detector and sensor. Defaults are meant to be about as hard as a COCO
    Mask R-CNN or YOLO-seg on real indoor frames (a large, fully visible object is found about 4 times
    in 5, tables and couches less, a quarter of the objects are hard in every frame, masks are a few
    pixels off, about one false detection every other frame); ``DetectorFaults.none()`` is a perfect
    detector and sensor.

    Detection (per visible instance):
        miss_rate: probability to miss a large, fully visible instance.
        small_area_px: instances with fewer visible pixels are "small"; the extra miss probability
            rises linearly from 0 at ``small_area_px`` to ``small_miss_rate`` at ``min_area_px``.
        min_area_px: instances with fewer visible pixels are never detected.
        truncated_miss_rate: extra miss probability, times the fraction of the instance's projected
            box that falls outside the image.
        occluded_miss_rate: extra miss probability, times the estimated occluded fraction.
        class_miss_rates: (label, extra miss probability) pairs: COCO detectors find some classes
            harder (a "dining table" seen from above, a couch seen from its side).
        hard_instance_rate, hard_miss_rate: the share of objects the detector finds hard (drawn once
            per object from the seed, the same in every frame, as a real detector's failures are),
            and their extra miss probability; hard objects are also confused three times as often.
        confusion_rate: probability that the label is replaced by a similar class (``CONFUSIONS``).
        split_rate: probability that one instance comes out as two detections (two halves of its mask).
        border_px: mask border error: the mask is grown or shrunk by up to about ``border_px`` pixels
            overall, plus a smooth random boundary jitter of the same order (0: exact masks).
    Scores:
        score_min, score_max: range of true detections' scores, rising with visible area, falling with
            occlusion and truncation; score_noise: Gaussian noise on scores. Confused labels score lower.
    Spurious detections (per frame):
        spurious_rate: mean number (Poisson) of detections of things that are no object: on clutter
            that looks like a class (``CLUTTER_LOOKALIKES``) or as a blob on a background surface.
        spurious_score_min, spurious_score_max: their score range (overlapping true scores).
    Sensor:
        depth_sigma_a_m, depth_sigma_b, depth_sigma_z0_m: depth noise sigma = a + b * (z - z0)**2 metres.
        depth_edge_dropout: probability that a pixel on the far side of a depth edge reads invalid (0).
        depth_flying_rate: probability that a far-side edge pixel not dropped reads a depth between the
            two surfaces (a "flying pixel").
        depth_edge_jump_m: depth jump between neighbours that makes an edge (also 3 % of depth).
        depth_dropout: probability of a random invalid pixel.
        depth_min_m, depth_max_m: the sensor's range; depth outside reads invalid (None: no limit).
        pose_noise_m: standard deviation of the reported pose's translation error per axis.
        pose_noise_deg: standard deviation of its rotation error angle.
    """

    miss_rate: float = 0.12
    small_area_px: int = 800
    small_miss_rate: float = 0.6
    min_area_px: int = 60
    truncated_miss_rate: float = 0.25
    occluded_miss_rate: float = 0.4
    class_miss_rates: tuple[tuple[str, float], ...] = (("table", 0.2), ("couch", 0.1))
    hard_instance_rate: float = 0.25
    hard_miss_rate: float = 0.4
    confusion_rate: float = 0.06
    split_rate: float = 0.04
    border_px: float = 3.5
    score_min: float = 0.45
    score_max: float = 0.95
    score_noise: float = 0.07
    spurious_rate: float = 0.6
    spurious_score_min: float = 0.25
    spurious_score_max: float = 0.7
    depth_sigma_a_m: float = 0.0012
    depth_sigma_b: float = 0.0019
    depth_sigma_z0_m: float = 0.4
    depth_edge_dropout: float = 0.5
    depth_flying_rate: float = 0.2
    depth_edge_jump_m: float = 0.1
    depth_dropout: float = 0.002
    depth_min_m: float | None = 0.3
    depth_max_m: float | None = 6.0
    pose_noise_m: float = 0.01
    pose_noise_deg: float = 0.3

    def __post_init__(self) -> None:
        for label, rate in self.class_miss_rates:
            if label not in CLASSES or isinstance(rate, bool) or not isinstance(rate, (int, float)) or not 0 <= rate <= 1:
                raise InvalidInput(
                    "DetectorFaults.class_miss_rates", f"(label in {CLASSES}, probability) pairs", repr((label, rate))
                )
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if (value is None and f.name in ("depth_min_m", "depth_max_m")) or f.name == "class_miss_rates":
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise InvalidInput(f"DetectorFaults.{f.name}", "a finite number >= 0", repr(value))
        for name in ("miss_rate", "small_miss_rate", "truncated_miss_rate", "occluded_miss_rate", "confusion_rate",
                     "hard_instance_rate", "hard_miss_rate", "split_rate", "depth_edge_dropout", "depth_flying_rate",
                     "depth_dropout"):  # fmt: skip
            if getattr(self, name) > 1:
                raise InvalidInput(f"DetectorFaults.{name}", "a probability in [0, 1]", repr(getattr(self, name)))
        if self.score_min > self.score_max or self.spurious_score_min > self.spurious_score_max or self.score_max > 1:
            raise InvalidInput("DetectorFaults scores", "min <= max <= 1", f"{self.score_min}..{self.score_max}")

    @classmethod
    def none(cls) -> DetectorFaults:
        """A perfect detector (every visible instance, exact masks, score 1) and a perfect sensor."""
        return cls(
            miss_rate=0.0,
            small_miss_rate=0.0,
            min_area_px=1,
            truncated_miss_rate=0.0,
            occluded_miss_rate=0.0,
            class_miss_rates=(),
            hard_instance_rate=0.0,
            confusion_rate=0.0,
            split_rate=0.0,
            border_px=0.0,
            score_min=1.0,
            score_max=1.0,
            score_noise=0.0,
            spurious_rate=0.0,
            depth_sigma_a_m=0.0,
            depth_sigma_b=0.0,
            depth_edge_dropout=0.0,
            depth_flying_rate=0.0,
            depth_dropout=0.0,
            depth_min_m=None,
            depth_max_m=None,
            pose_noise_m=0.0,
            pose_noise_deg=0.0,
        )

    def replace(self, **changes: Any) -> DetectorFaults:
        return dataclasses.replace(self, **changes)


def frame_rng(seed: int, frame_id: str, stream: int, *extra: int) -> np.random.Generator:
    """The generator of one random stream of one frame: the same in any process and call order."""
    return np.random.default_rng([int(seed), zlib.crc32(frame_id.encode("utf-8")), stream, *extra])


def pose_noise(faults: DetectorFaults, seed: int, frame_id: str) -> np.ndarray:
    """(4, 4) rigid noise of a frame's reported pose: ``reported_cam2world = true_cam2world @ noise``."""
    noise = np.eye(4)
    if faults.pose_noise_m == 0 and faults.pose_noise_deg == 0:
        return noise
    rng = frame_rng(seed, frame_id, STREAM_POSE)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = math.radians(rng.normal(0.0, faults.pose_noise_deg))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    noise[:3, :3] = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    noise[:3, 3] = rng.normal(0.0, faults.pose_noise_m, 3)
    return noise


def reported_pose(true_cam2world: np.ndarray, faults: DetectorFaults, seed: int, frame_id: str) -> np.ndarray:
    """The pose a device reports for a frame taken at ``true_cam2world``."""
    return np.asarray(true_cam2world, np.float64) @ pose_noise(faults, seed, frame_id)


def true_pose(reported_cam2world: np.ndarray, faults: DetectorFaults, seed: int, frame_id: str) -> np.ndarray:
    """The true pose of a frame from its reported pose (inverse of ``reported_pose``)."""
    noise = pose_noise(faults, seed, frame_id)
    inverse = np.eye(4)
    inverse[:3, :3] = noise[:3, :3].T
    inverse[:3, 3] = -noise[:3, :3].T @ noise[:3, 3]
    return np.asarray(reported_cam2world, np.float64) @ inverse


def apply_depth_faults(depth_m: np.ndarray, faults: DetectorFaults, rng: np.random.Generator) -> np.ndarray:
    """A noisy copy of a true z-depth image (H, W) float32 (0 = no reading): axial noise growing with
    depth squared, dropouts and flying pixels on the far side of depth edges, random dropouts, range."""
    depth = np.array(depth_m, dtype=np.float32, copy=True)
    flat = depth.ravel()  # a view
    valid = depth > 0
    if faults.depth_edge_dropout > 0 or faults.depth_flying_rate > 0:
        # Far-side edge pixels: a 4-neighbour is nearer by more than the jump.
        near = np.where(valid, depth, np.float32(np.inf))
        nearest = np.full_like(near, np.inf)
        np.minimum(nearest[1:], near[:-1], out=nearest[1:])
        np.minimum(nearest[:-1], near[1:], out=nearest[:-1])
        np.minimum(nearest[:, 1:], near[:, :-1], out=nearest[:, 1:])
        np.minimum(nearest[:, :-1], near[:, 1:], out=nearest[:, :-1])
        jump = np.maximum(np.float32(faults.depth_edge_jump_m), np.float32(0.03) * depth)
        far = np.flatnonzero((valid & (depth - nearest > jump)).ravel())
        draw = rng.random(far.size)
        p_drop = faults.depth_edge_dropout
        drop = far[draw < p_drop]
        flying = far[(draw >= p_drop) & (draw < p_drop + (1 - p_drop) * faults.depth_flying_rate)]
        nearer = nearest.ravel()[flying]
        flat[flying] = nearer + rng.random(flying.size, dtype=np.float32) * (flat[flying] - nearer)
        flat[drop] = 0.0
    if faults.depth_sigma_a_m > 0 or faults.depth_sigma_b > 0:
        sigma = (
            np.float32(faults.depth_sigma_a_m)
            + np.float32(faults.depth_sigma_b) * (depth - np.float32(faults.depth_sigma_z0_m)) ** 2
        )
        depth += rng.standard_normal(depth.shape, dtype=np.float32) * sigma
    if faults.depth_dropout > 0:
        flat[rng.integers(0, flat.size, rng.binomial(flat.size, faults.depth_dropout))] = 0.0
    invalid = ~valid | (depth <= 0)
    if faults.depth_min_m is not None:
        invalid |= depth < faults.depth_min_m
    if faults.depth_max_m is not None:
        invalid |= depth > faults.depth_max_m
    depth[invalid] = 0.0
    return depth


def _perturb_mask(mask: np.ndarray, border_px: float, rng: np.random.Generator) -> np.ndarray:
    """The mask (H, W) bool with its border moved by a random offset plus smooth jitter (pixels)."""
    import cv2

    if border_px <= 0:
        return mask.copy()
    h, w = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    margin = int(math.ceil(3 * border_px)) + 2
    r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)
    c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)
    crop = mask[r0:r1, c0:c1].astype(np.uint8)
    inside = cv2.distanceTransform(crop, cv2.DIST_L2, 3)
    outside = cv2.distanceTransform(1 - crop, cv2.DIST_L2, 3)
    signed = outside - inside  # > 0 outside, < 0 inside, |.| >= 1 px from the border
    ch, cw = crop.shape
    coarse = rng.normal(0.0, 1.0, (max(2, ch // 16 + 2), max(2, cw // 16 + 2))).astype(np.float32)
    jitter = cv2.resize(coarse, (cw, ch), interpolation=cv2.INTER_CUBIC) * (0.6 * border_px)
    offset = rng.uniform(-border_px, border_px)
    out = np.zeros_like(mask)
    out[r0:r1, c0:c1] = signed < offset + jitter
    return out


def _box_in_camera(lo: np.ndarray, hi: np.ndarray, world2cam: np.ndarray) -> np.ndarray:
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return corners @ world2cam[:3, :3].T + world2cam[:3, 3]


@dataclass(frozen=True)
class _Visible:
    """A visible instance: its mask and how visible it is."""

    mask: np.ndarray
    area_px: int
    truncated: float  # fraction of its projected box outside the image
    occluded: float  # estimated fraction hidden by nearer things


def _visibility(
    mask: np.ndarray, depth_m: np.ndarray, lo: np.ndarray, hi: np.ndarray, world2cam: np.ndarray, intrinsics: Intrinsics
) -> tuple[float, float]:
    """(truncated, occluded) fractions of an instance from its GT box: the share of the box's image
    rectangle outside the image, and within the image the pixels nearer than the box (other things in
    front) weighted by how much of its rectangle the instance fills where unoccluded."""
    h, w = mask.shape
    corners = _box_in_camera(lo, hi, world2cam)
    z = corners[:, 2]
    if np.any(z <= 0.05):
        return 1.0, 0.0
    u = intrinsics.fx * corners[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * corners[:, 1] / z + intrinsics.cy
    u0, u1, v0, v1 = u.min(), u.max(), v.min(), v.max()
    full = max((u1 - u0) * (v1 - v0), 1e-9)
    cu0, cu1, cv0, cv1 = max(u0, 0.0), min(u1, float(w)), max(v0, 0.0), min(v1, float(h))
    inside = max(cu1 - cu0, 0.0) * max(cv1 - cv0, 0.0)
    truncated = float(np.clip(1.0 - inside / full, 0.0, 1.0))
    r0, r1, c0, c1 = int(cv0), int(math.ceil(cv1)), int(cu0), int(math.ceil(cu1))
    if r1 <= r0 or c1 <= c0:
        return truncated, 0.0
    window = depth_m[r0:r1, c0:c1]
    visible = int(mask[r0:r1, c0:c1].sum())
    front = int(np.count_nonzero((window > 0) & (window < z.min() - 0.02)))
    free = window.size - front
    fill = visible / free if free > 0 else 1.0
    hidden = front * fill
    occluded = hidden / (visible + hidden) if visible + hidden > 0 else 0.0
    return truncated, float(occluded)


@dataclass(frozen=True, eq=False)
class FrameTruth:
    """What the detector needs to know of a frame, compactly: the hit triangle of every pixel
    (zlib-compressed, -1 where no hit) and, per visible object instance, its (truncated, occluded)
    fractions."""

    shape: tuple[int, int]
    dtype: str
    triangle_zlib: bytes
    visibility: dict[int, tuple[float, float]]

    def triangle(self) -> np.ndarray:
        """(H, W) int32 hit triangle ids, -1 where no hit."""
        return np.frombuffer(zlib.decompress(self.triangle_zlib), self.dtype).reshape(self.shape).astype(np.int32)


def frame_truth(
    room: Room,
    triangle: np.ndarray,
    depth_m: np.ndarray,
    cam2world: np.ndarray,
    intrinsics: Intrinsics,
    instance: np.ndarray | None = None,
) -> FrameTruth:
    """The truth of a frame rendered at ``cam2world`` into ``triangle`` (H, W) ids and z-depth (H, W)
    (and its instance image, when at hand)."""
    triangle = np.asarray(triangle)
    if instance is None:
        instance = np.where(triangle >= 0, room.triangle_instance[np.maximum(triangle, 0)], 0)
    world2cam = np.linalg.inv(cam2world)
    objects = {o.instance_id: o for o in room.objects}
    visibility = {}
    for instance_id in np.flatnonzero(np.bincount(instance.ravel())):
        obj = objects.get(int(instance_id))
        if obj is not None:
            mask = instance == instance_id
            visibility[int(instance_id)] = _visibility(mask, depth_m, obj.aabb_min, obj.aabb_max, world2cam, intrinsics)
    dtype = np.int16 if len(room.triangles) < np.iinfo(np.int16).max else np.int32
    packed = np.ascontiguousarray(triangle, dtype=dtype)
    return FrameTruth(packed.shape, np.dtype(dtype).str, zlib.compress(packed.tobytes(), 1), visibility)


def truth_key(frame_id: str, cam2world: np.ndarray, intrinsics: Intrinsics, width: int, height: int) -> tuple:
    """What determines a frame's truth: its true pose (bit for bit), camera and size (and id)."""
    pose = np.ascontiguousarray(cam2world, dtype=np.float64).tobytes()
    return (frame_id, pose, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, int(width), int(height))


#: Frames a ``FrameTruths`` keeps by default (about 30 KB a VGA frame, so at most ~150 MB).
TRUTH_CACHE_FRAMES = 5000


class FrameTruths:
    """The truths of one room's simulated frames by ``truth_key``: ``simulate_sequence(truths=...)``
    records them as it renders and ``SimulatedDetector(truths=...)`` reads them, so that detecting a
    simulated frame needs no second ray cast. A bounded LRU; thread-safe."""

    def __init__(self, room: Room, max_frames: int = TRUTH_CACHE_FRAMES) -> None:
        if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1:
            raise InvalidInput("max_frames", "an int >= 1", describe(max_frames))
        self.room = room
        self.max_frames = max_frames
        self._truths: OrderedDict[tuple, FrameTruth] = OrderedDict()
        self._lock = threading.Lock()

    def record(self, key: tuple, truth: FrameTruth) -> None:
        with self._lock:
            self._truths[key] = truth
            self._truths.move_to_end(key)
            while len(self._truths) > self.max_frames:
                self._truths.popitem(last=False)

    def get(self, key: tuple) -> FrameTruth | None:
        with self._lock:
            return self._truths.get(key)

    def __len__(self) -> int:
        return len(self._truths)


def check_truths(truths: object, room: Room) -> FrameTruths | None:
    """``truths`` if it is None or a ``FrameTruths`` of ``room``; raises ``InvalidInput`` otherwise."""
    if truths is not None and (not isinstance(truths, FrameTruths) or truths.room is not room):
        raise InvalidInput("truths", "None or a FrameTruths of this room", describe(truths))
    return truths


def _surface_ids(room: Room) -> np.ndarray:
    """(T,) int32: triangles on the same plane (rounded to a millimetre) share an id."""
    v = room.vertices.astype(np.float64)
    a, b, c = (v[room.triangles[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    normal *= np.where(normal[:, [0]] + 2 * normal[:, [1]] + 4 * normal[:, [2]] < 0, -1.0, 1.0)  # one sign
    offset = np.einsum("ij,ij->i", normal, a)
    key = np.round(np.column_stack([normal * 1000, offset * 1000])).astype(np.int64)
    return np.unique(key, axis=0, return_inverse=True)[1].astype(np.int32).ravel()


class SimulatedDetector:
    """A ``arcloud.ports.Detector`` for frames of a generated room (see the module docstring).

    ``seed`` and ``faults`` must be those the frames were simulated with (``simulate_sequence``), so
    that the true pose of a frame is recovered from its reported one, and ``truths`` those they
    recorded (None: every frame is ray-cast again, with the same result). ``threads``: ray-casting
    threads (0: one per core; a worker process sharing the machine with others takes its share).
    Thread-safe."""

    def __init__(
        self,
        room: Room,
        faults: DetectorFaults = DetectorFaults(),
        *,
        seed: int = 0,
        threads: int = 0,
        truths: FrameTruths | None = None,
    ) -> None:
        if not isinstance(faults, DetectorFaults):
            raise InvalidInput("faults", "a DetectorFaults", type(faults).__name__)
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 0:
            raise InvalidInput("threads", "an int >= 0 (0: one per core)", describe(threads))
        self.threads = int(threads)
        self.room = room
        self.faults = faults
        self.seed = int(seed)
        self.truths = check_truths(truths, room)
        self._renderer: MeshRenderer | None = None  # built on the first frame with no recorded truth
        self._renderer_lock = threading.Lock()
        self._instance = room.triangle_instance
        self._clutter = room.triangle_clutter if room.triangle_clutter is not None else np.zeros_like(room.triangle_instance)
        self._objects = {o.instance_id: o for o in room.objects}
        self._clutter_kinds = {c.clutter_id: c.kind for c in room.clutter}
        self._surface = _surface_ids(room)
        self._hard = {
            o.instance_id: bool(
                np.random.default_rng([self.seed, STREAM_OBJECT, o.instance_id]).random() < faults.hard_instance_rate
            )
            for o in room.objects
        }
        self._class_miss = dict(faults.class_miss_rates)

    def true_pose(self, frame: Frame) -> np.ndarray:
        return true_pose(frame.cam2world, self.faults, self.seed, frame.frame_id)

    def truth(self, frame: Frame) -> FrameTruth:
        """The frame's truth: recorded in ``truths`` by ``simulate_sequence``, else ray-cast now."""
        height, width = frame.shape
        cam2world = self.true_pose(frame)
        truth = None
        if self.truths is not None:
            truth = self.truths.get(truth_key(frame.frame_id, cam2world, frame.intrinsics, width, height))
        if truth is None:
            hits = self._room_renderer().raycast(cam2world, frame.intrinsics, width, height, threads=self.threads)
            truth = frame_truth(self.room, hits.triangle, hits.depth_m, cam2world, frame.intrinsics)
        return truth

    def _room_renderer(self) -> MeshRenderer:
        with self._renderer_lock:
            if self._renderer is None:
                self._renderer = room_renderer(self.room)
            return self._renderer

    def detect(self, frame: Frame) -> list[Detection]:
        """Detections of the frame's visible objects with this detector's faults, best score first."""
        faults = self.faults
        truth = self.truth(frame)
        triangle = truth.triangle()
        hit = triangle >= 0
        tri = np.maximum(triangle, 0)
        instance = np.where(hit, self._instance[tri], 0)
        detections: list[Detection] = []
        areas = np.bincount(instance.ravel())
        for instance_id in np.flatnonzero(areas):
            if instance_id == 0 or instance_id not in self._objects or areas[instance_id] < faults.min_area_px:
                continue
            truncated, occluded = truth.visibility[int(instance_id)]
            seen = _Visible(instance == instance_id, int(areas[instance_id]), truncated, occluded)
            rng = frame_rng(self.seed, frame.frame_id, STREAM_INSTANCE, int(instance_id))
            detections += self._detect_instance(self._objects[int(instance_id)].label, seen, self._hard[int(instance_id)], rng)
        if faults.spurious_rate > 0:
            clutter = np.where(hit, self._clutter[tri], 0)
            surface = np.where(hit, self._surface[tri], -1)
            detections += self._spurious(instance, clutter, surface, frame_rng(self.seed, frame.frame_id, STREAM_SPURIOUS))
        detections.sort(key=lambda d: -d.score)
        return detections

    def _detect_instance(self, label: str, seen: _Visible, hard: bool, rng: np.random.Generator) -> list[Detection]:
        f = self.faults
        # Draw every number up front, so that each fault's draw does not depend on the others.
        u_miss, u_confuse, u_split, u_pick = rng.random(4)
        score_noise = rng.normal(0.0, 1.0)
        small = np.clip((f.small_area_px - seen.area_px) / max(f.small_area_px - f.min_area_px, 1), 0.0, 1.0)
        p_detect = (
            (1 - f.miss_rate)
            * (1 - f.small_miss_rate * small)
            * (1 - f.truncated_miss_rate * seen.truncated)
            * (1 - f.occluded_miss_rate * seen.occluded)
            * (1 - self._class_miss.get(label, 0.0))
            * (1 - f.hard_miss_rate * hard)
        )
        if u_miss >= p_detect:
            return []
        confused = u_confuse < min(1.0, f.confusion_rate * (3 if hard else 1))
        if confused:
            options = CONFUSIONS[label]
            label = options[int(u_pick * len(options)) % len(options)]
        quality = math.sqrt(min(seen.area_px / 20000.0, 1.0)) * (1 - 0.5 * seen.occluded) * (1 - 0.4 * seen.truncated)
        score = f.score_min + (f.score_max - f.score_min) * quality + f.score_noise * score_noise
        if confused:
            score *= 0.85
        score = float(np.clip(score, 0.05, 0.99 if f.score_max < 1 else 1.0))
        mask = _perturb_mask(seen.mask, f.border_px, rng)
        if u_split < f.split_rate and seen.area_px >= 4 * f.small_area_px:
            rows, cols = np.nonzero(mask)
            if len(rows) > 0:
                along_cols = np.ptp(cols) >= np.ptp(rows)
                cut = np.median(cols if along_cols else rows)
                coords = np.arange(mask.shape[1])[None, :] if along_cols else np.arange(mask.shape[0])[:, None]
                first, second = mask & (coords < cut), mask & (coords >= cut)
                return [Detection(label, score, first), Detection(label, float(score * rng.uniform(0.6, 0.95)), second)]
        if not mask.any():
            return []
        return [Detection(label, score, mask)]

    def _spurious(
        self, instance: np.ndarray, clutter: np.ndarray, surface: np.ndarray, rng: np.random.Generator
    ) -> list[Detection]:
        f = self.faults
        n = int(rng.poisson(f.spurious_rate))
        out: list[Detection] = []
        if n == 0:
            return out
        areas = np.bincount(clutter.ravel())
        lookalikes = [k for k in np.flatnonzero(areas[1:] >= 300) + 1 if self._clutter_kinds.get(int(k)) in CLUTTER_LOOKALIKES]
        h, w = instance.shape
        background = np.flatnonzero(((instance == 0) & (surface >= 0)).ravel())
        for _ in range(n):
            score = float(rng.uniform(f.spurious_score_min, f.spurious_score_max))
            if lookalikes and rng.random() < 0.6:
                k = int(lookalikes[int(rng.integers(len(lookalikes)))])
                labels = CLUTTER_LOOKALIKES[self._clutter_kinds[k]]
                label = labels[int(rng.integers(len(labels)))]
                mask = _perturb_mask(clutter == k, f.border_px, rng)
            else:
                if len(background) == 0:
                    continue
                centre = int(background[int(rng.integers(len(background)))])
                cy, cx = divmod(centre, w)
                ry, rx = rng.uniform(12, 70, 2)
                ys, xs = np.ogrid[:h, :w]
                blob = ((ys - cy) / ry) ** 2 + ((xs - cx) / rx) ** 2 <= 1.0
                mask = blob & (surface == surface[cy, cx]) & (instance == 0)  # on one wall, floor, ...
                label = CLASSES[int(rng.integers(len(CLASSES)))]
            if mask.sum() >= 100:
                out.append(Detection(label, score, mask))
        return out


__all__: Sequence[str] = (
    "CONFUSIONS",
    "CLUTTER_LOOKALIKES",
    "DetectorFaults",
    "SimulatedDetector",
    "FrameTruth",
    "FrameTruths",
    "check_truths",
    "apply_depth_faults",
    "frame_truth",
    "frame_rng",
    "pose_noise",
    "reported_pose",
    "true_pose",
    "truth_key",
)
