"""The core's value types.

Conventions:
- Frames are named in matrices: ``cam2world`` maps points from camera to world coordinates.
- Camera axes follow OpenCV: x right, y down, z forward (depth along +z).
- Units are in names: ``_m`` metres, ``_s`` seconds, ``_px`` pixels.
- World "up" is +z unless ``Params.up`` says otherwise (ScanNet and the simulator are z-up).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import operator
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, TypeGuard

import numpy as np

from arcloud.core.errors import InvalidInput
from arcloud.core.gravity import Gravity

#: The object classes arcloud detects (the paper's five). Label indices refer to this tuple.
CLASSES: tuple[str, ...] = ("chair", "table", "laptop", "couch", "tv")
N_CLASSES = len(CLASSES)
CLASS_INDEX: dict[str, int] = {name: i for i, name in enumerate(CLASSES)}

#: A frame's vote for the wall behind a screen (``core.walls``): (direction in whole degrees, (frames, offset in mm)).
WallVote = tuple[int, tuple[int, int]]


@dataclass(frozen=True, slots=True)
class Intrinsics:
    """Pinhole intrinsics in pixels of the depth image."""

    fx: float
    fy: float
    cx: float
    cy: float

    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False, slots=True)
class Frame:
    """One validated RGB-D frame. Build it with ``arcloud.core.checks.make_frame``.

    rgb: (H, W, 3) uint8. depth_m: (H, W) float32 metres, 0 where invalid. cam2world: (4, 4) float64,
    the depth camera's pose. ``intrinsics`` are the depth camera's.

    Colour and depth from one sensor are often not registered (Kinect v1: another focal length and a
    few centimetres of baseline), so a mask drawn on the colour image is shifted by tens of pixels
    against the depth image near its borders. ``rgb_intrinsics`` (the colour camera's; None: the
    images are registered pixel for pixel) and ``depth2rgb`` ((4, 4) rigid, depth camera to colour
    camera coordinates; None: identity) let the voxelization look each depth pixel up in the colour
    image where it really lands.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    intrinsics: Intrinsics
    cam2world: np.ndarray
    timestamp_s: float
    map_id: str
    device_id: str
    frame_id: str
    rgb_intrinsics: Intrinsics | None = None
    depth2rgb: np.ndarray | None = None

    @property
    def registered(self) -> bool:
        """Whether colour pixel (u, v) sees what depth pixel (u, v) measures."""
        return self.rgb_intrinsics is None and self.depth2rgb is None

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth_m.shape

    @property
    def key(self) -> str:
        """Unique name of the frame within its map (for idempotent processing)."""
        return f"{self.device_id}/{self.frame_id}"


@dataclass(frozen=True, eq=False, slots=True)
class Detection:
    """A 2D instance: one of ``CLASSES``, a score in [0, 1] and an (H, W) bool mask of the frame."""

    label: str
    score: float
    mask: np.ndarray


@dataclass(frozen=True, eq=False, slots=True)
class VoxelDetection:
    """A detection back-projected into the world: sorted unique packed voxel keys (int64), and
    ``colors`` (N, 3) uint8 aligned with them: the mean RGB of the samples in each voxel (None: unknown).
    ``view_weight`` in (0, 1]: how well the frame saw it (``core.voxels.view_weights``); its label vote
    is its score times this. ``wall_vote``: where the frame found the wall behind it (``core.walls``), or None."""

    label_index: int
    score: float
    keys: np.ndarray
    colors: np.ndarray | None = None
    view_weight: float = 1.0
    wall_vote: WallVote | None = None


@dataclass(frozen=True, eq=False, slots=True)
class AABB:
    """Axis-aligned box: min and max corners, (3,) each, metres."""

    min: np.ndarray
    max: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return (self.min + self.max) / 2

    @property
    def size(self) -> np.ndarray:
        return self.max - self.min


@dataclass(frozen=True, eq=False, slots=True)
class OBB:
    """Gravity-aligned oriented box: centre (3,), full size along its own axes (3,), and ``rotation``
    (3, 3) whose columns are the box axes in world coordinates (box2world); ``yaw_rad`` about up."""

    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    yaw_rad: float


