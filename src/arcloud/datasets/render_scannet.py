"""Render a scanned, annotated ScanNet mesh into a ScanNet-layout scene walked by K users.

The room comes from the mesh and its annotation, in the scene's aligned frame (z up): the free floor is
the extent of the ``floor`` instance, the obstacles are the floor-plan boxes of every other annotated
instance that stands in the height band a person walks through (walls included), and the targets the
users look at are the centres of the objects of arcloud's classes (and of the other furniture when the
scene has fewer than three of those). Each user
walks one ``arcloud.virtual_camera.walk.plan_walk`` path; the users' frames follow one another in one
sequence (user u has frames ``u * N .. u * N + N - 1``), so the distributed protocol with K users cuts
it back into the users' walks.

Written per frame, with ScanNet's conventions (see docs/datasets.md): ``color/N.jpg`` (vertex colours,
shaded), ``depth/N.png`` (uint16 millimetres, 0 = no surface), ``pose/N.txt`` (cam2world in the
*unaligned* scan frame, as ScanNet stores it), ``instance-filt/N.png`` (the instance's ``object_id + 1``,
0 = unannotated; 8-bit, or 16-bit beyond 255 instances) and ``label-filt/N.png`` (uint16). Per scene:
``intrinsic/`` (colour = depth, both at the render size), ``<scene>.txt`` with ``axisAlignment``, the
mesh and the 3D annotation the scene was read with, the labels tsv beside the scene folder, and
``render.json`` (users, seeds, walk style and each user's drawn walk, ``annotation`` and ``label_ids``).

The 2D ground truth follows the scene's annotation (``ScanNetScene.annotation``), so that a render reads
back with the same instances and names its classes one way:

- v1: the aggregation and segs are copied; ``label-filt`` holds ScanNet label ids (the labels tsv's
  ``id`` of the raw category, as ScanNet's images do), ``render.json`` says ``"label_ids": "scannet"``;
- v2: ``labels_v2/`` is copied (and not the aggregation, whose objectIds the images do not hold);
  ``label-filt`` holds nyu40 ids (v2 has no raw categories), ``render.json`` says ``"label_ids": "nyu40"``.

Walk styles: ``"default"`` walks every user at ``eye_height_m`` with ``plan_walk``'s defaults;
``"random"`` draws each user's walk from the seed (``random_user_walk``): eye height 1.1-1.9 m, speed,
how much of the room a lap covers, glances or long looks, and a hand-held camera's shake; ``"scan"`` walks
the default path but swings the camera along the walls as an operator scanning the room does
(``arcloud.virtual_camera.walk.scan_walk``), looking at no object in particular.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from arcloud.core.types import Intrinsics
from arcloud.datasets.files import write_matrix, write_png
from arcloud.datasets.scannet import LABEL_TSV_NAMES, ScanNetScene, find_label_table, v2_label_paths
from arcloud.errors import DatasetError, InvalidInput
from arcloud.virtual_camera.render import MeshRenderer
from arcloud.virtual_camera.walk import plan_walk, scan_walk

logger = logging.getLogger(__name__)

#: ScanNet's usual depth intrinsics at 640x480 (used when the scene has none).
DEFAULT_DEPTH_INTRINSICS = Intrinsics(577.87, 577.87, 319.5, 239.5)
#: nyu40 ids and raw categories that are room structure, not obstacles one walks around or looks at.
FLOOR_NYU40, CEILING_NYU40, WALL_NYU40 = 2, 22, 1
STRUCTURE_RAW = {"floor", "ceiling", "wall", "window", "door", "doorframe", "curtain", "blinds", "ceiling light"}
#: The same structure by nyu40 id (door, window, blinds, curtain), for v2 scenes that have no raw categories.
STRUCTURE_NYU40 = {FLOOR_NYU40, CEILING_NYU40, WALL_NYU40, 8, 9, 13, 16}
#: What ``label-filt`` images hold, by the scene's annotation.
LABEL_IDS_OF_ANNOTATION = {"v1": "scannet", "v2": "nyu40"}
JPEG_QUALITY = 90
WALK_STYLES = ("default", "random", "scan")
#: Ranges of a random user's walk (``random_user_walk``), drawn uniformly.
EYE_HEIGHT_RANGE_M = (1.1, 1.9)
STEP_RANGE_M = (0.03, 0.1)  # walking speed: metres per frame
COVERAGE_RANGE = (0.5, 1.5)  # one lap of the room / the walk's length
FIXATION_RANGE_FRAMES = (6, 30)  # glances .. long looks
SHAKE_RANGE_DEG = (0.2, 1.5)  # hand-held camera: rotation noise
SHAKE_RANGE_M = (0.002, 0.01)  # and translation noise, per frame, smoothed over a few frames


@dataclass(frozen=True, eq=False)
class RoomLayout:
    """What a walk through the real room needs, in the aligned frame.

    floor_min_xy, floor_max_xy: (2,) the walkable extent. floor_z_m: floor height.
    obstacles_xy: ((2,), (2,)) floor-plan boxes to keep out of. targets: (N, 3) points to look at."""

    floor_min_xy: np.ndarray
    floor_max_xy: np.ndarray
    floor_z_m: float
    obstacles_xy: tuple[tuple[np.ndarray, np.ndarray], ...]
    targets: np.ndarray


def aligned_vertices(scene: ScanNetScene) -> np.ndarray:
    """(V, 3) float32 mesh vertices in the aligned frame."""
    if scene.mesh is None:
        raise DatasetError(f"{scene.root}: expected a mesh <scene>_vh_clean_2.ply, got none")
    a = scene.scan2aligned
    return (scene.mesh.vertices.astype(np.float64) @ a[:3, :3].T + a[:3, 3]).astype(np.float32)


def _is_structure(raw: str, nyu40: int) -> bool:
    return raw.strip().lower() in STRUCTURE_RAW or nyu40 in STRUCTURE_NYU40


def room_layout(
    scene: ScanNetScene, *, band_m: tuple[float, float] = (0.1, 1.9), margin_m: float = 0.0, min_targets: int = 3
) -> RoomLayout:
    """The floor, obstacles and targets of an annotated scene (see the module docstring): the targets are
    the centres of the objects of our classes, joined by the other furniture when fewer than
    ``min_targets``."""
    vertices = aligned_vertices(scene)
    floors = [i for i in scene.instances if i.nyu40_id == FLOOR_NYU40 or i.raw_category.lower() == "floor"]
    if floors:
        floor_points = vertices[np.concatenate([i.vertex_indices for i in floors])]
    else:
        low = vertices[:, 2] < np.percentile(vertices[:, 2], 2) + 0.1
        floor_points = vertices[low]
        logger.warning("scene %s: no floor instance; taking the lowest vertices as the floor", scene.scene_id)
    floor_z = float(np.median(floor_points[:, 2]))
    lo = np.percentile(floor_points[:, :2], 2, axis=0) + margin_m
    hi = np.percentile(floor_points[:, :2], 98, axis=0) - margin_m
    if np.any(hi <= lo):
        raise DatasetError(
            f"scene {scene.scene_id}: expected a floor wider than {2 * margin_m} m, got extent {hi - lo + 2 * margin_m}"
        )
    band_lo, band_hi = floor_z + band_m[0], floor_z + band_m[1]
    obstacles, targets, other_targets = [], [], []
    for inst in scene.instances:
        if inst.nyu40_id in (FLOOR_NYU40, CEILING_NYU40) or inst.raw_category.lower() in ("floor", "ceiling"):
            continue
        if inst.aabb_max[2] >= band_lo and inst.aabb_min[2] <= band_hi:
            obstacles.append((inst.aabb_min[:2].copy(), inst.aabb_max[:2].copy()))
        if inst.label is not None:
            targets.append(inst.center)
        elif not _is_structure(inst.raw_category, inst.nyu40_id):
            other_targets.append(inst.center)
    # Look at the objects of our classes; at other furniture too only when there are too few of ours.
    chosen = targets if len(targets) >= min_targets else targets + other_targets
    all_targets = np.array(chosen, dtype=np.float64).reshape(-1, 3)
    if all_targets.shape[0] == 0:
        all_targets = np.array([[*(lo + hi) / 2, floor_z + 0.8]])
    return RoomLayout(lo, hi, floor_z, tuple(obstacles), all_targets)


@dataclass(frozen=True)
class UserWalk:
    """One user's walk through a room, as drawn for the ``"random"`` style: ``plan_walk``'s eye height,
    step (speed), fixation length and ring inset (from ``coverage``: one lap / the walk's length), and the
    hand-held camera's shake (standard deviations per frame, smoothed over about two frames)."""

    eye_height_m: float
    step_m: float
    coverage: float
    fixation_frames: int
    shake_deg: float
    shake_m: float

    def walk_options(self, layout: RoomLayout, n_frames: int) -> dict[str, float | int]:
        """``plan_walk`` keyword arguments of this walk through ``layout``."""
        size = layout.floor_max_xy - layout.floor_min_xy
        ring_inset_m = max(0.0, float(2 * size.sum() - self.coverage * n_frames * self.step_m) / 8)
        return {"eye_height_m": self.eye_height_m, "eye_height_jitter_m": 0.0, "step_m": self.step_m,
                "fixation_frames": self.fixation_frames, "ring_inset_m": ring_inset_m}  # fmt: skip


def random_user_walk(seed: int, user: int) -> UserWalk:
    """User ``user``'s walk of a ``"random"`` render with ``seed``: every figure drawn uniformly from
    its range (``EYE_HEIGHT_RANGE_M``, ...)."""
    rng = np.random.default_rng([int(seed), int(user), 17])
    return UserWalk(
        eye_height_m=round(float(rng.uniform(*EYE_HEIGHT_RANGE_M)), 3),
        step_m=round(float(rng.uniform(*STEP_RANGE_M)), 4),
        coverage=round(float(rng.uniform(*COVERAGE_RANGE)), 3),
        fixation_frames=int(rng.integers(FIXATION_RANGE_FRAMES[0], FIXATION_RANGE_FRAMES[1] + 1)),
        shake_deg=round(float(rng.uniform(*SHAKE_RANGE_DEG)), 3),
        shake_m=round(float(rng.uniform(*SHAKE_RANGE_M)), 4),
    )


def shake(poses: list[np.ndarray], shake_deg: float, shake_m: float, rng: np.random.Generator) -> list[np.ndarray]:
    """(4, 4) cam2world poses moved as a hand-held camera moves about them: each pose times a small
    rigid motion in its camera frame, rotation and translation noise (standard deviations ``shake_deg``
    and ``shake_m`` per axis) smoothed over about two frames."""
    from scipy.ndimage import gaussian_filter1d
    from scipy.spatial.transform import Rotation

    n = len(poses)
    if n == 0 or (shake_deg == 0 and shake_m == 0):
        return [np.array(p, dtype=np.float64) for p in poses]
    sigma_frames = 2.0
    # Smoothing shrinks white noise by about 1 / sqrt(2 sqrt(pi) sigma); scale it back.
    gain = math.sqrt(2 * math.sqrt(math.pi) * sigma_frames)
    angles = gaussian_filter1d(rng.normal(0.0, math.radians(shake_deg), (n, 3)), sigma_frames, axis=0, mode="nearest") * gain
    offsets = gaussian_filter1d(rng.normal(0.0, shake_m, (n, 3)), sigma_frames, axis=0, mode="nearest") * gain
    motion = np.tile(np.eye(4), (n, 1, 1))
    motion[:, :3, :3] = Rotation.from_rotvec(angles).as_matrix()
    motion[:, :3, 3] = offsets
    return [np.asarray(p, dtype=np.float64) @ m for p, m in zip(poses, motion)]


def triangle_instances(scene: ScanNetScene) -> np.ndarray:
    """(T,) int32 per triangle: ``object_id + 1`` of its vertices (majority), 0 = unannotated."""
    assert scene.mesh is not None
    vertex_instance = np.zeros(len(scene.mesh.vertices), np.int32)
    for inst in scene.instances:
        vertex_instance[inst.vertex_indices] = inst.object_id + 1
    a, b, c = (vertex_instance[scene.mesh.triangles[:, i]] for i in range(3))
    return np.where(b == c, b, a).astype(np.int32)


def label_lookup(scene: ScanNetScene) -> np.ndarray:
    """(max instance id + 1,) uint16: the ``label-filt`` id of each 2D instance id (0 -> 0): its nyu40 id
    for a v2 scene, else its ScanNet label id (0 without a labels tsv)."""
    ids = [inst.object_id + 1 for inst in scene.instances]
    lookup = np.zeros(max(ids, default=0) + 1, np.uint16)
    for inst in scene.instances:
        if scene.annotation == "v2":
            lookup[inst.object_id + 1] = inst.nyu40_id
        elif scene.labels is not None:
            lookup[inst.object_id + 1] = scene.labels.label_id_of(inst.raw_category)
    return lookup


def scaled_intrinsics(intrinsics: Intrinsics, from_wh: tuple[int, int], to_wh: tuple[int, int]) -> Intrinsics:
    """Intrinsics of an image resized from ``from_wh`` to ``to_wh`` (pixel-centre convention)."""
    sx, sy = to_wh[0] / from_wh[0], to_wh[1] / from_wh[1]
    return Intrinsics(intrinsics.fx * sx, intrinsics.fy * sy, (intrinsics.cx + 0.5) * sx - 0.5, (intrinsics.cy + 0.5) * sy - 0.5)


def _write_scene_files(
    scene: ScanNetScene, scene_dir: Path, out_root: Path, k: Intrinsics, size_wh: tuple[int, int], n: int
) -> None:
    for sub in ("color", "depth", "pose", "intrinsic", "instance-filt", "label-filt"):
        (scene_dir / sub).mkdir(parents=True, exist_ok=True)
    matrix = np.eye(4)
    matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2] = k.fx, k.fy, k.cx, k.cy
    for name in ("intrinsic_color.txt", "intrinsic_depth.txt"):
        write_matrix(scene_dir / "intrinsic" / name, matrix)
    for name in ("extrinsic_color.txt", "extrinsic_depth.txt"):
        write_matrix(scene_dir / "intrinsic" / name, np.eye(4))
    width, height = size_wh
    meta = {
        "axisAlignment": " ".join(f"{v:.9g}" for v in scene.scan2aligned.ravel()),
        "colorHeight": height, "colorWidth": width, "depthHeight": height, "depthWidth": width,
        "fx_color": k.fx, "fy_color": k.fy, "mx_color": k.cx, "my_color": k.cy,
        "fx_depth": k.fx, "fy_depth": k.fy, "mx_depth": k.cx, "my_depth": k.cy,
        "numColorFrames": n, "numDepthFrames": n, "sceneType": "Rendered",
    }  # fmt: skip
    (scene_dir / f"{scene.scene_id}.txt").write_text("".join(f"{key} = {value}\n" for key, value in meta.items()))
    copied = [f"{scene.scene_id}_vh_clean_2.ply"]
    if scene.annotation == "v1":
        copied += [f"{scene.scene_id}.aggregation.json", f"{scene.scene_id}_vh_clean*.segs.json"]
    for pattern in copied:
        for source in scene.root.glob(pattern):
            shutil.copyfile(source, scene_dir / source.name)
    if scene.annotation == "v2":
        for source in v2_label_paths(scene.root, scene.scene_id):
            (scene_dir / source.parent.name).mkdir(exist_ok=True)
            shutil.copyfile(source, scene_dir / source.parent.name / source.name)
    tsv = find_label_table(scene.root)
    if tsv is not None:
        shutil.copyfile(tsv, out_root / tsv.name)
    elif not any((out_root / name).is_file() for name in LABEL_TSV_NAMES):
        logger.warning("scene %s: no labels tsv to copy; label-filt images hold 0", scene.scene_id)


