"""Furniture of the generated rooms as mesh parts: the five classes (chair, table, couch, TV, laptop)
and clutter (cabinets, shelves, plants, boxes, lamps), each in its own frame (footprint centred on
the origin, bottom at z = 0, front towards -y), with sizes of real furniture and colours drawn from
palettes."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from arcloud.sim.primitives import Part, box, cylinder, ellipsoid, rot_x

# ----------------------------------------------------------------------------------------------------
# Palettes (RGB) and per-object colour variation.

WOOD = ((150, 105, 65), (120, 80, 50), (182, 142, 98), (96, 66, 42), (205, 175, 135), (70, 50, 35))
FABRIC = ((112, 112, 120), (60, 80, 122), (172, 152, 122), (72, 102, 82), (140, 62, 56), (46, 46, 52), (150, 130, 160))
SEAT = ((60, 60, 66), (172, 42, 42), (42, 92, 152), (222, 222, 216), (92, 122, 72), (210, 160, 60))
METAL = ((52, 52, 56), (172, 172, 178), (30, 30, 32))
PAINT = ((226, 221, 206), (210, 216, 222), (232, 226, 216), (202, 212, 196), (222, 208, 196))
CABINET = ((232, 232, 228), (40, 40, 44), (150, 105, 65), (120, 80, 50), (190, 195, 200))
BOOKS = ((160, 40, 40), (40, 70, 140), (200, 170, 60), (40, 110, 70), (230, 230, 220), (90, 50, 110), (30, 30, 30))


def pick_color(rng: np.random.Generator, palette: Sequence[Sequence[int]], spread: float = 10.0) -> np.ndarray:
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
    wood = pick_color(rng, WOOD)
    seat_color = wood if style == 0 else pick_color(rng, SEAT)
    leg_color = wood if style == 0 else (pick_color(rng, METAL, 4) if style == 1 else seat_color * 0.85)
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
    tilt = rot_x(-math.radians(rng.uniform(2.0, 10.0)))  # lean the backrest back (towards +y)
    pivot = (0.0, d / 2 - back_t, seat_h)
    parts.append(
        box((-w / 2, d / 2 - back_t, seat_h), (w / 2, d / 2, seat_h + back_h), seat_color * 0.95, rotation=tilt, pivot=pivot)
    )
    return parts


def table_parts(rng: np.random.Generator) -> tuple[list[Part], float, float, float]:
    """A top on four legs with an apron: 1.2-1.8 x 0.7-0.95 m, 0.72-0.77 m tall.

    Returns the parts and the top's length (x), width (y) and height."""
    length, width = rng.uniform(1.2, 1.8), rng.uniform(0.7, 0.95)
    height, top_t = rng.uniform(0.72, 0.77), rng.uniform(0.025, 0.05)
    top_color = pick_color(rng, WOOD + ((235, 235, 230), (60, 60, 62)))
    leg_color = top_color * 0.9 if rng.random() < 0.6 else pick_color(rng, METAL, 4)
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
    fabric = pick_color(rng, FABRIC)
    feet = pick_color(rng, WOOD + METAL, 4)
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
        parts.append(
            box(
                (a + 0.005, -d / 2 + 0.01, seat_h - cushion_t),
                (b - 0.005, d / 2 - back_t, seat_h),
                fabric * rng.uniform(0.95, 1.05),
            )
        )
    parts.append(box((-w / 2, d / 2 - back_t, foot), (w / 2, d / 2, back_h), fabric * 0.97))
    for sx in (-1, 1):
        x0, x1 = sorted((sx * w / 2, sx * inner))
        parts.append(box((x0, -d / 2, foot), (x1, d / 2 - back_t, arm_h), fabric))
    return parts


