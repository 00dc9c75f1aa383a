"""Microsoft 7-Scenes sequences (and any folder in the same layout), parsed once into a dataclass.

A sequence folder holds ``frame-NNNNNN.color.jpg``, ``frame-NNNNNN.depth.png`` (uint16 millimetres;
0 and 65535 = invalid) and ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world, OpenCV camera axes);
optionally ``camera-intrinsics.txt`` (3x3; default fx = fy = 585, cx = 320, cy = 240, the 7-Scenes
Kinect) and ``gravity-direction.txt`` (3 numbers: the direction gravity pulls, in world coordinates).
A scene folder with ``seq-XX`` sub-folders is read as those sequences one after the other.

7-Scenes worlds are not z-up: up in the pose frame is chosen by ``arcloud.datasets.gravity.choose_up``
(given, ``gravity-direction.txt``, the ground truth's, or estimated from the depth), and with
``align_gravity=True`` the poses are rotated (the smallest rotation, ``arcloud.core.gravity.up_rotation``)
into a world whose +z is up, so that gravity-aligned boxes are simply boxes in that world.

Optional 3D ground truth, ``gt-boxes.json`` (``arcloud.datasets.gt_boxes``), holds boxes in its own
*aligned* frame (z up, floor at z = 0, x along the walls), related to the file's world by
``file2aligned``. The map's world reaches it through ``SevenScenesSequence.world2gt``
(``file2aligned @ world2file``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.types import Frame, Intrinsics
from arcloud.datasets.files import map_id_of, natural_key, read_matrix, read_png_u16, read_rgb
from arcloud.datasets.frames import ColourCamera, GravityAlignedSequence, LazyFrames
from arcloud.datasets.gravity import GRAVITY_FILE, choose_up, estimate_up_from_frames, gravity_world2file
from arcloud.datasets.gt_boxes import GT_BOXES_FILE, GroundTruthBoxes, load_ground_truth
from arcloud.errors import DatasetError

logger = logging.getLogger(__name__)

DEFAULT_INTRINSICS = Intrinsics(585.0, 585.0, 320.0, 240.0)
INVALID_DEPTH_MM = 65535
FRAME_RATE_HZ = 30.0
_SUFFIX = ".pose.txt"


@dataclass(frozen=True, eq=False)
class SevenScenesSequence(GravityAlignedSequence):
    """A parsed sequence. ``cam2world``: (N, 4, 4) poses of ``frame_names`` in the output world (the
    file world, or the gravity-aligned one when ``world2file`` is not the identity).

    up_file: (3,) unit up (opposite gravity) in the file's world, or None when unknown; ``up_source``
    says where it came from (``arcloud.datasets.gravity.choose_up``).
    world2file: (4, 4) maps output-world points to the file's world (identity unless gravity-aligned).
    ground_truth: ``gt-boxes.json`` parsed (the folder's, or the one given), or None.
    colour: the colour camera, when colour and depth are not registered (Kinect v1: frames then carry it,
    and masks drawn on colour land where the colour camera saw); None: registered pixel for pixel."""

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
    ground_truth: GroundTruthBoxes | None = None
    colour: ColourCamera | None = None
    device_id: str = "user-0"
    up_source: str = "none"

    def frame_number(self, name: str) -> int:
        """The number in a frame's file name (``frame-000123`` -> 123), as ground truth counts frames."""
        if name not in self._index:
            raise DatasetError(f"{self.root}: expected a frame named {name!r} with a valid pose, got none")
        return int(self.frame_stems[self._index[name]])

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
            rgb_intrinsics=None if self.colour is None else self.colour.intrinsics,
            depth2rgb=None if self.colour is None else self.colour.depth2rgb,
        )


def _sequence_dirs(root: Path) -> list[Path]:
    subdirs = sorted((p for p in root.iterdir() if p.is_dir() and p.name.startswith("seq")), key=lambda p: natural_key(p.name))
    return subdirs or [root]


def _find_file(root: Path, folders: list[Path], name: str) -> Path | None:
    for folder in [*folders, root, root.parent]:
        if (folder / name).is_file():
            return folder / name
    return None


def load_seven_scenes(
    root: str | Path,
    *,
    align_gravity: bool = False,
    name: str | None = None,
    colour: ColourCamera | None = None,
    gt_boxes: str | Path | None = None,
    up: object = None,
    estimate_up: bool = False,
) -> SevenScenesSequence:
    """Parse a 7-Scenes sequence (or a scene of ``seq-XX`` folders), with ``gt_boxes`` (a ground-truth
    file) or else the folder's ``gt-boxes.json`` when it has one. Frames whose pose is not finite are
    skipped with a logged count. ``name`` (default: the folder's name, as a map id) names the maps.

    Up in the pose frame: ``up`` (3 numbers), else ``gravity-direction.txt``, else the ground truth's,
    else, with ``estimate_up``, an estimate from the depth (``arcloud.datasets.gravity``).

    ``colour``: the colour camera (the 7-Scenes release does not calibrate it; its Kinect's colour and
    depth differ by focal length and a 3.5 cm baseline, so masks miss the depth by up to ~35 px near the
    borders). None takes the one the ground truth estimated, when present, else treats the images as
    registered."""
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

    gt_path = Path(gt_boxes) if gt_boxes is not None else base / GT_BOXES_FILE
    ground_truth = load_ground_truth(gt_path) if gt_boxes is not None or gt_path.is_file() else None
    cam2file = np.asarray(poses)
    in_file_world = SevenScenesSequence(
        name=name or map_id_of(base.name),
        root=base,
        intrinsics=intrinsics,
        frame_names=tuple(names),
        frame_dirs=tuple(dirs),
        frame_stems=tuple(stems_kept),
        cam2world=cam2file,
        skipped_frames=tuple(skipped),
        up_file=None,
        world2file=np.eye(4),
        ground_truth=ground_truth,
        colour=colour if colour is not None else (ground_truth.colour if ground_truth is not None else None),
    )
    choice = choose_up(
        given=up,
        gravity_file=_find_file(base, folders, GRAVITY_FILE),
        ground_truth=ground_truth,
        estimate=(lambda: estimate_up_from_frames(LazyFrames(names, in_file_world.load_frame, cache=False))) if estimate_up else None,
        where=base,
    )  # fmt: skip
    world2file = gravity_world2file(choice.up_file) if align_gravity else np.eye(4)
    return replace(
        in_file_world,
        cam2world=np.einsum("ij,njk->nik", np.linalg.inv(world2file), cam2file),
        up_file=choice.up_file,
        up_source=choice.source,
        world2file=world2file,
    )


__all__ = ["DEFAULT_INTRINSICS", "SevenScenesSequence", "load_seven_scenes"]