@dataclass(frozen=True, eq=False, slots=True)
class LabelledBox:
    """An axis-aligned box of one class, as evaluation, datasets and pictures use it: ``label``, ``min``
    and ``max`` corners ((3,) float64 each, metres, stored as read-only copies) and a ``score`` (1 for
    ground truth)."""

    label: str
    min: np.ndarray
    max: np.ndarray
    score: float = 1.0

    def __post_init__(self) -> None:
        from arcloud.core.checks import check_finite_number, describe  # checks imports this module

        if not isinstance(self.label, str) or not self.label:
            raise InvalidInput("LabelledBox.label", "a non-empty class name", describe(self.label))
        lo = _check_corner("LabelledBox.min", self.min)
        hi = _check_corner("LabelledBox.max", self.max)
        if np.any(hi < lo):
            raise InvalidInput("LabelledBox.max", f"max >= min on every axis (min {lo.tolist()})", hi.tolist())
        object.__setattr__(self, "min", lo)
        object.__setattr__(self, "max", hi)
        object.__setattr__(self, "score", check_finite_number("LabelledBox.score", self.score))

    @classmethod
    def from_aabb(cls, label: str, aabb: AABB, score: float = 1.0) -> LabelledBox:
        return cls(label, aabb.min, aabb.max, score)

    @property
    def center(self) -> np.ndarray:
        return (self.min + self.max) / 2

    @property
    def size(self) -> np.ndarray:
        return self.max - self.min

    def __repr__(self) -> str:
        return f"LabelledBox({self.label!r}, min={self.min.tolist()}, max={self.max.tolist()}, score={self.score:.4g})"


def _check_corner(field_name: str, value: object) -> np.ndarray:
    """A read-only (3,) float64 copy of finite corner coordinates."""
    try:
        corner = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInput(field_name, "3 numbers", repr(value)[:80]) from exc
    if corner.shape != (3,):
        raise InvalidInput(field_name, "shape (3,)", f"shape {corner.shape}")
    if not np.all(np.isfinite(corner)):
        raise InvalidInput(field_name, "finite values", corner.tolist())
    corner.setflags(write=False)
    return corner


@dataclass(frozen=True, eq=False, slots=True)
class MapObject:
    """One object of the map: sparse voxels with occupancy weights and label votes, plus what the
    refinement derives from them (label, score, boxes).

    keys: (N,) int64 sorted unique packed voxel keys. weights: (N,) float32 occupancy weights: the
    number of detections of this object that covered the voxel. votes: (N, N_CLASSES) float32
    score-weighted label votes per voxel. seen: (N,) float32, the number of those frames in which the
    voxel was visible (in view and not occluded) or covered; weights / seen is the voxel's occupancy.
    None means unknown and reads as equal to ``weights``. colors: (N, 3) uint8, each voxel's mean RGB
    over the pixels of the detections that covered it, weighted as ``weights`` count them (rounded to
    whole levels at each fusion); None means unknown (objects stored before colours: codec version 2).
    Colours are carried along, never used in a decision.

    Immutable: a change is a new object (``replace``). Construction makes the five voxel arrays
    read-only (the arrays themselves, not copies: hand over arrays you no longer write to), so one
    object can be shared by the store, the step and its events; ``floor_votes`` is never edited either.
    """

    id: int
    keys: np.ndarray
    weights: np.ndarray
    votes: np.ndarray
    seen: np.ndarray | None = None
    colors: np.ndarray | None = None
    n_frames: int = 0
    devices: frozenset[str] = frozenset()
    score_sum: float = 0.0
    version: int = 0
    created_at_s: float = 0.0
    updated_at_s: float = 0.0
    label: str = ""
    score: float = 0.0
    aabb: AABB | None = None
    obb: OBB | None = None
    bounds: AABB | None = None  # world bounds of all voxels (the spatial index uses these)
    confirmed: bool = False  # served to clients by default (see ``arcloud.core.confirm``)
    floor_votes: dict[int, int] = dataclasses.field(default_factory=dict)  # height bin -> frames (core.floor)
    wall_votes: dict[int, tuple[int, int]] = dataclasses.field(default_factory=dict)  # direction -> frames, offset (core.walls)
    n_missed: int = 0  # frames that saw it in view, unoccluded, and detected nothing there
    n_gone: int = 0  # frames that saw its place empty since it was last seen there (core.step.count_misses)
    label_purity: float = 0.0  # share of the box voxels' occupancy voting for its label (core.confirm)
    # id -> frames that detected that object of its class apart from it, in the same frame (core.step.mark_apart)
    apart: dict[int, int] = dataclasses.field(default_factory=dict)
    # id -> frames whose one mask, matched to this object, also covered that one, held apart (core.fusion.held_apart)
    # or a seat and back not yet joined (core.step.seat_and_back)
    spanned: dict[int, int] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        for array in (self.keys, self.weights, self.votes, self.seen, self.colors):
            if array is not None:
                array.flags.writeable = False

    @property
    def n_voxels(self) -> int:
        return int(self.keys.size)

    @property
    def seen_counts(self) -> np.ndarray:
        """``seen``, or ``weights`` where it is unknown."""
        return self.weights if self.seen is None else self.seen

    def replace(self, **changes: object) -> MapObject:
        """``dataclasses.replace(self, **changes)`` at a sixth of its cost (the step makes dozens a
        frame): the fields read at once (``attrgetter``) and set slot by slot, not through the frozen
        ``__init__``."""
        new = object.__new__(MapObject)
        for set_field, value in zip(_SET_MAP_OBJECT_FIELDS, _GET_MAP_OBJECT_FIELDS(self)):
            set_field(new, value)
        for name, value in changes.items():
            object.__setattr__(new, name, value)  # AttributeError for a name that is no field
        if not _VOXEL_ARRAYS.isdisjoint(changes):
            new.__post_init__()
        return new


