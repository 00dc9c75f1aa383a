"""The tools side points one way: virtual_camera <- sim, datasets <- eval <- accuracy <- demo, no cycles.

Every ``import`` of a module counts, also those inside functions (a lazy import is still an arrow)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import arcloud

PACKAGE = Path(arcloud.__file__).parent

#: What each tools-side package may import from arcloud (besides itself).
ALLOWED = {
    "virtual_camera": {"core", "errors"},
    "sim": {"core", "errors", "virtual_camera"},
    "datasets": {"core", "errors", "virtual_camera", "detectors", "argtypes"},
    "eval": {"core", "errors", "ports"},
    "accuracy": {"core", "errors", "ports", "stores", "detectors", "argtypes", "virtual_camera", "sim", "datasets", "eval"},
    "demo": {"core", "stores", "sim", "eval", "accuracy"},
}
#: Known exceptions, each with the reason it is still there.
EXCEPTIONS: set[tuple[str, str]] = set()


def arcloud_imports(path: Path) -> set[str]:
    """The arcloud packages (first name after ``arcloud.``) a module imports, anywhere in it."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = (
            [node.module or ""]
            if isinstance(node, ast.ImportFrom)
            else [a.name for a in node.names]
            if isinstance(node, ast.Import)
            else []
        )
        found |= {name.split(".")[1] for name in names if name.startswith("arcloud.")}
    return found


def modules_of(package: str) -> list[Path]:
    return [PACKAGE / "demo.py"] if package == "demo" else sorted((PACKAGE / package).rglob("*.py"))


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_package_imports_only_what_its_layer_allows(package: str) -> None:
    wrong = []
    for path in modules_of(package):
        relative = path.relative_to(PACKAGE).as_posix()
        for imported in arcloud_imports(path) - {package} - ALLOWED[package]:
            if (relative, imported) not in EXCEPTIONS:
                wrong.append(f"{relative} imports arcloud.{imported}")
    assert not wrong, wrong


def test_the_check_sees_lazy_imports(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from arcloud.eval.metrics import evaluate\n    import arcloud.sim.room\n")
    assert arcloud_imports(module) == {"eval", "sim"}
