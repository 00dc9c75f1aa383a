"""Charts of an evaluation without matplotlib: the command skips them in one line and writes no file."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from arcloud.accuracy.cli import _write_charts

ROWS = [{"users": 1, "map25_mean": 1.0, "map25_var": 0.0, "map50_mean": 0.5, "map50_var": 0.0}]


def test_without_matplotlib_the_charts_are_skipped_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ModuleNotFoundError
    assert _write_charts(tmp_path / "r.json", title="t", rows=ROWS) == []
    assert capsys.readouterr().out == "charts skipped: matplotlib is not installed (pip install matplotlib)\n"
    assert list(tmp_path.iterdir()) == []