_GET_MAP_OBJECT_FIELDS = operator.attrgetter(*(f.name for f in dataclasses.fields(MapObject)))
_SET_MAP_OBJECT_FIELDS = tuple(MapObject.__dict__[f.name].__set__ for f in dataclasses.fields(MapObject))
_VOXEL_ARRAYS = frozenset(("keys", "weights", "votes", "seen", "colors"))


@dataclass(frozen=True, eq=False, slots=True)
class ObjectMeta:
    """An object without its voxels: what listing the map needs (a ``MapObject`` has the same fields)."""

    id: int
    label: str
    score: float
    version: int
    n_voxels: int
    n_frames: int
    devices: frozenset[str]
    score_sum: float
    created_at_s: float
    updated_at_s: float
    aabb: AABB | None
    obb: OBB | None
    bounds: AABB | None
    confirmed: bool = False
    floor_votes: dict[int, int] = dataclasses.field(default_factory=dict)
    wall_votes: dict[int, tuple[int, int]] = dataclasses.field(default_factory=dict)
    label_purity: float = 0.0
    apart: dict[int, int] = dataclasses.field(default_factory=dict)
    spanned: dict[int, int] = dataclasses.field(default_factory=dict)

    @property
    def n_devices(self) -> int:
        return len(self.devices)


#: What a change does to one object: ``created``, ``updated`` (a new state), ``merged`` (into another object),
#: ``deleted`` (gone without a trace: a phantom, or refined to nothing), ``retired`` (seen gone: it left the
#: room, and the map's history keeps it for a while).
EventKind = Literal["created", "updated", "merged", "deleted", "retired"]


@dataclass(frozen=True, eq=False, slots=True)
class ObjectEvent:
    """A change to one object of the map (``EventKind``). ``object`` is the new state (None for merged,
    deleted and retired): the whole ``MapObject`` as the step made it, or its ``ObjectMeta`` as a change
    log gives it back; a merged object names the one it was merged into in ``merged_into``.
    ``was_confirmed``: whether the object was confirmed (served) before this change, so that a listener
    to the served map can tell an object leaving it from one it never had."""

    kind: EventKind
    map_id: str
    object_id: int
    object: MapObject | ObjectMeta | None = None
    merged_into: int | None = None
    was_confirmed: bool = False