def tv_parts(rng: np.random.Generator, *, wall_mounted: bool, width_m: tuple[float, float] = (0.72, 1.45)) -> list[Part]:
    """A thin panel (32-65 inch by default, 16:9; ``width_m`` 0.5-0.62 for a desk monitor) with a dark screen
    facing -y, on a foot and neck unless ``wall_mounted`` (then the panel's bottom is at z = 0 of the object frame)."""
    w = rng.uniform(*width_m)
    h = w * 9 / 16 + 0.04
    t = rng.uniform(0.03, 0.07)
    body = pick_color(rng, ((22, 22, 24), (40, 40, 44), (180, 180, 185)), 4)
    screen = np.clip(pick_color(rng, ((18, 22, 36), (26, 30, 44), (60, 80, 110)), 8), 0, 255)
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
    shell = pick_color(rng, ((190, 190, 196), (44, 44, 48), (120, 120, 128)), 6)
    keys = shell * 0.45
    screen = np.clip(pick_color(rng, ((30, 40, 70), (200, 210, 225), (60, 90, 140)), 12), 0, 255)
    open_deg = rng.uniform(95.0, 125.0)
    tilt = rot_x(-math.radians(open_deg - 90.0))
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
    color = pick_color(rng, CABINET, 6)
    parts = [box((-w / 2, -d / 2, 0.0), (w / 2, d / 2, h - 0.02), color)]
    parts.append(box((-w / 2, -d / 2, h - 0.02), (w / 2, d / 2, h), color * 0.92))
    for a, b in ((-w / 2 + 0.02, -0.005), (0.005, w / 2 - 0.02)):
        parts.append(box((a, -d / 2 - 0.006, 0.05), (b, -d / 2, h - 0.05), color * 0.96))
        hx = b - 0.05 if a < 0 else a + 0.05
        parts.append(box((hx - 0.01, -d / 2 - 0.02, h * 0.55), (hx + 0.01, -d / 2 - 0.006, h * 0.75), pick_color(rng, METAL, 4)))
    return parts


def bookshelf_parts(rng: np.random.Generator) -> list[Part]:
    """Side panels, back, shelves and rows of books: 0.6-1.0 m wide, 1.5-2.0 m tall."""
    w, d, h = rng.uniform(0.6, 1.0), rng.uniform(0.28, 0.38), rng.uniform(1.5, 2.0)
    wood, t = pick_color(rng, CABINET, 6), 0.02
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
                parts.append(
                    box((x, -d / 2 + rng.uniform(0.02, 0.06), z0), (x + bw, d / 2 - 0.02, z0 + bh), pick_color(rng, BOOKS, 20))
                )
            x += bw + 0.002
    return parts


def plant_parts(rng: np.random.Generator) -> list[Part]:
    """A pot, a stem and a leafy crown."""
    r, pot_h = rng.uniform(0.12, 0.2), rng.uniform(0.25, 0.4)
    crown = rng.uniform(0.25, 0.4)
    stem_h = rng.uniform(0.2, 0.6)
    pot = pick_color(rng, ((170, 90, 60), (232, 232, 228), (60, 60, 64)), 8)
    leaves = pick_color(rng, ((50, 110, 50), (70, 130, 60), (40, 90, 45)), 10)
    parts = [cylinder((0.0, 0.0), 0.0, pot_h, r, pot, segments=12)]
    parts.append(cylinder((0.0, 0.0), pot_h, pot_h + stem_h, 0.015, (90, 70, 40), segments=6))
    parts.append(
        ellipsoid(
            (0.0, 0.0, pot_h + stem_h + crown * 0.8),
            (crown, crown * rng.uniform(0.8, 1.0), crown * rng.uniform(0.9, 1.3)),
            leaves,
        )
    )
    return parts


def boxes_parts(rng: np.random.Generator) -> list[Part]:
    """One to three stacked cardboard boxes."""
    parts, z = [], 0.0
    w, d = rng.uniform(0.35, 0.6), rng.uniform(0.3, 0.5)
    for _ in range(int(rng.integers(1, 4))):
        h = rng.uniform(0.2, 0.45)
        color = pick_color(rng, ((182, 142, 92), (160, 120, 80), (200, 170, 120)), 8)
        parts.append(box((-w / 2, -d / 2, z), (w / 2, d / 2, z + h), color))
        z += h
        w, d = w * rng.uniform(0.7, 1.0), d * rng.uniform(0.7, 1.0)
    return parts


def lamp_parts(rng: np.random.Generator) -> list[Part]:
    """A floor lamp: base disc, pole and shade."""
    h, shade_r = rng.uniform(1.4, 1.75), rng.uniform(0.16, 0.24)
    metal, shade = pick_color(rng, METAL, 4), pick_color(rng, ((240, 232, 210), (220, 220, 220), (200, 180, 150)), 6)
    return [
        cylinder((0.0, 0.0), 0.0, 0.03, 0.14, metal, segments=12),
        cylinder((0.0, 0.0), 0.03, h - 0.25, 0.012, metal, segments=6),
        cylinder((0.0, 0.0), h - 0.28, h, shade_r, shade, segments=14),
    ]
