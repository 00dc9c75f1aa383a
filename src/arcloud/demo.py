"""`arcloud demo`: the paper's Table 1 on a simulated room, in one process with the embedded store.

One generated room; one user's walk through it rendered to RGB-D; a simulated detector with realistic
faults. The centralized run (one user, frames in order) and distributed runs (K = 10, 50, 100 users,
shuffled segments, concurrent workers) build maps that are scored against the room's exact boxes.
Writes ``results.json`` (Table 1 scored on every object, as the ScanNet evaluation ranks predictions, and
the precision and recall of what a client is served: the confirmed objects of each approach's first
map) and top-down pictures of the ground-truth and served boxes to the output folder.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from arcloud import __version__
from arcloud.accuracy.common import score_run
from arcloud.core.types import MapObject, Params
from arcloud.eval.plot import draw_top_down
from arcloud.eval.protocol import object_boxes, table1
from arcloud.sim.detector import DetectorFaults, FrameTruths, SimulatedDetector
from arcloud.sim.room import generate_room
from arcloud.sim.sequence import simulate_sequence
from arcloud.stores.memory import MemoryStore

log = logging.getLogger(__name__)


def run_demo(
    out_dir: Path,
    *,
    seed: int = 0,
    n_frames: int = 300,
    runs: int = 3,
    users: tuple[int, ...] = (10, 50, 100),
    workers: int = 4,
    params: Params | None = None,
    show_progress: bool = True,
) -> dict[str, Any]:
    """Run the demo and write its results; returns what ``results.json`` holds."""
    params = params or Params()
    faults = DetectorFaults()  # the demo's detector: the simulator's default faults
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    room = generate_room(seed)
    truths = FrameTruths(room)
    frames = simulate_sequence(room, n_frames=n_frames, seed=seed, faults=faults, truths=truths)
    ground_truth = [o.box for o in room.objects]
    detector = SimulatedDetector(room, faults, seed=seed, truths=truths)
    rendered_s = time.perf_counter() - started

    maps: dict[tuple[str, int], list[MapObject]] = {}

    def keep_first_map(approach: str, k: int, run: int, objects: list[MapObject]) -> None:
        if run == 0:
            maps[(approach, k)] = objects

    total = n_frames * (1 + runs * len(users))
    with tqdm(total=total, unit="frame", desc="demo", disable=not show_progress, leave=False) as bar:
        results = table1(
            frames,
            detector,
            ground_truth,
            params,
            new_store=MemoryStore,
            users=users,
            runs=runs,
            seed=seed,
            workers=workers,
            scene=f"room{seed}",
            progress=bar.update,
            on_run=keep_first_map,
        )
    pictures, served = {}, {}
    for (approach, k), objects in maps.items():
        name = f"topdown_{approach}_{k}.png"
        draw_top_down(
            out_dir / name,
            gt=ground_truth,
            predictions=object_boxes([o for o in objects if o.confirmed]),
            title=f"{approach}, {k} user{'s' if k > 1 else ''}: ground truth (green) and the served (confirmed) boxes",
        )
        pictures[f"{approach}_{k}"] = name
        figures = score_run(objects, ground_truth)
        served[f"{approach}_{k}"] = {
            key: figures[key]
            for key in (
                "n_served",
                "n_objects",
                "n_gt",
                "served_precision25",
                "served_recall25",
                "served_precision50",
                "served_recall50",
            )
        }
    results.update(
        {
            "scene": {
                "seed": seed,
                "frames": n_frames,
                "objects": len(ground_truth),
                "classes": sorted({b.label for b in ground_truth}),
            },
            "workers": workers,
            "params": dataclasses.asdict(params),
            "faults": dataclasses.asdict(faults),
            "served": served,
            "pictures": pictures,
            "seconds": {"render": round(rendered_s, 2), "total": round(time.perf_counter() - started, 2)},
            "versions": {"arcloud": __version__, "python": platform.python_version(), "numpy": np.__version__},
            "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine()},
        }
    )
    (out_dir / "results.json").write_text(json.dumps(results, indent=2))
    return results


def format_table1(results: dict[str, Any]) -> str:
    """The paper's Table 1 as text."""
    lines = [
        f"{'approach':<12} {'users':>5} {'runs':>4}   {'mAP@0.25':>8} {'var':>9}   {'mAP@0.5':>8} {'var':>9}",
    ]
    for row in results["table1"]:
        lines.append(
            f"{row['approach']:<12} {row['users']:>5} {row['runs']:>4}   {row['map25_mean']:>8.4f} {row['map25_var']:>9.2e}"
            f"   {row['map50_mean']:>8.4f} {row['map50_var']:>9.2e}"
        )
    served = results.get("served") or {}
    if served:
        lines += [
            "",
            f"{'served (confirmed), first run':<32} {'served':>6} {'of':>4} {'gt':>4}   {'P@0.25':>6} {'R@0.25':>6}   {'P@0.5':>6} {'R@0.5':>6}",
        ]
        for name, row in served.items():
            lines.append(
                f"{name:<32} {row['n_served']:>6} {row['n_objects']:>4} {row['n_gt']:>4}   {row['served_precision25']:>6.3f} "
                f"{row['served_recall25'] or 0:>6.3f}   {row['served_precision50']:>6.3f} {row['served_recall50'] or 0:>6.3f}"
            )
    return "\n".join(lines)