@dataclass(frozen=True)  # not slots: it keeps what it derives (``gravity``) beside its fields
class Params:
    """Every tunable of the algorithm, frozen; configure once and pass down.

    What follows from the fields is worked out once, when the parameters are built: ``gravity`` (the
    rotation ``up`` implies, ``core.gravity``)."""

    # Voxelization
    voxel_size_m: float = 0.05
    depth_min_m: float = 0.1
    depth_max_m: float = 5.0
    erode_px: int = 2
    min_voxels_per_detection: int = 8
    # Masks are sampled every n-th pixel row and column, n per frame the largest that still gives a voxel
    # at the frame's near depth (5th percentile) two samples per edge, and at most this (1: every pixel)
    pixel_stride_max_px: int = 4
    # Depth cleanup of each mask (core.voxels.front_samples); layer_margin_m None turns it off
    layer_jump_m: float = 0.03
    layer_jump_rel: float = 0.04
    layer_min_fraction: float = 0.25
    layer_margin_m: float | None = 0.1
    layer_touch_m: float = 0.15
    layer_classes: tuple[str, ...] = ("chair", "table", "laptop")  # see core.voxels.front_samples
    # The wall behind a screen (core.voxels.off_wall_samples); wall_margin_m None turns it off
    wall_classes: tuple[str, ...] = ("tv",)
    wall_margin_m: float | None = 0.12
    wall_screen_depth_m: float = 0.1
    wall_front_share: float = 0.5
    wall_depth_share: float = 0.3
    # Association (cost = 1 - overlap; overlap: the smaller set's voxels on the other, those beside it a half,
    # over its size: core.associate)
    association_min_overlap: float = 0.15
    association_tolerance_voxels: int = 1
    class_aware: bool = True
    class_mismatch_penalty: float = 0.3
    class_mismatch_min_overlap: float = 0.6
    split_min_frames: int = 3
    split_classes: tuple[str, ...] = ("chair", "laptop", "tv")  # see core.associate.Association
    apart_min_frames: int = 3  # detected apart in this many frames, two objects stay two (core.fusion.seen_apart; 0: off)
    # Label votes weighted by how well each view saw the object (core.voxels.view_weights)
    view_truncated_weight: float = 0.5  # a mask touching the image border (the object is cut off)
    view_full_mask_share: float = 0.01  # a mask covering less of the image weighs in proportion
    view_far_m: float = 3.0  # a view from farther weighs in proportion (view_far_m / median depth)
    view_oblique_min: float = 0.3  # a flat object seen edge-on weighs this (face-on 1; 1: no angle weighting)
    # Fusion and refinement
    visibility_tolerance_m: float = 0.1
    prune_min_seen: float = 10.0
    prune_max_occupancy: float = 0.1
    box_rel_weight: float = 0.05
    box_min_occupancy: float = 0.4
    min_component_fraction: float = 0.2
    merge_min_overlap: float = 0.3
    merge_min_overlap_parts: float = 0.1  # for classes outside split_classes: see core.fusion.find_duplicates
    merge_min_box_containment: float = 0.6
    merge_spanned_min_footprint: float = 0.25  # pieces one mask spans: see core.step.joined_by_masks
    score_support_frames: float = 3.0
    implausible_score_factor: float = 0.3
    # Confirmation (see core.confirm): what an object needs to be served by default
    confirm_min_frames: int = 3
    confirm_min_detection_rate: float = 0.4
    confirm_min_score: float = 0.2
    confirm_evidence_frames: int = 15  # detected in this many frames: the score need not reach confirm_min_score (0: off)
    # Phantoms (core.confirm.is_phantom): seen in this many frames, detected in fewer than this share (0: never): deleted
    discard_min_sightings: int = 50
    discard_max_detection_rate: float = 0.1
    miss_min_visible: float = 0.3  # an undetected object counts as missed when this share of it is visible
    rescore_write_delta: float = 0.05  # a miss rewrites an object when its score moves by more (else: a counter)
    # Change over time (core.step.count_misses): an undetected object whose place a frame sees empty
    gone_min_free: float = 0.5  # seen gone when this share of its upper part has depth measured clearly behind it
    gone_above_base_m: float = 0.08  # its upper part: what lies more than this above its base (10th percentile height)
    retire_min_gone_frames: int = 3  # seen gone in this many frames since last seen there: removed (0: never)
    # Floor (core.floor): found per frame, voted per object; floor-standing classes reach it
    floor_bin_m: float = 0.04
    floor_max_tilt_deg: float = 15.0
    floor_min_samples: int = 30
    floor_min_share: float = 0.05
    floor_min_below_camera_m: float = 0.9
    floor_min_votes: int = 2
    floor_min_vote_share: float = 0.25
    floor_clearance_m: float = 0.04
    floor_ring_margin_m: float = 0.12  # a frame votes for the floor under an object when it sees the floor beside it:
    floor_ring_min_seen: int = 1  # this many of 8 points around its footprint, this far outside (0: no check)
    floor_standing: tuple[str, ...] = ("chair", "table", "couch")
    floor_reach_max_m: float = 1.0
    # Boxes: voxel centres, grown by this many voxels per side (0: centre to centre, which is unbiased
    # for surfaces: an extreme voxel's centre is within half a voxel of the true extreme either way)
    box_pad_voxels: float = 0.0
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    world2aligned: tuple[tuple[float, ...], ...] | None = None
    # Store
    index_cell_m: float = 1.0
    lock_ttl_s: float = 10.0
    lock_timeout_s: float = 30.0

    def __post_init__(self) -> None:
        check_params(self)
        object.__setattr__(self, "_gravity", Gravity.of(self.up))

    @property
    def gravity(self) -> Gravity:
        """The rotation that ``up`` implies (read-only, shared by everything these parameters reach)."""
        return self._gravity  # type: ignore[attr-defined]  # set in __post_init__, kept out of the dataclass's fields

    def replace(self, **changes: Any) -> Params:
        return dataclasses.replace(self, **changes)


