"""How much the real-data figures rest on the camera's calibration: the 7-Scenes report case mapped with
the intrinsics moved a little.

The map is only as right as the rays it back-projects: a focal length 2 % off scales every point about
the camera by 2 % (5 cm at 2.5 m), a principal point 8 px off turns every ray by ~0.8 degrees, and the
ground truth was made with the published depth intrinsics (fx = fy = 585, cx = 320, cy = 240). A Kinect
v1's colour camera is not registered to its depth here: its intrinsics were estimated (f = 527,
c = (324, 239): ``gt-boxes.json``), and masks drawn on colour are carried to depth through them.

Two kinds of variant, each mapping frames 0-999 centralized (one user, YOLO11n-seg run once per frame and
replayed) and scored against the observed ground truth as ``make accuracy`` scores it:
- ``camera``: both cameras' intrinsics moved alike (the rays turn or scale, masks stay where they were on
  depth): a whole device calibrated that far off.
- ``registration``: only the colour camera's moved (the rays stay, masks land a few pixels off on depth):
  colour and depth registered that far off.
The JSON holds every variant's figures, the published intrinsics' beside them, the worst of each kind,
versions and machine; pictures of each map go under ``--work``.

``--office``: the simulated office split instead (``accuracy.sim``'s four ``office`` seeds, the held-out real
office as issue 20 describes it; no detector to run), its frames mapped centralized, scored against the
objects each walk shows; ``registration`` variants have the simulated detector draw its masks with the
moved intrinsics (colour cx / cy: masks that far off on the depth); per variant the mean and worst.

    .venv/bin/python bench/bench_calibration.py [--stride 1] [--office] [--out bench/results/calibration.json]
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
from arcloud.datasets.sevenscenes import SevenScenesSequence, load_seven_scenes
from arcloud.detectors import make_detector
from arcloud.eval.map_pictures import write_pictures
from arcloud.eval.protocol import CachedDetector, run_map
from arcloud.stores.memory import MemoryStore

#: name -> (kind, focal length scale (both axes), cx shift px, cy shift px).
VARIANTS = {
    "published": ("published", 1.0, 0.0, 0.0),
    "focal x0.98": ("camera", 0.98, 0.0, 0.0),
    "focal x1.02": ("camera", 1.02, 0.0, 0.0),
    "cx -8 px": ("camera", 1.0, -8.0, 0.0),
    "cx +8 px": ("camera", 1.0, 8.0, 0.0),
    "cy -8 px": ("camera", 1.0, 0.0, -8.0),
    "cy +8 px": ("camera", 1.0, 0.0, 8.0),
    "cy -16 px": ("camera", 1.0, 0.0, -16.0),
    "cy +16 px": ("camera", 1.0, 0.0, 16.0),
    "colour cx -4 px": ("registration", 1.0, -4.0, 0.0),
    "colour cx +4 px": ("registration", 1.0, 4.0, 0.0),
    "colour cy -4 px": ("registration", 1.0, 0.0, -4.0),
    "colour cy +4 px": ("registration", 1.0, 0.0, 4.0),
}
FIGURES = ("served_map25", "served_map50", "served_precision25", "served_recall25", "map25", "map50")


def moved(intrinsics: Intrinsics, focal_scale: float, dcx: float, dcy: float) -> Intrinsics:
    return Intrinsics(intrinsics.fx * focal_scale, intrinsics.fy * focal_scale, intrinsics.cx + dcx, intrinsics.cy + dcy)


def with_intrinsics(sequence: SevenScenesSequence, kind: str, *change: float) -> SevenScenesSequence:
    """The sequence with the intrinsics of a variant's kind moved (see the module docstring)."""
    colour = sequence.colour
    assert colour is not None, "7-Scenes frames carry their colour camera"
    if kind == "published":
        return sequence
    moved_colour = dataclasses.replace(colour, intrinsics=moved(colour.intrinsics, *change))
    if kind == "registration":
        return dataclasses.replace(sequence, colour=moved_colour)
    return dataclasses.replace(sequence, intrinsics=moved(sequence.intrinsics, *change), colour=moved_colour)


class _DrawnMoved:
    """A simulated detector whose masks a camera with the intrinsics moved by ``change`` drew: masks off against
    the depth, as colour and depth registered that far off."""

    def __init__(self, inner: Any, change: list[float]) -> None:
        self.inner, self.change = inner, change

    def detect(self, frame: Any) -> Any:
        return self.inner.detect(dataclasses.replace(frame, intrinsics=moved(frame.intrinsics, *self.change)))


