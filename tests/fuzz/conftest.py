"""The fuzz suite reuses the service tests' helpers (frames, servers): tests/service on sys.path."""

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "service"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from fuzz_helpers import FuzzApi, serve


@pytest.fixture(scope="session")
def extra_headers() -> dict[str, str]:
    """Headers every fuzz request carries besides the app's own token (``serve`` adds an admin key's
    `Authorization: Bearer` when the app asks for keys); override to fuzz with others."""
    return {}


@pytest.fixture(scope="module", params=["embedded", pytest.param("redis", marks=pytest.mark.redis)])
def fuzz_api(request: pytest.FixtureRequest, extra_headers: dict[str, str]) -> Iterator[FuzzApi]:
    """The real app over real HTTP, each with its default access: embedded (memory store, ``sim:0`` detector, auth
    none) or on a real redis-server (one worker process, auth keys)."""
    with serve(request.param, extra_headers) as api:
        yield api