#: What each field of ``Params`` must hold (``check_params``), by kind: the expectation said when not.
_PARAM_EXPECTED = {
    "positive": "a finite number > 0",
    "non-negative": "a finite number >= 0",
    "optional non-negative": "None or a finite number >= 0",
    "fraction": "a number in [0, 1]",
    "count": "an integer >= 0",
    "stride": "an integer >= 1",
    "flag": "True or False",
    "classes": f"a tuple of class names from {CLASSES}",
    "tilt": "degrees in [0, 90]",
    "up": "a tuple of 3 finite numbers, not all 0",
    "transform": "None or a (4, 4) tuple of tuples of finite numbers",
}
_PARAM_KINDS: dict[str, str] = {
    **dict.fromkeys(
        (
            "voxel_size_m",
            "depth_min_m",
            "depth_max_m",
            "layer_touch_m",
            "wall_screen_depth_m",
            "score_support_frames",
            "floor_bin_m",
            "index_cell_m",
            "lock_ttl_s",
        ),
        "positive",
    ),
    **dict.fromkeys(
        (
            "layer_jump_m",
            "layer_jump_rel",
            "class_mismatch_penalty",
            "visibility_tolerance_m",
            "gone_above_base_m",
            "prune_min_seen",
            "floor_min_below_camera_m",
            "floor_clearance_m",
            "floor_ring_margin_m",
            "view_far_m",
            "floor_reach_max_m",
            "box_pad_voxels",
            "lock_timeout_s",
        ),
        "non-negative",
    ),
    **dict.fromkeys(("layer_margin_m", "wall_margin_m"), "optional non-negative"),
    **dict.fromkeys(
        (
            "layer_min_fraction",
            "wall_front_share",
            "wall_depth_share",
            "association_min_overlap",
            "class_mismatch_min_overlap",
            "prune_max_occupancy",
            "box_rel_weight",
            "box_min_occupancy",
            "min_component_fraction",
            "merge_min_overlap",
            "merge_min_box_containment",
            "merge_min_overlap_parts",
            "merge_spanned_min_footprint",
            "implausible_score_factor",
            "confirm_min_detection_rate",
            "confirm_min_score",
            "discard_max_detection_rate",
            "miss_min_visible",
            "rescore_write_delta",
            "gone_min_free",
            "floor_min_share",
            "floor_min_vote_share",
            "view_truncated_weight",
            "view_full_mask_share",
            "view_oblique_min",
        ),
        "fraction",
    ),
    **dict.fromkeys(
        (
            "erode_px",
            "min_voxels_per_detection",
            "association_tolerance_voxels",
            "split_min_frames",
            "apart_min_frames",
            "confirm_evidence_frames",
            "confirm_min_frames",
            "discard_min_sightings",
            "retire_min_gone_frames",
            "floor_min_samples",
            "floor_min_votes",
            "floor_ring_min_seen",
        ),
        "count",
    ),
    "pixel_stride_max_px": "stride",
    "class_aware": "flag",
    **dict.fromkeys(("layer_classes", "wall_classes", "split_classes", "floor_standing"), "classes"),
    "floor_max_tilt_deg": "tilt",
    "up": "up",
    "world2aligned": "transform",
}


