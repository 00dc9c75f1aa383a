"""Mesh primitives of the generated rooms: convex solids (boxes, cylinders, ellipsoids) with
outward-facing triangles and per-triangle colours, and the rigid moves that place them."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

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


def rot_x(angle_rad: float) -> np.ndarray:
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
    face_colors: Mapping[str, Sequence[float] | np.ndarray] | None = None,
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
    center_xy: Sequence[float], z0: float, z1: float, radius: float, color: Sequence[float] | np.ndarray, *, segments: int = 12
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
        [
            np.column_stack([np.full(segments, 2 * segments), j, i]),
            np.column_stack([np.full(segments, 2 * segments + 1), i + segments, j + segments]),
        ]
    )
    triangles = _orient_outward(vertices, np.concatenate([sides, caps]).astype(np.int64))
    return Part(vertices, triangles, _colors(color, len(triangles)))


def ellipsoid(
    center: Sequence[float], radii: Sequence[float], color: Sequence[float] | np.ndarray, *, stacks: int = 6, slices: int = 10
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


def transformed(parts: Sequence[Part], yaw_rad: float, translation: Sequence[float]) -> list[Part]:
    rotation = rot_z(yaw_rad)
    t = np.asarray(translation, np.float64)
    return [Part(p.vertices @ rotation.T + t, p.triangles, p.colors) for p in parts]


def bounds(parts: Sequence[Part]) -> tuple[np.ndarray, np.ndarray]:
    """AABB of the parts' vertices, as the float32 mesh will store them."""
    vertices = np.concatenate([p.vertices for p in parts]).astype(np.float32).astype(np.float64)
    return vertices.min(axis=0), vertices.max(axis=0)