def office_rows() -> dict[str, dict[str, Any]]:
    """Every variant on the simulated office split (``--office``): ``camera`` ones map the depth with the intrinsics
    moved, ``registration`` ones have the simulated detector draw its masks with them."""
    from arcloud.accuracy.common import score_run
    from arcloud.accuracy.sim import FULL_CASES, observable_objects, without_unseen
    from arcloud.sim.detector import DetectorFaults, FrameTruths, SimulatedDetector
    from arcloud.sim.room import room_walk
    from arcloud.sim.sequence import simulate_sequence

    faults, params = DetectorFaults(), Params()
    per_variant: dict[str, list[dict[str, Any]]] = {}
    for case in (c for c in FULL_CASES if c.split == "office"):
        room = case.room()
        truths = FrameTruths(room)
        poses = room_walk(room, case.frames, case.walk_seed, style=case.style())
        frames = simulate_sequence(
            room, n_frames=case.frames, seed=case.walk_seed, faults=faults, map_id=case.name, poses=poses, truths=truths
        )
        simulated = SimulatedDetector(room, faults, seed=case.walk_seed, truths=truths)
        observable = observable_objects(room, frames, simulated)
        detector = CachedDetector(simulated)
        unseen = [o for o in room.objects if o not in observable]
        for name, (kind, *change) in VARIANTS.items():
            if kind == "registration":  # the masks drawn by a camera so far off, the depth mapped as rendered
                mapped, detecting = frames, CachedDetector(_DrawnMoved(simulated, change))
            else:  # the depth mapped so far off, the masks where they were drawn (cached from the first variant)
                mapped, detecting = [dataclasses.replace(f, intrinsics=moved(f.intrinsics, *change)) for f in frames], detector
            objects = run_map(
                mapped, detecting, params, new_store=MemoryStore, users=1, seed=case.walk_seed * 1000, workers=1, map_id=case.name
            )
            scores = score_run(without_unseen(objects, unseen), [o.box for o in observable], scene=case.name)
            per_variant.setdefault(name, []).append({"case": case.name, **{key: scores[key] for key in FIGURES}})
            print(case.name, name, {key: None if scores[key] is None else round(scores[key], 3) for key in FIGURES}, flush=True)
    rows: dict[str, dict[str, Any]] = {}
    for name, cases in per_variant.items():
        figures = {key: [c[key] or 0.0 for c in cases] for key in FIGURES}
        rows[name] = {
            "kind": VARIANTS[name][0],
            "mean": {key: round(sum(v) / len(v), 4) for key, v in figures.items()},
            "worst": {key: min(v) for key, v in figures.items()},
            "cases": cases,
        }
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stride", type=int, default=1, help="map every stride-th frame (1: all 1000)")
    parser.add_argument("--model", choices=tuple(MODELS_REL), default=next(iter(MODELS_REL)))
    parser.add_argument("--out", type=Path, default=Path("bench/results/calibration.json"))
    parser.add_argument("--work", type=Path, default=Path("out/calibration"), help="pictures of every map")
    parser.add_argument("--office", action="store_true", help="the simulated office split instead of 7-Scenes")
    args = parser.parse_args()
    if args.office:
        started = time.perf_counter()
        rows = office_rows()
        write_json(
            args.out,
            {"benchmark": "calibration", "suite": "sim office", "variants": rows, "wall_s": round(time.perf_counter() - started, 1),
             **environment(("arcloud", "numpy", "scipy"))},
        )  # fmt: skip
        return
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
    for name, (kind, *change) in VARIANTS.items():
        started = time.perf_counter()
        variant = with_intrinsics(sequence, kind, *change)
        frames = LazyFrames(names, variant.load_frame, cache=False)
        objects = run_map(frames, detector, params, new_store=MemoryStore, users=1, seed=0, workers=1, map_id="calibration")
        scores = score_against(objects, ground_truth, scene=sequence.name)["observed"]
        pictures = write_pictures(
            args.work / name.replace(" ", "_"), frames, objects, {}, title=f"{sequence.name}: intrinsics {name}",
            gt=ground_truth.boxes("observed"), world2boxes=export_frame.world2export,
        )  # fmt: skip
        rows[name] = {
            "kind": kind,
            "depth_intrinsics": list(dataclasses.astuple(variant.intrinsics)),
            "colour_intrinsics": list(dataclasses.astuple(variant.colour.intrinsics)) if variant.colour else None,
            **{key: scores[key] for key in FIGURES},
            "n_served": scores["n_served"],
            "pictures": pictures,
            "wall_s": round(time.perf_counter() - started, 1),
        }
        print(name, {key: None if scores[key] is None else round(scores[key], 3) for key in FIGURES}, flush=True)
    worst = {
        kind: {key: min(row[key] or 0.0 for row in rows.values() if row["kind"] == kind) for key in FIGURES}
        for kind in ("camera", "registration")
    }
    write_json(
        args.out,
        {
            "benchmark": "calibration",
            "sequence": sequence.name,
            "model": MODELS_REL[args.model],
            "frames": len(names),
            "stride": args.stride,
            "variants": rows,
            "worst": worst,
            **environment(("arcloud", "numpy", "scipy", "onnxruntime")),
        },
    )


if __name__ == "__main__":
    main()
