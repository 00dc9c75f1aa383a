"""The tables written by hand beside the code they describe hold what the code holds: every setting in the
settings table of docs/service.md, every port in its ports table (with adapters that exist), every exception
of the project in the tree of ``arcloud.core.errors``, every Redis key in the key table of
``arcloud.stores.keys``; and the measured figures of README.md and docs/measurements.md are what
``bench/measurements.py`` writes from the results files kept in the repository, each README figure found in its file.
Each reads sources or small modules only, so that the file runs in well under 2 s."""

from __future__ import annotations

import ast
import copy
import importlib.util
import inspect
import re
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

import arcloud.core.errors
import arcloud.core.ports
import arcloud.ports
import arcloud.stores.keys as keys
from arcloud.service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "arcloud"
SERVICE_MD = (ROOT / "docs" / "service.md").read_text()


def table_after(heading: str) -> list[list[str]]:
    """The cells of the first table after ``heading`` in docs/service.md, header and rule left out."""
    text = SERVICE_MD[SERVICE_MD.index(heading) :]
    rows = []
    for line in text.splitlines()[1:]:
        if line.startswith("|"):
            rows.append([cell.strip() for cell in line.strip("|").split(" | ")])
        elif rows:
            break
    return rows[2:]


def first_names(rows: list[list[str]], pattern: str) -> list[str]:
    """The names in backticks in each row's first cell that match ``pattern``."""
    return [name for row in rows for name in re.findall(rf"`({pattern})`", row[0])]


def differences(in_code: list[str], documented: list[str]) -> dict[str, list[str]]:
    """What the table misses and what it lists that the code has not (or lists twice); both empty when tied."""
    twice = sorted({name for name in documented if documented.count(name) > 1})
    return {
        "missing": sorted(set(in_code) - set(documented)),
        "not in the code, or twice": sorted(set(documented) - set(in_code)) + twice,
    }


TIED: dict[str, list[str]] = {"missing": [], "not in the code, or twice": []}


def test_the_settings_table_lists_every_setting_and_no_other() -> None:
    documented = first_names(table_after("## Settings (`ARCLOUD_*`"), "[A-Z0-9_]+")
    assert differences([name.upper() for name in Settings.model_fields], documented) == TIED


def test_the_ports_table_lists_every_port_once_with_adapters_that_exist() -> None:
    ports = {
        name
        for module in (arcloud.ports, arcloud.core.ports)
        for name, cls in inspect.getmembers(module, inspect.isclass)
        if cls.__module__ == module.__name__ and getattr(cls, "_is_protocol", False)
    }
    rows = table_after("## Ports and adapters")
    named = [re.findall(r"`(\w+)`", row[0])[:1] for row in rows]  # each row's port: the first name in its first cell
    assert differences(sorted(ports), [name for names in named for name in names]) == TIED and all(named)
    adapters = {a for row in rows for cell in row[1:] for a in re.findall(r"`((?:stores|events)\.\w+)\.(\w+)`", cell)}
    assert adapters, "no adapter named in the ports table"
    for module, name in adapters:
        source = (SRC / (module.replace(".", "/") + ".py")).read_text()
        assert f"\nclass {name}" in source, f"docs/service.md names {module}.{name}, which src/arcloud does not define"


def test_the_exception_tree_draws_every_exception_of_the_project() -> None:
    """Every class of ``src/arcloud`` that derives from ``ArcloudError`` (read from the sources, so that no
    adapter has to be imported), and nothing else, is in the tree."""
    bases: dict[str, set[str]] = {}
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                named = {
                    b.id if isinstance(b, ast.Name) else b.attr for b in node.bases if isinstance(b, ast.Name | ast.Attribute)
                }
                bases.setdefault(node.name, set()).update(named)
    errors = {"ArcloudError"}
    while grown := {name for name, parents in bases.items() if parents & errors} - errors:
        errors |= grown
    tree = (arcloud.core.errors.__doc__ or "").split("\n\n")[1]
    drawn = re.findall(r"^\s+(?:[│ ]*[├└]── )?([A-Z]\w+)", tree, re.MULTILINE)
    assert differences(sorted(errors), drawn) == TIED


# The keys' templates: arguments standing for the placeholders of the table, then the placeholders put back
ARGUMENTS = {
    "map_id": "m",
    "tag": "t",
    "object_id": 7,
    "cell": (1, 2, 3),
    "bucket": "<bucket>",
    "digest": "<digest>",
    "key_id": "<key-id>",
    "lease_key": "<lock or claim key>",
    "entry_id": "<entry>",
}
PLACEHOLDERS = [(":7", ":<id>"), (":1:2:3", ":<i>:<j>:<k>"), (":map:m:", ":map:<m>:")]


