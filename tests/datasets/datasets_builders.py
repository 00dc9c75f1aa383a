"""Builders of tiny ScanNet-layout, 7-Scenes-layout and TUM-RGB-D-layout folders (in tmp_path) for the dataset tests."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from arcloud.core.types import Intrinsics
from arcloud.virtual_camera.gaze import look_at

SCENE_ID = "scene0042_00"
DEPTH_WH = (32, 24)
COLOR_WH = (64, 48)
DEPTH_K = (30.0, 30.0, 15.5, 11.5)

#: A rotation of 90 degrees about z and a shift: the scene's axisAlignment (scan2aligned).
ALIGNMENT = np.array([[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, -2.0], [0.0, 0.0, 1.0, 0.5], [0.0, 0.0, 0.0, 1.0]])

# label ids (the tsv's "id") and nyu40 ids of the raw categories the tiny scene uses
TSV_ROWS = [
    # id, raw category, category, nyu40id
    (2, "chair", "chair", 5),
    (4, "table", "table", 7),
    (9, "desk", "desk", 14),
    (77, "laptop", "laptop", 40),
    (11, "floor", "floor", 2),
    (33, "tv", "television", 25),
]


def box_mesh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and triangles (12, 3) of an axis-aligned box."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    triangles = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return corners, np.array(triangles)


def write_ply(path: Path, vertices: np.ndarray, colors: np.ndarray, triangles: np.ndarray, *, binary: bool) -> None:
    header = (
        "ply\nformat {} 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
        "element face {}\nproperty list uchar int vertex_indices\nend_header\n"
    ).format("binary_little_endian" if binary else "ascii", len(vertices), len(triangles))
    if binary:
        vdtype = np.dtype([("p", "<f4", (3,)), ("c", "u1", (4,))])
        vblock = np.empty(len(vertices), vdtype)
        vblock["p"] = vertices
        vblock["c"] = np.column_stack([colors, np.full(len(colors), 255)])
        fdtype = np.dtype([("n", "u1"), ("v", "<i4", (3,))])
        fblock = np.empty(len(triangles), fdtype)
        fblock["n"] = 3
        fblock["v"] = triangles
        path.write_bytes(header.encode() + vblock.tobytes() + fblock.tobytes())
    else:
        lines = [f"{x} {y} {z} {r} {g} {b} 255" for (x, y, z), (r, g, b) in zip(vertices.tolist(), colors.tolist())]
        lines += [f"3 {a} {b} {c}" for a, b, c in triangles.tolist()]
        path.write_text(header + "\n".join(lines) + "\n")


def write_tsv(path: Path, version: int) -> None:
    if version == 1:
        head = "id\tcategory\tcount\tnyuId\tnyu40id\teigen13id\tnyuClass\tnyu40class"
        rows = [f"{i}\t{raw}\t10\t0\t{nyu}\t0\t{cat}\t{cat}" for i, raw, cat, nyu in TSV_ROWS]
    else:
        head = "id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass\tnyu40class"
        rows = [f"{i}\t{raw}\t{cat}\t10\t{nyu}\t0\t{cat}\t{cat}" for i, raw, cat, nyu in TSV_ROWS]
    path.write_text("\n".join([head, *rows]) + "\n")


@dataclass
class TinyScanNet:
    scene_dir: Path
    poses_scan: dict[str, np.ndarray]
    #: raw category -> (min, max) of its box in the scan frame
    boxes_scan: dict[str, tuple[np.ndarray, np.ndarray]]


def build_scannet(
    root: Path, *, tsv_version: int = 2, alignment: bool = True, binary_ply: bool = True, labels_2d: bool = True
) -> TinyScanNet:
    """A scene with a chair, a table, a desk and a floor; frames 0, 1 (invalid pose), 2, 10."""
    scene = root / SCENE_ID
    for sub in ("color", "depth", "pose", "intrinsic", "instance-filt", "label-filt"):
        (scene / sub).mkdir(parents=True)
    write_tsv(root / "scannetv2-labels.combined.tsv", tsv_version)

    parts = {
        "chair": (np.array([0.0, 0.0, 0.0]), np.array([0.5, 0.5, 1.0])),
        "table": (np.array([1.0, 1.0, 0.0]), np.array([2.2, 1.8, 0.75])),
        "desk": (np.array([-2.0, 1.0, 0.0]), np.array([-1.0, 1.6, 0.8])),
        "floor": (np.array([-3.0, -3.0, -0.02]), np.array([3.0, 3.0, 0.0])),
    }
    vertices, triangles, seg_indices = [], [], []
    for segment, (lo, hi) in enumerate(parts.values()):
        v, t = box_mesh(lo, hi)
        triangles.append(t + sum(len(x) for x in vertices))
        vertices.append(v)
        seg_indices += [100 + segment] * len(v)
    vertices_all = np.concatenate(vertices).astype(np.float32)
    colors = np.tile(np.array([[200, 100, 50]], np.uint8), (len(vertices_all), 1))
    write_ply(scene / f"{SCENE_ID}_vh_clean_2.ply", vertices_all, colors, np.concatenate(triangles), binary=binary_ply)
    (scene / f"{SCENE_ID}_vh_clean_2.0.010000.segs.json").write_text(json.dumps({"sceneId": SCENE_ID, "segIndices": seg_indices}))
    groups = [{"id": i, "objectId": i, "segments": [100 + i], "label": raw} for i, raw in enumerate(parts)]
    (scene / f"{SCENE_ID}.aggregation.json").write_text(json.dumps({"sceneId": SCENE_ID, "segGroups": groups}))

    meta = ["colorHeight = 48", "colorWidth = 64", "depthHeight = 24", "depthWidth = 32"]
    if alignment:
        meta.append("axisAlignment = " + " ".join(f"{v:g}" for v in ALIGNMENT.ravel()))
    (scene / f"{SCENE_ID}.txt").write_text("\n".join(meta) + "\n")
    k = np.eye(4)
    k[0, 0], k[1, 1], k[0, 2], k[1, 2] = DEPTH_K
    np.savetxt(scene / "intrinsic" / "intrinsic_depth.txt", k)
    np.savetxt(scene / "intrinsic" / "intrinsic_color.txt", k * np.array([[2], [2], [1], [1]]))

    rng = np.random.default_rng(7)
    poses = {}
    for index, name in enumerate(["0", "1", "2", "10"]):
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * index, -3.0, 1.2]
        if name == "1":
            pose[:] = -np.inf
        poses[name] = pose
        np.savetxt(scene / "pose" / f"{name}.txt", pose)
        # colour: left half red, right half blue (at colour size), to check the resize
        color = np.zeros((COLOR_WH[1], COLOR_WH[0], 3), np.uint8)
        color[:, : COLOR_WH[0] // 2] = (255, 0, 0)
        color[:, COLOR_WH[0] // 2 :] = (0, 0, 255)
        cv2.imwrite(str(scene / "color" / f"{name}.jpg"), color[..., ::-1])
        depth = rng.integers(500, 3000, size=(DEPTH_WH[1], DEPTH_WH[0])).astype(np.uint16)
        depth[0, 0] = 0
        cv2.imwrite(str(scene / "depth" / f"{name}.png"), depth)
        if labels_2d:
            # instance-filt at colour size: chair (objectId 0 -> 1) top-left block, table (-> 2)
            # bottom-right block, floor (-> 4) elsewhere; a 2x2 speck of desk (-> 3).
            instance = np.full((COLOR_WH[1], COLOR_WH[0]), 4, np.uint8)
            instance[:20, :24] = 1
            instance[28:, 36:] = 2
            instance[:2, 62:] = 3
            label = np.select([instance == 1, instance == 2, instance == 3], [2, 4, 9], 11).astype(np.uint16)
            cv2.imwrite(str(scene / "instance-filt" / f"{name}.png"), instance)
            cv2.imwrite(str(scene / "label-filt" / f"{name}.png"), label)
    return TinyScanNet(scene, poses, parts)


def write_v2_labels(scene_dir: Path, instance_ids: np.ndarray, nyu40_ids: np.ndarray, *, scene_id: str = SCENE_ID) -> None:
    """The v2 annotation files ``labels_v2/<scene>_{ins,sem}_label_all.npy`` (saved as given: ScanNet's are uint32)."""
    folder = scene_dir / "labels_v2"
    folder.mkdir(exist_ok=True)
    np.save(folder / f"{scene_id}_ins_label_all.npy", instance_ids)
    np.save(folder / f"{scene_id}_sem_label_all.npy", nyu40_ids)


#: v2 labels of ``build_scannet``'s 32 vertices (8 a box: chair, table, desk, floor): the chair is
#: instance 12 (nyu40 5), the table and the desk one instance 5 whose vertices vote nyu40 7 (10) over 14
#: (6), the floor instance 1 (nyu40 2).
TINY_V2_INSTANCES = np.repeat(np.array([12, 5, 5, 1], np.uint32), 8)
TINY_V2_NYU40 = np.array([5] * 8 + [7] * 8 + [14] * 6 + [7] * 2 + [2] * 8, np.uint32)


def build_seven_scenes(root: Path, *, n_frames: int = 3, gravity: np.ndarray | None = None, sequences: int = 0) -> Path:
    """A 7-Scenes-layout folder with ``n_frames`` frames (the last pose NaN), 64x48 images."""
    folders = [root / f"seq-{i + 1:02d}" for i in range(sequences)] if sequences else [root]
    for folder in folders:
        folder.mkdir(parents=True, exist_ok=True)
        for index in range(n_frames):
            stem = f"frame-{index:06d}"
            pose = np.eye(4)
            pose[:3, 3] = [index * 0.05, 0.0, 0.0]
            if index == n_frames - 1:
                pose[0, 0] = np.nan
            np.savetxt(folder / f"{stem}.pose.txt", pose)
            cv2.imwrite(str(folder / f"{stem}.color.jpg"), np.full((48, 64, 3), 90, np.uint8))
            depth = np.full((48, 64), 1500, np.uint16)
            depth[:, :4] = 65535
            depth[:, 4:8] = 0
            cv2.imwrite(str(folder / f"{stem}.depth.png"), depth)
    np.savetxt(root / "camera-intrinsics.txt", np.array([[58.5, 0, 32.0], [0, 58.5, 24.0], [0, 0, 1]]))
    if gravity is not None:
        np.savetxt(root / "gravity-direction.txt", gravity)
    return root


#: TUM timestamps of ``build_tum_from_seven_scenes``: 7-Scenes frame N was taken at TUM_START_S + N / 30 s.
TUM_START_S = 1305031102.0
#: How long after its depth image each colour image of ``build_tum_from_seven_scenes`` was taken.
TUM_RGB_DELAY_S = 0.008


def tum_time(frame_number: int) -> str:
    return f"{TUM_START_S + frame_number / 30.0:.6f}"


def build_tum_from_seven_scenes(
    seven_root: Path,
    root: Path,
    frame_numbers: list[int],
    *,
    intrinsics: bool = True,
    trajectory_frames: list[int] | None = None,
    pose_clock_s: float = 0.0,
    depth_scale: float = 1.0,
) -> Path:
    """A TUM RGB-D layout recording of frames of a 7-Scenes folder: colour as PNG (``rgb/``, taken
    ``TUM_RGB_DELAY_S`` after the depth, plus one stray colour image 0.5 s after the last), depth in TUM's
    units (``depth/``: millimetres x 5; 7-Scenes' invalid 65535 -> 0, and one more depth image 1 s after
    the last, beyond the trajectory), and ``groundtruth.txt`` holding the poses of ``trajectory_frames``
    (default: those with images) as quaternion lines at their depth timestamps plus ``pose_clock_s`` (a
    trajectory whose clock runs that far ahead of the camera's), newest first. ``intrinsics``: copy
    ``camera-intrinsics.txt``. ``depth_scale``: the depth written that much long (a sensor reading long)."""
    from scipy.spatial.transform import Rotation

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines, pose_lines = ["# color images", "# timestamp filename"], ["# depth maps"], []
    for number in frame_numbers if trajectory_frames is None else trajectory_frames:
        pose = np.loadtxt(seven_root / f"frame-{number:06d}.pose.txt")
        quaternion = Rotation.from_matrix(pose[:3, :3]).as_quat()
        pose_time = f"{float(tum_time(number)) + pose_clock_s:.6f}"
        pose_lines.append(" ".join([pose_time, *(f"{v:.9f}" for v in (*pose[:3, 3], *quaternion))]))
    for number in frame_numbers:
        stem = f"frame-{number:06d}"
        depth_time, rgb_time = tum_time(number), f"{float(tum_time(number)) + TUM_RGB_DELAY_S:.6f}"
        depth_mm = cv2.imread(str(seven_root / f"{stem}.depth.png"), cv2.IMREAD_UNCHANGED)
        depth_mm = np.where(depth_mm == 65535, 0, depth_mm).astype(np.uint32)
        cv2.imwrite(
            str(root / "depth" / f"{depth_time}.png"), np.minimum(np.round(depth_mm * 5 * depth_scale), 65535).astype(np.uint16)
        )
        cv2.imwrite(str(root / "rgb" / f"{rgb_time}.png"), cv2.imread(str(seven_root / f"{stem}.color.jpg")))
        rgb_lines.append(f"{rgb_time} rgb/{rgb_time}.png")
        depth_lines.append(f"{depth_time} depth/{depth_time}.png")
    late = f"{float(tum_time(frame_numbers[-1])) + 1.0:.6f}"
    cv2.imwrite(str(root / "depth" / f"{late}.png"), np.zeros((48, 64), np.uint16))
    cv2.imwrite(str(root / "rgb" / f"{late}.png"), np.zeros((48, 64, 3), np.uint8))
    depth_lines.append(f"{late} depth/{late}.png")
    rgb_lines += [f"{late} rgb/{late}.png", f"{float(late) - 0.5:.6f} rgb/{late}.png"]
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(reversed(pose_lines)) + "\n")
    if intrinsics:
        (root / "camera-intrinsics.txt").write_text((seven_root / "camera-intrinsics.txt").read_text())
    return root


