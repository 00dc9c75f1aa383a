"""How much the real-data figures rest on the camera's calibration: the 7-Scenes report case mapped with
the depth intrinsics moved a little.

The map is only as right as the rays it back-projects: a focal length 2 % off scales every point about
the camera by 2 % (5 cm at 2.5 m), a principal point 8 px off turns every ray by ~0.8 degrees, and the
ground truth was made with the published intrinsics (fx = fy = 585, cx = 320, cy = 240). Real devices
are calibrated to about that (a Kinect v1's colour camera differs from its default by 16 px in cy; TUM
publishes both), so this bench shows how far the figures move within a calibration's error.

Each variant maps frames 0-999 centralized (one user, YOLO11n-seg run once per frame and replayed) with
the sequence's intrinsics changed, and scores the served and all-object boxes against the observed ground
truth as ``make accuracy`` does. The JSON holds every variant's figures, the baseline's, the worst
variant's beside it, versions and machine; pictures of each map go under ``--work``.

    .venv/bin/python bench/bench_calibration.py [--stride 1] [--out bench/results/calibration.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from common import SHARED, environment, write_json

from arcloud.accuracy.sevenscenes import MODELS_REL, SEQUENCE_REL, score_against
from arcloud.core.types import Intrinsics, Params
from arcloud.datasets.export import seven_scenes_export_frame
from arcloud.datasets.frames import LazyFrames
from arcloud.datasets.sevenscenes import load_seven_scenes
from arcloud.detectors import make_detector
from arcloud.eval.map_pictures import write_pictures
from arcloud.eval.protocol import CachedDetector, run_map
from arcloud.stores.memory import MemoryStore

#: name -> (focal length scale, cx shift px, cy shift px), applied to both focal lengths.
VARIANTS = {
    "published": (1.0, 0.0, 0.0),
    "focal x0.98": (0.98, 0.0, 0.0),
    "focal x1.02": (1.02, 0.0, 0.0),
    "cx -8 px": (1.0, -8.0, 0.0),
    "cx +8 px": (1.0, 8.0, 0.0),
    "cy -8 px": (1.0, 0.0, -8.0),
    "cy +8 px": (1.0, 0.0, 8.0),
    "cy -16 px": (1.0, 0.0, -16.0),
    "cy +16 px": (1.0, 0.0, 16.0),
}
FIGURES = ("served_map25", "served_map50", "served_precision25", "served_recall25", "map25", "map50")


def moved(intrinsics: Intrinsics, focal_scale: float, dcx: float, dcy: float) -> Intrinsics:
    return Intrinsics(intrinsics.fx * focal_scale, intrinsics.fy * focal_scale, intrinsics.cx + dcx, intrinsics.cy + dcy)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stride", type=int, default=1, help="map every stride-th frame (1: all 1000)")
    parser.add_argument("--model", choices=tuple(MODELS_REL), default=next(iter(MODELS_REL)))
    parser.add_argument("--out", type=Path, default=Path("bench/results/calibration.json"))
    parser.add_argument("--work", type=Path, default=Path("out/calibration"), help="pictures of every map")
    args = parser.parse_args()
    root = SHARED / SEQUENCE_REL
    if not (root / "gt-boxes.json").is_file():
        raise SystemExit(f"{root}: the 7-Scenes sequence with gt-boxes.json must be in {SHARED} (see its README)")
    sequence = load_seven_scenes(root, align_gravity=True)
    export_frame = seven_scenes_export_frame(sequence)
    params = export_frame.params(Params())
    ground_truth = sequence.ground_truth
    assert ground_truth is not None
    detector = CachedDetector(make_detector(f"onnx:{SHARED / MODELS_REL[args.model]}"))
    names = sequence.frame_names[:: args.stride]
    rows: dict[str, dict[str, Any]] = {}
    for name, change in VARIANTS.items():
        started = time.perf_counter()
        variant = dataclasses.replace(sequence, intrinsics=moved(sequence.intrinsics, *change))
        frames = LazyFrames(names, variant.load_frame, cache=False)
        objects = run_map(frames, detector, params, new_store=MemoryStore, users=1, seed=0, workers=1, map_id="calibration")
        scores = score_against(objects, ground_truth, scene=sequence.name)["observed"]
        pictures = write_pictures(
            args.work / name.replace(" ", "_"), frames, objects, {}, title=f"{sequence.name}: intrinsics {name}",
            gt=ground_truth.boxes("observed"), world2boxes=export_frame.world2export,
        )  # fmt: skip
        rows[name] = {
            "intrinsics": list(dataclasses.astuple(variant.intrinsics)),
            **{key: scores[key] for key in FIGURES},
            "n_served": scores["n_served"],
            "pictures": pictures,
            "wall_s": round(time.perf_counter() - started, 1),
        }
        print(name, {key: None if scores[key] is None else round(scores[key], 3) for key in FIGURES}, flush=True)
    moved_rows = [row for name, row in rows.items() if name != "published"]
    worst = {key: min(row[key] or 0.0 for row in moved_rows) for key in FIGURES}
    write_json(
        args.out,
        {
            "benchmark": "calibration",
            "sequence": sequence.name,
            "model": MODELS_REL[args.model],
            "frames": len(names),
            "stride": args.stride,
            "published_intrinsics": list(dataclasses.astuple(sequence.intrinsics)),
            "variants": rows,
            "worst_moved": worst,
            **environment(("arcloud", "numpy", "scipy", "onnxruntime")),
        },
    )


if __name__ == "__main__":
    main()
