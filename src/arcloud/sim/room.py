"""Procedural rooms: a z-up box room with furniture of the five classes, clutter and exact GT boxes.

World frame: z up, the floor is z = 0 over [0, size_x] x [0, size_y], the ceiling at z = size_z.
Every object is built from boxes, cylinders and ellipsoids in its own frame (origin on the floor at
the centre of its footprint, front towards -y), then turned about z (yaw) and moved into place.
Objects never interpenetrate: their axis-aligned boxes are kept apart (stacked ones only touch),
and furniture groups keep a walkway between them so that a user can walk around.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from arcloud.core.types import CLASSES
from arcloud.errors import InvalidInput

log = logging.getLogger(__name__)

DEFAULT_SIZE_M = (8.0, 6.0, 2.7)
#: Anything whose bottom is below this height blocks a walking user (metres).
HEAD_CLEARANCE_M = 2.0

# Required gaps (metres) between things of different groups: the larger of the two pads applies.
_PAD_WALKWAY = 0.7  # table groups keep a walkway to everything else
_PAD_WALL_ITEM = 0.05  # couches, cabinets, shelves side by side along a wall
_PAD_SMALL = 0.12  # plants, boxes, lamps
_PAD_LONE_CHAIR = 0.3
_WALL_GAP = (0.03, 0.08)  # gap between a wall and the back of what stands against it


class _PlacementFailed(Exception):
    """A layout attempt could not place an object; the caller retries with the next draw."""


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

    def renderer(self):  # -> MeshRenderer (imported lazily: Open3D is heavy)
        """The room's (cached) ``MeshRenderer``."""
        from arcloud.sim.render import room_renderer

        return room_renderer(self)


# ----------------------------------------------------------------------------------------------------
# Primitives: convex solids with outward-facing triangles.

# Unit cube corners: bit 0 -> x, bit 1 -> y, bit 2 -> z.
_CUBE = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64) - 0.5
# Faces in a fixed order (-x, +x, -y, +y, -z, +z), two triangles each, so callers can colour faces.
_CUBE_QUADS = ((0, 2, 6, 4), (1, 3, 7, 5), (0, 1, 5, 4), (2, 3, 7, 6), (0, 1, 3, 2), (4, 5, 7, 6))
FACE = {"-x": 0, "+x": 1, "-y": 2, "+y": 3, "-z": 4, "+z": 5}


