"""The simulated suite: generated rooms, each walked once in a varied style, with the default faults.

A *case* is one room and one walk. The room is ``generate_room(room_seed)`` at a size and with
objects drawn from the room seed (5.5-9 x 4.5-7 m, 2.4-3 m high; two table groups, or two to three
from 40 m2 of floor, with 2-4 chairs a table; 1-4 laptops, 1-2 couches, 1-2 TVs). The walk is
``room_walk`` in a ``WalkStyle`` drawn from the room seed (eye height 1.1-1.9 m, speed, laps of the
room from a third of one, glances at the floor and ceiling, fast turns, hand-held jitter), rendered by
``simulate_sequence`` and detected by ``SimulatedDetector``, both with the default ``DetectorFaults``
and seed ``walk_seed``. Maps are built with ``arcloud.eval.protocol.run_map``: the centralized run
(frames in order) and ``runs`` distributed runs of ``USERS`` users (run r: seed ``walk_seed * 1000 + r``),
each scored by ``arcloud.accuracy.common.score_run``.

Ground truth is what the walk shows (``observable_objects``): with partial coverage, a short walk or
glances away, some objects are never seen well, and a map cannot be blamed for them. The case record
counts them (``n_unseen``) and names them (``unseen``). A map may still find one of them: an object of
the map that matches an unseen one counts neither for nor against it (``without_unseen``; each run
records how many as ``n_matched_unseen``).

Rooms ``TUNE_ROOMS`` are the ``tune`` split (parameters may be tuned on them), ``REPORT_ROOMS`` the
``report`` split. The quick mode walks ``QUICK_CASES``: two other rooms of the same kind, 150 frames
each, one distributed run (about 20 s).

``OFFICE_SEEDS`` are the ``office`` split: ``office_room(seed)``, an office laid out as the held-out
real one is described (two desks pushed together, two monitors side by side and one back to back with
them, three chairs, a laptop), walked in the seed's style; no parameter is tuned on it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from arcloud.accuracy.common import USERS, case_record, case_runs, score_run, summarise
from arcloud.core.types import Frame, LabelledBox, MapObject, Params
from arcloud.errors import InvalidInput
from arcloud.eval.metrics import iou_aabb
from arcloud.eval.protocol import CachedDetector, object_boxes
from arcloud.sim.detector import DetectorFaults, FrameTruths, SimulatedDetector
from arcloud.sim.room import Room, RoomObject, generate_room, office_room, room_walk
from arcloud.sim.sequence import simulate_sequence
from arcloud.virtual_camera.walk import WalkStyle

logger = logging.getLogger(__name__)

RUNS = 3
QUICK_RUNS = 1
FRAMES = 300
QUICK_FRAMES = 150
TUNE_ROOMS = tuple(range(0, 6))
REPORT_ROOMS = tuple(range(6, 26))
OFFICE_SEEDS = tuple(range(0, 4))
#: An object is observable on a walk when at least ``MIN_VISIBLE_PX`` of its pixels (32 x 32: COCO's
#: smallest "medium" object) are in view in at least ``MIN_VISIBLE_FRAMES`` frames (1/3 s at 30 Hz).
MIN_VISIBLE_PX = 1024
MIN_VISIBLE_FRAMES = 10
# Words that, with the room seed, seed what is drawn per room (its size and counts, its walk's style).
_ROOM_WORD, _STYLE_WORD = 11, 12


@dataclass(frozen=True)
class SimCase:
    """One room (``room_seed``) walked once (``walk_seed``: path, faults and detector) for ``frames``
    frames, in the ``tune`` or ``report`` split."""

    room_seed: int
    split: str
    walk_seed: int
    frames: int = FRAMES

    @property
    def name(self) -> str:
        return f"{'office' if self.split == 'office' else 'room'}-{self.room_seed:02d}"

    def room(self) -> Room:
        """The case's room: ``office_room`` in the office split, else ``generate_room`` as ``room_spec`` draws it."""
        if self.split == "office":
            return office_room(self.room_seed)
        size_m, counts = self.room_spec()
        return generate_room(self.room_seed, size_m=size_m, counts=counts)

    def room_spec(self) -> tuple[tuple[float, float, float], dict[str, int]]:
        """The room's (x, y, height) in metres and its objects per class, drawn from the room seed."""
        rng = np.random.default_rng([self.room_seed, _ROOM_WORD])
        size = (
            round(float(rng.uniform(5.5, 9.0)), 2),
            round(float(rng.uniform(4.5, 7.0)), 2),
            round(float(rng.uniform(2.4, 3.0)), 2),
        )
        tables = int(rng.integers(2, 4)) if size[0] * size[1] >= 40.0 else 2
        chairs, laptops, couches, tvs = (
            int(rng.integers(low, high + 1)) for low, high in ((2 * tables, 4 * tables), (1, 4), (1, 2), (1, 2))
        )
        return size, {"chair": chairs, "table": tables, "laptop": laptops, "couch": couches, "tv": tvs}

    def style(self) -> WalkStyle:
        return WalkStyle.sample(np.random.default_rng([self.room_seed, _STYLE_WORD]))


