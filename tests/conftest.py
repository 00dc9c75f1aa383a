"""Fixtures shared by every test module.

Real assets (models, 7-Scenes, ScanNet) live in ``../shared`` beside the project root and are never
copied into the repository; tests that need them skip with a clear reason when they are absent.
Set ``ARCLOUD_SHARED`` to use another folder.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from redis_server import LocalCluster

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("ARCLOUD_SHARED", PROJECT_ROOT.parent / "shared"))


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
