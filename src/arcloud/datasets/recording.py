"""Any posed RGB-D recording as an evaluation reads it, whatever its layout: a ScanNet scene, a 7-Scenes
sequence or a TUM RGB-D recording, in a folder of any name.

``load_recording`` detects the layout (``detect_layout``), parses the folder with its reader and gives
one ``Recording``: the frames (by name, read on demand), the ground truth (``gt_boxes``, else the
folder's ``gt-boxes.json``, else a ScanNet scene's mesh annotation), the frame maps are boxed and
exported in (``ExportFrame``: the ground truth's aligned frame when there is one) and how up was chosen.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from arcloud.errors import DatasetError

logger = logging.getLogger(__name__)

if TYPE_CHECKING:
    from arcloud.core.types import Frame, Intrinsics
    from arcloud.datasets.export import ExportFrame
    from arcloud.datasets.frames import ColourCamera
    from arcloud.datasets.gravity import UpChoice
    from arcloud.datasets.gt_boxes import GroundTruthBoxes

#: The layouts ``load_recording`` reads (importing this module is light: the CLI's parser takes them).
LAYOUTS = ("scannet", "7scenes", "tum")


@dataclass(frozen=True, eq=False)
class Recording:
    """A parsed recording: ``layout`` (one of ``LAYOUTS``), ``name`` (a map id), ``frame_names`` in
    order and ``load_frame(name)``; ``ground_truth`` (None without); ``export_frame``: the frame maps
    are boxed and exported in (``world2export``: ``Params.world2aligned``); ``gravity``: up in the pose
    frame and its source; ``frame_numbers``: each frame's number, as a ground truth's ``visible_frames`` counts
    (7-Scenes and ScanNet: the number of its files' names; TUM: its place among depth.txt's images, from 0);
    ``facts``: what else the layout's reader says, for the results."""

    layout: str
    name: str
    root: Path
    frame_names: tuple[str, ...]
    load_frame: Callable[[str], Frame]
    ground_truth: GroundTruthBoxes | None
    export_frame: ExportFrame
    gravity: UpChoice
    frame_numbers: tuple[int, ...]
    facts: Mapping[str, Any] = field(default_factory=dict)

    def scored_frames(self, names: Sequence[str]) -> tuple[int, int] | None:
        """The (first, last) frame numbers whose visible ground-truth objects a map of ``names`` (some of the
        frames: a stride, fewer frames) is scored against; None: every object. Every object when ``names`` span the
        recording, or when an object's ``visible_frames`` lie outside all its frame numbers (the file counts frames
        otherwise, or is of a longer sequence than this folder holds: logged whichever frames are used), so that a
        file numbered another way is never read as "nothing visible"."""
        if self.ground_truth is None or not names:
            return None
        number = dict(zip(self.frame_names, self.frame_numbers, strict=True))
        used = (min(number[n] for n in names), max(number[n] for n in names))
        recorded = (min(self.frame_numbers), max(self.frame_numbers))
        outside = [o.id for o in self.ground_truth.objects if not o.visible_within(*recorded)]
        if outside:  # said whichever frames are used: a folder of part of a sequence with the whole one's file reads so too
            logger.warning(
                "%s: visible_frames of %s lie outside this recording's frame numbers %d..%d: every object is scored, "
                "whichever frames are used (the file counts frames another way, or is of more than this recording: "
                "then give --gt-boxes a file of the objects in it)", self.ground_truth.path, ", ".join(outside), *recorded,
            )  # fmt: skip
            return None
        if used == recorded:
            return None
        return used


