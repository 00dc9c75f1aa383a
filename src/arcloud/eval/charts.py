"""Charts of an evaluation's figures, written as PNGs beside its results JSON (``arcloud eval ...``): each class's AP
at IoU 0.25 and 0.5 (bars), the precision-recall curve of each class at both thresholds, and mAP against the number
of users K (Table 1's rows, the spread of the runs as error bars).

matplotlib is optional (the ``dev`` extra, not ``datasets``): ``write_charts`` raises ``ModuleNotFoundError`` without
it, and the commands say in one line that they skipped the charts. Figures are ``matplotlib.figure.Figure`` objects
(no pyplot: no global state, no display needed).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from matplotlib.figure import Figure

THRESHOLDS = ("0.25", "0.5")  # the IoU thresholds charted, as the results' keys
DPI = 100

#: Per threshold key, class -> AP (None: no ground truth of the class).
APPerClass = Mapping[str, Mapping[str, float | None]]
#: Per threshold key, class -> {"recall": [...], "precision": [...]} along the ranked predictions.
Curves = Mapping[str, Mapping[str, Mapping[str, Sequence[float]]]]


def ap_bars(ap_per_class: APPerClass, title: str) -> Figure:
    """Each class's AP (classes with ground truth), one bar per threshold."""
    from matplotlib.figure import Figure

    classes = sorted({c for t in THRESHOLDS for c, ap in ap_per_class.get(t, {}).items() if ap is not None})
    figure = Figure(figsize=(max(5.0, 1.2 * len(classes) + 2), 4), dpi=DPI)
    axes = figure.add_subplot()
    width = 0.8 / len(THRESHOLDS)
    for i, threshold in enumerate(THRESHOLDS):
        values = [ap_per_class.get(threshold, {}).get(c) or 0.0 for c in classes]
        axes.bar([x + (i - 0.5) * width for x in range(len(classes))], values, width, label=f"AP@{threshold}")
    axes.set_xticks(range(len(classes)), classes)
    axes.set_ylim(0, 1.05)
    axes.set_ylabel("average precision")
    axes.set_title(title)
    axes.legend()
    figure.tight_layout()
    return figure


def pr_curves(curves: Curves, title: str) -> Figure:
    """One panel per threshold: each class's precision against recall."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(10, 4), dpi=DPI)
    for i, threshold in enumerate(THRESHOLDS):
        axes = figure.add_subplot(1, len(THRESHOLDS), i + 1)
        for name, curve in sorted(curves.get(threshold, {}).items()):
            axes.plot([0.0, *curve["recall"]], [1.0, *curve["precision"]], drawstyle="steps-post", label=name)
        axes.set_xlim(0, 1.02)
        axes.set_ylim(0, 1.05)
        axes.set_xlabel("recall")
        axes.set_ylabel("precision")
        axes.set_title(f"{title}: IoU {threshold}")
        if axes.lines:
            axes.legend(loc="lower left")
    figure.tight_layout()
    return figure


def map_against_users(rows: Sequence[Mapping[str, Any]], title: str) -> Figure:
    """mAP at both thresholds against K users (``users``, ``mapNN_mean``, ``mapNN_var`` of each row; the error bars
    one standard deviation over the runs)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6, 4), dpi=DPI)
    axes = figure.add_subplot()
    rows = sorted(rows, key=lambda r: int(r["users"]))
    users = [int(r["users"]) for r in rows]
    for key, threshold in (("map25", "0.25"), ("map50", "0.5")):
        means = [_number(r[f"{key}_mean"]) for r in rows]
        spread = [math.sqrt(max(0.0, _number(r[f"{key}_var"]))) for r in rows]
        axes.errorbar(users, means, yerr=spread, marker="o", capsize=3, label=f"mAP@{threshold}")
    if users and max(users) / min(users) >= 10:
        axes.set_xscale("log")
    axes.set_xticks(users, [str(k) for k in users])
    axes.set_ylim(0, 1.05)
    axes.set_xlabel("users K")
    axes.set_ylabel("mAP")
    axes.set_title(title)
    axes.legend()
    figure.tight_layout()
    return figure


def write_charts(
    base: Path,
    *,
    title: str,
    rows: Sequence[Mapping[str, Any]],
    ap_per_class: APPerClass | None = None,
    curves: Curves | None = None,
) -> list[Path]:
    """Write ``<base>_ap_per_class.png`` (with ``ap_per_class``), ``<base>_pr_curves.png`` (with ``curves``) and
    ``<base>_map_vs_users.png``; returns their paths. ``ModuleNotFoundError`` without matplotlib."""
    import matplotlib  # noqa: F401 - loaded first, so that a missing matplotlib fails before any file is written

    figures = {}
    if ap_per_class is not None:
        figures["ap_per_class"] = ap_bars(ap_per_class, f"{title}: AP per class")
    if curves is not None:
        figures["pr_curves"] = pr_curves(curves, title)
    figures["map_vs_users"] = map_against_users(rows, f"{title}: mAP against users")
    paths = []
    for name, figure in figures.items():
        path = base.with_name(f"{base.name}_{name}.png")
        path.parent.mkdir(parents=True, exist_ok=True)
        figure.savefig(path)
        paths.append(path)
    return paths


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


__all__ = ["ap_bars", "map_against_users", "pr_curves", "write_charts"]
