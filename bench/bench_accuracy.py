"""Run the accuracy suites and write their records to one JSON file with versions and machine.

Suites (``arcloud.accuracy``): ``sim`` (generated rooms walked in varied styles), ``scannet`` (a real
scan rendered along randomised walks), ``7scenes`` (a real sequence through the real model, the one the
parameters are tuned on) and ``hololens`` (another real room through the same suite, tuned on by nobody:
``bench/data/hololens-office``, its README says where it comes from). A suite
whose module is not there, or whose data is missing from ../shared, is skipped with its reason; a suite
that crashes is recorded under ``failed`` with its traceback, the others still run, and the exit status
is 1. The file is rewritten after each suite. Prints, per
suite, split and approach, the mean and the worst case (lowest) of mAP@0.25, mAP@0.5 and the served
set's precision and recall at IoU 0.25, then the simulated suite's targets on its report split.

    .venv/bin/python bench/bench_accuracy.py [--quick] [--suites sim,scannet,7scenes] [--out FILE] [--work DIR]
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import time
import traceback
from collections.abc import Mapping
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from common import environment, write_json

from arcloud.errors import DatasetError

SUITE_MODULES = {
    "sim": "arcloud.accuracy.sim",
    "scannet": "arcloud.accuracy.scannet",
    "7scenes": "arcloud.accuracy.sevenscenes",  # YOLO11n-seg, the default model
    "7scenes-yolov8n": "arcloud.accuracy.sevenscenes",  # the same suite with YOLOv8n-seg, measured beside it
    "hololens": "arcloud.accuracy.sevenscenes",
    "hololens-yolov8n": "arcloud.accuracy.sevenscenes",
}
#: The second real sequence, kept in the repository (its licence allows it).
HOLOLENS_DIR = Path(__file__).parent / "data" / "hololens-office"
#: Options a suite's run_suite takes besides the common ones.
SUITE_OPTIONS: dict[str, dict[str, Any]] = {
    "7scenes-yolov8n": {"model": "yolov8n"},
    "hololens": {"root": HOLOLENS_DIR},
    "hololens-yolov8n": {"root": HOLOLENS_DIR, "model": "yolov8n"},
}
#: Figures of the table: (summary key, column title). "served": what a plain GET .../objects returns.
COLUMNS = (
    ("map25", "mAP@.25"),
    ("map50", "mAP@.5"),
    ("served_map25", "served mAP@.25"),
    ("served_map50", "served mAP@.5"),
    ("served_precision25", "served P"),
    ("served_recall25", "served R"),
)
#: The simulated suite's targets on its report split (the issue's), for each approach:
#: the mean over rooms of served precision and recall at IoU 0.25, the worst room's mAP@0.25...
SIM_TARGETS = {"served_precision25": ("mean", 0.9), "served_recall25": ("mean", 0.9), "map25": ("worst", 0.8)}
#: ...and the mean drop of a room's distributed mAP@0.25 below its centralized one.
SIM_MAX_GAP_MAP25 = 0.03


def run_suite(name: str, *, quick: bool, work_dir: Path, shared: Path | None) -> tuple[dict[str, Any] | None, str | None]:
    """The suite's record, or None and why it was skipped."""
    module_name = SUITE_MODULES[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name != module_name:
            raise
        return None, f"module {module_name} is not there"
    options: dict[str, Any] = {"quick": quick, "out_dir": work_dir / name, **SUITE_OPTIONS.get(name, {})}
    if shared is not None and name != "sim":
        options["shared"] = shared
    try:
        return module.run_suite(**options), None
    except DatasetError as exc:
        return None, f"data missing: {exc}"


def format_table(records: Mapping[str, Mapping[str, Any]]) -> str:
    """One row per suite, split and approach: ``mean (worst)`` of each of ``COLUMNS``."""
    header = (
        f"{'suite':8} {'split':7} {'cases':>5} {'approach':12}"
        + "".join(f" {title:>15}" for _, title in COLUMNS)
        + f" {'gap mAP@.25':>15}"
    )
    lines = [header, "-" * len(header)]
    for suite, record in records.items():
        for split, entry in record["summary"].items():
            for approach in ("centralized", "distributed"):
                figures = entry.get(approach)
                if figures is None:
                    continue
                cells = "".join(f" {_mean_worst(figures[key]):>15}" for key, _ in COLUMNS)
                gap = entry.get("gap_map25") if approach == "distributed" else None
                gap_cell = f"{gap['mean']:.3f} ({gap['worst']:.3f})" if gap else ""
                lines.append(f"{suite:8} {split:7} {entry['cases']:>5} {approach:12}{cells} {gap_cell:>15}")
    return "\n".join(lines) + "\n(each cell: mean over cases (worst case); gap: distributed below centralized, mean (largest))"


def sim_targets(record: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The simulated suite's targets on its report split: each figure measured, its bound, whether met."""
    report = record["summary"].get("report")
    if report is None:
        return []
    rows = []
    for approach in ("centralized", "distributed"):
        for key, (statistic, bound) in SIM_TARGETS.items():
            value = report.get(approach, {}).get(key, {}).get(statistic)
            rows.append(
                {
                    "figure": f"{approach} {key} ({statistic})",
                    "value": value,
                    "bound": f">= {bound}",
                    "met": value is not None and value >= bound,
                }
            )
    gap = report.get("gap_map25", {}).get("mean")
    rows.append({"figure": "map25 gap, centralized - distributed (mean)", "value": gap, "bound": f"<= {SIM_MAX_GAP_MAP25}",
                 "met": gap is not None and gap <= SIM_MAX_GAP_MAP25})  # fmt: skip
    return rows


#: The 7-Scenes suite's targets on its report case (issue "Right on rooms it has never seen"), served set, YOLO11n-seg...
SEVENSCENES_TARGETS = {"served_map25": 0.75, "served_map50": 0.6, "served_precision25": 0.85, "served_recall25": 0.6}
#: ...the second real sequence's, with the parameters tuned on 7-Scenes only...
HOLOLENS_TARGETS = {"served_map25": 0.6}
#: ...and for both the largest drop of the K = 10 mean's served mAP@0.25 below the centralized one.
SEVENSCENES_MAX_GAP = 0.05
#: Each real sequence's suite (YOLO11n-seg) and the key of its targets in the results file.
REAL_TARGETS = {"7scenes": ("sevenscenes_targets", SEVENSCENES_TARGETS), "hololens": ("hololens_targets", HOLOLENS_TARGETS)}


def sevenscenes_targets(record: Mapping[str, Any], targets: Mapping[str, float] = SEVENSCENES_TARGETS) -> list[dict[str, Any]]:
    """A real sequence's targets on its report split (centralized figures; the K = 10 gap): each measured, its bound, met."""
    report = record["summary"].get("report")
    if report is None:
        return []
    rows = []
    for key, bound in targets.items():
        value = report.get("centralized", {}).get(key, {}).get("mean")
        rows.append(
            {"figure": f"centralized {key}", "value": value, "bound": f">= {bound}", "met": value is not None and value >= bound}
        )
    central = report.get("centralized", {}).get("served_map25", {}).get("mean")
    distributed = report.get("distributed", {}).get("served_map25", {}).get("mean")
    gap = None if central is None or distributed is None else abs(central - distributed)
    rows.append({"figure": "served_map25 |centralized - K = 10|", "value": gap, "bound": f"<= {SEVENSCENES_MAX_GAP}",
                 "met": gap is not None and gap <= SEVENSCENES_MAX_GAP})  # fmt: skip
    return rows


def _mean_worst(entry: Mapping[str, Any]) -> str:
    if entry["mean"] is None:
        return "-"
    return f"{entry['mean']:.3f} ({entry['worst']:.3f})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the suites' quick versions (a few minutes in all)")
    parser.add_argument("--suites", default=",".join(SUITE_MODULES), help=f"comma-separated, from {','.join(SUITE_MODULES)}")
    parser.add_argument(
        "--out", type=Path, default=None, help="JSON file (default bench/results/accuracy.json, accuracy_quick.json with --quick)"
    )
    parser.add_argument("--work", type=Path, default=Path("out/accuracy"), help="folder for renders, exports and pictures")
    parser.add_argument(
        "--shared", type=Path, default=None, help="folder with the real data (default: the suites' own, ../shared)"
    )
    args = parser.parse_args()
    suites = [s.strip() for s in args.suites.split(",") if s.strip()]
    unknown = [s for s in suites if s not in SUITE_MODULES]
    if unknown or not suites:
        parser.error(f"--suites: expected names from {','.join(SUITE_MODULES)}, got {args.suites!r}")
    out = args.out or Path("bench/results") / ("accuracy_quick.json" if args.quick else "accuracy.json")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    from arcloud.allocator import keep_freed_memory

    keep_freed_memory()  # as the CLI's commands do
    started = time.perf_counter()
    records: dict[str, dict[str, Any]] = {}
    skipped: dict[str, str] = {}
    failed: dict[str, str] = {}
    payload: dict[str, Any] = {"benchmark": "accuracy suites", "quick": args.quick, "suites": records,
                               "skipped": skipped, "failed": failed,
                               **environment(("arcloud", "numpy", "scipy", "open3d", "onnxruntime"))}  # fmt: skip
    for name in suites:
        print(f"suite {name}: running{' (quick)' if args.quick else ''}", flush=True)
        try:
            record, reason = run_suite(name, quick=args.quick, work_dir=args.work, shared=args.shared)
        except Exception:  # noqa: BLE001 - one suite's crash must not cost the others' figures
            failed[name] = traceback.format_exc()
            print(f"suite {name}: FAILED\n{failed[name]}", file=sys.stderr, flush=True)
        else:
            if record is None:
                skipped[name] = str(reason)
                print(f"suite {name}: skipped: {reason}", flush=True)
            else:
                records[name] = record
                print(f"suite {name}: done in {record.get('wall_s', 0.0):.0f} s", flush=True)
        if "sim" in records:
            payload["sim_targets"] = sim_targets(records["sim"])
        for suite, (key, targets) in REAL_TARGETS.items():
            if suite in records:
                payload[key] = sevenscenes_targets(records[suite], targets)
        payload["wall_s"] = round(time.perf_counter() - started, 1)
        write_json(out, payload)
    print(format_table(records))
    for suite, key in (("sim", "sim_targets"), *((suite, key) for suite, (key, _) in REAL_TARGETS.items())):
        for row in payload.get(key, []):
            value = "-" if row["value"] is None else f"{row['value']:.3f}"
            print(
                f"target {suite}/report {row['figure']}: {value} {row['bound']}: {'met' if row['met'] else 'NOT MET'}{' (quick run: indicative)' if args.quick else ''}"
            )
    print(
        f"accuracy suites: {len(records)} run, {len(skipped)} skipped, {len(failed)} failed ({', '.join(failed) or 'none'}), {payload['wall_s']:.0f} s"
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
