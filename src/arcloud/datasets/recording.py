"""Any posed RGB-D recording as an evaluation reads it, whatever its layout: a ScanNet scene, a 7-Scenes
sequence or a TUM RGB-D recording, in a folder of any name.

``load_recording`` detects the layout (``detect_layout``), parses the folder with its reader and gives
one ``Recording``: the frames (by name, read on demand), the ground truth (``gt_boxes``, else the
folder's ``gt-boxes.json``, else a ScanNet scene's mesh annotation), the frame maps are boxed and
exported in (``ExportFrame``: the ground truth's aligned frame when there is one) and how up was chosen.
"""

from __future__ import annotations

import logging
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
    frame and its source; ``facts``: what else the layout's reader says, for the results."""

    layout: str
    name: str
    root: Path
    frame_names: tuple[str, ...]
    load_frame: Callable[[str], Frame]
    ground_truth: GroundTruthBoxes | None
    export_frame: ExportFrame
    gravity: UpChoice
    facts: Mapping[str, Any] = field(default_factory=dict)


def detect_layout(root: Path) -> str:
    """``tum`` (``rgb.txt`` and ``depth.txt``), ``7scenes`` (``frame-*.pose.txt``, or ``seq-*`` folders of
    them) or ``scannet`` (a scene folder with ``pose/``, or a ``<name>.txt``)."""
    from arcloud.datasets.scannet import is_scene_dir
    from arcloud.datasets.tum import is_tum_recording

    if not root.is_dir():
        raise DatasetError(f"{root}: expected a recording folder, got no such folder")
    if is_tum_recording(root):
        return "tum"
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
        tum_export_frame(sequence), UpChoice(sequence.up_file, sequence.up_source), facts,
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
        seven_scenes_export_frame(sequence), UpChoice(sequence.up_file, sequence.up_source), facts,
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
        "scannet", map_id_of(scene.scene_id), base, scene.frame_names, scene.load_frame,
        ground_truth, export_frame, UpChoice(up_file, "ScanNet axis-aligned frame: z up"), facts,
    )  # fmt: skip


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


#: ``register_colour``: the frames it reads, spread over the recording; the moves of the colour camera it tries
#: (pixels, each way: every second pixel, then the pixels around the best); how much stronger the edges must agree
#: at the best move for it to be taken. 16 px is the gap between the two principal points TUM publishes for its
#: freiburg1 camera (its colour camera's calibration, and the values for its registered depth).
REGISTRATION_FRAMES = 40
REGISTRATION_SHIFT_PX = 20
REGISTRATION_MARGIN = 0.1


def register_colour(
    frame_names: Sequence[str],
    load_frame: Callable[[str], Frame],
    shift_px: tuple[float, float] | None = None,
    *,
    where: object = "",
) -> tuple[Callable[[str], Frame], dict[str, Any]]:
    """``load_frame`` with the colour camera moved by ``shift_px`` (du, dv pixels: its principal point), or, when
    None, by the move of up to ``REGISTRATION_SHIFT_PX`` each way (every second pixel, then the pixels around the
    strongest) at which the near sides of the depth edges of up to ``REGISTRATION_FRAMES`` of ``frame_names`` land
    on the strongest colour gradients (``core.calibration.colour_edge_strength``), when they are
    ``REGISTRATION_MARGIN`` stronger there than where the frames put them and the move is not on the search's border
    (a climb towards a border is no peak); and what was found, as JSON (logged as a
    warning naming ``where`` when a move is taken). A mask is drawn on colour and looked up on depth, so a colour
    camera a few pixels off moves every mask's border across its object's edge."""
    import numpy as np

    from arcloud.core.calibration import colour_edge_strength

    out: dict[str, Any] = {}
    if shift_px is None:
        names = frame_names[:: max(1, -(-len(frame_names) // REGISTRATION_FRAMES))]
        frames = [load_frame(name) for name in names]
        reach = range(-REGISTRATION_SHIFT_PX, REGISTRATION_SHIFT_PX + 1, 2)
        moves = [(0.0, 0.0)] + [(float(du), float(dv)) for dv in reach for du in reach if du or dv]
        strength = colour_edge_strength(frames, moves)
        if not np.isfinite(strength).all():  # no depth edge lands in any colour image: nothing to tell
            return load_frame, {"frames": len(names), "edge_strength": None, "shift_px": [0.0, 0.0]}
        coarse = moves[int(np.argmax(strength))]
        around = [(coarse[0] + du, coarse[1] + dv) for dv in (-1.0, 0.0, 1.0) for du in (-1.0, 0.0, 1.0) if du or dv]
        moves += around
        strength = np.concatenate([strength, colour_edge_strength(frames, around)])
        best = int(np.argmax(strength))
        # a peak, not the edge of the search: colour and depth that differ by more than a shift (another focal
        # length, a baseline) make the strength climb a little towards some border, and that is no registration
        inside = max(abs(moves[best][0]), abs(moves[best][1])) < REGISTRATION_SHIFT_PX
        taken = bool(inside and strength[best] > (1 + REGISTRATION_MARGIN) * strength[0])
        shift_px = moves[best] if taken else (0.0, 0.0)
        out = {
            "frames": len(names),
            "edge_strength": round(float(strength[0]), 2),
            "strongest_shift_px": list(moves[best]),
            "strongest_edge_strength": round(float(strength[best]), 2),
        }
        if taken:
            logger.warning(
                "%s: the depth's edges meet the colour's %.0f %% better with the colour camera moved by %+g, %+g px; "
                "moving it (--colour-shift 0,0 keeps it)",
                where, 100 * (strength[best] / strength[0] - 1), *shift_px,
            )  # fmt: skip
    du, dv = float(shift_px[0]), float(shift_px[1])
    out["shift_px"] = [du, dv]
    if not (du or dv):
        return load_frame, out

    def moved(name: str) -> Frame:
        frame = load_frame(name)
        colour = frame.rgb_intrinsics or frame.intrinsics
        return replace(frame, rgb_intrinsics=replace(colour, cx=colour.cx + du, cy=colour.cy + dv))

    return moved, out


__all__ = ["CHECK_FRAMES", "LAYOUTS", "Recording", "check_intrinsics", "detect_layout", "load_recording", "register_colour"]
