"""Layout of the generated rooms: the structure (floor, walls, door, window, pictures) and where the
furniture goes. Things are kept apart by their axis-aligned boxes (stacked ones only touch) with
pads between groups, and furniture groups keep a walkway between them so that a user can walk around."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from arcloud.core.types import CLASSES
from arcloud.errors import InvalidInput
from arcloud.sim.furniture import (
    BOOKS,
    FABRIC,
    METAL,
    PAINT,
    WOOD,
    bookshelf_parts,
    boxes_parts,
    cabinet_parts,
    chair_parts,
    couch_parts,
    lamp_parts,
    laptop_parts,
    pick_color,
    plant_parts,
    table_parts,
    tv_parts,
)
from arcloud.sim.primitives import Part, bounds, box, transformed

# Required gaps (metres) between things of different groups: the larger of the two pads applies.
_PAD_WALKWAY = 0.7  # table groups keep a walkway to everything else
_PAD_WALL_ITEM = 0.05  # couches, cabinets, shelves side by side along a wall
_PAD_SMALL = 0.12  # plants, boxes, lamps
_PAD_LONE_CHAIR = 0.3
_WALL_GAP = (0.03, 0.08)  # gap between a wall and the back of what stands against it


class PlacementFailed(Exception):
    """A layout attempt could not place an object; the caller retries with the next draw."""


@dataclass
class PlacedItem:
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


class Layout:
    def __init__(self, rng: np.random.Generator, size_m: np.ndarray) -> None:
        self.rng = rng
        self.size = size_m
        self.items: list[PlacedItem] = []
        self.structure: list[Part] = []
        self._group = 0

    def new_group(self) -> int:
        self._group += 1
        return self._group

    def fits(self, item: PlacedItem, *, wall_margin: float = 0.0) -> bool:
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

    def make(
        self, parts_local: list[Part], yaw_rad: float, xyz: Sequence[float], *, pad: float, group: int, **kw: Any
    ) -> PlacedItem:
        parts = transformed(parts_local, yaw_rad, xyz)
        lo, hi = bounds(parts)
        return PlacedItem(parts, lo, hi, pad, group, yaw_rad=yaw_rad, **kw)

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
        members: Sequence[tuple[list[Part], Mapping[str, object]]],
        *,
        pad: float,
        against_wall: bool,
        tries: int = 60,
        z: float = 0.0,
        interior_margin_m: float = 0.7,
    ) -> list[PlacedItem] | None:
        """Place parts that move together (each member: local parts and ``PlacedItem`` fields such as
        label or kind), either with their back (local +y side) against a random wall, facing the
        room, or as an island turned by about 0 or 90 degrees. None when no try fits."""
        lo, hi = bounds([p for parts, _ in members for p in parts])
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
            if all(_boxes_apart((a.lo, a.hi), (b.lo, b.hi)) for k, a in enumerate(items) for b in items[k + 1 :]):
                return items
        return None

    def place_against_wall(
        self, parts_local: list[Part], *, pad: float, tries: int = 60, z: float = 0.0, **kw: object
    ) -> PlacedItem | None:
        """Place one thing with its back (local +y side) against a wall; None when no try fits."""
        items = self.place_group([(parts_local, kw)], pad=pad, against_wall=True, tries=tries, z=z)
        return None if items is None else items[0]

    def add(self, *items: PlacedItem) -> None:
        self.items.extend(items)


def _structure(layout: Layout) -> None:
    """Floor (planks or tiles), walls, ceiling, baseboards, a door, a window and pictures."""
    rng, (x_size, y_size, z_size) = layout.rng, layout.size
    parts = layout.structure
    floor_base = pick_color(rng, WOOD[:5] + ((150, 150, 150), (120, 115, 110), (200, 195, 185)), 8)
    if rng.random() < 0.65:  # planks along x, staggered
        plank = rng.uniform(0.14, 0.24)
        for y0 in np.arange(0.0, y_size, plank):
            x = -rng.uniform(0.0, 1.2)
            while x < x_size:
                x1 = min(x + rng.uniform(0.9, 2.0), x_size)
                parts.append(
                    box((max(x, 0.0), y0, -0.01), (x1, min(y0 + plank, y_size), 0.0), floor_base * rng.uniform(0.9, 1.1))
                )
                x = x1
    else:  # square tiles
        tile = rng.uniform(0.4, 0.6)
        for x0 in np.arange(0.0, x_size, tile):
            for y0 in np.arange(0.0, y_size, tile):
                parts.append(
                    box(
                        (x0, y0, -0.01),
                        (min(x0 + tile, x_size), min(y0 + tile, y_size), 0.0),
                        floor_base * rng.uniform(0.95, 1.05),
                    )
                )
    paint = pick_color(rng, PAINT, 6)
    t = 0.05
    parts += [
        box((-t, -t, 0.0), (x_size + t, 0.0, z_size), paint),
        box((x_size, -t, 0.0), (x_size + t, y_size + t, z_size), paint * 0.98),
        box((-t, y_size, 0.0), (x_size + t, y_size + t, z_size), paint * 1.01),
        box((-t, -t, 0.0), (0.0, y_size + t, z_size), paint * 0.99),
        box((-t, -t, z_size), (x_size + t, y_size + t, z_size + t), (242, 242, 240)),
    ]
    trim = pick_color(rng, ((240, 240, 238), (150, 105, 65), (60, 60, 62)), 4)
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
    door = [
        box(
            (-door_w / 2, -0.015, 0.0),
            (door_w / 2, 0.015, 2.05),
            pick_color(rng, ((210, 190, 160), (240, 240, 236), (120, 80, 50)), 6),
        )
    ]
    door.append(box((door_w / 2 - 0.1, -0.06, 0.95), (door_w / 2 - 0.05, -0.015, 1.0), pick_color(rng, METAL, 4)))
    door_item = layout.make(door, yaw, (centre[0], centre[1], 0.0), pad=0.0, group=layout.new_group(), kind="door")
    swing = layout.make(
        [box((-0.6, -1.0, 0.0), (0.6, 0.0, 2.05), (0, 0, 0))], yaw, (centre[0], centre[1], 0.0), pad=0.0, group=layout.new_group()
    )
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
    window = [box((-win_w / 2, -0.01, z0), (win_w / 2, 0.01, z1), pick_color(rng, ((170, 200, 232), (190, 215, 240)), 8))]
    for a, b in (
        ((-win_w / 2 - 0.05, z0 - 0.05), (win_w / 2 + 0.05, z0)),
        ((-win_w / 2 - 0.05, z1), (win_w / 2 + 0.05, z1 + 0.05)),
    ):
        window.append(box((a[0], -0.03, a[1]), (b[0], 0.01, b[1]), frame))
    for sx in (-1, 1):
        window.append(box((sx * win_w / 2 - 0.05 * (sx < 0), -0.03, z0), (sx * win_w / 2 + 0.05 * (sx > 0), 0.01, z1), frame))
    window.append(box((-0.02, -0.02, z0), (0.02, 0.0, z1), frame))
    layout.add(layout.make(window, yaw, (centre[0], centre[1], 0.0), pad=0.0, group=layout.new_group(), kind="window"))
    for _ in range(int(rng.integers(1, 4))):
        pw, ph = rng.uniform(0.3, 0.9), rng.uniform(0.3, 0.7)
        picture = [
            box((-pw / 2, -0.025, 0.0), (pw / 2, 0.0, ph), (30, 30, 30), face_colors={"-y": pick_color(rng, BOOKS + FABRIC, 30)})
        ]
        for _ in range(10):
            w = int(rng.choice(walls))
            if pw + 0.4 > layout.wall_length(w):
                continue
            centre, yaw = layout.wall_pose(w, rng.uniform(pw / 2 + 0.2, layout.wall_length(w) - pw / 2 - 0.2), 0.025, 0.0)
            item = layout.make(
                picture, yaw, (centre[0], centre[1], rng.uniform(1.3, 1.7)), pad=0.05, group=layout.new_group(), kind="picture"
            )
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
    table_local, length, width, _height = table_parts(rng)
    table_lo, table_hi = bounds(table_local)
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
        lo, hi = bounds(chair_local)
        depth = hi[1] - lo[1]
        gap = rng.uniform(0.08, 0.3)
        if side != 0:  # a long side, facing the table: the chair's front (its local -y) points at it
            centre = np.array([x + rng.normal(0.0, 0.04), side * (width / 2 + gap + depth / 2)])
            yaw = 0.0 if side > 0 else math.pi
        else:  # an end
            centre = np.array([x * (length / 2 + gap + depth / 2), rng.normal(0.0, 0.04)])
            yaw = math.pi / 2 if x < 0 else -math.pi / 2
        yaw += math.radians(rng.normal(0.0, 8.0))
        parts = transformed(chair_local, yaw, (centre[0], centre[1], 0.0))
        chair_box = bounds(parts)
        if all(_boxes_apart(chair_box, other) for other in kept):
            kept.append(chair_box)
            members.append((parts, {"label": "chair"}))
    laptops: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(n_laptops):
        laptop_local = laptop_parts(rng)
        for _ in range(20):
            centre = rng.uniform((-length / 2 + 0.2, -width / 2 + 0.2), (length / 2 - 0.2, width / 2 - 0.2))
            # Keyboard towards the nearer long side, where its user sits; a desk's user sits at -y.
            toward = 0.0 if centre[1] < 0 or against_wall else math.pi
            parts = transformed(
                laptop_local, toward + math.radians(rng.normal(0.0, 15.0)), (centre[0], centre[1], float(table_hi[2]))
            )
            lo, hi = bounds(parts)
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


def default_counts(rng: np.random.Generator) -> dict[str, int]:
    tables = int(rng.integers(2, 4))
    return {"chair": 2 * tables, "table": tables, "laptop": int(rng.integers(2, 4)), "couch": 2, "tv": 2}


def check_counts(counts: Mapping[str, int]) -> dict[str, int]:
    checked = {name: 0 for name in CLASSES}
    for name, n in counts.items():
        if name not in CLASSES:
            raise InvalidInput("counts", f"class names from {CLASSES}", repr(name))
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0 or n > 40:
            raise InvalidInput(f"counts[{name!r}]", "an integer from 0 to 40", repr(n))
        checked[name] = int(n)
    return checked


def layout_room(rng: np.random.Generator, size_m: np.ndarray, counts: dict[str, int]) -> Layout:
    layout = Layout(rng, size_m)
    _structure(layout)
    for _ in range(counts["couch"]):
        item = layout.place_against_wall(couch_parts(rng), pad=_PAD_WALL_ITEM, label="couch")
        if item is None:
            raise PlacementFailed("couch")
        layout.add(item)
    for _ in range(counts["tv"]):
        if rng.random() < 0.35:  # on the wall, 0.9-1.3 m up
            item = layout.place_against_wall(
                tv_parts(rng, wall_mounted=True), pad=_PAD_WALL_ITEM, z=rng.uniform(0.9, 1.3), label="tv"
            )
            if item is None:
                raise PlacementFailed("tv")
            layout.add(item)
            continue
        # On a low cabinet, standing on its top near the back.
        tv_local = tv_parts(rng, wall_mounted=False)
        lo, hi = bounds(tv_local)
        cab_w, cab_d, cab_h = (hi[0] - lo[0]) + rng.uniform(0.15, 0.6), rng.uniform(0.38, 0.5), rng.uniform(0.4, 0.6)
        tv_on_top = transformed(tv_local, math.radians(rng.normal(0.0, 3.0)), (0.0, cab_d / 2 - 0.14, cab_h))
        members = [(cabinet_parts(rng, cab_w, cab_d, cab_h), {"kind": "tv cabinet"}), (tv_on_top, {"label": "tv"})]
        items = layout.place_group(members, pad=_PAD_WALL_ITEM, against_wall=True)
        if items is None:
            raise PlacementFailed("tv on a cabinet")
        layout.add(*items)
    n_tables = counts["table"]
    chairs_left, laptops_left = counts["chair"], counts["laptop"]
    for k in range(n_tables):
        chairs_here = min(6, math.ceil(chairs_left / (n_tables - k))) if chairs_left else 0
        laptops_here = min(2, math.ceil(laptops_left / (n_tables - k))) if laptops_left else 0
        items = None
        for against_wall in (False, True) if rng.random() < 0.75 else (True, False):
            table_members = _table_group_local(rng, chairs_here, laptops_here, against_wall=against_wall)
            items = layout.place_group(table_members, pad=_PAD_WALKWAY, against_wall=against_wall, tries=80)
            if items is not None:
                break
        if items is None:
            raise PlacementFailed("table group")
        layout.add(*items)
        chairs_left -= sum(i.label == "chair" for i in items)
        laptops_left -= sum(i.label == "laptop" for i in items)
    for _ in range(laptops_left):  # laptops that found no table: on a cabinet of their own
        cab_w, cab_d, cab_h = rng.uniform(0.8, 1.2), rng.uniform(0.4, 0.5), rng.uniform(0.7, 0.8)
        laptop_on_top = transformed(laptop_parts(rng), math.radians(rng.normal(0.0, 10.0)), (0.0, 0.0, cab_h))
        members = [(cabinet_parts(rng, cab_w, cab_d, cab_h), {"kind": "cabinet"}), (laptop_on_top, {"label": "laptop"})]
        items = layout.place_group(members, pad=_PAD_WALL_ITEM, against_wall=True)
        if items is None:
            raise PlacementFailed("laptop on a cabinet")
        layout.add(*items)
    for _ in range(chairs_left):  # chairs that found no table: against a wall, facing the room
        item = layout.place_against_wall(chair_parts(rng), pad=_PAD_LONE_CHAIR, label="chair")
        if item is None:
            raise PlacementFailed("chair")
        layout.add(item)
    # Clutter: shelves and cabinets along walls, plants, boxes, a lamp. Best effort.
    clutter: list[tuple[str, Callable[[np.random.Generator], list[Part]], float]]
    clutter = [("bookshelf", bookshelf_parts, _PAD_WALL_ITEM)] * int(rng.integers(1, 3))
    clutter += [
        ("cabinet", lambda r: cabinet_parts(r, r.uniform(0.6, 1.2), r.uniform(0.35, 0.5), r.uniform(0.7, 0.95)), _PAD_WALL_ITEM)
    ] * int(rng.integers(0, 2))
    clutter += [("plant", plant_parts, _PAD_SMALL)] * int(rng.integers(1, 3))
    clutter += [("boxes", boxes_parts, _PAD_SMALL)] * int(rng.integers(1, 3))
    clutter += [("lamp", lamp_parts, _PAD_SMALL)] * int(rng.integers(0, 2))
    for kind, build, pad in clutter:
        item = layout.place_against_wall(build(rng), pad=pad, kind=kind, tries=30)
        if item is not None:
            layout.add(item)
    return layout


def office_layout(rng: np.random.Generator, size_m: np.ndarray) -> Layout:
    """An office as the held-out real one is described (issue 20): two desks pushed together along their long
    sides in the middle of the room; on the first, two monitors side by side (0.02-0.08 m apart) facing its
    user; on the second, one monitor back to back with them (their screens 0.25-0.35 m apart) and a laptop;
    a chair at each desk, a third against a wall; shelves and a cabinet along the walls."""
    layout = Layout(rng, size_m)
    _structure(layout)
    group = layout.new_group()
    centre = np.array([size_m[0] / 2 + rng.uniform(-0.3, 0.3), size_m[1] / 2 + rng.uniform(-0.2, 0.2)])
    yaw = math.radians(rng.normal(0.0, 3.0))
    first, _, width_a, height_a = table_parts(rng)
    second, length_b, width_b, height_b = table_parts(rng)
    turn = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])

    def at(parts: list[Part], local_xy: Sequence[float], local_yaw: float, z: float = 0.0, **kw: Any) -> PlacedItem:
        xy = centre + turn @ np.asarray(local_xy, float)
        return layout.make(parts, yaw + local_yaw, (xy[0], xy[1], z), pad=0.0, group=group, **kw)

    items = [
        at(first, (0.0, -width_a / 2 - 0.003), 0.0, label="table"),
        at(second, (rng.uniform(-0.2, 0.2), width_b / 2 + 0.003), 0.0, label="table"),
    ]
    gap = rng.uniform(0.02, 0.08)
    apart = rng.uniform(0.25, 0.35)  # screen to screen, back to back
    monitors = [tv_parts(rng, wall_mounted=False, width_m=(0.5, 0.62)) for _ in range(3)]
    widths = [float(np.ptp(bounds(m)[0:2], axis=0)[0]) for m in monitors]
    x0 = -(widths[0] + gap) / 2
    items += [
        at(monitors[0], (x0, -apart / 2), 0.0, height_a, label="tv"),
        at(monitors[1], (x0 + (widths[0] + widths[1]) / 2 + gap, -apart / 2), 0.0, height_a, label="tv"),
        at(monitors[2], (rng.uniform(-0.2, 0.2), apart / 2), math.pi, height_b, label="tv"),
        at(laptop_parts(rng), (rng.choice((-1, 1)) * (length_b / 2 - 0.3), width_b / 2 + 0.1), math.pi, height_b, label="laptop"),
    ]
    for side, width in ((-1, width_a), (1, width_b)):
        chair = chair_parts(rng)
        depth = float(np.ptp(bounds(chair)[0:2], axis=0)[1])
        offset = side * (width + rng.uniform(0.0, 0.25) + depth / 2)
        items.append(
            at(
                chair,
                (rng.uniform(-0.3, 0.3), offset),
                (0.0 if side > 0 else math.pi) + math.radians(rng.normal(0, 10)),
                label="chair",
            )
        )
    layout.add(*items)
    lone = layout.place_against_wall(chair_parts(rng), pad=_PAD_LONE_CHAIR, label="chair")
    if lone is None:
        raise PlacementFailed("chair")
    layout.add(lone)
    for kind, build in (
        ("bookshelf", bookshelf_parts),
        ("bookshelf", bookshelf_parts),
        ("cabinet", lambda r: cabinet_parts(r, 0.9, 0.45, 0.8)),
    ):
        item = layout.place_against_wall(build(rng), pad=_PAD_WALL_ITEM, kind=kind, tries=30)
        if item is not None:
            layout.add(item)
    return layout
