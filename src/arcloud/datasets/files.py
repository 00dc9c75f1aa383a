"""Small readers and writers for the files dataset folders hold: images, matrices, PLY meshes.

Every reader raises ``DatasetError`` naming the file and what was wrong with it.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from arcloud.errors import DatasetError

#: PLY property types -> numpy little-endian dtypes.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_rgb(path: Path, size_wh: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a colour image, resized (area interpolation) to ``size_wh`` if given."""
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DatasetError(f"{path}: expected a readable colour image, got an unreadable or missing file")
    if size_wh is not None and (bgr.shape[1], bgr.shape[0]) != tuple(size_wh):
        bgr = cv2.resize(bgr, tuple(size_wh), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_png_u16(path: Path) -> np.ndarray:
    """(H, W) uint16 of a 16-bit PNG (depth in millimetres, label ids)."""
    image = read_label_png(path)
    if image.dtype != np.uint16:
        raise DatasetError(f"{path}: expected a 16-bit single-channel PNG, got dtype {image.dtype}")
    return image


def read_label_png(path: Path) -> np.ndarray:
    """(H, W) integer image (8- or 16-bit) of a single-channel PNG, values unchanged."""
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: expected a readable PNG, got an unreadable or missing file")
    if image.ndim != 2:
        raise DatasetError(f"{path}: expected a single-channel image, got shape {image.shape}")
    return image


def resize_nearest(image: np.ndarray, shape_hw: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W) resized to ``shape_hw`` by nearest neighbour (labels must not blend), each pixel taking the
    one under its centre (OpenCV's plain nearest takes one a third of a pixel off: ScanNet's 1296 x 968 labels
    laid on its 640 x 480 depth moved right and down)."""
    import cv2

    if image.shape[:2] == tuple(shape_hw):
        return image
    return cv2.resize(image, (shape_hw[1], shape_hw[0]), interpolation=cv2.INTER_NEAREST_EXACT)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an (H, W) uint8/uint16 image or an (H, W, 3) uint8 RGB image (PNG or JPEG by suffix)."""
    import cv2

    array = image[..., ::-1] if image.ndim == 3 else image
    if not cv2.imwrite(str(path), np.ascontiguousarray(array)):
        raise DatasetError(f"{path}: could not write the image")


def read_matrix(path: Path, shape: tuple[int, ...]) -> np.ndarray:
    """A whitespace-separated matrix of ``shape`` (e.g. a 4x4 pose), float64; may hold inf/nan."""
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: expected {shape} numbers, got an unreadable file ({exc})") from exc
    if values.size != int(np.prod(shape)):
        raise DatasetError(f"{path}: expected {int(np.prod(shape))} numbers {shape}, got {values.size}")
    return values.reshape(shape)


def write_matrix(path: Path, matrix: np.ndarray) -> None:
    """Write a matrix as rows of space-separated numbers (the ScanNet and 7-Scenes pose format)."""
    path.write_text("\n".join(" ".join(f"{v:.9g}" for v in row) for row in np.atleast_2d(matrix)) + "\n")


def read_key_values(path: Path) -> dict[str, str]:
    """``key = value`` lines (a ScanNet ``<scene>.txt``) as a dict of strings."""
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f"{path}: expected a readable text file ({exc})") from exc
    pairs = (line.split("=", 1) for line in lines if "=" in line)
    return {key.strip(): value.strip() for key, value in pairs}