def detect_layout(root: Path) -> str:
    """``tum`` (``rgb.txt`` and ``depth.txt``), ``7scenes`` (``frame-*.pose.txt``, or ``seq-*`` folders of
    them) or ``scannet`` (a scene folder with ``pose/``, or a ``<name>.txt``)."""
    from arcloud.datasets.scannet import is_scene_dir
    from arcloud.datasets.tum import is_tum_recording

    if not root.is_dir():
        raise DatasetError(f"{root}: expected a recording folder, got no such folder")
    if is_tum_recording(root):
        return "tum"
    listed = [name for name in ("rgb.txt", "depth.txt") if (root / name).is_file()]
    if len(listed) == 1:  # half of a TUM recording: say which file is missing, not "none of them"
        missing = "depth.txt" if listed == ["rgb.txt"] else "rgb.txt"
        raise DatasetError(f"{root}: expected {missing} beside {listed[0]} (TUM RGB-D layout), got no such file")
    if any(root.glob("frame-*.pose.txt")) or any(root.glob("seq*/frame-*.pose.txt")):
        return "7scenes"
    if is_scene_dir(root):
        return "scannet"
    raise DatasetError(
        f"{root}: expected a recording (TUM: rgb.txt and depth.txt; 7-Scenes: frame-*.pose.txt; ScanNet: pose/), got none of them"
    )


def load_recording(
    root: str | Path,
    *,
    layout: str = "auto",
    gt_boxes: str | Path | None = None,
    up: object = None,
    intrinsics: Intrinsics | None = None,
    depth_factor: float | None = None,
    pose_time_offset_s: float | None = None,
    colour: ColourCamera | None = None,
    estimate_up: bool = True,
) -> Recording:
    """Parse the recording in ``root`` (``layout`` ``"auto"``: ``detect_layout``). 7-Scenes and TUM worlds
    are gravity-aligned (up: ``up``, ``gravity-direction.txt``, the ground truth's, else estimated when
    ``estimate_up``); ScanNet's are z-up by the layout's convention (``up`` is refused).
    ``intrinsics``, ``depth_factor`` and ``pose_time_offset_s`` are the TUM reader's; ``colour`` the
    7-Scenes reader's; other layouts refuse them."""
    base = Path(root)
    chosen = detect_layout(base) if layout == "auto" else layout
    if chosen not in LAYOUTS:
        raise DatasetError(f"layout: expected auto or one of {LAYOUTS}, got {layout!r}")
    refused = {
        "--up": up is not None and chosen == "scannet",
        "--intrinsics": intrinsics is not None and chosen != "tum",
        "--depth-factor": depth_factor is not None and chosen != "tum",
        "--pose-time-offset-s": pose_time_offset_s is not None and chosen != "tum",
        "--colour-camera": colour is not None and chosen != "7scenes",
    }
    if any(refused.values()):
        raise DatasetError(f"{', '.join(k for k, v in refused.items() if v)}: not used by the {chosen} layout ({base})")
    if chosen == "tum":
        return _tum(base, gt_boxes, up, intrinsics, depth_factor, pose_time_offset_s, estimate_up)
    if chosen == "7scenes":
        return _seven_scenes(base, gt_boxes, up, colour, estimate_up)
    return _scannet(base, gt_boxes)


def _tum(
    base: Path,
    gt_boxes: str | Path | None,
    up: object,
    intrinsics: Intrinsics | None,
    depth_factor: float | None,
    pose_time_offset_s: float | None,
    estimate_up: bool,
) -> Recording:
    from arcloud.datasets.export import tum_export_frame
    from arcloud.datasets.gravity import UpChoice
    from arcloud.datasets.tum import load_tum

    sequence = load_tum(
        base, intrinsics=intrinsics, depth_factor=depth_factor,
        pose_time_offset_s=pose_time_offset_s, gt_boxes=gt_boxes, up=up, estimate_up=estimate_up,
    )  # fmt: skip
    facts = {
        "intrinsics": [sequence.intrinsics.fx, sequence.intrinsics.fy, sequence.intrinsics.cx, sequence.intrinsics.cy],
        "intrinsics_source": sequence.intrinsics_source,
        "depth_factor": sequence.depth_factor,
        "depth_factor_source": sequence.depth_factor_source,
        "pose_time_offset_s": sequence.pose_time_offset_s,
        "pose_time_offset_source": sequence.pose_time_offset_source,
        "dropped_frames": len(sequence.dropped_frames),
        "colour_turn_deg": sequence.colour_turn_deg(),
    }
    return Recording(
        "tum", sequence.name, base, sequence.frame_names, sequence.load_frame, sequence.ground_truth,
        tum_export_frame(sequence), UpChoice(sequence.up_file, sequence.up_source), sequence.depth_indices, facts,
    )  # fmt: skip