FULL_CASES = tuple(
    SimCase(seed, "tune" if seed in TUNE_ROOMS else "report", walk_seed=seed) for seed in TUNE_ROOMS + REPORT_ROOMS
) + tuple(SimCase(seed, "office", walk_seed=seed) for seed in OFFICE_SEEDS)
QUICK_CASES = tuple(SimCase(seed, "report", walk_seed=seed, frames=QUICK_FRAMES) for seed in (100, 101))


def observable_objects(
    room: Room,
    frames: Sequence[Frame],
    detector: SimulatedDetector,
    *,
    min_visible_px: int = MIN_VISIBLE_PX,
    min_frames: int = MIN_VISIBLE_FRAMES,
) -> list[RoomObject]:
    """The room's objects that the walk shows: at least ``min_visible_px`` pixels of the object in
    view (not occluded, in the true instance image of the frame: ``SimulatedDetector.truth``) in at
    least ``min_frames`` of ``frames``. Depth beyond the sensor's range is not taken into account."""
    frames_seen = np.zeros(int(room.triangle_instance.max()) + 1, np.int64)
    for frame in frames:
        triangle = detector.truth(frame).triangle()
        instance = np.where(triangle >= 0, room.triangle_instance[np.maximum(triangle, 0)], 0)
        area_px = np.bincount(instance.ravel(), minlength=len(frames_seen))
        frames_seen += area_px >= min_visible_px
    return [o for o in room.objects if frames_seen[o.instance_id] >= min_frames]


def without_unseen(objects: Sequence[MapObject], unseen: Sequence[RoomObject]) -> list[MapObject]:
    """The map's objects less those that match an unseen object: same label and a box IoU above 0.25
    (as a true positive of mAP@0.25). Finding what the walk barely showed is no error, and missing
    it is none either: such an object is left out of the scoring, like KITTI's "don't care" regions."""

    def matches_unseen(obj: MapObject) -> bool:
        return obj.aabb is not None and any(
            o.label == obj.label and iou_aabb(o.aabb_min, o.aabb_max, obj.aabb.min, obj.aabb.max) > 0.25 for o in unseen
        )

    return [o for o in objects if not matches_unseen(o)]


def run_suite(
    *,
    quick: bool,
    out_dir: Path | None = None,
    cases: Sequence[SimCase] | None = None,
    faults: DetectorFaults = DetectorFaults(),
    params: Params | None = None,
    runs: int | None = None,
    workers: int = 2,
) -> dict[str, Any]:
    """Walk, map and score every case (``QUICK_CASES`` when ``quick``, else ``FULL_CASES``), with
    ``runs`` distributed runs each (default ``QUICK_RUNS`` or ``RUNS``) on ``workers`` threads.
    Returns ``{"suite": "sim", "cases": [...], "summary": summarise(cases), ...}`` (see
    ``arcloud.accuracy.common``). ``out_dir``: where to draw each case's centralized served map
    (``pictures/<case>.png``: observable ground truth in green, the walk as dots), or None."""
    started = time.perf_counter()
    chosen = tuple(cases) if cases is not None else (QUICK_CASES if quick else FULL_CASES)
    n_runs = runs if runs is not None else (QUICK_RUNS if quick else RUNS)
    if isinstance(n_runs, bool) or not isinstance(n_runs, int) or n_runs < 1:
        raise InvalidInput("runs", "an integer >= 1 (distributed runs per case)", repr(runs))
    params = params if params is not None else Params()
    records = []
    for case in chosen:
        try:
            records.append(evaluate_case(case, faults, params, runs=n_runs, workers=workers, out_dir=out_dir))
        except Exception as exc:  # a crash is a failure of the suite: say which case to rerun
            exc.add_note(f"in sim case {case.name} ({case})")
            raise
    return {
        "suite": "sim",
        "quick": quick,
        "cases": records,
        "summary": summarise(records),
        "users": USERS,
        "runs": n_runs,
        "tune_rooms": [c.room_seed for c in chosen if c.split == "tune"],
        "report_rooms": [c.room_seed for c in chosen if c.split == "report"],
        "office_seeds": [c.room_seed for c in chosen if c.split == "office"],
        "ground_truth": {"min_visible_px": MIN_VISIBLE_PX, "min_frames": MIN_VISIBLE_FRAMES},
        "faults": dataclasses.asdict(faults),
        "params": dataclasses.asdict(params),
        "wall_s": round(time.perf_counter() - started, 2),
    }