def read_ply_mesh(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """A triangle mesh from a PLY file (ascii or binary little endian).

    Returns vertices (V, 3) float32, vertex colours (V, 3) uint8 or None, triangles (T, 3) int32.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: expected a readable PLY mesh ({exc})") from exc
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path}: expected a PLY header, got {data[:20]!r}")
    body_start = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, ...]]]] = []
    for line in header:
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            elements[-1][2].append(tuple(words[1:]))
    if fmt not in ("ascii", "binary_little_endian"):
        raise DatasetError(f"{path}: expected an ascii or binary_little_endian PLY, got format {fmt!r}")
    names = [name for name, _, _ in elements]
    if "vertex" not in names or "face" not in names:
        raise DatasetError(f"{path}: expected vertex and face elements, got {names}")

    if fmt == "ascii":
        tokens = data[body_start:].split()
        position = 0
        parsed: dict[str, np.ndarray] = {}
        for name, count, props in elements:
            if name == "face":
                triangles = np.empty((count, 3), np.int64)
                for i in range(count):
                    n = int(tokens[position])
                    if n != 3:
                        raise DatasetError(f"{path}: expected triangles, face {i} has {n} vertices")
                    triangles[i] = [int(t) for t in tokens[position + 1 : position + 4]]
                    position += 1 + n + (len(props) - 1)
                parsed["face"] = triangles
            else:
                width = len(props)
                block = np.array(tokens[position : position + count * width], dtype=np.float64)
                parsed[name] = block.reshape(count, width)
                position += count * width
        vertex_props = next(props for name, _, props in elements if name == "vertex")
        columns = {prop[-1]: parsed["vertex"][:, i] for i, prop in enumerate(vertex_props)}
        triangles = parsed["face"]
    else:
        offset = body_start
        columns = {}
        triangles = np.empty((0, 3), np.int64)
        for name, count, props in elements:
            if name == "face":
                if len(props) != 1 or props[0][0] != "list":
                    raise DatasetError(f"{path}: expected faces with one list property, got {props}")
                count_type, index_type = _PLY_TYPES[props[0][1]], _PLY_TYPES[props[0][2]]
                dtype = np.dtype([("n", "<" + count_type), ("v", "<" + index_type, (3,))])
                faces = np.frombuffer(data, dtype, count=count, offset=offset)
                if count and not np.all(faces["n"] == 3):
                    raise DatasetError(f"{path}: expected only triangles, got faces of other sizes")
                triangles = faces["v"].astype(np.int64)
                offset += dtype.itemsize * count
                continue
            if any(p[0] == "list" for p in props):
                raise DatasetError(f"{path}: element {name!r} has list properties, which this reader does not support")
            dtype = np.dtype([(p[1], "<" + _PLY_TYPES[p[0]]) for p in props])
            records: np.ndarray = np.frombuffer(data, dtype, count=count, offset=offset)
            offset += dtype.itemsize * count
            if name == "vertex":
                columns = {p[1]: records[p[1]] for p in props}
    missing = [axis for axis in "xyz" if axis not in columns]
    if missing:
        raise DatasetError(f"{path}: expected vertex properties x, y, z, missing {missing}")
    vertices = np.stack([columns[a] for a in "xyz"], axis=1).astype(np.float32)
    colors = None
    if all(c in columns for c in ("red", "green", "blue")):
        rgb = np.stack([columns[c] for c in ("red", "green", "blue")], axis=1).astype(np.float64)
        if rgb.size and rgb.max() <= 1.0 and not np.issubdtype(columns["red"].dtype, np.integer):
            rgb = rgb * 255.0
        colors = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    if triangles.size and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise DatasetError(f"{path}: expected face indices in [0, {len(vertices)}), got out-of-range indices")
    return vertices, colors, triangles.astype(np.int32)


def map_id_of(name: str) -> str:
    """A map id made of a folder's name: characters a map id may not hold become '_', at most 128 of them."""
    from arcloud.core.checks import MAP_ID_CHARACTERS, MAX_ID_LENGTH

    return "".join(c if c in MAP_ID_CHARACTERS else "_" for c in name)[:MAX_ID_LENGTH] or "recording"


def natural_key(name: str) -> tuple[int, str]:
    """Sort key putting '2' before '10' (frame file stems)."""
    digits = re.findall(r"\d+", name)
    return (int(digits[-1]) if digits else -1, name)