def test_the_key_table_lists_every_redis_key() -> None:
    doc = keys.__doc__ or ""
    documented = set(re.findall(r"^    (<[^>]+>\S*|\S+)\s+(?:STRING|HASH|SET|ZSET|LIST|STREAM)\s", doc, re.MULTILINE))
    made = []
    for name, function in inspect.getmembers(keys, inspect.isfunction):
        if function.__module__ == keys.__name__ and (name.endswith("_key") or name.startswith("ingest_")):
            key = function(*(ARGUMENTS[p] for p in inspect.signature(function).parameters))
            for value, placeholder in PLACEHOLDERS:
                key = key.replace(value, placeholder)
            made.append(key)
    service_wide = {name: value for name, value in vars(keys).items() if isinstance(value, str) and value.startswith("arcloud:")}
    assert len(made) >= 20 and len(service_wide) >= 4
    made.extend(service_wide.values())
    assert differences(made, [key for key in documented if key in made]) == TIED  # the table may name keys of before


def load_measurements() -> ModuleType:
    """``bench/measurements.py`` (bench is no package)."""
    spec = importlib.util.spec_from_file_location("measurements", ROOT / "bench" / "measurements.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


measurements = load_measurements()
README = (ROOT / "README.md").read_text()
MEASURED = README[README.index("## Measured\n") :]
MEASURED = MEASURED[: MEASURED.index("\n## ", 1)]
# A figure: a number not part of a name (mAP@0.25, v1, p99); thousands with commas
FIGURE = re.compile(r"(?<![@\w.,])\d[\d,]*(?:\.\d+)?")


def generated(text: str) -> str:
    return text[text.index(measurements.BEGIN) + len(measurements.BEGIN) : text.index(measurements.END)].strip("\n")


def test_the_measured_tables_are_what_the_results_files_give() -> None:
    results = measurements.load()
    assert generated(README) == measurements.readme_table(results), "run `make measurements`"
    docs = (ROOT / "docs" / "measurements.md").read_text()
    assert generated(docs) == measurements.measurements_table(results), "run `make measurements`"


def test_a_changed_results_file_changes_the_readme_table() -> None:
    results = measurements.load()
    changed = copy.deepcopy(results)
    summary = changed[measurements.ACCURACY]["suites"]["sim"]["summary"]["report"]["centralized"]
    summary["map25"]["mean"] = 0.5
    assert measurements.readme_table(changed) != measurements.readme_table(results)
    assert "mAP@0.25 0.500" in measurements.readme_table(changed)


def test_every_figure_of_the_readme_is_in_its_results_file() -> None:
    """Each number of the README table's measured cells is a value of the file its row links to, as shown (at the
    decimals shown), or bytes of it shown in kB."""
    rows = [[cell.strip() for cell in line.strip("|").split(" | ")] for line in generated(README).splitlines()[2:]]
    assert len(rows) >= 4
    for what, measured, _, source in rows:
        (path,) = re.findall(r"\]\((bench/results/[^)]+\.json)\)", source)
        values = [
            v
            for _, v in measurements.leaves(measurements.load_json(ROOT / path))
            if isinstance(v, int | float) and not isinstance(v, bool)
        ]
        figures = FIGURE.findall(measured)
        assert figures, what
        for figure in figures:
            decimals = len(figure.partition(".")[2])
            shown = {f"{v:,.{decimals}f}" for v in values} | {f"{v / 1000:,.{decimals}f}" for v in values}
            assert figure in shown, f"README, {what}: {figure} is not in {path}"


def test_the_readme_measured_section_has_no_figure_outside_the_written_table() -> None:
    around = MEASURED.replace(generated(README), "")
    assert FIGURE.findall(around) == []


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_the_results_files_behind_the_figures_are_not_git_ignored() -> None:
    for figure in measurements.FIGURES:
        assert (ROOT / figure.source).is_file(), figure.source
        ignored = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", figure.source], check=False)
        assert ignored.returncode == 1, f"{figure.source} is git-ignored: the README would quote a file it does not ship"


def test_every_file_the_docs_name_is_in_the_repository() -> None:
    """A path in backticks under a folder of the repository or of the package (``core/step.py``) names a file or
    folder that exists (what a bench writes, under bench/results/, is made by running it)."""
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    folders = sorted({path.split("/")[0] for path in tracked if "/" in path} | {p.name for p in SRC.iterdir() if p.is_dir()})
    named = re.compile(rf"`((?:{'|'.join(map(re.escape, folders))})/[A-Za-z0-9_./-]+)`")
    missing = [
        (doc.name, path)
        for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
        for path in (found.rstrip(".") for found in named.findall(doc.read_text()))
        if not path.startswith("bench/results/") and not (ROOT / path).exists() and not (SRC / path).exists()
    ]
    assert missing == []