def write_room_tum(
    root: Path,
    intrinsics: Intrinsics,
    n_frames: int = 8,
    *,
    colour_delay_s: float = 0.0,
    colour_shift_px: tuple[float, float] = (0.0, 0.0),
    distortion: tuple[float, ...] | None = None,
    turn_deg: float = 12.0,
    depth_scale: float = 1.0,
) -> Path:
    """A 640 x 480 recording of exact renders (``handmade_frames.cast_boxes``) of ``BOX_ROOM`` made with ``intrinsics``
    along ``turning_poses`` at 30 frames a second, depth in TUM's units; each colour image taken ``colour_delay_s``
    after its depth image (the trajectory holds the poses at both times) by a camera whose principal point lies
    ``colour_shift_px`` from the depth camera's, black but for ``BOX_ROOM``'s table, painted (255, 0, 0) where the
    camera saw it then. ``distortion``: both images taken through that lens (registered pixel for pixel, as TUM's).
    ``turn_deg``: the camera turns that much a frame (0: it steps sideways, level); ``depth_scale``: the depth
    written that much long."""
    from handmade_frames import BOX_ROOM, cast_boxes, turning_pose
    from scipy.spatial.transform import Rotation

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    lines: dict[str, list[str]] = {"rgb": [], "depth": [], "groundtruth": []}

    def pose_line(t: str, pose: np.ndarray) -> str:
        return " ".join([t, *map(str, pose[:3, 3]), *map(str, Rotation.from_matrix(pose[:3, :3]).as_quat())])

    for i in range(n_frames):
        t, t_colour = f"{100.0 + i / 30:.6f}", f"{100.0 + i / 30 + colour_delay_s:.6f}"
        moving = {"step_deg": turn_deg, "pitching": turn_deg != 0}
        pose, colour_pose = turning_pose(i, **moving), turning_pose(i + colour_delay_s * 30, **moving)
        depth_m = cast_boxes(pose, BOX_ROOM, intrinsics=intrinsics, shape=(480, 640), distortion=distortion)[0]
        cv2.imwrite(str(root / "depth" / f"{t}.png"), np.round(depth_m * 5000 * depth_scale).astype(np.uint16))
        colour = np.zeros((480, 640, 3), np.uint8)
        colour_camera = Intrinsics(
            intrinsics.fx, intrinsics.fy, intrinsics.cx + colour_shift_px[0], intrinsics.cy + colour_shift_px[1]
        )
        seen = cast_boxes(colour_pose, BOX_ROOM, intrinsics=colour_camera, shape=(480, 640), distortion=distortion)[1]
        colour[seen == TABLE_IN_BOX_ROOM] = (0, 0, 255)
        cv2.imwrite(str(root / "rgb" / f"{t_colour}.png"), colour)  # BGR
        lines["rgb"].append(f"{t_colour} rgb/{t_colour}.png")
        lines["depth"].append(f"{t} depth/{t}.png")
        lines["groundtruth"] += [pose_line(t, pose)] + ([pose_line(t_colour, colour_pose)] if colour_delay_s else [])
    for name, listed in lines.items():
        (root / f"{name}.txt").write_text("\n".join(listed) + "\n")
    return root