def render_scannet(
    scene: ScanNetScene,
    out_root: Path,
    *,
    users: int = 10,
    frames_per_user: int = 60,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    intrinsics: Intrinsics | None = None,
    eye_height_m: float = 1.5,
    min_valid_fraction: float = 0.5,
    progress: bool = False,
    walk: Callable[..., list[np.ndarray]] | None = None,
    style: str = "default",
) -> Path:
    """Render ``users`` walks of ``frames_per_user`` frames through ``scene``'s mesh into
    ``out_root/<scene>/`` (see the module docstring); returns that folder.

    User u walks with seed ``seed * 1000 + u``: at ``eye_height_m`` (``style="default"``), or as
    ``random_user_walk(seed, u)`` draws it (``style="random"``, which ignores ``eye_height_m``). A frame
    that sees less than ``min_valid_fraction`` of surface (a camera in a wall, or looking out through a
    hole of the scan) is dropped, logged. ``walk`` replaces ``arcloud.virtual_camera.walk.plan_walk`` (same
    signature; the random style passes it plan_walk's ``eye_height_jitter_m``, ``step_m``,
    ``fixation_frames`` and ``ring_inset_m`` too)."""
    if walk is None:
        walk = scan_walk if style == "scan" else plan_walk
    if users < 1 or frames_per_user < 1:
        raise InvalidInput("users, frames_per_user", "both >= 1", (users, frames_per_user))
    if style not in WALK_STYLES:
        raise InvalidInput("style", f"one of {WALK_STYLES}", repr(style))
    if scene.mesh is None or not scene.instances or scene.annotation not in LABEL_IDS_OF_ANNOTATION:
        raise DatasetError(f"{scene.root}: expected a mesh with its annotation (aggregation and segs, or labels_v2/), got none")
    label_ids = LABEL_IDS_OF_ANNOTATION[scene.annotation]
    base = intrinsics or (
        scaled_intrinsics(scene.depth_intrinsics, (640, 480), (width, height)) if scene.depth_intrinsics
        else scaled_intrinsics(DEFAULT_DEPTH_INTRINSICS, (640, 480), (width, height))
    )  # fmt: skip
    layout = room_layout(scene)
    renderer = MeshRenderer(
        aligned_vertices(scene),
        scene.mesh.triangles,
        vertex_colors=scene.mesh.colors,
        triangle_instance=triangle_instances(scene),
    )
    lookup = label_lookup(scene)
    instance_dtype = np.uint8 if len(lookup) <= 256 else np.uint16
    aligned2scan = np.linalg.inv(scene.scan2aligned)
    scene_dir = Path(out_root) / scene.scene_id
    _write_scene_files(scene, scene_dir, Path(out_root), base, (width, height), users * frames_per_user)

    from tqdm import tqdm

    user_frames: list[tuple[int, int]] = []  # [first, stop) frame numbers of each user
    dropped, index = 0, 0
    user_walks = [random_user_walk(seed, u) if style == "random" else None for u in range(users)]
    pending: list[Future[None]] = []
    with (
        ThreadPoolExecutor(max_workers=2) as writer,
        tqdm(total=users * frames_per_user, disable=not progress, desc="render", unit="frame") as bar,
    ):
        for user, user_walk in enumerate(user_walks):
            options = user_walk.walk_options(layout, frames_per_user) if user_walk else {"eye_height_m": eye_height_m}
            poses = walk(
                layout.floor_min_xy, layout.floor_max_xy, layout.targets, frames_per_user, seed * 1000 + user,
                floor_z_m=layout.floor_z_m, obstacles_xy=layout.obstacles_xy, **options,
            )  # fmt: skip
            if user_walk is not None:
                poses = shake(poses, user_walk.shake_deg, user_walk.shake_m, np.random.default_rng([seed, user, 18]))
            first = index
            for cam2world in poses:
                bar.update(1)
                result = renderer.render(cam2world, base, width, height)
                if np.count_nonzero(result.depth_m > 0) < min_valid_fraction * width * height:
                    dropped += 1
                    continue
                name = str(index)
                index += 1
                instance = np.where(result.instance < len(lookup), result.instance, 0)
                pending.append(writer.submit(_write_frame, scene_dir, name, result.rgb, result.depth_m,
                                             instance.astype(instance_dtype), lookup[instance], aligned2scan @ cam2world))  # fmt: skip
            user_frames.append((first, index))
            for future in pending:
                future.result()
            pending.clear()
    if dropped:
        logger.warning(
            "scene %s: dropped %d of %d frames that saw too little surface", scene.scene_id, dropped, users * frames_per_user
        )
    record = {"users": users, "frames_per_user": frames_per_user, "seed": seed, "style": style, "width": width, "height": height,
              "eye_height_m": None if style == "random" else eye_height_m,
              "walk_seeds": [seed * 1000 + u for u in range(users)],
              "walk_styles": [asdict(w) if w else {"eye_height_m": eye_height_m} for w in user_walks],
              "user_frames": user_frames, "frames": index, "dropped": dropped,
              "annotation": scene.annotation, "label_ids": label_ids}  # fmt: skip
    (scene_dir / "render.json").write_text(json.dumps(record, indent=1))
    logger.info("rendered %d frames of %s by %d users into %s", index, scene.scene_id, users, scene_dir)
    return scene_dir


def _write_frame(
    scene_dir: Path,
    name: str,
    rgb: np.ndarray,
    depth_m: np.ndarray,
    instance: np.ndarray,
    label: np.ndarray,
    cam2scan: np.ndarray,
) -> None:
    import cv2

    path = scene_dir / "color" / f"{name}.jpg"
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
        raise DatasetError(f"{path}: could not write the image")
    depth_mm = np.clip(np.rint(depth_m * 1000.0), 0, 65535).astype(np.uint16)
    write_png(scene_dir / "depth" / f"{name}.png", depth_mm)
    write_png(scene_dir / "instance-filt" / f"{name}.png", instance)
    write_png(scene_dir / "label-filt" / f"{name}.png", label)
    write_matrix(scene_dir / "pose" / f"{name}.txt", cam2scan)


__all__ = [
    "LABEL_IDS_OF_ANNOTATION",
    "WALK_STYLES",
    "RoomLayout",
    "UserWalk",
    "label_lookup",
    "random_user_walk",
    "render_scannet",
    "room_layout",
    "scaled_intrinsics",
    "shake",
    "triangle_instances",
]
