"""The layers of the whole package point one way, as docs/method.md draws them:

    core  <-  errors, argtypes, allocator, access  <-  ports, proto  <-  stores, detectors, events  <-  service, client
          <-  virtual_camera  <-  sim, datasets, eval  <-  accuracy, tools  <-  demo  <-  cli

A package may import only packages of lower layers (and itself); every import counts, also those inside
functions. Between modules, imports at the top of a module form no cycle. ``test_service_layers`` and
``test_tools_layers`` hold the finer rules of the service and of the tools side."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import arcloud

PACKAGE = Path(arcloud.__file__).parent

#: Each package's (or top-level module's) layer: imports go to lower layers only.
LAYER = {
    "core": 0,
    "errors": 1, "argtypes": 1, "allocator": 1, "access": 1,
    "formats": 2,
    "ports": 2, "proto": 2,
    "stores": 3, "detectors": 3, "events": 3,
    "service": 4, "client": 4,
    "virtual_camera": 5,
    "sim": 6, "datasets": 6, "eval": 6,
    "accuracy": 7, "tools": 7,
    "demo": 8,
    "cli": 9,
}  # fmt: skip
#: Libraries the core may use: it is pure computation (no I/O, no network, no service framework).
CORE_LIBRARIES = {"numpy", "scipy", "__future__", "collections", "dataclasses", "typing", "math", "functools", "itertools",
                  "threading", "time", "enum", "abc", "logging", "warnings", "operator", "contextlib", "numbers"}  # fmt: skip


def unit_of(path: Path) -> str:
    """The package (first folder under ``arcloud/``) or top-level module a file belongs to."""
    relative = path.relative_to(PACKAGE)
    return relative.parts[0] if len(relative.parts) > 1 else relative.stem


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(tree: ast.AST, *, top_level_only: bool = False) -> Iterator[str]:
    """Absolute module names imported (``from a import b`` gives ``a`` and ``a.b``); with
    ``top_level_only``, only statements run at import time outside functions and ``TYPE_CHECKING``."""
    nodes = _top_level(tree) if top_level_only else ast.walk(tree)
    for node in nodes:
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module
            yield from (f"{node.module}.{alias.name}" for alias in node.names)


def _top_level(tree: ast.AST) -> Iterator[ast.AST]:
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            continue
        yield node
        if isinstance(node, (ast.ClassDef, ast.If, ast.Try, ast.With)):
            yield from _top_level(node)


def sources() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "proto/arcloud" not in p.as_posix())


def test_every_package_has_a_layer() -> None:
    assert {unit_of(p) for p in sources()} - {"__init__"} == set(LAYER)


def test_imports_point_down_the_layers() -> None:
    wrong = []
    for path in sources():
        unit = unit_of(path)
        if unit == "__init__":
            continue
        for name in imports(ast.parse(path.read_text())):
            parts = name.split(".")
            if (
                parts[0] == "arcloud"
                and len(parts) > 1
                and parts[1] in LAYER
                and parts[1] != unit
                and LAYER[parts[1]] >= LAYER[unit]
            ):
                wrong.append(
                    f"{path.relative_to(PACKAGE)} ({unit}, layer {LAYER[unit]}) imports {name} (layer {LAYER[parts[1]]})"
                )
    assert not wrong, "\n".join(wrong)


def test_the_core_uses_no_io_library() -> None:
    wrong = [
        f"{path.relative_to(PACKAGE)} imports {name}"
        for path in sorted((PACKAGE / "core").rglob("*.py"))
        for name in imports(ast.parse(path.read_text()))
        if name.split(".")[0] not in CORE_LIBRARIES and not name.startswith("arcloud.core")
    ]
    assert not wrong, wrong


def test_no_import_cycle_between_modules() -> None:
    modules = {module_name(p): p for p in sources()}
    edges = {
        name: {m for m in imports(ast.parse(path.read_text()), top_level_only=True) if m in modules and m != name}
        for name, path in modules.items()
    }
    assert find_cycle(edges) is None


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One cycle of a directed graph (the nodes along it), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt) :] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for start in sorted(edges):
        if start not in state and (found := visit(start)):
            return found
    return None


def test_the_checks_see_wrong_arrows_and_cycles(tmp_path: Path) -> None:
    tree = ast.parse(
        "import os\nif TYPE_CHECKING:\n    import arcloud.x\ndef f():\n    from arcloud.eval.metrics import evaluate\n"
    )
    assert set(imports(tree)) == {"os", "arcloud.x", "arcloud.eval.metrics", "arcloud.eval.metrics.evaluate"}
    assert set(imports(tree, top_level_only=True)) == {"os"}
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