#: ``handmade_frames.BOX_ROOM``'s table.
TABLE_IN_BOX_ROOM = 4


#: The annotated room of ``build_room_scene``: raw category -> (min, max) in the aligned frame.
ROOM_PARTS = {
    "floor": (np.array([-3.0, -3.0, -0.05]), np.array([3.0, 3.0, 0.0])),
    "wall": (np.array([-3.0, 3.0, 0.0]), np.array([3.0, 3.1, 2.5])),
    "chair": (np.array([0.8, 0.8, 0.0]), np.array([1.3, 1.3, 0.9])),
    "table": (np.array([-1.6, -0.9, 0.0]), np.array([-0.4, -0.1, 0.75])),
}
#: Unannotated walls (instance 0) closing the room.
ROOM_WALLS = [
    (np.array([-3.0, -3.1, 0.0]), np.array([3.0, -3.0, 2.5])),
    (np.array([-3.1, -3.0, 0.0]), np.array([-3.0, 3.0, 2.5])),
    (np.array([3.0, -3.0, 0.0]), np.array([3.1, 3.0, 2.5])),
]


#: The v2 annotation of ``build_room_scene(v2=True)`` per part (8 vertices each): instance id, nyu40 id.
#: The table is a desk (nyu40 14: class table, ScanNet label id 9); the walls are unannotated.
ROOM_V2 = {"floor": (3, 2), "wall": (0, 0), "chair": (9, 5), "table": (300, 14)}