def _orient_outward(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Flip triangles of a convex solid so that their normals point away from its centroid."""
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    outward = np.einsum("ij,ij->i", normals, (a + b + c) / 3 - vertices.mean(axis=0)) >= 0
    return np.where(outward[:, None], triangles, triangles[:, [0, 2, 1]])


def _quads_to_triangles(quads: Sequence[Sequence[int]]) -> np.ndarray:
    return np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int64)


_CUBE_TRIANGLES = _orient_outward(_CUBE, _quads_to_triangles(_CUBE_QUADS))


@dataclass
class Part:
    """A piece of mesh with per-triangle colours, in its owner's frame."""

    vertices: np.ndarray  # (n, 3) float64
    triangles: np.ndarray  # (m, 3) int64
    colors: np.ndarray  # (m, 3) uint8


def _colors(color: Sequence[float] | np.ndarray, n_triangles: int) -> np.ndarray:
    color = np.asarray(color, dtype=np.float64)
    if color.ndim == 1:
        color = np.broadcast_to(color, (n_triangles, 3))
    return np.clip(np.rint(color), 0, 255).astype(np.uint8)


def _rot_x(angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation about +z by ``angle_rad`` (exact for quarter turns)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    c, s = (0.0 if abs(c) < 1e-12 else c), (0.0 if abs(s) < 1e-12 else s)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def box(
    lo: Sequence[float],
    hi: Sequence[float],
    color: Sequence[float] | np.ndarray,
    *,
    rotation: np.ndarray | None = None,
    pivot: Sequence[float] | None = None,
    face_colors: Mapping[str, Sequence[float]] | None = None,
) -> Part:
    """A box spanning [lo, hi], optionally turned by ``rotation`` about ``pivot`` (default its centre).
    ``face_colors`` recolours faces by name ("-x", "+x", "-y", "+y", "-z", "+z")."""
    lo_arr, hi_arr = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    vertices = np.where(_CUBE > 0, hi_arr, lo_arr)  # exact corners
    if rotation is not None:
        origin = (lo_arr + hi_arr) / 2 if pivot is None else np.asarray(pivot, np.float64)
        vertices = (vertices - origin) @ rotation.T + origin
    colors = np.array(_colors(color, 12))
    for name, face_color in (face_colors or {}).items():
        colors[2 * FACE[name] : 2 * FACE[name] + 2] = _colors(face_color, 2)
    return Part(vertices, _CUBE_TRIANGLES.copy(), colors)


def cylinder(
    center_xy: Sequence[float], z0: float, z1: float, radius: float, color: Sequence[float], *, segments: int = 12
) -> Part:
    """A vertical cylinder (a prism of ``segments`` sides) from z0 to z1."""
    angles = np.arange(segments) * (2 * math.pi / segments)
    ring = np.column_stack([np.cos(angles) * radius + center_xy[0], np.sin(angles) * radius + center_xy[1]])
    vertices = np.concatenate(
        [
            np.column_stack([ring, np.full(segments, z0)]),
            np.column_stack([ring, np.full(segments, z1)]),
            [[center_xy[0], center_xy[1], z0], [center_xy[0], center_xy[1], z1]],
        ]
    )
    i = np.arange(segments)
    j = (i + 1) % segments
    sides = np.concatenate([np.column_stack([i, j, j + segments]), np.column_stack([i, j + segments, i + segments])])
    caps = np.concatenate(
        [np.column_stack([np.full(segments, 2 * segments), j, i]), np.column_stack([np.full(segments, 2 * segments + 1), i + segments, j + segments])]
    )
    triangles = _orient_outward(vertices, np.concatenate([sides, caps]).astype(np.int64))
    return Part(vertices, triangles, _colors(color, len(triangles)))


def ellipsoid(
    center: Sequence[float], radii: Sequence[float], color: Sequence[float], *, stacks: int = 6, slices: int = 10
) -> Part:
    """A low-poly ellipsoid (UV sphere scaled by ``radii``)."""
    theta = np.linspace(0, math.pi, stacks + 1)[1:-1]
    phi = np.arange(slices) * (2 * math.pi / slices)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    rings = np.column_stack([(np.sin(tt) * np.cos(pp)).ravel(), (np.sin(tt) * np.sin(pp)).ravel(), np.cos(tt).ravel()])
    unit = np.concatenate([rings, [[0, 0, 1.0], [0, 0, -1.0]]])
    vertices = unit * np.asarray(radii, np.float64) + np.asarray(center, np.float64)
    top, bottom = len(unit) - 2, len(unit) - 1
    tris = []
    for s in range(slices):
        t = (s + 1) % slices
        tris.append((top, s, t))
        tris.append((bottom, (stacks - 2) * slices + t, (stacks - 2) * slices + s))
        for r in range(stacks - 2):
            a, b = r * slices + s, r * slices + t
            tris += [(a, b, b + slices), (a, b + slices, a + slices)]
    triangles = _orient_outward(vertices, np.array(tris, dtype=np.int64))
    return Part(vertices, triangles, _colors(color, len(triangles)))


def _transform(parts: Sequence[Part], yaw_rad: float, translation: Sequence[float]) -> list[Part]:
    rotation = rot_z(yaw_rad)
    t = np.asarray(translation, np.float64)
    return [Part(p.vertices @ rotation.T + t, p.triangles, p.colors) for p in parts]


def _bounds(parts: Sequence[Part]) -> tuple[np.ndarray, np.ndarray]:
    """AABB of the parts' vertices, as the float32 mesh will store them."""
    vertices = np.concatenate([p.vertices for p in parts]).astype(np.float32).astype(np.float64)
    return vertices.min(axis=0), vertices.max(axis=0)


# ----------------------------------------------------------------------------------------------------
# Palettes (RGB) and per-object colour variation.

_WOOD = ((150, 105, 65), (120, 80, 50), (182, 142, 98), (96, 66, 42), (205, 175, 135), (70, 50, 35))
_FABRIC = ((112, 112, 120), (60, 80, 122), (172, 152, 122), (72, 102, 82), (140, 62, 56), (46, 46, 52), (150, 130, 160))
_SEAT = ((60, 60, 66), (172, 42, 42), (42, 92, 152), (222, 222, 216), (92, 122, 72), (210, 160, 60))
_METAL = ((52, 52, 56), (172, 172, 178), (30, 30, 32))
_PAINT = ((226, 221, 206), (210, 216, 222), (232, 226, 216), (202, 212, 196), (222, 208, 196))
_CABINET = ((232, 232, 228), (40, 40, 44), (150, 105, 65), (120, 80, 50), (190, 195, 200))
_BOOKS = ((160, 40, 40), (40, 70, 140), (200, 170, 60), (40, 110, 70), (230, 230, 220), (90, 50, 110), (30, 30, 30))


def _pick(rng: np.random.Generator, palette: Sequence[Sequence[int]], spread: float = 10.0) -> np.ndarray:
    base = np.asarray(palette[int(rng.integers(len(palette)))], dtype=np.float64)
    return np.clip(base + rng.uniform(-spread, spread, 3), 0, 255)


# ----------------------------------------------------------------------------------------------------
# Objects of the five classes, in their own frame: footprint centred on the origin, bottom at z = 0,
# front towards -y. Sizes follow real furniture.


def chair_parts(rng: np.random.Generator) -> list[Part]:
    """Seat, backrest and four legs: 0.42-0.50 m wide, seat at 0.43-0.48 m, 0.8-1.0 m tall."""
    w, d = rng.uniform(0.42, 0.50), rng.uniform(0.42, 0.50)
    seat_h, seat_t = rng.uniform(0.43, 0.48), rng.uniform(0.03, 0.06)
    back_h, back_t = rng.uniform(0.36, 0.50), rng.uniform(0.025, 0.045)
    style = int(rng.integers(3))  # 0 wooden, 1 padded on metal legs, 2 one-colour plastic
    wood = _pick(rng, _WOOD)
    seat_color = wood if style == 0 else _pick(rng, _SEAT)
    leg_color = wood if style == 0 else (_pick(rng, _METAL, 4) if style == 1 else seat_color * 0.85)
    parts = [box((-w / 2, -d / 2, seat_h - seat_t), (w / 2, d / 2, seat_h), seat_color)]
    inset = rng.uniform(0.02, 0.04)
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (w / 2 - inset), sy * (d / 2 - inset)
            if style == 1:
                parts.append(cylinder((cx, cy), 0.0, seat_h - seat_t, rng.uniform(0.011, 0.016), leg_color, segments=8))
            else:
                r = rng.uniform(0.016, 0.022)
                parts.append(box((cx - r, cy - r, 0.0), (cx + r, cy + r, seat_h - seat_t), leg_color))
    tilt = _rot_x(-math.radians(rng.uniform(2.0, 10.0)))  # lean the backrest back (towards +y)
    pivot = (0.0, d / 2 - back_t, seat_h)
    parts.append(box((-w / 2, d / 2 - back_t, seat_h), (w / 2, d / 2, seat_h + back_h), seat_color * 0.95, rotation=tilt, pivot=pivot))
    return parts


def table_parts(rng: np.random.Generator) -> tuple[list[Part], float, float, float]:
    """A top on four legs with an apron: 1.2-1.8 x 0.7-0.95 m, 0.72-0.77 m tall.

    Returns the parts and the top's length (x), width (y) and height."""
    length, width = rng.uniform(1.2, 1.8), rng.uniform(0.7, 0.95)
    height, top_t = rng.uniform(0.72, 0.77), rng.uniform(0.025, 0.05)
    top_color = _pick(rng, _WOOD + ((235, 235, 230), (60, 60, 62)))
    leg_color = top_color * 0.9 if rng.random() < 0.6 else _pick(rng, _METAL, 4)
    parts = [box((-length / 2, -width / 2, height - top_t), (length / 2, width / 2, height), top_color)]
    leg, inset = rng.uniform(0.025, 0.035), rng.uniform(0.04, 0.09)
    lx, ly = length / 2 - inset, width / 2 - inset
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(box((sx * lx - leg, sy * ly - leg, 0.0), (sx * lx + leg, sy * ly + leg, height - top_t), leg_color))
    apron_h, apron_t = rng.uniform(0.06, 0.1), 0.02
    z0, z1 = height - top_t - apron_h, height - top_t
    parts.append(box((-lx + leg, -ly, z0), (lx - leg, -ly + apron_t, z1), leg_color))
    parts.append(box((-lx + leg, ly - apron_t, z0), (lx - leg, ly, z1), leg_color))
    return parts, length, width, height


def couch_parts(rng: np.random.Generator) -> list[Part]:
    """Base, seat cushions, back and two arms on small feet: 1.6-2.3 m wide, 0.8-0.95 m deep."""
    w, d = rng.uniform(1.6, 2.3), rng.uniform(0.8, 0.95)
    foot, seat_h = rng.uniform(0.04, 0.1), rng.uniform(0.40, 0.46)
    back_h, back_t = rng.uniform(0.75, 0.9), rng.uniform(0.15, 0.25)
    arm_w, arm_h = rng.uniform(0.1, 0.2), rng.uniform(0.55, 0.65)
    cushion_t = rng.uniform(0.1, 0.15)
    fabric = _pick(rng, _FABRIC)
    feet = _pick(rng, _WOOD + _METAL, 4)
    parts = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (w / 2 - 0.06), sy * (d / 2 - 0.06)
            parts.append(box((cx - 0.03, cy - 0.03, 0.0), (cx + 0.03, cy + 0.03, foot), feet))
    inner = w / 2 - arm_w
    parts.append(box((-inner, -d / 2, foot), (inner, d / 2 - back_t, seat_h - cushion_t), fabric * 0.9))
    n_cushions = int(rng.integers(2, 4))
    edges = np.linspace(-inner, inner, n_cushions + 1)
    for a, b in zip(edges[:-1], edges[1:]):
        parts.append(box((a + 0.005, -d / 2 + 0.01, seat_h - cushion_t), (b - 0.005, d / 2 - back_t, seat_h), fabric * rng.uniform(0.95, 1.05)))
    parts.append(box((-w / 2, d / 2 - back_t, foot), (w / 2, d / 2, back_h), fabric * 0.97))
    for sx in (-1, 1):
        x0, x1 = sorted((sx * w / 2, sx * inner))
        parts.append(box((x0, -d / 2, foot), (x1, d / 2 - back_t, arm_h), fabric))
    return parts


def tv_parts(rng: np.random.Generator, *, wall_mounted: bool) -> list[Part]:
    """A thin panel (32-65 inch, 16:9) with a dark screen facing -y, on a foot and neck unless
    ``wall_mounted`` (then the panel's bottom is at z = 0 of the object frame)."""
    w = rng.uniform(0.72, 1.45)
    h = w * 9 / 16 + 0.04
    t = rng.uniform(0.03, 0.07)
    body = _pick(rng, ((22, 22, 24), (40, 40, 44), (180, 180, 185)), 4)
    screen = np.clip(_pick(rng, ((18, 22, 36), (26, 30, 44), (60, 80, 110)), 8), 0, 255)
    parts = []
    z0 = 0.0
    if not wall_mounted:
        foot_w, foot_d, neck_h = w * rng.uniform(0.3, 0.45), rng.uniform(0.18, 0.26), rng.uniform(0.06, 0.12)
        parts.append(box((-foot_w / 2, -foot_d / 2, 0.0), (foot_w / 2, foot_d / 2, 0.02), body))
        parts.append(box((-0.03, -0.02, 0.02), (0.03, 0.02, 0.02 + neck_h + 0.05), body))
        z0 = 0.02 + neck_h
    parts.append(box((-w / 2, -t / 2, z0), (w / 2, t / 2, z0 + h), body, face_colors={"-y": screen}))
    return parts


def laptop_parts(rng: np.random.Generator) -> list[Part]:
    """A base with a keyboard and an open screen hinged at its back edge: 0.30-0.38 m wide."""
    w, d = rng.uniform(0.30, 0.38), rng.uniform(0.21, 0.26)
    base_t, screen_t = rng.uniform(0.015, 0.022), rng.uniform(0.006, 0.009)
    screen_h = d * rng.uniform(0.9, 1.0)
    shell = _pick(rng, ((190, 190, 196), (44, 44, 48), (120, 120, 128)), 6)
    keys = shell * 0.45
    screen = np.clip(_pick(rng, ((30, 40, 70), (200, 210, 225), (60, 90, 140)), 12), 0, 255)
    open_deg = rng.uniform(95.0, 125.0)
    tilt = _rot_x(-math.radians(open_deg - 90.0))
    parts = [box((-w / 2, -d / 2, 0.0), (w / 2, d / 2, base_t), shell, face_colors={"+z": keys})]
    parts.append(
        box(
            (-w / 2, d / 2 - screen_t, base_t),
            (w / 2, d / 2, base_t + screen_h),
            shell,
            rotation=tilt,
            pivot=(0.0, d / 2, base_t),
            face_colors={"-y": screen},
        )
    )
    return parts


# ----------------------------------------------------------------------------------------------------
# Clutter (background, instance 0).


def cabinet_parts(rng: np.random.Generator, w: float, d: float, h: float) -> list[Part]:
    """A low cabinet with a top slab, two door fronts and handles (front towards -y)."""
    color = _pick(rng, _CABINET, 6)
    parts = [box((-w / 2, -d / 2, 0.0), (w / 2, d / 2, h - 0.02), color)]
    parts.append(box((-w / 2, -d / 2, h - 0.02), (w / 2, d / 2, h), color * 0.92))
    for a, b in ((-w / 2 + 0.02, -0.005), (0.005, w / 2 - 0.02)):
        parts.append(box((a, -d / 2 - 0.006, 0.05), (b, -d / 2, h - 0.05), color * 0.96))
        hx = b - 0.05 if a < 0 else a + 0.05
        parts.append(box((hx - 0.01, -d / 2 - 0.02, h * 0.55), (hx + 0.01, -d / 2 - 0.006, h * 0.75), _pick(rng, _METAL, 4)))
    return parts


def bookshelf_parts(rng: np.random.Generator) -> list[Part]:
    """Side panels, back, shelves and rows of books: 0.6-1.0 m wide, 1.5-2.0 m tall."""
    w, d, h = rng.uniform(0.6, 1.0), rng.uniform(0.28, 0.38), rng.uniform(1.5, 2.0)
    wood, t = _pick(rng, _CABINET, 6), 0.02
    parts = [
        box((-w / 2, -d / 2, 0.0), (-w / 2 + t, d / 2, h), wood),
        box((w / 2 - t, -d / 2, 0.0), (w / 2, d / 2, h), wood),
        box((-w / 2 + t, d / 2 - 0.01, 0.0), (w / 2 - t, d / 2, h), wood * 0.9),
    ]
    n_shelves = int(rng.integers(4, 6))
    levels = np.linspace(0.0, h - t, n_shelves + 1)
    for z in levels:
        parts.append(box((-w / 2 + t, -d / 2, z), (w / 2 - t, d / 2 - 0.01, z + t), wood))
    for z0, z1 in zip(levels[:-1] + t, levels[1:]):
        x = -w / 2 + t + rng.uniform(0.0, 0.1)
        while True:
            bw, bh = rng.uniform(0.02, 0.05), (z1 - z0) * rng.uniform(0.6, 0.92)
            if x + bw > w / 2 - t - 0.005:
                break
            if rng.random() < 0.85:
                parts.append(box((x, -d / 2 + rng.uniform(0.02, 0.06), z0), (x + bw, d / 2 - 0.02, z0 + bh), _pick(rng, _BOOKS, 20)))
            x += bw + 0.002
    return parts


def plant_parts(rng: np.random.Generator) -> list[Part]:
    """A pot, a stem and a leafy crown."""
    r, pot_h = rng.uniform(0.12, 0.2), rng.uniform(0.25, 0.4)
    crown = rng.uniform(0.25, 0.4)
    stem_h = rng.uniform(0.2, 0.6)
    pot = _pick(rng, ((170, 90, 60), (232, 232, 228), (60, 60, 64)), 8)
    leaves = _pick(rng, ((50, 110, 50), (70, 130, 60), (40, 90, 45)), 10)
    parts = [cylinder((0.0, 0.0), 0.0, pot_h, r, pot, segments=12)]
    parts.append(cylinder((0.0, 0.0), pot_h, pot_h + stem_h, 0.015, (90, 70, 40), segments=6))
    parts.append(ellipsoid((0.0, 0.0, pot_h + stem_h + crown * 0.8), (crown, crown * rng.uniform(0.8, 1.0), crown * rng.uniform(0.9, 1.3)), leaves))
    return parts


def boxes_parts(rng: np.random.Generator) -> list[Part]:
    """One to three stacked cardboard boxes."""
    parts, z = [], 0.0
    w, d = rng.uniform(0.35, 0.6), rng.uniform(0.3, 0.5)
    for _ in range(int(rng.integers(1, 4))):
        h = rng.uniform(0.2, 0.45)
        color = _pick(rng, ((182, 142, 92), (160, 120, 80), (200, 170, 120)), 8)
        parts.append(box((-w / 2, -d / 2, z), (w / 2, d / 2, z + h), color))
        z += h
        w, d = w * rng.uniform(0.7, 1.0), d * rng.uniform(0.7, 1.0)
    return parts


def lamp_parts(rng: np.random.Generator) -> list[Part]:
    """A floor lamp: base disc, pole and shade."""
    h, shade_r = rng.uniform(1.4, 1.75), rng.uniform(0.16, 0.24)
    metal, shade = _pick(rng, _METAL, 4), _pick(rng, ((240, 232, 210), (220, 220, 220), (200, 180, 150)), 6)
    return [
        cylinder((0.0, 0.0), 0.0, 0.03, 0.14, metal, segments=12),
        cylinder((0.0, 0.0), 0.03, h - 0.25, 0.012, metal, segments=6),
        cylinder((0.0, 0.0), h - 0.28, h, shade_r, shade, segments=14),
    ]


# ----------------------------------------------------------------------------------------------------
# Layout.


@dataclass
class _Item:
    """Something placed: world parts, AABB, whether it is an object of a class or clutter."""

    parts: list[Part]
    lo: np.ndarray
    hi: np.ndarray
    pad: float
    group: int
    label: str | None = None  # a class name for objects
    kind: str | None = None  # a clutter kind
    yaw_rad: float = 0.0
    solid: bool = True  # False for reserved free space (a door's swing): blocks placement, not rendered


class _Layout:
    def __init__(self, rng: np.random.Generator, size_m: np.ndarray) -> None:
        self.rng = rng
        self.size = size_m
        self.items: list[_Item] = []
        self.structure: list[Part] = []
        self._group = 0

    def new_group(self) -> int:
        self._group += 1
        return self._group

    def fits(self, item: _Item, *, wall_margin: float = 0.0) -> bool:
        x_max, y_max = self.size[0] - wall_margin, self.size[1] - wall_margin
        if item.lo[0] < wall_margin or item.lo[1] < wall_margin or item.hi[0] > x_max or item.hi[1] > y_max:
            return False
        if item.hi[2] > self.size[2] - 0.05:
            return False
        for other in self.items:
            pad = 0.01 if other.group == item.group else max(item.pad, other.pad)
            if (
                item.lo[0] < other.hi[0] + pad
                and other.lo[0] < item.hi[0] + pad
                and item.lo[1] < other.hi[1] + pad
                and other.lo[1] < item.hi[1] + pad
                and item.lo[2] < other.hi[2]
                and other.lo[2] < item.hi[2]
            ):
                return False
        return True

    def make(self, parts_local: list[Part], yaw_rad: float, xyz: Sequence[float], *, pad: float, group: int, **kw: object) -> _Item:
        parts = _transform(parts_local, yaw_rad, xyz)
        lo, hi = _bounds(parts)
        return _Item(parts, lo, hi, pad, group, yaw_rad=yaw_rad, **kw)  # type: ignore[arg-type]

    def wall_pose(self, wall: int, along_m: float, depth_m: float, gap_m: float) -> tuple[np.ndarray, float]:
        """Centre (x, y) and yaw of something ``depth_m`` deep with its back ``gap_m`` from wall
        ``wall`` (0: y = 0, 1: x = X, 2: y = Y, 3: x = 0), ``along_m`` along the wall, facing the room."""
        x_size, y_size = self.size[0], self.size[1]
        off = gap_m + depth_m / 2
        if wall == 0:
            return np.array([along_m, off]), math.pi  # faces +y
        if wall == 1:
            return np.array([x_size - off, along_m]), -math.pi / 2  # faces -x
        if wall == 2:
            return np.array([along_m, y_size - off]), 0.0  # faces -y
        return np.array([off, along_m]), math.pi / 2  # faces +x

    def wall_length(self, wall: int) -> float:
        return float(self.size[0] if wall % 2 == 0 else self.size[1])

    def place_group(
        self,
        members: Sequence[tuple[list[Part], dict[str, object]]],
        *,
        pad: float,
        against_wall: bool,
        tries: int = 60,
        z: float = 0.0,
        interior_margin_m: float = 0.7,
    ) -> list[_Item] | None:
        """Place parts that move together (each member: local parts and ``_Item`` fields such as
        label or kind), either with their back (local +y side) against a random wall, facing the
        room, or as an island turned by about 0 or 90 degrees. None when no try fits."""
        lo, hi = _bounds([p for parts, _ in members for p in parts])
        for _ in range(tries):
            group = self.new_group()
            if against_wall:
                wall = int(self.rng.integers(4))
                length = self.wall_length(wall)
                if hi[0] - lo[0] + 0.1 > length:
                    continue
                along = self.rng.uniform(-lo[0] + 0.05, length - hi[0] - 0.05)
                centre, yaw = self.wall_pose(wall, along, 2 * hi[1], self.rng.uniform(*_WALL_GAP))
                yaw += math.radians(self.rng.normal(0.0, 1.0))
            else:
                yaw = (math.pi / 2 if self.rng.random() < 0.5 else 0.0) + math.radians(self.rng.normal(0.0, 4.0))
                centre = self.rng.uniform((1.0, 1.0), (self.size[0] - 1.0, self.size[1] - 1.0))
            items = [self.make(parts, yaw, (centre[0], centre[1], z), pad=pad, group=group, **kw) for parts, kw in members]
            if not against_wall:
                group_lo = np.min([i.lo for i in items], axis=0)
                group_hi = np.max([i.hi for i in items], axis=0)
                if np.any(group_lo[:2] < interior_margin_m) or np.any(group_hi[:2] > self.size[:2] - interior_margin_m):
                    continue
            if not all(self.fits(i) for i in items):
                continue
            if all(_apart(a, b) for k, a in enumerate(items) for b in items[k + 1 :]):
                return items
        return None

    def place_against_wall(self, parts_local: list[Part], *, pad: float, tries: int = 60, z: float = 0.0, **kw: object) -> _Item | None:
        """Place one thing with its back (local +y side) against a wall; None when no try fits."""
        items = self.place_group([(parts_local, kw)], pad=pad, against_wall=True, tries=tries, z=z)
        return None if items is None else items[0]

    def add(self, *items: _Item) -> None:
        self.items.extend(items)


def _structure(layout: _Layout) -> None:
    """Floor (planks or tiles), walls, ceiling, baseboards, a door, a window and pictures."""
    rng, (x_size, y_size, z_size) = layout.rng, layout.size
    parts = layout.structure
    floor_base = _pick(rng, _WOOD[:5] + ((150, 150, 150), (120, 115, 110), (200, 195, 185)), 8)
    if rng.random() < 0.65:  # planks along x, staggered
        plank = rng.uniform(0.14, 0.24)
        for y0 in np.arange(0.0, y_size, plank):
            x = -rng.uniform(0.0, 1.2)
            while x < x_size:
                x1 = min(x + rng.uniform(0.9, 2.0), x_size)
                parts.append(box((max(x, 0.0), y0, -0.01), (x1, min(y0 + plank, y_size), 0.0), floor_base * rng.uniform(0.9, 1.1)))
                x = x1
    else:  # square tiles
        tile = rng.uniform(0.4, 0.6)
        for x0 in np.arange(0.0, x_size, tile):
            for y0 in np.arange(0.0, y_size, tile):
                parts.append(box((x0, y0, -0.01), (min(x0 + tile, x_size), min(y0 + tile, y_size), 0.0), floor_base * rng.uniform(0.95, 1.05)))
    paint = _pick(rng, _PAINT, 6)
    t = 0.05
    parts += [
        box((-t, -t, 0.0), (x_size + t, 0.0, z_size), paint),
        box((x_size, -t, 0.0), (x_size + t, y_size + t, z_size), paint * 0.98),
        box((-t, y_size, 0.0), (x_size + t, y_size + t, z_size), paint * 1.01),
        box((-t, -t, 0.0), (0.0, y_size + t, z_size), paint * 0.99),
        box((-t, -t, z_size), (x_size + t, y_size + t, z_size + t), (242, 242, 240)),
    ]
    trim = _pick(rng, ((240, 240, 238), (150, 105, 65), (60, 60, 62)), 4)
    bh, bt = 0.08, 0.012
    parts += [
        box((0.0, 0.0, 0.0), (x_size, bt, bh), trim),
        box((0.0, y_size - bt, 0.0), (x_size, y_size, bh), trim),
        box((0.0, bt, 0.0), (bt, y_size - bt, bh), trim),
        box((x_size - bt, bt, 0.0), (x_size, y_size - bt, bh), trim),
    ]
    # Door: a panel on a wall with its swing kept free.
    wall = int(rng.integers(4))
    door_w = 0.9
    along = rng.uniform(0.3 + door_w / 2, layout.wall_length(wall) - 0.3 - door_w / 2)
    centre, yaw = layout.wall_pose(wall, along, 0.03, 0.0)
    door = [box((-door_w / 2, -0.015, 0.0), (door_w / 2, 0.015, 2.05), _pick(rng, ((210, 190, 160), (240, 240, 236), (120, 80, 50)), 6))]
    door.append(box((door_w / 2 - 0.1, -0.06, 0.95), (door_w / 2 - 0.05, -0.015, 1.0), _pick(rng, _METAL, 4)))
    door_item = layout.make(door, yaw, (centre[0], centre[1], 0.0), pad=0.0, group=layout.new_group(), kind="door")
    swing = layout.make([box((-0.6, -1.0, 0.0), (0.6, 0.0, 2.05), (0, 0, 0))], yaw, (centre[0], centre[1], 0.0), pad=0.0, group=layout.new_group())
    swing.solid = False
    swing.pad = 0.3
    layout.add(door_item, swing)
    # Window on another wall, pictures on the rest.
    walls = [w for w in range(4) if w != wall]
    win_wall = int(rng.choice(walls))
    win_w = rng.uniform(1.0, min(2.0, layout.wall_length(win_wall) - 1.0))
    along = rng.uniform(0.5 + win_w / 2, layout.wall_length(win_wall) - 0.5 - win_w / 2)
    centre, yaw = layout.wall_pose(win_wall, along, 0.02, 0.0)
    z0, z1 = rng.uniform(0.85, 1.0), rng.uniform(2.0, min(2.3, z_size - 0.2))
    frame = (240, 240, 238)
    window = [box((-win_w / 2, -0.01, z0), (win_w / 2, 0.01, z1), _pick(rng, ((170, 200, 232), (190, 215, 240)), 8))]
    for a, b in (((-win_w / 2 - 0.05, z0 - 0.05), (win_w / 2 + 0.05, z0)), ((-win_w / 2 - 0.05, z1), (win_w / 2 + 0.05, z1 + 0.05))):
        window.append(box((a[0], -0.03, a[1]), (b[0], 0.01, b[1]), frame))
    for sx in (-1, 1):
        window.append(box((sx * win_w / 2 - 0.05 * (sx < 0), -0.03, z0), (sx * win_w / 2 + 0.05 * (sx > 0), 0.01, z1), frame))
    window.append(box((-0.02, -0.02, z0), (0.02, 0.0, z1), frame))
    layout.add(layout.make(window, yaw, (centre[0], centre[1], 0.0), pad=0.0, group=layout.new_group(), kind="window"))
    for _ in range(int(rng.integers(1, 4))):
        pw, ph = rng.uniform(0.3, 0.9), rng.uniform(0.3, 0.7)
        picture = [
            box((-pw / 2, -0.025, 0.0), (pw / 2, 0.0, ph), (30, 30, 30), face_colors={"-y": _pick(rng, _BOOKS + _FABRIC, 30)})
        ]
        for _ in range(10):
            w = int(rng.choice(walls))
            if pw + 0.4 > layout.wall_length(w):
                continue
            centre, yaw = layout.wall_pose(w, rng.uniform(pw / 2 + 0.2, layout.wall_length(w) - pw / 2 - 0.2), 0.025, 0.0)
            item = layout.make(picture, yaw, (centre[0], centre[1], rng.uniform(1.3, 1.7)), pad=0.05, group=layout.new_group(), kind="picture")
            if layout.fits(item):
                layout.add(item)
                break


def _table_group_local(
    rng: np.random.Generator, n_chairs: int, n_laptops: int, *, against_wall: bool
) -> list[tuple[list[Part], dict[str, object]]]:
    """A table with up to ``n_chairs`` chairs around it and up to ``n_laptops`` laptops on it, in the
    table's frame (top centred on the origin, length along x). Against a wall the table's +y side
    is the wall's and chairs stand only on its -y side; as an island chairs take both long sides,
    then the ends."""
    table_local, length, width, height = table_parts(rng)
    table_lo, table_hi = _bounds(table_local)
    members: list[tuple[list[Part], dict[str, object]]] = [(table_local, {"label": "table"})]
    side_x = [-length / 4, length / 4] if length >= 1.35 else [0.0]
    slots = [(x, -1) for x in side_x]
    if not against_wall:
        slots += [(x, 1) for x in side_x]
        order = rng.permutation(len(slots))
        slots = [slots[i] for i in order] + [(-1.0, 0), (1.0, 0)]
    kept: list[tuple[np.ndarray, np.ndarray]] = [(table_lo, table_hi)]
    for x, side in slots[:n_chairs]:
        chair_local = chair_parts(rng)
        lo, hi = _bounds(chair_local)
        depth = hi[1] - lo[1]
        gap = rng.uniform(0.08, 0.3)
        if side != 0:  # a long side, facing the table: the chair's front (its local -y) points at it
            centre = np.array([x + rng.normal(0.0, 0.04), side * (width / 2 + gap + depth / 2)])
            yaw = 0.0 if side > 0 else math.pi
        else:  # an end
            centre = np.array([x * (length / 2 + gap + depth / 2), rng.normal(0.0, 0.04)])
            yaw = math.pi / 2 if x < 0 else -math.pi / 2
        yaw += math.radians(rng.normal(0.0, 8.0))
        parts = _transform(chair_local, yaw, (centre[0], centre[1], 0.0))
        bounds = _bounds(parts)
        if all(_boxes_apart(bounds, other) for other in kept):
            kept.append(bounds)
            members.append((parts, {"label": "chair"}))
    laptops: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(n_laptops):
        laptop_local = laptop_parts(rng)
        for _ in range(20):
            centre = rng.uniform((-length / 2 + 0.2, -width / 2 + 0.2), (length / 2 - 0.2, width / 2 - 0.2))
            # Keyboard towards the nearer long side, where its user sits; a desk's user sits at -y.
            toward = 0.0 if centre[1] < 0 or against_wall else math.pi
            parts = _transform(laptop_local, toward + math.radians(rng.normal(0.0, 15.0)), (centre[0], centre[1], float(table_hi[2])))
            lo, hi = _bounds(parts)
            inside = np.all(lo[:2] >= table_lo[:2] + 0.01) and np.all(hi[:2] <= table_hi[:2] - 0.01)
            if inside and all(_boxes_apart((lo, hi), other) for other in laptops):
                laptops.append((lo, hi))
                members.append((parts, {"label": "laptop"}))
                break
    return members


def _boxes_apart(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], gap_m: float = 0.01) -> bool:
    """Whether two boxes (lo, hi) are disjoint: touching in z counts as apart, x or y need a gap."""
    (alo, ahi), (blo, bhi) = a, b
    return bool(
        alo[2] >= bhi[2]
        or blo[2] >= ahi[2]
        or alo[0] >= bhi[0] + gap_m
        or blo[0] >= ahi[0] + gap_m
        or alo[1] >= bhi[1] + gap_m
        or blo[1] >= ahi[1] + gap_m
    )


def _apart(a: _Item, b: _Item, gap_m: float = 0.01) -> bool:
    return _boxes_apart((a.lo, a.hi), (b.lo, b.hi), gap_m)


def _default_counts(rng: np.random.Generator) -> dict[str, int]:
    tables = int(rng.integers(2, 4))
    return {"chair": 2 * tables, "table": tables, "laptop": int(rng.integers(2, 4)), "couch": 2, "tv": 2}


def _check_counts(counts: Mapping[str, int]) -> dict[str, int]:
    checked = {name: 0 for name in CLASSES}
    for name, n in counts.items():
        if name not in CLASSES:
            raise InvalidInput("counts", f"class names from {CLASSES}", repr(name))
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0 or n > 40:
            raise InvalidInput(f"counts[{name!r}]", "an integer from 0 to 40", repr(n))
        checked[name] = int(n)
    return checked


def _layout_room(rng: np.random.Generator, size_m: np.ndarray, counts: dict[str, int]) -> _Layout:
    layout = _Layout(rng, size_m)
    _structure(layout)
    for _ in range(counts["couch"]):
        item = layout.place_against_wall(couch_parts(rng), pad=_PAD_WALL_ITEM, label="couch")
        if item is None:
            raise _PlacementFailed("couch")
        layout.add(item)
    for _ in range(counts["tv"]):
        if rng.random() < 0.35:  # on the wall, 0.9-1.3 m up
            item = layout.place_against_wall(tv_parts(rng, wall_mounted=True), pad=_PAD_WALL_ITEM, z=rng.uniform(0.9, 1.3), label="tv")
            if item is None:
                raise _PlacementFailed("tv")
            layout.add(item)
            continue
        # On a low cabinet, standing on its top near the back.
        tv_local = tv_parts(rng, wall_mounted=False)
        lo, hi = _bounds(tv_local)
        cab_w, cab_d, cab_h = (hi[0] - lo[0]) + rng.uniform(0.15, 0.6), rng.uniform(0.38, 0.5), rng.uniform(0.4, 0.6)
        tv_on_top = _transform(tv_local, math.radians(rng.normal(0.0, 3.0)), (0.0, cab_d / 2 - 0.14, cab_h))
        members = [(cabinet_parts(rng, cab_w, cab_d, cab_h), {"kind": "tv cabinet"}), (tv_on_top, {"label": "tv"})]
        items = layout.place_group(members, pad=_PAD_WALL_ITEM, against_wall=True)
        if items is None:
            raise _PlacementFailed("tv on a cabinet")
        layout.add(*items)
    n_tables = counts["table"]
    chairs_left, laptops_left = counts["chair"], counts["laptop"]
    for k in range(n_tables):
        chairs_here = min(6, math.ceil(chairs_left / (n_tables - k))) if chairs_left else 0
        laptops_here = min(2, math.ceil(laptops_left / (n_tables - k))) if laptops_left else 0
        items = None
        for against_wall in (False, True) if rng.random() < 0.75 else (True, False):
            members = _table_group_local(rng, chairs_here, laptops_here, against_wall=against_wall)
            items = layout.place_group(members, pad=_PAD_WALKWAY, against_wall=against_wall, tries=80)
            if items is not None:
                break
        if items is None:
            raise _PlacementFailed("table group")
        layout.add(*items)
        chairs_left -= sum(i.label == "chair" for i in items)
        laptops_left -= sum(i.label == "laptop" for i in items)
    for _ in range(laptops_left):  # laptops that found no table: on a cabinet of their own
        cab_w, cab_d, cab_h = rng.uniform(0.8, 1.2), rng.uniform(0.4, 0.5), rng.uniform(0.7, 0.8)
        laptop_on_top = _transform(laptop_parts(rng), math.radians(rng.normal(0.0, 10.0)), (0.0, 0.0, cab_h))
        members = [(cabinet_parts(rng, cab_w, cab_d, cab_h), {"kind": "cabinet"}), (laptop_on_top, {"label": "laptop"})]
        items = layout.place_group(members, pad=_PAD_WALL_ITEM, against_wall=True)
        if items is None:
            raise _PlacementFailed("laptop on a cabinet")
        layout.add(*items)
    for _ in range(chairs_left):  # chairs that found no table: against a wall, facing the room
        item = layout.place_against_wall(chair_parts(rng), pad=_PAD_LONE_CHAIR, label="chair")
        if item is None:
            raise _PlacementFailed("chair")
        layout.add(item)
    # Clutter: shelves and cabinets along walls, plants, boxes, a lamp. Best effort.
    clutter = [("bookshelf", bookshelf_parts, _PAD_WALL_ITEM)] * int(rng.integers(1, 3))
    clutter += [("cabinet", lambda r: cabinet_parts(r, r.uniform(0.6, 1.2), r.uniform(0.35, 0.5), r.uniform(0.7, 0.95)), _PAD_WALL_ITEM)] * int(rng.integers(0, 2))
    clutter += [("plant", plant_parts, _PAD_SMALL)] * int(rng.integers(1, 3))
    clutter += [("boxes", boxes_parts, _PAD_SMALL)] * int(rng.integers(1, 3))
    clutter += [("lamp", lamp_parts, _PAD_SMALL)] * int(rng.integers(0, 2))
    for kind, build, pad in clutter:
        item = layout.place_against_wall(build(rng), pad=pad, kind=kind, tries=30)
        if item is not None:
            layout.add(item)
    return layout


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
    wanted = _check_counts(counts) if counts is not None else _default_counts(rng)
    for attempt in range(40):
        try:
            layout = _layout_room(rng, size, wanted)
            break
        except _PlacementFailed as exc:
            log.debug("room seed %d: layout attempt %d failed to place a %s", seed, attempt, exc)
    else:
        raise InvalidInput("counts", f"objects that fit a {size[0]:g} x {size[1]:g} m room", repr(wanted))
    return _build_room(seed, size, layout)


def _build_room(seed: int, size: np.ndarray, layout: _Layout) -> Room:
    vertices, triangles, colors, instance, clutter_ids = [], [], [], [], []
    objects, clutter = [], []
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
    room = Room(
        seed=seed,
        size_m=size,
        objects=tuple(objects),
        vertices=np.concatenate(vertices).astype(np.float32),
        triangles=np.concatenate(triangles).astype(np.int32),
        triangle_colors=np.concatenate(colors),
        triangle_instance=np.concatenate(instance),
        clutter=tuple(clutter),
        triangle_clutter=np.concatenate(clutter_ids),
    )
    for array in (room.size_m, room.vertices, room.triangles, room.triangle_colors, room.triangle_instance, room.triangle_clutter):
        array.flags.writeable = False
    log.debug("room seed %d: %d objects, %d clutter items, %d triangles", seed, len(objects), len(clutter), len(room.triangles))
    return room


def gt_boxes(room: Room) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(label, min (3,), max (3,)) of every object of the room, for evaluation."""
    return [(o.label, o.aabb_min.copy(), o.aabb_max.copy()) for o in room.objects]
