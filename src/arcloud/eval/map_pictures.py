"""Pictures of maps over the frames they were built from: top-down views over fused points and boxes
drawn into frames, with ground truth in green."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from arcloud.core.types import Frame, LabelledBox, MapObject, Params


def fused_points(frames: Sequence[Frame], *, every: int = 20, stride_px: int = 8, max_depth_m: float = 4.0) -> np.ndarray:
    """(N, 3) world points back-projected from every ``every``-th frame (every ``stride_px``-th pixel)."""
    from arcloud.core.voxels import mask_points

    params = Params(depth_max_m=max_depth_m, erode_px=0)
    chunks = [
        mask_points(frames[i], np.ones(frames[i].shape, bool), params, stride_px) for i in range(0, len(frames), max(1, every))
    ]
    return np.concatenate(chunks) if chunks else np.zeros((0, 3))


def served(objects: Sequence[MapObject]) -> list[MapObject]:
    """What a client is served: the confirmed objects."""
    return [o for o in objects if o.confirmed]


def write_pictures(
    stem: Path,
    frames: Sequence[Frame],
    centralized: list[MapObject],
    first_runs: dict[int, list[MapObject]],
    *,
    title: str = "",
    n_frames: int = 4,
    gt: Sequence[LabelledBox] = (),
    world2boxes: np.ndarray | None = None,
) -> list[str]:
    """Top-down pictures (served boxes over fused points) of the centralized and first distributed maps, and
    the centralized boxes drawn into ``n_frames`` frames spread over the sequence; ground-truth boxes
    ``gt`` in green in all of them. ``world2boxes`` (4, 4) maps the world of the frames to the frame
    the boxes are in (``Params.world2aligned``; None: the world). Returns the paths."""
    from arcloud.eval.plot import GT_COLOR_RGB, draw_boxes_in_image, draw_top_down, write_png
    from arcloud.eval.protocol import object_boxes

    world2boxes = np.eye(4) if world2boxes is None else np.asarray(world2boxes, np.float64)
    points = fused_points(frames) @ world2boxes[:3, :3].T + world2boxes[:3, 3]
    written = [
        draw_top_down(f"{stem}_topdown_users1.png", gt=gt, predictions=object_boxes(served(centralized)), points_xyz=points,
                      title=f"{title or stem.name}: centralized, {len(frames)} frames, served objects")
    ]  # fmt: skip
    for k, objects in sorted(first_runs.items()):
        written.append(
            draw_top_down(f"{stem}_topdown_users{k}.png", gt=gt, predictions=object_boxes(served(objects)), points_xyz=points,
                          title=f"{title or stem.name}: {k} users, run 0, served objects")
        )  # fmt: skip
    boxes = object_boxes(served(centralized))
    for index in np.linspace(0, len(frames) - 1, n_frames).round().astype(int) if len(frames) else []:
        frame = frames[int(index)]
        cam2boxes = world2boxes @ frame.cam2world
        image = draw_boxes_in_image(frame.rgb, gt, cam2boxes, frame.intrinsics, color_rgb=GT_COLOR_RGB, show_labels=False)
        image = draw_boxes_in_image(image, boxes, cam2boxes, frame.intrinsics)
        written.append(write_png(f"{stem}_frame_{frame.frame_id}.png", image))
    return [str(p) for p in written]