def build_room_scene(root: Path, *, v2: bool = False) -> Path:
    """A closed 6 x 6 m room mesh with a chair and a table, annotated like ScanNet (aggregation, segs,
    v2 tsv; with ``v2`` also ``labels_v2/`` as ``ROOM_V2`` says), its scan frame related to the aligned
    frame by ``ALIGNMENT``; no frames. Returns the scene folder."""
    scene = root / SCENE_ID
    scene.mkdir(parents=True)
    write_tsv(root / "scannetv2-labels.combined.tsv", 2)
    vertices, triangles, seg_indices = [], [], []
    boxes = [(100 + i, lo, hi) for i, (lo, hi) in enumerate(ROOM_PARTS.values())] + [(999, lo, hi) for lo, hi in ROOM_WALLS]
    for segment, lo, hi in boxes:
        v, t = box_mesh(lo, hi)
        triangles.append(t + sum(len(x) for x in vertices))
        vertices.append(v)
        seg_indices += [segment] * len(v)
    aligned = np.concatenate(vertices)
    scan2aligned_inv = np.linalg.inv(ALIGNMENT)
    scan = aligned @ scan2aligned_inv[:3, :3].T + scan2aligned_inv[:3, 3]
    colors = np.tile(np.array([[180, 160, 140]], np.uint8), (len(scan), 1))
    write_ply(scene / f"{SCENE_ID}_vh_clean_2.ply", scan.astype(np.float32), colors, np.concatenate(triangles), binary=True)
    (scene / f"{SCENE_ID}_vh_clean_2.0.010000.segs.json").write_text(json.dumps({"segIndices": seg_indices}))
    groups = [{"id": i, "objectId": i, "segments": [100 + i], "label": raw} for i, raw in enumerate(ROOM_PARTS)]
    (scene / f"{SCENE_ID}.aggregation.json").write_text(json.dumps({"sceneId": SCENE_ID, "segGroups": groups}))
    (scene / f"{SCENE_ID}.txt").write_text("axisAlignment = " + " ".join(f"{v:g}" for v in ALIGNMENT.ravel()) + "\n")
    if v2:
        per_box = [ROOM_V2[raw] for raw in ROOM_PARTS] + [(0, 0)] * len(ROOM_WALLS)
        write_v2_labels(
            scene,
            np.repeat(np.array([i for i, _ in per_box], np.uint32), 8),
            np.repeat(np.array([n for _, n in per_box], np.uint32), 8),
        )
    return scene


def circle_walk(floor_min_xy, floor_max_xy, targets, n_frames, seed, *, eye_height_m, floor_z_m=0.0, obstacles_xy=()):
    """A stand-in for ``plan_walk``: a circle of radius 2 m around the room centre, looking at it."""
    eye_height_m = floor_z_m + eye_height_m
    centre = (np.asarray(floor_min_xy) + np.asarray(floor_max_xy)) / 2
    angles = seed * 0.7 + np.linspace(0, 2 * np.pi, n_frames, endpoint=False)
    eyes = [np.array([centre[0] + 2 * np.cos(a), centre[1] + 2 * np.sin(a), eye_height_m]) for a in angles]
    return [look_at(eye, np.array([*centre, 0.4])) for eye in eyes]