def evaluate_case(
    case: SimCase, faults: DetectorFaults, params: Params, *, runs: int, workers: int = 2, out_dir: Path | None = None
) -> dict[str, Any]:
    """The case's record (``arcloud.accuracy.common.case_record``): its centralized map and ``runs``
    maps of ``USERS`` users, scored against the objects observable on its walk."""
    started = time.perf_counter()
    room = case.room()
    style = case.style()
    poses = room_walk(room, case.frames, case.walk_seed, style=style)
    truths = FrameTruths(room)
    frames = simulate_sequence(
        room, n_frames=case.frames, seed=case.walk_seed, faults=faults, map_id=case.name, poses=poses, truths=truths
    )
    detector = SimulatedDetector(room, faults, seed=case.walk_seed, truths=truths)
    observable = observable_objects(room, frames, detector)
    ground_truth = [o.box for o in observable]
    unseen = [o for o in room.objects if o not in observable]
    simulated_s = time.perf_counter() - started

    maps: list[list[MapObject]] = []

    def score(users: int, run: int, objects: list[MapObject]) -> dict[str, Any]:
        maps.append(objects)
        scored = without_unseen(objects, unseen)
        return {**score_run(scored, ground_truth, scene=case.name), "n_matched_unseen": len(objects) - len(scored)}

    centralized, distributed = case_runs(
        frames, CachedDetector(detector), params, score, name=case.name, runs=runs, workers=workers, seed=case.walk_seed * 1000
    )
    centralized_map = maps[0]
    if out_dir is not None:
        _draw_case(Path(out_dir) / "pictures" / f"{case.name}.png", case, ground_truth, centralized_map, poses)
    record = case_record(
        case.name, case.split, centralized, distributed, users=USERS,
        room_seed=case.room_seed, walk_seed=case.walk_seed, frames=case.frames, room_size_m=[float(v) for v in room.size_m],
        style=dataclasses.asdict(style), n_room_objects=len(room.objects), n_unseen=len(unseen),
        unseen=[f"{o.label}-{o.instance_id}" for o in unseen],
        simulate_s=round(simulated_s, 2), eval_s=round(time.perf_counter() - started - simulated_s, 2),
    )  # fmt: skip
    mean = record["distributed"]["mean"]
    logger.info(
        "case %s: %d/%d objects observable; centralized mAP@0.25 %.3f served P/R %.3f/%.3f; K=%d mean mAP@0.25 %.3f",
        case.name, len(ground_truth), len(room.objects), centralized["map25"] or 0.0, centralized["served_precision25"],
        centralized["served_recall25"] or 0.0, USERS, mean.get("map25", 0.0),
    )  # fmt: skip
    return record


def _draw_case(
    path: Path, case: SimCase, ground_truth: list[LabelledBox], objects: list[MapObject], poses: Sequence[np.ndarray]
) -> None:
    from arcloud.eval.plot import draw_top_down

    walk_xyz = np.array([pose[:3, 3] for pose in poses])
    served = object_boxes([o for o in objects if o.confirmed])
    draw_top_down(path, gt=ground_truth, predictions=served, points_xyz=walk_xyz,
                  title=f"{case.name} ({case.split}), centralized: observable ground truth (green), served boxes, the walk")  # fmt: skip


__all__ = [
    "FULL_CASES", "OFFICE_SEEDS", "QUICK_CASES", "REPORT_ROOMS", "SimCase", "TUNE_ROOMS", "evaluate_case", "observable_objects", "run_suite", "without_unseen",
]  # fmt: skip