def _seven_scenes(
    base: Path, gt_boxes: str | Path | None, up: object, colour: ColourCamera | None, estimate_up: bool
) -> Recording:
    from arcloud.datasets.export import seven_scenes_export_frame
    from arcloud.datasets.gravity import UpChoice
    from arcloud.datasets.sevenscenes import load_seven_scenes

    sequence = load_seven_scenes(base, align_gravity=True, colour=colour, gt_boxes=gt_boxes, up=up, estimate_up=estimate_up)
    facts = {"skipped_frames": len(sequence.skipped_frames), "colour_camera": sequence.colour is not None}
    return Recording(
        "7scenes", sequence.name, base, sequence.frame_names, sequence.load_frame, sequence.ground_truth,
        seven_scenes_export_frame(sequence), UpChoice(sequence.up_file, sequence.up_source),
        _numbers_in(sequence.frame_stems), facts,
    )  # fmt: skip


def _scannet(base: Path, gt_boxes: str | Path | None) -> Recording:
    import numpy as np

    from arcloud.datasets.export import scannet_export_frame
    from arcloud.datasets.files import map_id_of
    from arcloud.datasets.gravity import UpChoice
    from arcloud.datasets.gt_boxes import load_ground_truth
    from arcloud.datasets.scannet import load_scannet_scene

    scene = load_scannet_scene(base)
    if not scene.frame_names:
        raise DatasetError(f"{base}: expected pose/N.txt files with finite poses, got none")
    ground_truth = load_ground_truth(gt_boxes) if gt_boxes is not None else scene.ground_truth()
    export_frame = scannet_export_frame(scene, ground_truth if gt_boxes is not None else None)
    up_file = np.linalg.inv(scene.scan2aligned)[:3, 2]
    facts = {"skipped_frames": len(scene.skipped_frames), "annotation": scene.annotation}
    return Recording(
        "scannet", map_id_of(scene.scene_id), base, scene.frame_names, scene.load_frame, ground_truth, export_frame,
        UpChoice(up_file, "ScanNet axis-aligned frame: z up"), _numbers_in(scene.frame_names), facts,
    )  # fmt: skip


def _numbers_in(names: Sequence[str]) -> tuple[int, ...]:
    """The number each name ends in (``000042``: 42), else its place among ``names``."""
    found = [re.search(r"(\d+)$", name) for name in names]
    return tuple(int(m.group(1)) if m is not None else i for i, m in enumerate(found))


#: Frames ``check_intrinsics`` reads, spread over the recording; the share of disagreement it calls notable.
CHECK_FRAMES = 150
CHECK_NOTABLE = 0.9


