"""Which way is up in a recording's pose frame, and the gravity-aligned world the readers build from it.

``choose_up`` takes the first of:

1. ``given`` (``--up x,y,z``): up in the pose frame;
2. ``gravity-direction.txt`` in the folder (the 7-Scenes convention: the direction gravity *pulls*, in
   the pose frame);
3. the ground truth's up (``GroundTruthBoxes.up_file``: its ``up_axis_world``, else its aligned +z);
4. an estimate from the recording's own depth (``estimate_up_from_frames``), when the reader asks for one.

With none, up is unknown and the pose frame is taken as it is (z up). ``gravity_world2file`` gives the
reader's output world: the pose frame turned by the smallest rotation that takes up to +z.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from arcloud.core.gravity import UpEstimate, depth_normals, estimate_up, up_rotation
from arcloud.core.types import Frame
from arcloud.datasets.files import read_matrix
from arcloud.errors import DatasetError

if TYPE_CHECKING:
    from arcloud.datasets.gt_boxes import GroundTruthBoxes

logger = logging.getLogger(__name__)

GRAVITY_FILE = "gravity-direction.txt"
#: Frames whose depth normals ``estimate_up_from_frames`` reads, spread over the recording.
ESTIMATE_FRAMES = 40


@dataclass(frozen=True, eq=False)
class UpChoice:
    """``up_file`` (3,) unit up in the pose frame, None when unknown; ``source``: where it came from."""

    up_file: np.ndarray | None
    source: str

    def to_json(self) -> dict[str, object]:
        return {"up_file": None if self.up_file is None else [round(float(v), 6) for v in self.up_file], "source": self.source}


def check_up(value: object, source: str) -> np.ndarray:
    """(3,) unit vector of a finite non-zero 3-vector, else ``DatasetError`` naming ``source``."""
    try:
        up = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{source}: expected 3 finite numbers, not all 0, got {value!r}") from exc
    if up.shape != (3,) or not np.all(np.isfinite(up)) or np.linalg.norm(up) < 1e-9:
        raise DatasetError(f"{source}: expected 3 finite numbers, not all 0, got {np.asarray(value).tolist()}")
    return up / np.linalg.norm(up)


def read_gravity_direction(path: Path) -> np.ndarray:
    """Up (3,) unit, opposite the direction ``gravity-direction.txt`` says gravity pulls."""
    return -check_up(read_matrix(path, (3,)), str(path))


def estimate_up_from_frames(frames: Sequence[Frame], *, samples: int = ESTIMATE_FRAMES) -> UpEstimate:
    """Up in the frames' world from the depth normals of ``samples`` frames spread over ``frames``, the
    mean of their cameras' -y axes (image up) as the prior (``arcloud.core.gravity.estimate_up``)."""
    if len(frames) == 0:
        raise DatasetError("gravity estimate: expected at least one frame, got none")
    picked = [frames[int(i)] for i in np.unique(np.linspace(0, len(frames) - 1, min(samples, len(frames))).round())]
    prior = -np.mean([frame.cam2world[:3, 1] for frame in picked], axis=0)
    normals = [depth_normals(frame.depth_m, frame.intrinsics) @ frame.cam2world[:3, :3].T for frame in picked]
    return estimate_up(np.concatenate(normals), prior)


def choose_up(
    *,
    given: object = None,
    gravity_file: Path | None = None,
    ground_truth: GroundTruthBoxes | None = None,
    estimate: Callable[[], UpEstimate] | None = None,
    where: object = "recording",
) -> UpChoice:
    """Up in the pose frame from the first source there (see the module docstring); the choice is logged."""
    if given is not None:
        up, source = check_up(given, "--up"), "given (--up)"
    elif gravity_file is not None and gravity_file.is_file():
        up, source = read_gravity_direction(gravity_file), str(gravity_file)
    elif ground_truth is not None:
        up, source = ground_truth.up_file, f"{ground_truth.path} ({ground_truth.up_field})"
    elif estimate is not None:
        found = estimate()
        if found.n_normals == 0:
            logger.warning("%s: no horizontal surface near the cameras' mean image up; taking that as up", where)
        up = found.up
        source = (
            f"estimated from {found.n_normals} depth normals ({found.prior_error_deg:.1f} deg from the cameras' mean image up)"
        )
    else:
        return UpChoice(None, "none (the pose frame taken as z-up)")
    logger.info("%s: up %s in the pose frame, from %s", where, np.round(up, 4).tolist(), source)
    return UpChoice(up, source)


def gravity_world2file(up_file: np.ndarray | None) -> np.ndarray:
    """(4, 4) maps the gravity-aligned world (+z = ``up_file``) to the pose frame; identity when up is unknown."""
    world2file = np.eye(4)
    if up_file is not None:
        world2file[:3, :3] = up_rotation(up_file).T  # up_rotation takes up to +z: file -> world
    return world2file


__all__ = [
    "GRAVITY_FILE",
    "UpChoice",
    "check_up",
    "choose_up",
    "estimate_up_from_frames",
    "gravity_world2file",
    "read_gravity_direction",
]
