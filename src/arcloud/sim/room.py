"""Procedural rooms: a z-up box room with furniture of the five classes, clutter and exact GT boxes.

World frame: z up, the floor is z = 0 over [0, size_x] x [0, size_y], the ceiling at z = size_z.
Every object is built from boxes, cylinders and ellipsoids in its own frame (origin on the floor at
the centre of its footprint, front towards -y), then turned about z (yaw) and moved into place.
Objects never interpenetrate: their axis-aligned boxes are kept apart (stacked ones only touch),
and furniture groups keep a walkway between them so that a user can walk around.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from arcloud.core.types import CLASSES, LabelledBox
from arcloud.errors import InvalidInput
from arcloud.sim.layout import Layout, PlacementFailed, check_counts, default_counts, layout_room, office_layout
from arcloud.sim.primitives import Part
from arcloud.virtual_camera.render import MeshRenderer
from arcloud.virtual_camera.walk import WalkStyle, plan_walk

log = logging.getLogger(__name__)

DEFAULT_SIZE_M = (8.0, 6.0, 2.7)
#: Anything whose bottom is below this height blocks a walking user (metres).
HEAD_CLEARANCE_M = 2.0


@dataclass(frozen=True)
class RoomObject:
    """One object of a class in ``CLASSES`` with its exact axis-aligned GT box in the world (z-up)."""

    instance_id: int
    label: str
    aabb_min: np.ndarray = field(compare=False)
    aabb_max: np.ndarray = field(compare=False)
    yaw_rad: float = 0.0

    @property
    def center(self) -> np.ndarray:
        return (self.aabb_min + self.aabb_max) / 2

    @property
    def size(self) -> np.ndarray:
        return self.aabb_max - self.aabb_min

    @property
    def box(self) -> LabelledBox:
        """The object's ground-truth box, for evaluation."""
        return LabelledBox(self.label, self.aabb_min, self.aabb_max)


@dataclass(frozen=True)
class ClutterItem:
    """Background geometry that is no object of ``CLASSES`` (cabinet, shelf, plant, box, lamp, door, ...)."""

    clutter_id: int
    kind: str
    aabb_min: np.ndarray = field(compare=False)
    aabb_max: np.ndarray = field(compare=False)


