"""Points with colours as a binary little-endian PLY (``x y z`` float32, ``red green blue`` uchar), plus
an ``object`` int32 property naming the object each point belongs to (readers that do not know it skip it)."""

from __future__ import annotations

import numpy as np

from arcloud.core.errors import InvalidInput


def points_ply(points_m: np.ndarray, colors: np.ndarray, object_ids: np.ndarray, *, comment: str = "") -> bytes:
    """(N, 3) points, (N, 3) 0-255 colours and (N,) object ids -> the PLY file's bytes."""
    points = np.asarray(points_m, np.float64)
    rgb = np.asarray(colors)
    ids = np.asarray(object_ids)
    n = len(points)
    if points.shape != (n, 3) or rgb.shape != (n, 3) or ids.shape != (n,):
        raise InvalidInput(
            "points", "(N, 3) points, (N, 3) colours, (N,) object ids", f"{points.shape}, {rgb.shape}, {ids.shape}"
        )
    if not np.all(np.isfinite(points)):
        raise InvalidInput("points", "finite coordinates", "NaN or infinity")
    record = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("object", "<i4")]
    )
    rows = np.empty(n, record)
    rows["x"], rows["y"], rows["z"] = points.T
    rows["red"], rows["green"], rows["blue"] = np.clip(rgb, 0, 255).astype(np.uint8).T
    rows["object"] = ids
    comments = "".join(f"comment {line}\n" for line in comment.splitlines() if line)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"{comments}element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "property int object\nend_header\n"
    )
    return header.encode("ascii") + rows.tobytes()
