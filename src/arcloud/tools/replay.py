"""`arcloud replay`: stream a simulated room through a running service as K concurrent users, then score
the map it built.

The walk through ``generate_room(seed)`` is rendered (``simulate_sequence``), cut into K contiguous
segments that are shuffled (``eval.protocol.user_streams``, as the paper's protocol does), and each
segment is uploaded by its own user (device ``user-<k>``) over HTTP, all users at once, each in order.
When every frame is processed, the map's objects are fetched and scored against the room's exact boxes
(its ground truth, in the map's frame: the walk's poses are the room's): every object
(``?include=tentative``) for Table 1's mAP, as the in-process protocol scores its maps; and what a
client is served (a plain ``GET /v1/maps/{map}/objects``: confirmed objects) for its precision and
recall at 3D IoU 0.25 and 0.5 (``eval.metrics.precision_recall``) and its mAP. The service must run the
same simulated detector: ``--detector sim:<seed>`` (the simulator's detector derives each frame's
faults from its frame id, so the result does not depend on which user sent a frame).

Results JSON::

    {"table1": [{"approach": "distributed", "users": K, "runs": 1, "map25_mean", "map25_var": 0,
                 "map50_mean", "map50_var": 0}],
     "served": {"objects", "precision25", "recall25", "precision50", "recall50", "map25", "map50",
                "matches": {"0.25": {"true_positives", "n_predictions", "n_gt", ...}, "0.5": {...}}},
     "objects": {"confirmed", "tentative"},
     "ground_truth": [{"label", "aabb_min", "aabb_max"}],
     "frames": {"sent", "accepted", "duplicate", "processed", "failed", "lost"}, ...}

The map is kept as it is, so that a device key (which may upload, not delete) can replay into its map;
``fresh`` (``--fresh``, an admin key) deletes it first, so that no earlier frame counts in the scores. The
frame counts are those of the frames replay sent, whatever else the map holds (the SDK's
``wait_until_processed`` asks each frame's status).

The client tries every request again through an outage of the service or its store (``RetryPolicy``:
``REPLAY_RETRIES`` times, up to 10 s apart): a frame sent twice is answered ``duplicate``. Frames the
store lost (Redis restarted without its data) are counted ``lost``: the wait ends when every frame sent
is processed, failed or lost.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from arcloud import __version__
from arcloud.client.http import AsyncArcloudClient, ServiceError, frame_body
from arcloud.client.results import ObjectOut

log = logging.getLogger(__name__)

REPLAY_RETRIES = 20  # per request, 0.25 s doubling up to 10 s apart: rides out about 3 minutes of outage


def replay(
    url: str,
    map_id: str,
    users: int,
    seed: int,
    out: Path | str | None,
    *,
    n_frames: int = 300,
    width: int = 640,
    height: int = 480,
    timeout_s: float = 1800.0,
    show_progress: bool = True,
    fresh: bool = False,
    token: str | None = None,
) -> dict[str, Any]:
    """Replay and score; writes the results JSON to ``out`` (unless None) and returns it. ``fresh``: delete
    the map first (an admin key's), so that earlier frames do not count."""
    from arcloud.core.types import Intrinsics
    from arcloud.eval.metrics import evaluate, precision_recall
    from arcloud.eval.protocol import user_streams
    from arcloud.sim.room import generate_room
    from arcloud.sim.sequence import simulate_sequence

    started = time.perf_counter()
    room = generate_room(seed)
    scale = width / 640
    intrinsics = Intrinsics(525.0 * scale, 525.0 * scale, (width - 1) / 2, (height - 1) / 2)
    frames = simulate_sequence(
        room, n_frames=n_frames, seed=seed, width=width, height=height, intrinsics=intrinsics, map_id=map_id
    )
    streams = user_streams(len(frames), users, np.random.default_rng(seed))
    rendered_s = time.perf_counter() - started

    sent_at = time.perf_counter()
    sent, answers, done, served, every = asyncio.run(
        _stream(url, map_id, frames, streams, timeout_s, show_progress, fresh, token)
    )
    processed_s = time.perf_counter() - sent_at

    ground_truth = [o.box for o in room.objects]
    gt = {map_id: ground_truth}
    scores = evaluate({map_id: _boxes(every)}, gt)
    served_boxes = {map_id: _boxes(served)}
    served_scores = evaluate(served_boxes, gt)
    matches = {f"{iou:g}": precision_recall(served_boxes, gt, iou_threshold=iou) for iou in (0.25, 0.5)}
    results: dict[str, Any] = {
        "table1": [
            {
                "approach": "distributed",
                "users": users,
                "runs": 1,
                "map25_mean": _finite(scores.map_at(0.25)),
                "map25_var": 0.0,
                "map50_mean": _finite(scores.map_at(0.5)),
                "map50_var": 0.0,
            }
        ],
        "served": {
            "objects": len(served),
            "precision25": matches["0.25"].precision,
            "recall25": _finite(matches["0.25"].recall),
            "precision50": matches["0.5"].precision,
            "recall50": _finite(matches["0.5"].recall),
            "map25": _finite(served_scores.map_at(0.25)),
            "map50": _finite(served_scores.map_at(0.5)),
            "matches": {iou: pr.to_dict() for iou, pr in matches.items()},
        },
        "objects": {
            "confirmed": sum(1 for o in every if o.status == "confirmed"),
            "tentative": sum(1 for o in every if o.status == "tentative"),
        },
        "ground_truth": [
            {"label": box.label, "aabb_min": box.min.tolist(), "aabb_max": box.max.tolist()} for box in ground_truth
        ],
        "frames": {
            "sent": sent,
            "accepted": sum(1 for a in answers if a == "queued"),
            "duplicate": sum(1 for a in answers if a == "duplicate"),
            "processed": done["processed"],
            "failed": done["failed"],
            "lost": done["lost"],
        },
        "evaluation": scores.to_dict(),
        "scene": {"seed": seed, "frames": n_frames, "width": width, "height": height, "objects": len(ground_truth)},
        "service": {"url": url, "map_id": map_id},
        "seconds": {
            "render": round(rendered_s, 2),
            "stream_and_process": round(processed_s, 2),
            "frames_per_s": round(n_frames / processed_s, 2) if processed_s > 0 else None,
        },
        "versions": {"arcloud": __version__, "python": platform.python_version(), "numpy": np.__version__},
    }
    if out is not None:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(results, indent=2))
        log.info("wrote %s", path)
    return results


