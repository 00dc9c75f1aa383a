"""Fixtures of the dataset tests: tiny folders built in tmp_path (see datasets_builders.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from datasets_builders import TinyScanNet, build_scannet


@pytest.fixture
def tiny_scannet(tmp_path: Path) -> TinyScanNet:
    return build_scannet(tmp_path)
