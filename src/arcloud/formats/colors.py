"""Colours of the exports: one per class (the same in every export) and one per object id."""

from __future__ import annotations

import colorsys

from arcloud.core.types import CLASSES

RGB = tuple[int, int, int]

#: One colour per class (0-255 RGB); other labels are grey.
CLASS_COLORS: dict[str, RGB] = dict(
    zip(CLASSES, [(230, 159, 0), (86, 180, 233), (0, 158, 115), (213, 94, 0), (204, 121, 167)], strict=True)
)
OTHER_COLOR: RGB = (150, 150, 150)


def class_color(label: str) -> RGB:
    return CLASS_COLORS.get(label, OTHER_COLOR)


def object_color(object_id: int) -> RGB:
    """A colour per object id, far from its neighbours' (golden-ratio hues)."""
    hue = (int(object_id) * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return round(r * 255), round(g * 255), round(b * 255)
