"""Fixtures shared by every test module.

Real assets (models, 7-Scenes, ScanNet) live in ``../shared`` beside the project root and are never
copied into the repository; tests that need them skip with a clear reason when they are absent.
Set ``ARCLOUD_SHARED`` to use another folder.

The tests that ``serial_tests.SERIAL`` names are marked ``serial``: ``make test`` runs the rest on two processes
(pytest-xdist, ``--serial skip``), then these alone, one at a time (``--serial only``).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from redis_server import LocalCluster
from serial_tests import SERIAL, is_serial

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("ARCLOUD_SHARED", PROJECT_ROOT.parent / "shared"))


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--serial",
        choices=("with", "skip", "only"),
        default="with",
        help="the tests marked serial (tests/serial_tests.py): run with the rest (default), leave them out, or run only "
        "them; `make test` runs `-n 2 --serial skip`, then `--serial only`. Not -m, so that PYTEST_ARGS can hold one",
    )


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """With ``--serial only``, a module that holds no serial test is not imported (16 s of collection less)."""
    if config.getoption("serial") != "only" or collection_path.suffix != ".py":
        return None
    try:
        relative = collection_path.relative_to(config.rootpath).as_posix()
    except ValueError:
        return None
    return None if any(relative.startswith(entry.partition("::")[0]) for entry in SERIAL) else True


@pytest.hookimpl(tryfirst=True)  # marked before ``-m`` selects on the marks
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    wanted = config.getoption("serial")
    kept: list[pytest.Item] = []
    left: list[pytest.Item] = []
    for item in items:
        serial = is_serial(item.nodeid)
        if serial:
            item.add_marker(pytest.mark.serial)
        (left if (wanted == "skip" and serial) or (wanted == "only" and not serial) else kept).append(item)
    if left:
        config.hook.pytest_deselected(items=left)
        items[:] = kept


def shared_path(relative: str) -> Path:
    """A path under ../shared, or skip the test saying what is missing."""
    path = SHARED_DIR / relative
    if not path.exists():
        pytest.skip(f"real asset {relative} not found under {SHARED_DIR} (set ARCLOUD_SHARED to its folder)")
    return path


@pytest.fixture
def shared() -> type:
    """``shared.path("models/x.onnx")`` gives a real asset's path or skips the test."""

    class Shared:
        root = SHARED_DIR
        path = staticmethod(shared_path)

    return Shared


@pytest.fixture(scope="session")
def redis_cluster() -> Iterator[LocalCluster]:
    """One real 3-primary Redis Cluster on 127.0.0.1 for the whole session (skips without redis-server or
    redis-cli); tests empty it with ``flush()`` before use."""
    cluster = LocalCluster.start(masters=3)
    yield cluster
    cluster.stop()
