"""The measured figures of README.md and docs/measurements.md, written from the results files kept in the
repository (each benchmark's JSON, with its date, versions and machine), so that no figure there is typed by hand.

Each ``Figure`` is one claim: what was measured, and the figures as shown, both read from one results file. The
tables go between ``BEGIN`` and ``END`` in both files; ``tests/test_docs_tied.py`` checks that they are what this
writes from the files, and that each figure of the README's table is in its file. To quote a new run, keep its JSON
under a dated folder of ``bench/results/`` (the folder itself is git-ignored, its subfolders are not) and point a
figure at it.

    .venv/bin/python bench/measurements.py          # rewrite the tables
    .venv/bin/python bench/measurements.py --check  # exit 1 when a table is not what the files give
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BEGIN = "<!-- measured: written by bench/measurements.py from the results files; do not edit by hand -->"
END = "<!-- /measured -->"

Results = Mapping[str, Any]  # one results file's JSON


@dataclass(frozen=True)
class Figure:
    what: Callable[[Results], str]  # markdown: what was measured, and how
    measured: Callable[[Results], str]  # markdown: the figures
    source: str  # the results file, from the repository root
    readme: bool  # a headline of README.md's table too


def leaves(data: Any) -> Iterator[tuple[str, Any]]:
    """(path, value) of every scalar of a JSON document, paths like ``.suites.sim.users``."""
    if isinstance(data, dict):
        for key, value in data.items():
            for path, leaf in leaves(value):
                yield f".{key}{path}", leaf
    elif isinstance(data, list):
        for i, value in enumerate(data):
            for path, leaf in leaves(value):
                yield f"[{i}]{path}", leaf
    else:
        yield "", data


def report(data: Results, suite: str, split: str = "report") -> Mapping[str, Any]:
    """A split's summary of an accuracy suite (``bench/bench_accuracy.py``), by default the report split's."""
    summary: Mapping[str, Any] = data["suites"][suite]["summary"][split]
    return summary


def accuracy_figures(data: Results, suite: str, split: str = "report") -> str:
    """mAP and served precision / recall at IoU 0.25 of one user, and mAP@0.25 of K users (the split's mean)."""
    one, many = report(data, suite, split)["centralized"], report(data, suite, split)["distributed"]
    worst = f" (worst {one['map25']['worst']:.3f})" if report(data, suite, split)["cases"] > 1 else ""
    return (
        f"one user: mAP@0.25 {one['map25']['mean']:.3f}{worst}, @0.5 {one['map50']['mean']:.3f}; served mAP@0.25 "
        f"{one['served_map25']['mean']:.3f}, precision {one['served_precision25']['mean']:.3f}, recall "
        f"{one['served_recall25']['mean']:.3f}; K = {data['suites'][suite]['users']} users: served mAP@0.25 "
        f"{many['served_map25']['mean']:.3f}"
    )


def redkitchen(data: Results) -> str:
    suite = data["suites"]["7scenes"]
    frames = [case["frames"] for case in suite["cases"] if case["split"] == "report"]
    return f"7-Scenes redkitchen, {sum(frames):,} real frames, {suite['model'].removesuffix('.onnx')}, {suite['primary_boxes']} boxes"


def hololens_office(data: Results) -> str:
    suite = data["suites"]["hololens"]
    frames = [case["frames"] for case in suite["cases"] if case["split"] == "report"]
    return (
        f"a second real room, tuned on by nobody: HoloLens 2 office, {sum(frames):,} frames, "
        f"{suite['model'].removesuffix('.onnx')}, {suite['primary_boxes']} boxes"
    )


def simulated_rooms(data: Results) -> str:
    return f"{report(data, 'sim')['cases']} simulated rooms, simulated detector faults"


def simulated_office(data: Results) -> str:
    return f"the simulated office (desks pushed together, monitors side by side and back to back), {report(data, 'sim', 'office')['cases']} walks, no parameter tuned on it"


def scannet_walks(data: Results) -> str:
    suite = data["suites"]["scannet"]
    return f"the real ScanNet mesh {suite['scene']}, {report(data, 'scannet')['cases']} walks, {suite['annotation']} masks with faults"


def service_row(data: Results) -> Mapping[str, Any]:
    """The service's one row of a ``bench/bench_scaling.py`` run at one worker count."""
    (row,) = data["service"]["rows"]
    assert isinstance(row, Mapping)
    return row


def on_many_cores(data: Results) -> str:
    prefetch = "on" if data["setup"]["worker_prefetch"] else "off"
    return (
        f"the service on Redis on {data['machine']['cores']} cores, {service_row(data)['workers']} workers, "
        f"{data['setup']['model'].removesuffix('.onnx')} on the CPU, prefetch {prefetch}"
    )


def throughput_on_many_cores(data: Results) -> str:
    row = service_row(data)
    runs = [value for path, value in leaves(row) if path.endswith(".redis_bytes_in")]
    return (
        f"{row['many_maps']['as_fast']['fps']:.1f} frames/s over {row['many_maps']['maps']} maps "
        f"({row['many_maps']['service_over_ceiling']:.2f}x of {row['workers']} bare sessions), "
        f"{row['one_map']['as_fast']['fps']:.1f} on one map ({row['one_map']['service_over_ceiling']:.2f}x); "
        f"{min(runs) / 1000:.0f}-{max(runs) / 1000:.0f} kB a frame into Redis"
    )


def latency_on_many_cores(data: Results) -> str:
    row = service_row(data)
    return (
        f"POST-to-commit p50 / p99 at 70 % of its rate: {row['many_maps']['at_70']['latency_p50_s']:.2f} / "
        f"{row['many_maps']['at_70']['latency_p99_s']:.2f} s over {row['many_maps']['maps']} maps, "
        f"{row['one_map']['at_70']['latency_p50_s']:.2f} / {row['one_map']['at_70']['latency_p99_s']:.2f} s on one map"
    )


ACCURACY = "bench/results/accuracy-2026-11-28b/accuracy.json"  # one `make accuracy` run: every suite, the office split, the untuned and low-eye ScanNet walks too
SCANNET = ACCURACY  # its ScanNet suite runs every case at K = 10
HOLOLENS = "bench/results/accuracy-2026-11-28c/accuracy.json"  # the hololens suites alone, the day the sequence came
SIXTEEN_CORES = "bench/results/device-2026-11-26b/call1-w15.json"
FIGURES: tuple[Figure, ...] = (
    Figure(redkitchen, lambda data: accuracy_figures(data, "7scenes"), ACCURACY, readme=True),
    Figure(hololens_office, lambda data: accuracy_figures(data, "hololens"), HOLOLENS, readme=True),
    Figure(simulated_rooms, lambda data: accuracy_figures(data, "sim"), ACCURACY, readme=True),
    Figure(scannet_walks, lambda data: accuracy_figures(data, "scannet"), SCANNET, readme=True),
    Figure(simulated_office, lambda data: accuracy_figures(data, "sim", "office"), ACCURACY, readme=False),
    Figure(on_many_cores, throughput_on_many_cores, SIXTEEN_CORES, readme=True),
    Figure(on_many_cores, latency_on_many_cores, SIXTEEN_CORES, readme=False),
)


def load_json(path: Path) -> Results:
    data: Results = json.loads(path.read_text())
    return data


def load(figures: tuple[Figure, ...] = FIGURES) -> dict[str, Results]:
    """Each figure's results file, read once: source -> its JSON."""
    return {f.source: load_json(ROOT / f.source) for f in figures}


def conditions(data: Results) -> str:
    """The machine and the day, and the commit where the file records it."""
    machine = f"{data['machine']['cpu']}, {data['machine']['cores']} cores"
    source = data.get("source", {})
    commit = source.get("commit")
    changed = " with changes to src/ not yet committed" if source.get("src_changed") else ""
    return f"{machine}, {data['date'][:10]}" + (f", at {commit[:7]}{changed}" if commit else "")


def table(figures: tuple[Figure, ...], results: Mapping[str, Results], link_prefix: str) -> str:
    """The markdown table of ``figures``, each row with its machine, day and results file (linked)."""
    rows = ["| what | measured | on | results file |", "|---|---|---|---|"]
    for f in figures:
        data = results[f.source]
        name = f.source.removeprefix("bench/results/")
        rows.append(f"| {f.what(data)} | {f.measured(data)} | {conditions(data)} | [{name}]({link_prefix}{f.source}) |")
    return "\n".join(rows)


def readme_table(results: Mapping[str, Results]) -> str:
    return table(tuple(f for f in FIGURES if f.readme), results, "")


def measurements_table(results: Mapping[str, Results]) -> str:
    return table(FIGURES, results, "../")


def between_markers(text: str, block: str, name: str) -> str:
    """``text`` with what stands between ``BEGIN`` and ``END`` replaced by ``block``."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise SystemExit(f"{name}: expected the lines {BEGIN!r} and then {END!r}")
    return f"{text[: start + len(BEGIN)]}\n{block}\n{text[end:]}"


def written(results: Mapping[str, Results]) -> dict[Path, str]:
    """README.md and docs/measurements.md as they should read: path -> text."""
    blocks = {ROOT / "README.md": readme_table(results), ROOT / "docs" / "measurements.md": measurements_table(results)}
    return {path: between_markers(path.read_text(), block, path.name) for path, block in blocks.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 when a table is out of date")
    args = parser.parse_args()
    stale = []
    for path, text in written(load()).items():
        if path.read_text() != text:
            stale.append(path)
            if not args.check:
                path.write_text(text)
    for path in stale:
        print(f"{path.relative_to(ROOT)}: {'out of date' if args.check else 'rewritten'}")
    return 1 if stale and args.check else 0


if __name__ == "__main__":
    sys.exit(main())
