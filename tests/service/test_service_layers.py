"""The service talks to ports only: no module under ``arcloud/service`` imports redis, an adapter, the
simulator, evaluation, the client SDK, datasets or the composition root, at the top or inside a function."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import arcloud.service

SERVICE_DIR = Path(arcloud.service.__file__).parent

#: Modules (and their submodules) the service must not import: adapters and the tools above it.
FORBIDDEN = (
    "redis",
    "zenoh",
    "arcloud.stores",
    "arcloud.events",
    "arcloud.detectors",
    "arcloud.sim",
    "arcloud.virtual_camera",
    "arcloud.eval",
    "arcloud.client",
    "arcloud.datasets",
    "arcloud.accuracy",
    "arcloud.demo",
    "arcloud.tools",
)


def imported_modules(source: str) -> list[tuple[int, str]]:
    """(line, module) of every import in ``source``, nested ones too; ``from a import b`` gives both
    ``a`` and ``a.b`` (``b`` may be a submodule)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = ("." * node.level) + (node.module or "")
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def forbidden(module: str) -> bool:
    return any(module == name or module.startswith(f"{name}.") for name in FORBIDDEN)


def test_the_import_scan_sees_nested_and_from_imports() -> None:
    source = "import os\ndef f():\n    import redis.client\n    from arcloud import stores\n    from arcloud.ports import ObjectStore\n"
    assert [m for _, m in imported_modules(source) if forbidden(m)] == ["redis.client", "arcloud.stores"]


@pytest.mark.parametrize("path", sorted(SERVICE_DIR.rglob("*.py")), ids=lambda p: p.name)
def test_service_modules_import_no_adapter(path: Path) -> None:
    imports = imported_modules(path.read_text())
    assert all(not module.startswith(".") for _, module in imports), f"{path.name}: relative import"
    bad = [f"line {line}: {module}" for line, module in imports if forbidden(module)]
    assert not bad, f"{path.name} imports what the service must not (talk to arcloud.ports instead): {', '.join(bad)}"
