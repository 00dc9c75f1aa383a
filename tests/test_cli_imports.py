"""``arcloud --help`` stays fast: building the CLI's parsers imports no heavy module; each command's
handler imports what it runs. Checked on the set of modules a fresh interpreter loads (``-X importtime``
lists every one), not on time: timings on shared machines are noise. About 0.05 s cumulative when
written, against 0.2 s when ``import arcloud.cli`` loaded numpy and the dataset readers."""

from __future__ import annotations

import subprocess
import sys

import pytest

#: Top-level packages the CLI's parsers must not load (numpy included: argument types are plain Python).
HEAVY = ("numpy", "scipy", "cv2", "open3d", "onnxruntime", "fastapi", "starlette", "pydantic", "uvicorn", "redis", "zenoh", "google", "httpx", "tqdm")  # fmt: skip

COMMANDS = (
    [],
    ["demo"],
    ["eval"],
    ["eval", "scannet"],
    ["eval", "7scenes"],
    ["eval", "recording"],
    ["render-scannet"],
    ["serve"],
    ["worker"],
    ["replay"],
    ["frames"],
    ["frames", "failed"],
    ["frames", "retry"],
    ["models"],
    ["models", "pull"],
)


def imported_modules(code: str) -> dict[str, int]:
    """Every module a fresh interpreter imports running ``code``, with its cumulative import time (us)."""
    done = subprocess.run([sys.executable, "-X", "importtime", "-c", code], capture_output=True, text=True, timeout=120)
    modules = {}
    for line in done.stderr.splitlines():
        if line.startswith("import time:") and "|" in line and "cumulative" not in line:
            _, cumulative, name = line.removeprefix("import time:").split("|")
            modules[name.strip()] = int(cumulative)
    assert modules, done.stderr[-2000:]
    return modules


def heavy(modules: dict[str, int]) -> list[str]:
    return sorted(name for name in modules if name.split(".")[0] in HEAVY)


def test_importing_the_cli_loads_no_heavy_module() -> None:
    modules = imported_modules("import arcloud.cli")
    assert "arcloud.cli" in modules
    assert heavy(modules) == [], f"import arcloud.cli loads {heavy(modules)}"


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: " ".join(c) or "arcloud")
def test_help_of_every_command_loads_no_heavy_module(command: list[str]) -> None:
    code = f"import sys; from arcloud.cli import main\ntry:\n    main({[*command, '--help']!r})\nexcept SystemExit as exit:\n    sys.exit(exit.code)"
    modules = imported_modules(code)
    assert heavy(modules) == [], f"arcloud {' '.join(command)} --help loads {heavy(modules)}"


def test_the_check_sees_a_heavy_import() -> None:
    assert heavy(imported_modules("import arcloud.cli, numpy")) != []