def check_intrinsics(recording: Recording) -> dict[str, Any]:
    """How well the recording's depth and poses agree with its depth intrinsics, and the intrinsics near them they
    agree with best (``core.calibration.agreeing_intrinsics``, up to ``CHECK_FRAMES`` frames), as JSON; logged as
    a warning when those disagree less than ``CHECK_NOTABLE`` as much (a camera calibrated a few pixels off, or a
    recording read with another camera's intrinsics)."""
    import numpy as np

    from arcloud.core.calibration import agreeing_intrinsics, depth_disagreement, view_pairs

    names = recording.frame_names[:: max(1, -(-len(recording.frame_names) // CHECK_FRAMES))]
    if not names:
        return {"frames": 0, "pairs": 0}
    depths, poses = [], []
    for name in names:  # the depth and pose of each, not its colour (150 VGA frames: 180 MB of depth)
        frame = recording.load_frame(name)
        depths.append(frame.depth_m)
        poses.append(frame.cam2world)
    cam2world = np.stack(poses)
    pairs = view_pairs(cam2world)
    used = frame.intrinsics
    out: dict[str, Any] = {"intrinsics": [used.fx, used.fy, used.cx, used.cy], "frames": len(names), "pairs": len(pairs)}
    if not pairs:
        return out
    gap = depth_disagreement(depths, cam2world, used, pairs)
    best, best_gap = agreeing_intrinsics(depths, cam2world, used, pairs)
    out |= {
        "disagreement_mm": round(gap * 1000, 2),
        "agreeing": [round(v, 2) for v in (best.fx, best.fy, best.cx, best.cy)],
        "agreeing_disagreement_mm": round(best_gap * 1000, 2),
    }
    if best_gap < CHECK_NOTABLE * gap:
        logger.warning(
            "%s: the depth and poses agree better with fx %.1f, fy %.1f, cx %.1f, cy %.1f than with the intrinsics used "
            "(%s): %.1f mm against %.1f mm; check the camera's intrinsics (TUM: --intrinsics)",
            recording.root, best.fx, best.fy, best.cx, best.cy, out["intrinsics"], best_gap * 1000, gap * 1000,
        )  # fmt: skip
    return out


#: ``register_colour``: the frames it reads, spread over the recording; how far it moves the colour camera (its focal
#: lengths times 1 -+ ``REGISTRATION_SCALE``, its principal point up to ``REGISTRATION_SHIFT_PX`` each way, the
#: camera up to ``REGISTRATION_BASELINE_M`` along its x axis); how much stronger the edges must agree at the best
#: move for it to be taken. 16 px is the gap between the two principal points TUM publishes for its freiburg1
#: camera; a Kinect v1's colour camera has a focal length about 10 % shorter than its depth camera's, 2.5-3.5 cm
#: to the side (7-Scenes' unregistered frames).
REGISTRATION_FRAMES = 40
REGISTRATION_SCALE = 0.16
REGISTRATION_SHIFT_PX = 20
REGISTRATION_BASELINE_M = 0.06
REGISTRATION_MARGIN = 0.1
#: No move: the colour camera where the frames put it.
STILL_COLOUR: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)


def _grid(centre: Sequence[float], steps: Sequence[Sequence[float]]) -> list[tuple[float, float, float, float]]:
    """Moves (scale, du, dv, tx_m) around ``centre``: each coordinate plus each of its ``steps``."""
    import itertools

    return [
        (round(centre[0] + a, 4), round(centre[1] + b, 4), round(centre[2] + c, 4), round(centre[3] + d, 4))
        for a, b, c, d in itertools.product(*steps)
    ]


def strongest_colour_move(frames: Sequence[Frame]) -> tuple[tuple[float, float, float, float], dict[str, Any]]:
    """The move (scale, du, dv, tx_m) of the frames' colour camera at which their depth edges meet the colour's
    best (``core.calibration.colour_edge_strength``), searched coarse to fine: focal length and principal point
    (every 4 %, every 4 px), then the baseline with them (every centimetre), then the finest steps; and the
    figures, as JSON. ``STILL_COLOUR`` when no edge lands in any colour image."""
    import numpy as np

    from arcloud.core.calibration import colour_edge_strength

    def strongest(moves: list[tuple[float, float, float, float]]) -> tuple[tuple[float, float, float, float], float]:
        strength = colour_edge_strength(frames, moves)
        k = int(np.nanargmax(strength))  # a move that carries no edge into any image tells nothing
        return moves[k], float(strength[k])

    scales = np.arange(-REGISTRATION_SCALE, REGISTRATION_SCALE + 1e-9, 0.04).tolist()
    shifts = range(-REGISTRATION_SHIFT_PX, REGISTRATION_SHIFT_PX + 1, 4)
    coarse = _grid(STILL_COLOUR, [scales, shifts, shifts, [0.0]])  # STILL_COLOUR among them
    strengths = colour_edge_strength(frames, coarse)
    still = float(strengths[coarse.index(STILL_COLOUR)])
    if not np.isfinite(still):
        return STILL_COLOUR, {"frames": len(frames), "edge_strength": None}
    best, strength = coarse[int(np.nanargmax(strengths))], float(np.nanmax(strengths))
    baselines = np.arange(-REGISTRATION_BASELINE_M, REGISTRATION_BASELINE_M + 1e-9, 0.01).tolist()  # about the first stage's 0
    best, strength = strongest(_grid(best, [[-0.02, 0.0, 0.02], range(-8, 9, 2), [-2, 0, 2], baselines]))
    best, strength = strongest(_grid(best, [[-0.01, 0.0, 0.01], [-1, 0, 1], [-1, 0, 1], [-0.005, 0.0, 0.005]]))
    return best, {
        "frames": len(frames),
        "edge_strength": round(still, 2),
        "strongest_move": list(best),
        "strongest_edge_strength": round(strength, 2),
    }


def register_colour(
    frame_names: Sequence[str],
    load_frame: Callable[[str], Frame],
    move: Sequence[float] | None = None,
    *,
    where: object = "",
) -> tuple[Callable[[str], Frame], dict[str, Any]]:
    """``load_frame`` with the colour camera moved by ``move`` (scale, du, dv, tx_m: its focal lengths times
    scale, its principal point by du, dv pixels, the camera tx_m metres along its x axis), or, when None, by the
    move at which the depth edges of up to ``REGISTRATION_FRAMES`` of ``frame_names`` meet their colour edges best
    (``strongest_colour_move``), when they meet ``REGISTRATION_MARGIN`` more strongly there than where the frames
    put the colour camera and the move is not on the search's border (a climb towards a border is no peak); and
    what was found, as JSON (logged as a warning naming ``where`` when a move is taken). A mask is drawn on colour
    and looked up on depth, so a colour camera a few pixels off moves every mask's border across its object's
    edge."""
    import numpy as np

    out: dict[str, Any] = {}
    if move is None:
        names = frame_names[:: max(1, -(-len(frame_names) // REGISTRATION_FRAMES))]
        strongest, out = strongest_colour_move([load_frame(name) for name in names])
        scale, du, dv, tx = strongest
        inside = (
            abs(scale - 1.0) < REGISTRATION_SCALE - 1e-9
            and max(abs(du), abs(dv)) < REGISTRATION_SHIFT_PX
            and abs(tx) < REGISTRATION_BASELINE_M - 1e-9
        )
        taken = out["edge_strength"] is not None and inside
        taken = taken and out["strongest_edge_strength"] > (1 + REGISTRATION_MARGIN) * out["edge_strength"]
        move = strongest if taken else STILL_COLOUR
        if taken:
            logger.warning(
                "%s: the depth's edges meet the colour's %.0f %% better with the colour camera's focal lengths x%g, "
                "its principal point moved by %+g, %+g px and the camera by %+g m along x; moving it "
                "(--colour-move 1,0,0,0 keeps it)",
                where, 100 * (out["strongest_edge_strength"] / out["edge_strength"] - 1), *move,
            )  # fmt: skip
    scale, du, dv, tx = (float(v) for v in move)
    out["move"] = [scale, du, dv, tx]
    if (scale, du, dv, tx) == STILL_COLOUR:
        return load_frame, out
    beside = np.eye(4)
    beside[0, 3] = tx

    def moved(name: str) -> Frame:
        frame = load_frame(name)
        colour = frame.rgb_intrinsics or frame.intrinsics
        depth2rgb = beside if frame.depth2rgb is None else beside @ frame.depth2rgb
        camera = replace(colour, fx=colour.fx * scale, fy=colour.fy * scale, cx=colour.cx + du, cy=colour.cy + dv)
        return replace(frame, rgb_intrinsics=camera, depth2rgb=depth2rgb if tx else frame.depth2rgb)

    return moved, out


__all__ = [
    "CHECK_FRAMES",
    "LAYOUTS",
    "Recording",
    "check_intrinsics",
    "detect_layout",
    "load_recording",
    "register_colour",
    "strongest_colour_move",
]
