"""Pictures of results: a top-down map of 3D boxes, and 3D boxes drawn into camera images.

Images taken and returned are RGB (H, W, 3) uint8 and colours are RGB triples; only the PNG writer
converts to OpenCV's BGR. OpenCV is imported when a picture is drawn, not when this module is imported.

Top-down pictures look down the world's z axis (z-up worlds: ScanNet, the simulator): world x points
right and world y points up in the picture; ``px_per_m`` pixels per metre on both axes.
"""

from __future__ import annotations

import logging
import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from arcloud.core.checks import check_finite_number, check_intrinsics, check_pose, check_rgb, describe
from arcloud.core.types import OBB, Intrinsics, LabelledBox
from arcloud.errors import InvalidInput

logger = logging.getLogger(__name__)

RGB = tuple[int, int, int]
#: An oriented box for the top-down picture: the core's gravity-aligned ``OBB`` (yaw about world z) and
#: the label drawn beside it.
LabelledOBB = tuple[str, OBB]

GT_COLOR_RGB: RGB = (0, 160, 60)
CLASS_COLORS_RGB: Mapping[str, RGB] = {
    "chair": (235, 120, 0),
    "table": (30, 90, 220),
    "laptop": (190, 0, 190),
    "couch": (215, 25, 35),
    "tv": (0, 160, 190),
}
POINT_COLOR_RGB: RGB = (190, 190, 190)
BACKGROUND_RGB: RGB = (255, 255, 255)
TEXT_RGB: RGB = (25, 25, 25)

