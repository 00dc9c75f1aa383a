"""Microsoft 7-Scenes sequences (and any folder in the same layout), parsed once into a dataclass.

A sequence folder holds ``frame-NNNNNN.color.jpg``, ``frame-NNNNNN.depth.png`` (uint16 millimetres;
0 and 65535 = invalid) and ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world, OpenCV camera axes);
optionally ``camera-intrinsics.txt`` (3x3; default fx = fy = 585, cx = 320, cy = 240, the 7-Scenes
Kinect) and ``gravity-direction.txt`` (3 numbers: the direction gravity pulls, in world coordinates).
A scene folder with ``seq-XX`` sub-folders is read as those sequences one after the other.

7-Scenes worlds are not z-up: with ``align_gravity=True`` the poses are rotated (the smallest rotation,
``arcloud.core.boxes.up_rotation``) into a world whose +z is up (opposite gravity), so that gravity-aligned boxes are simply boxes in that world.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from arcloud.core.boxes import up_rotation
from arcloud.core.checks import make_frame
from arcloud.core.types import Frame, Intrinsics
from arcloud.datasets.files import natural_key, read_matrix, read_png_u16, read_rgb
from arcloud.errors import DatasetError

logger = logging.getLogger(__name__)

DEFAULT_INTRINSICS = Intrinsics(585.0, 585.0, 320.0, 240.0)
INVALID_DEPTH_MM = 65535
FRAME_RATE_HZ = 30.0
_SUFFIX = ".pose.txt"


@dataclass(frozen=True, eq=False)
class SevenScenesSequence:
    """A parsed sequence. ``cam2world``: (N, 4, 4) poses of ``frame_names`` in the output world (the
    file world, or the gravity-aligned one when ``world2file`` is not the identity).

    up_file: (3,) unit up (opposite gravity) in the file's world, or None without gravity-direction.txt.
    world2file: (4, 4) maps output-world points to the file's world (identity unless gravity-aligned)."""

    name: str
    root: Path
    intrinsics: Intrinsics
    frame_names: tuple[str, ...]
    frame_dirs: tuple[Path, ...]
    frame_stems: tuple[str, ...]
    cam2world: np.ndarray
    skipped_frames: tuple[str, ...]
    up_file: np.ndarray | None
    world2file: np.ndarray
    device_id: str = "user-0"

    @cached_property
    def _index(self) -> dict[str, int]:
        return {name: i for i, name in enumerate(self.frame_names)}

    @property
    def n_frames(self) -> int:
        return len(self.frame_names)

    @property
    def up(self) -> tuple[float, float, float]:
        """Up in the output world, for ``Params.up`` (+z once gravity-aligned; +z when unknown)."""
        if self.up_file is None:
            return (0.0, 0.0, 1.0)
        up = self.world2file[:3, :3].T @ self.up_file
        return tuple(float(v) for v in up / np.linalg.norm(up))  # type: ignore[return-value]

    def load_frame(self, name: str, *, device_id: str | None = None) -> Frame:
        """The frame ``name``: RGB resized to the depth size if they differ; invalid depth -> 0."""
        if name not in self._index:
            raise DatasetError(f"{self.root}: expected a frame named {name!r} with a valid pose, got none")
        index = self._index[name]
        folder, stem = self.frame_dirs[index], self.frame_stems[index]
        depth_mm = read_png_u16(folder / f"frame-{stem}.depth.png")
        depth_mm = np.where(depth_mm == INVALID_DEPTH_MM, 0, depth_mm).astype(np.uint16)
        rgb = read_rgb(folder / f"frame-{stem}.color.jpg", (depth_mm.shape[1], depth_mm.shape[0]))
        return make_frame(
            rgb,
            depth_mm,
            self.intrinsics,
            self.cam2world[index],
            timestamp_s=index / FRAME_RATE_HZ,
            map_id=self.name,
            device_id=device_id or self.device_id,
            frame_id=name,
            depth_scale=1000.0,
        )

    def frames(self, *, stride: int = 1, limit: int | None = None) -> Iterator[Frame]:
        for name in self.frame_names[:: max(1, int(stride))][:limit]:
            yield self.load_frame(name)


def _sequence_dirs(root: Path) -> list[Path]:
    subdirs = sorted((p for p in root.iterdir() if p.is_dir() and p.name.startswith("seq")), key=lambda p: natural_key(p.name))
    return subdirs or [root]


def _find_file(root: Path, folders: list[Path], name: str) -> Path | None:
    for folder in [*folders, root, root.parent]:
        if (folder / name).is_file():
            return folder / name
    return None


def load_seven_scenes(root: str | Path, *, align_gravity: bool = False, name: str | None = None) -> SevenScenesSequence:
    """Parse a 7-Scenes sequence (or a scene of ``seq-XX`` folders). Frames whose pose is not finite
    are skipped with a logged count."""
    base = Path(root)
    if not base.is_dir():
        raise DatasetError(f"{base}: expected a 7-Scenes folder, got no such folder")
    folders = _sequence_dirs(base)
    intrinsics_path = _find_file(base, folders, "camera-intrinsics.txt")
    if intrinsics_path is not None:
        k = read_matrix(intrinsics_path, (3, 3))
        intrinsics = Intrinsics(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    else:
        logger.info("%s: no camera-intrinsics.txt; using the 7-Scenes default %s", base, DEFAULT_INTRINSICS)
        intrinsics = DEFAULT_INTRINSICS
    gravity_path = _find_file(base, folders, "gravity-direction.txt")
    up_file = None
    if gravity_path is not None:
        gravity = read_matrix(gravity_path, (3,))
        if not np.all(np.isfinite(gravity)) or np.linalg.norm(gravity) < 1e-9:
            raise DatasetError(f"{gravity_path}: expected a finite non-zero direction, got {gravity}")
        up_file = -gravity / np.linalg.norm(gravity)

    names, dirs, stems_kept, poses, skipped = [], [], [], [], []
    for folder in folders:
        stems = sorted((p.name[len("frame-") : -len(_SUFFIX)] for p in folder.glob(f"frame-*{_SUFFIX}")), key=natural_key)
        prefix = f"{folder.name}-" if folder != base else ""
        for stem in stems:
            pose = read_matrix(folder / f"frame-{stem}{_SUFFIX}", (4, 4))
            if not np.all(np.isfinite(pose)):
                skipped.append(prefix + stem)
                continue
            names.append(prefix + stem)
            dirs.append(folder)
            stems_kept.append(stem)
            poses.append(pose)
    if not names:
        raise DatasetError(f"{base}: expected frame-*.pose.txt files with finite poses, got none")
    if skipped:
        logger.warning("%s: skipped %d of %d frames with invalid poses", base, len(skipped), len(names) + len(skipped))

    world2file = np.eye(4)
    if align_gravity and up_file is not None:
        world2file[:3, :3] = up_rotation(up_file).T  # up_rotation takes up to +z: file -> world
    cam2file = np.asarray(poses)
    cam2world = np.einsum("ij,njk->nik", np.linalg.inv(world2file), cam2file)
    return SevenScenesSequence(
        name=name or base.name,
        root=base,
        intrinsics=intrinsics,
        frame_names=tuple(names),
        frame_dirs=tuple(dirs),
        frame_stems=tuple(stems_kept),
        cam2world=cam2world,
        skipped_frames=tuple(skipped),
        up_file=up_file,
        world2file=world2file,
    )


__all__ = ["DEFAULT_INTRINSICS", "SevenScenesSequence", "load_seven_scenes"]