def _finite(value: float) -> float | None:
    return None if not np.isfinite(value) else float(value)


def _boxes(objects: list[ObjectOut]) -> list[Any]:
    """The listed objects that have a box, as scored boxes."""
    from arcloud.core.types import LabelledBox

    return [
        LabelledBox(o.label, np.array(o.aabb.min), np.array(o.aabb.max), o.score)
        for o in objects
        if o.aabb is not None and o.label
    ]


async def _stream(
    url: str,
    map_id: str,
    frames: list[Any],
    streams: list[list[int]],
    timeout_s: float,
    show_progress: bool,
    fresh: bool,
    token: str | None = None,
) -> tuple[int, list[str], dict[str, int], list[ObjectOut], list[ObjectOut]]:
    """Upload every user's frames, wait until they are done; returns (frames sent, answers, the frames
    sent by outcome (processed, failed, lost), the served objects (a plain GET), every object)."""
    from tqdm import tqdm

    answers: list[str] = []
    async with AsyncArcloudClient(url, max_retries=REPLAY_RETRIES, token=token) as client:
        if fresh:
            try:
                await client.delete_map(map_id)
            except ServiceError as exc:
                if exc.status != 404:
                    raise
        with tqdm(
            total=len(frames), unit="frame", desc=f"replay {len(streams)} users", disable=not show_progress, leave=False
        ) as bar:

            async def user(k: int, indices: list[int]) -> None:
                for index in indices:
                    frame = dataclasses.replace(frames[index], map_id=map_id, device_id=f"user-{k:03d}")
                    _, body = await asyncio.to_thread(frame_body, frame)
                    answer = await client.send_encoded(map_id, body)
                    answers.append(answer.status)
                    bar.update(1)

            await asyncio.gather(*(user(k, indices) for k, indices in enumerate(streams)))
        done = (await client.wait_until_processed(map_id, timeout_s=timeout_s))["frames"]
        if done["lost"]:
            log.warning("map %s: %d of %d frames sent are lost (the store lost its data?)", map_id, done["lost"], len(frames))
        if done["lost"] == done["sent"]:  # the store lost the whole map
            return len(frames), answers, done, [], []
        served = await client.list_objects(map_id)
        every = await client.list_objects(map_id, include_tentative=True)
    return len(frames), answers, done, served, every