MARGIN_PX = 30
MAX_SIDE_PX = 4096
MIN_WIDTH_PX = 420
GT_THICKNESS_PX = 3
BOX_THICKNESS_PX = 2
EMPTY_EXTENT_M = 1.0
_FONT_SCALE = 0.45
_LINE_SHIFT = 4  # cv2 fixed-point fraction bits: sub-pixel line ends
_EDGES = np.array([(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit])  # (12, 2) corner ids


def color_for(label: str) -> RGB:
    """The colour of a class: fixed for ``CLASSES``, a stable hash-derived colour for others."""
    if label in CLASS_COLORS_RGB:
        return CLASS_COLORS_RGB[label]
    h = zlib.crc32(label.encode())
    channels = [(h >> shift) & 0xFF for shift in (0, 8, 16)]
    r, g, b = (int(40 + c * 160 / 255) for c in channels)
    return r, g, b


def box_corners(box: LabelledBox) -> np.ndarray:
    """(8, 3) corners of a box; corner i takes max on x if bit 0 of i is set, y for bit 1, z for bit 2."""
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    return np.where(bits == 1, box.max, box.min)


# ---------------------------------------------------------------- top-down picture


@dataclass(frozen=True, slots=True)
class TopDownView:
    """How world (x, y) maps to picture pixels: u = left_px + (x - x_min_m) * px_per_m,
    v = top_px + (y_max_m - y) * px_per_m (pixel centres at integer u, v)."""

    x_min_m: float
    y_max_m: float
    px_per_m: float
    left_px: int
    top_px: int

    def to_px(self, xy_m: np.ndarray) -> np.ndarray:
        """(N, 2) world x, y in metres -> (N, 2) float pixel u, v."""
        xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        u = self.left_px + (xy[:, 0] - self.x_min_m) * self.px_per_m
        v = self.top_px + (self.y_max_m - xy[:, 1]) * self.px_per_m
        return np.stack([u, v], axis=1)


@dataclass(frozen=True, eq=False, slots=True)
class TopDownPicture:
    """A rendered top-down picture: ``image_rgb`` (H, W, 3) uint8 and the ``view`` that placed it."""

    image_rgb: np.ndarray
    view: TopDownView


def render_top_down(
    *,
    gt: Sequence[LabelledBox] = (),
    predictions: Sequence[LabelledBox] = (),
    points_xyz: np.ndarray | None = None,
    obbs: Sequence[LabelledOBB] = (),
    title: str = "",
    px_per_m: float = 80,
    point_radius_px: int = 1,
) -> TopDownPicture:
    """The top-down picture in memory (see ``draw_top_down``)."""
    import cv2

    gt_boxes = _check_boxes("gt", gt)
    pred_boxes = _check_boxes("predictions", predictions)
    points = _check_points(points_xyz)
    oriented = [_check_obb(i, o) for i, o in enumerate(obbs)]
    scale = check_finite_number("px_per_m", px_per_m, positive=True)

    xy = [points[:, :2]]
    xy += [np.array([b.min[:2], b.max[:2]]) for b in (*gt_boxes, *pred_boxes)]
    xy += [corners for corners, _, _ in oriented]
    xy_all = np.concatenate(xy) if any(a.size for a in xy) else np.zeros((1, 2))
    lo, hi = xy_all.min(axis=0), xy_all.max(axis=0)
    span = np.maximum(hi - lo, 0.0)
    pad = (np.maximum(span, EMPTY_EXTENT_M * (span == 0)) - span) / 2  # empty axes get 1 m
    lo, hi = lo - pad, hi + pad
    if max(hi - lo) * scale > MAX_SIDE_PX:
        capped = MAX_SIDE_PX / float(max(hi - lo))
        logger.info("top-down picture: %.1f px/m would exceed %d px; using %.1f px/m", scale, MAX_SIDE_PX, capped)
        scale = capped

    legend = _legend_entries(gt_boxes, pred_boxes, oriented, points.shape[0] > 0)
    content_w, content_h = (int(math.ceil(s * scale)) + 1 for s in hi - lo)
    width = max(content_w + 2 * MARGIN_PX, MIN_WIDTH_PX)
    header = 28 if title else 0
    legend_rows = _layout_legend(cv2, legend, width)
    footer = 30 + 22 * max(len(legend_rows), 1)
    height = header + content_h + 2 * MARGIN_PX + footer
    left = (width - content_w) // 2
    view = TopDownView(float(lo[0]), float(hi[1]), scale, left, header + MARGIN_PX)

    image = np.full((height, width, 3), BACKGROUND_RGB, dtype=np.uint8)
    _draw_points(image, view.to_px(points[:, :2]), point_radius_px)
    for b in gt_boxes:
        _rectangle(cv2, image, view, b, GT_COLOR_RGB, GT_THICKNESS_PX)
    for b in pred_boxes:
        _rectangle(cv2, image, view, b, color_for(b.label), BOX_THICKNESS_PX)
    for corners, label, heading in oriented:
        color = color_for(label)
        polygon = view.to_px(corners)
        cv2.polylines(image, [_fixed(polygon)], True, color, BOX_THICKNESS_PX, cv2.LINE_8, _LINE_SHIFT)
        heading_from, heading_to = _fixed(view.to_px(heading))
        cv2.line(image, heading_from, heading_to, color, 1, cv2.LINE_8, _LINE_SHIFT)
        top = polygon[np.argmin(polygon[:, 1])]
        _text(cv2, image, label, top + (0, -5), color)
    for b in pred_boxes:  # labels last so no box covers them
        corner = view.to_px(np.array([[b.min[0], b.max[1]]]))[0]
        _text(cv2, image, f"{b.label} {b.score:.2f}", corner + (0, -5), color_for(b.label))

    if title:  # as large as fits the picture's width, down to a size still read
        title_w = cv2.getTextSize(title, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)[0][0]
        _text(cv2, image, title, (MARGIN_PX // 2, 20), TEXT_RGB, scale=max(0.3, min(0.6, 0.6 * (width - MARGIN_PX) / title_w)))
    footer_top = header + content_h + 2 * MARGIN_PX
    _draw_scale_bar(cv2, image, scale, (MARGIN_PX // 2, footer_top + 12))
    _draw_legend(cv2, image, legend_rows, footer_top + 40)
    return TopDownPicture(image, view)


def draw_top_down(
    path: str | Path,
    *,
    gt: Sequence[LabelledBox] = (),
    predictions: Sequence[LabelledBox] = (),
    points_xyz: np.ndarray | None = None,
    obbs: Sequence[LabelledOBB] = (),
    title: str = "",
    px_per_m: float = 80,
    point_radius_px: int = 1,
) -> Path:
    """Write a top-down PNG of ground-truth and predicted boxes; returns the path written.

    World x is right and y is up. ``points_xyz`` (N, 3) (e.g. fused voxel centres) are drawn as grey
    dots underneath; ``gt`` boxes as thick green outlines; ``predictions`` in a colour per class with
    their label and score; ``obbs`` (label, OBB) as rotated outlines with a heading
    tick. The picture fits all content with a margin, with a legend and a scale bar below. The side is
    at most ``MAX_SIDE_PX``: larger content lowers ``px_per_m``. The parent folder is created."""
    picture = render_top_down(
        gt=gt,
        predictions=predictions,
        points_xyz=points_xyz,
        obbs=obbs,
        title=title,
        px_per_m=px_per_m,
        point_radius_px=point_radius_px,
    )
    return write_png(path, picture.image_rgb)


def write_png(path: str | Path, image_rgb: np.ndarray) -> Path:
    """Write an RGB (H, W, 3) uint8 image as PNG, creating the parent folder; returns the path."""
    import cv2

    out = Path(path)
    if out.suffix.lower() != ".png":
        raise InvalidInput("path", "a file name ending in .png", str(out))
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(check_rgb(image_rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"OpenCV could not encode a PNG of shape {image_rgb.shape}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(encoded.tobytes())
    logger.debug("wrote %s (%d x %d px)", out, image_rgb.shape[1], image_rgb.shape[0])
    return out


def _check_boxes(field_name: str, boxes: Sequence[LabelledBox]) -> list[LabelledBox]:
    checked = list(boxes)
    for i, b in enumerate(checked):
        if not isinstance(b, LabelledBox):
            raise InvalidInput(f"{field_name}[{i}]", "a LabelledBox", describe(b))
    return checked


def _check_points(points_xyz: np.ndarray | None) -> np.ndarray:
    if points_xyz is None:
        return np.zeros((0, 3))
    points = np.asarray(points_xyz, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise InvalidInput("points_xyz", "shape (N, 3)", f"shape {points.shape}")
    return points[np.all(np.isfinite(points), axis=1)]


def _check_obb(i: int, obb: LabelledOBB) -> tuple[np.ndarray, str, np.ndarray]:
    """(4, 2) footprint corners, the label, and the (2, 2) heading tick (centre to the +x face)."""
    try:
        label, box = obb
    except (TypeError, ValueError) as exc:
        raise InvalidInput(f"obbs[{i}]", "(label, OBB)", describe(obb)) from exc
    if not isinstance(box, OBB):
        raise InvalidInput(f"obbs[{i}]", "(label, OBB)", describe(obb))
    c = np.asarray(box.center, dtype=np.float64).ravel()
    s = np.asarray(box.size, dtype=np.float64).ravel()
    if c.shape != (3,) or s.shape != (3,) or not (np.all(np.isfinite(c)) and np.all(np.isfinite(s))):
        raise InvalidInput(f"obbs[{i}]", "finite center (3,) and size (3,)", f"{describe(c)}, {describe(s)}")
    yaw = check_finite_number(f"obbs[{i}].yaw_rad", box.yaw_rad)
    axes = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])  # box x, y in world
    half = s[:2] / 2
    signs = np.array([(1, 1), (-1, 1), (-1, -1), (1, -1)])
    corners = c[:2] + (signs * half) @ axes
    heading = np.array([c[:2], c[:2] + half[0] * axes[0]])
    return corners, str(label), heading


def _fixed(px: np.ndarray) -> np.ndarray:
    """Float pixels -> int32 fixed point for cv2 drawing with ``_LINE_SHIFT``."""
    return np.rint(np.asarray(px) * (1 << _LINE_SHIFT)).astype(np.int32)


def _rectangle(cv2: ModuleType, image: np.ndarray, view: TopDownView, b: LabelledBox, color: RGB, thickness: int) -> None:
    corners = view.to_px(np.array([[b.min[0], b.max[1]], [b.max[0], b.min[1]]]))
    top_left, bottom_right = np.rint(corners).astype(int)
    cv2.rectangle(image, tuple(top_left.tolist()), tuple(bottom_right.tolist()), color, thickness, cv2.LINE_8)


def _draw_points(image: np.ndarray, uv: np.ndarray, radius_px: int) -> None:
    if uv.size == 0:
        return
    height, width = image.shape[:2]
    centres = np.rint(uv).astype(np.int64)
    r = max(int(radius_px), 0)
    for du in range(-r, r + 1):
        for dv in range(-r, r + 1):
            u, v = centres[:, 0] + du, centres[:, 1] + dv
            inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
            image[v[inside], u[inside]] = POINT_COLOR_RGB


def _text(
    cv2: ModuleType,
    image: np.ndarray,
    text: str,
    origin: np.ndarray | Sequence[float],
    color: RGB,
    scale: float = _FONT_SCALE,
    *,
    filled: bool = False,
) -> None:
    """Text kept inside the picture: ``color`` with a white halo, or (``filled``) white on a ``color``
    label box, which reads on any photo."""
    (w, h), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    height, width = image.shape[:2]
    x = int(np.clip(round(float(origin[0])), 3, max(width - w - 3, 3)))
    y = int(np.clip(round(float(origin[1])), h + 3, max(height - baseline - 3, h + 3)))
    if filled:
        cv2.rectangle(image, (x - 2, y - h - 2), (x + w + 2, y + baseline), color, -1)
        cv2.putText(image, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, BACKGROUND_RGB, 1, cv2.LINE_AA)
        return
    cv2.putText(image, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, BACKGROUND_RGB, 3, cv2.LINE_AA)
    cv2.putText(image, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def _scale_bar_m(px_per_m: float) -> float:
    """1 m unless that is shorter than 40 px or longer than 300 px; then 1, 2 or 5 times a power of ten."""
    if 40 <= px_per_m <= 300:
        return 1.0
    for exponent in range(-3, 6):
        for mantissa in (1, 2, 5):
            length = mantissa * 10.0**exponent
            if length * px_per_m >= 40:
                return length
    return 1e5


def _draw_scale_bar(cv2: ModuleType, image: np.ndarray, px_per_m: float, origin: tuple[int, int]) -> None:
    length_m = _scale_bar_m(px_per_m)
    x0, y = origin
    x1 = x0 + int(round(length_m * px_per_m))
    cv2.line(image, (x0, y), (x1, y), TEXT_RGB, 2, cv2.LINE_8)
    for x in (x0, x1):
        cv2.line(image, (x, y - 5), (x, y + 5), TEXT_RGB, 2, cv2.LINE_8)
    label = f"{length_m:g} m" if length_m >= 1 else f"{length_m * 100:g} cm"
    _text(cv2, image, label, (x1 + 8, y + 5), TEXT_RGB)


@dataclass(frozen=True, slots=True)
class _LegendEntry:
    text: str
    color: RGB
    thickness: int
    kind: str  # "line" or "dot"


def _legend_entries(
    gt: list[LabelledBox], predictions: list[LabelledBox], oriented: list[tuple[np.ndarray, str, np.ndarray]], has_points: bool
) -> list[_LegendEntry]:
    entries = []
    if gt:
        entries.append(_LegendEntry("ground truth", GT_COLOR_RGB, GT_THICKNESS_PX, "line"))
    labels = dict.fromkeys([*(b.label for b in predictions), *(label for _, label, _ in oriented)])
    known = [name for name in CLASS_COLORS_RGB if name in labels]
    for name in known + sorted(set(labels) - set(known)):
        entries.append(_LegendEntry(name, color_for(name), BOX_THICKNESS_PX, "line"))
    if has_points:
        entries.append(_LegendEntry("points", POINT_COLOR_RGB, 0, "dot"))
    return entries


def _layout_legend(cv2: ModuleType, entries: list[_LegendEntry], width: int) -> list[list[tuple[int, _LegendEntry]]]:
    """Entries in rows that fit the width: (x offset, entry) per row."""
    rows: list[list[tuple[int, _LegendEntry]]] = [[]]
    x = MARGIN_PX // 2
    for entry in entries:
        (text_w, _), _ = cv2.getTextSize(entry.text, cv2.FONT_HERSHEY_SIMPLEX, _FONT_SCALE, 1)
        entry_w = 30 + text_w + 18
        if rows[-1] and x + entry_w > width - MARGIN_PX // 2:
            rows.append([])
            x = MARGIN_PX // 2
        rows[-1].append((x, entry))
        x += entry_w
    return rows


def _draw_legend(cv2: ModuleType, image: np.ndarray, rows: list[list[tuple[int, _LegendEntry]]], top: int) -> None:
    for r, row in enumerate(rows):
        y = top + 22 * r
        for x, entry in row:
            if entry.kind == "dot":
                cv2.rectangle(image, (x + 8, y - 4), (x + 16, y + 4), entry.color, -1)
            else:
                cv2.line(image, (x, y), (x + 24, y), entry.color, entry.thickness, cv2.LINE_8)
            _text(cv2, image, entry.text, (x + 30, y + 5), TEXT_RGB)


# ---------------------------------------------------------------- boxes in camera images


def draw_boxes_in_image(
    rgb: np.ndarray,
    boxes: Sequence[LabelledBox],
    cam2world: np.ndarray,
    intrinsics: Intrinsics | Mapping[str, float] | Sequence[float],
    *,
    color_rgb: RGB | None = None,
    thickness_px: int = 2,
    show_labels: bool = True,
    near_m: float = 0.05,
) -> np.ndarray:
    """A copy of ``rgb`` (H, W, 3) uint8 with the 12 edges of each 3D box projected into it.

    cam2world (4, 4) is the camera's pose (OpenCV axes); ``intrinsics`` are pinhole fx, fy, cx, cy in
    pixels of this image. Edges are clipped at the plane z = ``near_m`` in front of the camera, so parts
    behind it are not drawn. Colours are per class unless ``color_rgb`` is given (e.g.
    ``GT_COLOR_RGB`` for ground truth); labels show the class and score when ``show_labels``."""
    import cv2

    image = check_rgb(rgb).copy()
    world2cam = np.linalg.inv(check_pose("cam2world", cam2world))
    k = check_intrinsics(intrinsics)
    near = check_finite_number("near_m", near_m, positive=True)
    height, width = image.shape[:2]
    labels: list[tuple[str, np.ndarray, RGB]] = []
    for b in _check_boxes("boxes", boxes):
        corners_cam = box_corners(b) @ world2cam[:3, :3].T + world2cam[:3, 3]
        segments = _clip_near(corners_cam[_EDGES], near)  # (E, 2, 3)
        if segments.shape[0] == 0:
            continue
        uv = np.stack(
            [k.fx * segments[..., 0] / segments[..., 2] + k.cx, k.fy * segments[..., 1] / segments[..., 2] + k.cy],
            axis=-1,
        )  # (E, 2, 2)
        uv = _clip_to_rect(uv, width, height)
        if uv.shape[0] == 0:
            continue
        color = color_rgb if color_rgb is not None else color_for(b.label)
        for start, end in _fixed(uv):
            cv2.line(image, tuple(start.tolist()), tuple(end.tolist()), color, thickness_px, cv2.LINE_8, _LINE_SHIFT)
        top = uv.reshape(-1, 2)[np.argmin(uv[..., 1].ravel())]
        labels.append((f"{b.label} {b.score:.2f}", top + (0, -6), color))
    if show_labels:  # after every edge, so no edge crosses a label
        for text, origin, color in labels:
            _text(cv2, image, text, origin, color, filled=True)
    return image


def _clip_near(segments: np.ndarray, near_m: float) -> np.ndarray:
    """(E, 2, 3) camera-frame segments cut to z >= near_m; segments wholly behind are dropped."""
    z = segments[..., 2]
    keep = np.any(z >= near_m, axis=1)
    seg = segments[keep].copy()
    z = z[keep]
    for end, other in ((0, 1), (1, 0)):
        behind = z[:, end] < near_m
        t = (near_m - z[behind, end]) / (z[behind, other] - z[behind, end])
        seg[behind, end] = seg[behind, end] + t[:, None] * (seg[behind, other] - seg[behind, end])
    return seg


def _clip_to_rect(uv: np.ndarray, width: int, height: int, pad_px: float = 4.0) -> np.ndarray:
    """(E, 2, 2) pixel segments clipped to the image (plus ``pad_px``) by Liang-Barsky; segments
    outside are dropped. Keeps the coordinates small enough for cv2's fixed-point ints."""
    p0, d = uv[:, 0], uv[:, 1] - uv[:, 0]
    lo = np.array([-pad_px, -pad_px])
    hi = np.array([width - 1 + pad_px, height - 1 + pad_px])
    t0 = np.zeros(len(uv))
    t1 = np.ones(len(uv))
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(2):
            ta = (lo[axis] - p0[:, axis]) / d[:, axis]
            tb = (hi[axis] - p0[:, axis]) / d[:, axis]
            parallel = d[:, axis] == 0
            outside = parallel & ((p0[:, axis] < lo[axis]) | (p0[:, axis] > hi[axis]))
            t0 = np.where(parallel, t0, np.maximum(t0, np.minimum(ta, tb)))
            t1 = np.where(parallel, t1, np.minimum(t1, np.maximum(ta, tb)))
            t1 = np.where(outside, -1.0, t1)
    keep = t0 <= t1
    start = p0[keep] + t0[keep, None] * d[keep]
    end = p0[keep] + t1[keep, None] * d[keep]
    return np.stack([start, end], axis=1)


__all__ = [
    "CLASS_COLORS_RGB",
    "GT_COLOR_RGB",
    "LabelledOBB",
    "TopDownPicture",
    "TopDownView",
    "box_corners",
    "color_for",
    "draw_boxes_in_image",
    "draw_top_down",
    "render_top_down",
    "write_png",
]