def _is_number(value: object) -> TypeGuard[numbers.Real]:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _holds(kind: str, value: object) -> bool:
    """Whether ``value`` is of ``kind`` (a key of ``_PARAM_EXPECTED``)."""
    if kind in ("positive", "non-negative", "fraction", "tilt"):
        if not _is_number(value):
            return False
        number = float(value)
        return {"positive": number > 0, "non-negative": number >= 0, "fraction": 0 <= number <= 1, "tilt": 0 <= number <= 90}[
            kind
        ]
    if kind == "optional non-negative":
        return value is None or _holds("non-negative", value)
    if kind in ("count", "stride"):
        return isinstance(value, numbers.Integral) and not isinstance(value, bool) and int(value) >= (0 if kind == "count" else 1)
    if kind == "flag":
        return isinstance(value, bool)
    if kind == "classes":
        return isinstance(value, tuple) and all(name in CLASS_INDEX for name in value)
    if kind == "up":
        return isinstance(value, tuple) and len(value) == 3 and all(map(_is_number, value)) and any(float(x) != 0 for x in value)
    if kind == "transform":
        return value is None or (
            isinstance(value, tuple)
            and len(value) == 4
            and all(isinstance(row, tuple) and len(row) == 4 and all(map(_is_number, row)) for row in value)
        )
    raise AssertionError(f"unknown kind {kind}")


def check_param_value(field: str, kind: str, value: object) -> None:
    """Raise ``InvalidInput(field, ...)`` unless ``value`` is of ``kind`` (a key of ``_PARAM_EXPECTED``)."""
    if not _holds(kind, value):
        raise InvalidInput(field, _PARAM_EXPECTED[kind], repr(value))


def check_params(params: Params) -> None:
    """Raise ``InvalidInput`` for the first field of ``params`` out of its range (see ``_PARAM_KINDS``),
    or a depth range that is empty."""
    for field in dataclasses.fields(params):
        check_param_value(f"Params.{field.name}", _PARAM_KINDS[field.name], getattr(params, field.name))
    if params.depth_max_m <= params.depth_min_m:
        raise InvalidInput("Params.depth_max_m", f"more than depth_min_m ({params.depth_min_m})", repr(params.depth_max_m))


def params_from_json(fields: Mapping[str, object], field: str = "params") -> Params:
    """``Params`` with these fields set, as a decoded JSON object gives them (every command's ``--params``,
    ``$ARCLOUD_PARAMS`` and the service's ``params`` setting): lists become tuples, integers become floats
    where the field holds numbers, None stands for an optional field left unset. ``InvalidInput`` names the
    first wrong field (``field.name``), what it expected and what came."""
    known = {f.name for f in dataclasses.fields(Params)}
    values: dict[str, Any] = {}
    for name, value in fields.items():
        if name not in known:
            raise InvalidInput(field, f"fields of Params ({', '.join(sorted(known))})", repr(name))
        kind = _PARAM_KINDS[name]
        value = _tuples(value)
        check_param_value(f"{field}.{name}", kind, value)
        values[name] = _as_floats(value) if kind in _NUMBER_KINDS else value
    try:
        return Params(**values)
    except InvalidInput as exc:  # a combination of fields (check_params): named as given here
        raise InvalidInput(field + exc.field.removeprefix("Params"), exc.expected, exc.got) from None


#: Kinds of ``Params`` field that hold numbers (or None): a JSON integer there is read as a float.
_NUMBER_KINDS = frozenset(("positive", "non-negative", "optional non-negative", "fraction", "tilt", "up", "transform"))


def _tuples(value: object) -> object:
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _as_floats(value: Any) -> Any:
    """None, a number or nested tuples of numbers, with every number a float."""
    if value is None:
        return None
    return tuple(_as_floats(v) for v in value) if isinstance(value, tuple) else float(value)


def empty_object(object_id: int) -> MapObject:
    """An object with no voxels yet."""
    return MapObject(
        id=object_id,
        keys=np.empty(0, np.int64),
        weights=np.empty(0, np.float32),
        votes=np.empty((0, N_CLASSES), np.float32),
        seen=np.empty(0, np.float32),
        colors=np.empty((0, 3), np.uint8),
    )


__all__ = [
    "AABB",
    "CLASSES",
    "CLASS_INDEX",
    "Detection",
    "EventKind",
    "Frame",
    "Intrinsics",
    "MapObject",
    "N_CLASSES",
    "OBB",
    "ObjectEvent",
    "ObjectMeta",
    "Params",
    "VoxelDetection",
    "empty_object",
    "params_from_json",
]