@dataclass(frozen=True, eq=False)
class Room:
    """A generated room: its mesh with per-triangle colours and instance ids, and its objects.

    vertices: (V, 3) float32 world metres. triangles: (T, 3) int32. triangle_colors: (T, 3) uint8.
    triangle_instance: (T,) int32, the ``instance_id`` of the object a triangle belongs to, 0 for
    background (floor, walls, ceiling, clutter). triangle_clutter: (T,) int32, ``clutter_id`` of the
    clutter item a triangle belongs to, 0 otherwise. size_m: (3,) x and y extent from the origin, height.
    """

    seed: int
    size_m: np.ndarray
    objects: tuple[RoomObject, ...]
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_colors: np.ndarray
    triangle_instance: np.ndarray
    clutter: tuple[ClutterItem, ...] = ()
    triangle_clutter: np.ndarray | None = None

    @property
    def floor_min_xy(self) -> np.ndarray:
        return np.zeros(2)

    @property
    def floor_max_xy(self) -> np.ndarray:
        return np.asarray(self.size_m[:2], dtype=np.float64)

    def obstacles_xy(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(min_xy, max_xy) footprints of every object and clutter item a walking user must avoid."""
        boxes = [(o.aabb_min, o.aabb_max) for o in self.objects]
        boxes += [(c.aabb_min, c.aabb_max) for c in self.clutter]
        return [(lo[:2].copy(), hi[:2].copy()) for lo, hi in boxes if lo[2] < HEAD_CLEARANCE_M]

    def object(self, instance_id: int) -> RoomObject:
        for obj in self.objects:
            if obj.instance_id == instance_id:
                return obj
        raise KeyError(instance_id)


def generate_room(seed: int, *, size_m: Sequence[float] = DEFAULT_SIZE_M, counts: Mapping[str, int] | None = None) -> Room:
    """A furnished room, the same for the same arguments.

    size_m: (x, y, height) in metres; the floor spans [0, x] x [0, y]. counts: objects per class
    (classes left out get none); by default 2-3 tables with two chairs each, 2-3 laptops on the tables,
    2 couches against walls and 2 TVs (on low cabinets or wall-mounted). Raises ``InvalidInput`` when
    the objects do not fit the room."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidInput("seed", "an integer >= 0", repr(seed))
    size = np.asarray(size_m, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or np.any(size[:2] < 3.0) or not 2.2 <= size[2] <= 5.0:
        raise InvalidInput("size_m", "(x, y, height) with x, y >= 3 m and height 2.2-5 m", np.array2string(size))
    rng = np.random.default_rng(seed)
    wanted = check_counts(counts) if counts is not None else default_counts(rng)
    for attempt in range(40):
        try:
            layout = layout_room(rng, size, wanted)
            break
        except PlacementFailed as exc:
            log.debug("room seed %d: layout attempt %d failed to place a %s", seed, attempt, exc)
    else:
        raise InvalidInput("counts", f"objects that fit a {size[0]:g} x {size[1]:g} m room", repr(wanted))
    return _build_room(seed, size, layout)


#: The office's (x, y, height) in metres.
OFFICE_SIZE_M = (5.0, 4.2, 2.6)


def office_room(seed: int) -> Room:
    """The office of ``office_layout`` (desks pushed together, monitors side by side and back to back),
    the same for the same seed."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidInput("seed", "an integer >= 0", repr(seed))
    size = np.asarray(OFFICE_SIZE_M, dtype=np.float64)
    return _build_room(seed, size, office_layout(np.random.default_rng([seed, 20]), size))


def _build_room(seed: int, size: np.ndarray, layout: Layout) -> Room:
    vertices, triangles, colors, instance, clutter_ids = [], [], [], [], []
    objects: list[RoomObject] = []
    clutter: list[ClutterItem] = []
    offset = 0
    rng = np.random.default_rng([seed, 1])  # colour noise only, independent of the layout draws

    def emit(parts: Sequence[Part], instance_id: int, clutter_id: int) -> None:
        nonlocal offset
        for p in parts:
            vertices.append(p.vertices)
            triangles.append(p.triangles + offset)
            noise = rng.integers(-5, 6, size=(1, 3))  # per part: faces of a part stay even
            colors.append(np.clip(p.colors.astype(np.int16) + noise, 0, 255).astype(np.uint8))
            instance.append(np.full(len(p.triangles), instance_id, np.int32))
            clutter_ids.append(np.full(len(p.triangles), clutter_id, np.int32))
            offset += len(p.vertices)

    emit(layout.structure, 0, 0)
    # Objects in a stable class order so that instance ids read naturally.
    ordered = sorted((i for i in layout.items if i.label is not None), key=lambda i: CLASSES.index(i.label or ""))
    for k, item in enumerate(ordered, start=1):
        emit(item.parts, k, 0)
        objects.append(RoomObject(k, item.label or "", item.lo, item.hi, yaw_rad=float(item.yaw_rad)))
    for item in layout.items:
        if item.label is None and item.solid:
            clutter.append(ClutterItem(len(clutter) + 1, item.kind or "clutter", item.lo, item.hi))
            emit(item.parts, 0, len(clutter))
    triangle_clutter = np.concatenate(clutter_ids)
    room = Room(
        seed=seed,
        size_m=size,
        objects=tuple(objects),
        vertices=np.concatenate(vertices).astype(np.float32),
        triangles=np.concatenate(triangles).astype(np.int32),
        triangle_colors=np.concatenate(colors),
        triangle_instance=np.concatenate(instance),
        clutter=tuple(clutter),
        triangle_clutter=triangle_clutter,
    )
    for array in (room.size_m, room.vertices, room.triangles, room.triangle_colors, room.triangle_instance, triangle_clutter):
        array.flags.writeable = False
    log.debug("room seed %d: %d objects, %d clutter items, %d triangles", seed, len(objects), len(clutter), len(room.triangles))
    return room


#: Objects moved by ``rearranged_room`` keep this gap (metres) to everything else, walls included.
MOVE_GAP_M = 0.1
#: Something whose bottom is within this of an object's top rests on it (metres).
RESTS_ON_M = 0.02


def rearranged_room(
    room: Room, shifts_xy: Mapping[int, Sequence[float] | np.ndarray] | None = None, removed: Sequence[int] = ()
) -> Room:
    """The room after someone rearranged it: the objects of ``shifts_xy`` (instance id -> (dx, dy),
    metres) slid along the floor, the objects of ``removed`` taken out; everything else as it was (seed,
    instance ids, the rest of the mesh). Raises ``InvalidInput`` for an unknown id, an object that
    something rests on (a table holding a laptop), or a move that leaves the floor or comes within
    ``MOVE_GAP_M`` of another object or clutter item."""
    shifts = {int(k): np.asarray(v, np.float64) for k, v in (shifts_xy or {}).items()}
    gone = {int(i) for i in removed}
    known = {o.instance_id for o in room.objects}
    for instance_id in sorted(set(shifts) | gone):
        if instance_id not in known:
            raise InvalidInput("instance id", f"one of the room's objects {sorted(known)}", instance_id)
    for instance_id, shift in shifts.items():
        if shift.shape != (2,) or not np.all(np.isfinite(shift)):
            raise InvalidInput(f"shifts_xy[{instance_id}]", "(dx, dy) in metres", repr(shift.tolist()))
    if gone & set(shifts):
        raise InvalidInput("removed", "objects not also moved", sorted(gone & set(shifts)))
    clutter = [(-c.clutter_id, c.aabb_min, c.aabb_max) for c in room.clutter]  # negative: no instance id
    for instance_id in sorted(set(shifts) | gone):
        obj = room.object(instance_id)
        for other, lo, hi in [(o.instance_id, o.aabb_min, o.aabb_max) for o in room.objects] + clutter:
            if other == instance_id:
                continue
            if abs(lo[2] - obj.aabb_max[2]) <= RESTS_ON_M and _overlap_xy(lo, hi, obj.aabb_min, obj.aabb_max, 0.0):
                raise InvalidInput(f"object {instance_id}", "nothing resting on it", f"something at z {lo[2]:.2f} on its top")
    objects = []
    for obj in room.objects:
        if obj.instance_id in gone:
            continue
        if obj.instance_id in shifts:
            delta = np.array([*shifts[obj.instance_id], 0.0])
            obj = RoomObject(obj.instance_id, obj.label, obj.aabb_min + delta, obj.aabb_max + delta, yaw_rad=obj.yaw_rad)
        objects.append(obj)
    still = clutter + [(o.instance_id, o.aabb_min, o.aabb_max) for o in objects]
    for obj in objects:
        if obj.instance_id not in shifts:
            continue
        if np.any(obj.aabb_min[:2] < MOVE_GAP_M) or np.any(obj.aabb_max[:2] > room.size_m[:2] - MOVE_GAP_M):
            raise InvalidInput(
                f"shifts_xy[{obj.instance_id}]", "a move that stays on the floor", obj.center[:2].round(2).tolist()
            )
        for other, lo, hi in still:
            if other == obj.instance_id:
                continue
            if (
                lo[2] < obj.aabb_max[2]
                and obj.aabb_min[2] < hi[2]
                and _overlap_xy(lo, hi, obj.aabb_min, obj.aabb_max, MOVE_GAP_M)
            ):
                raise InvalidInput(
                    f"shifts_xy[{obj.instance_id}]",
                    "a free place",
                    f"it would meet something at {((lo + hi) / 2).round(2).tolist()}",
                )
    vertices = room.vertices.copy()
    for instance_id, shift in shifts.items():
        mine = room.triangle_instance == instance_id
        used = np.unique(room.triangles[mine])
        if np.isin(used, room.triangles[~mine]).any():  # parts are emitted per object: never shared
            raise AssertionError(f"object {instance_id} shares vertices with other triangles")
        vertices[used, :2] += shift.astype(np.float32)
    keep = ~np.isin(room.triangle_instance, sorted(gone))
    clutter_ids = room.triangle_clutter[keep] if room.triangle_clutter is not None else None
    moved = Room(
        seed=room.seed,
        size_m=room.size_m,
        objects=tuple(objects),
        vertices=vertices,
        triangles=room.triangles[keep],
        triangle_colors=room.triangle_colors[keep],
        triangle_instance=room.triangle_instance[keep],
        clutter=room.clutter,
        triangle_clutter=clutter_ids,
    )
    for array in (moved.vertices, moved.triangles, moved.triangle_colors, moved.triangle_instance, clutter_ids):
        if array is not None:
            array.flags.writeable = False
    return moved


def free_shifts(room: Room, instance_ids: Sequence[int], seed: int, *, max_tries: int = 500) -> dict[int, np.ndarray]:
    """(dx, dy) per object of ``instance_ids`` to a free place of the floor (``rearranged_room`` accepts
    them all together) clear of where it stood, drawn from ``seed``; ``InvalidInput`` when some object
    finds none in ``max_tries`` draws."""
    rng = np.random.default_rng([seed, 7])
    shifts: dict[int, np.ndarray] = {}
    for instance_id in instance_ids:
        obj = room.object(instance_id)
        half = obj.size[:2] / 2
        for _ in range(max_tries):
            center = rng.uniform(half + MOVE_GAP_M, room.size_m[:2] - half - MOVE_GAP_M)
            shift = center - obj.center[:2]
            if _overlap_xy(obj.aabb_min, obj.aabb_max, obj.aabb_min + [*shift, 0], obj.aabb_max + [*shift, 0], MOVE_GAP_M):
                continue  # still partly where it was
            try:
                rearranged_room(room, {**shifts, instance_id: shift})
            except InvalidInput:
                continue
            shifts[instance_id] = shift
            break
        else:
            raise InvalidInput("instance_ids", f"objects that fit elsewhere ({max_tries} draws)", instance_id)
    return shifts


def _overlap_xy(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray, gap_m: float) -> bool:
    """Whether two boxes' footprints come within ``gap_m`` of each other."""
    return bool(np.all(lo_a[:2] < hi_b[:2] + gap_m) and np.all(lo_b[:2] < hi_a[:2] + gap_m))


def room_renderer(room: Room) -> MeshRenderer:
    """A renderer of the room's mesh. Building one costs an Embree scene: keep it while rendering."""
    return MeshRenderer(
        room.vertices, room.triangles, triangle_colors=room.triangle_colors, triangle_instance=room.triangle_instance
    )


def room_walk(
    room: Room, n_frames: int = 300, seed: int = 0, *, style: WalkStyle | None = None, **kwargs: Any
) -> list[np.ndarray]:
    """A walk through a generated room looking at its objects, in ``style`` (None: the default walk;
    see ``plan_walk`` for ``kwargs``)."""
    targets = np.array([o.center for o in room.objects]).reshape(-1, 3)
    extents = np.array([np.linalg.norm(o.size) for o in room.objects])
    kwargs.setdefault("target_extents_m", extents)
    return plan_walk(
        room.floor_min_xy, room.floor_max_xy, targets, n_frames, seed, obstacles_xy=room.obstacles_xy(), style=style, **kwargs
    )


def gt_boxes(room: Room) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, min (3,), max (3,)) of every object of the room; kept for ``arcloud.service.replay``, use
    ``RoomObject.box``."""
    return [(o.label, o.aabb_min.copy(), o.aabb_max.copy()) for o in room.objects]
