"""The public API, pinned (as httpx pins its own): the names ``arcloud``, ``arcloud.client`` and
``arcloud.errors`` export are exactly these, and each one imports. Changing a list here is changing the API."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

PUBLIC = {
    "arcloud": ["__version__"],
    "arcloud.client": ["ArcloudClient", "AsyncArcloudClient", "ServiceError", "frame_body", "subscribe"],
    "arcloud.client.results": [
        "AlignmentDeleted",
        "Box",
        "DeviceAlignment",
        "DeviceEvent",
        "DeviceOut",
        "DeviceRemovedEvent",
        "FrameAccepted",
        "FrameCounts",
        "FrameState",
        "MapDeleted",
        "MapEvent",
        "MapRestored",
        "MapStats",
        "MapSummary",
        "ObjectCounts",
        "ObjectDetail",
        "ObjectOut",
        "OrientedBox",
        "RemovedEvent",
        "ResetEvent",
        "SnapshotEvent",
        "UpsertEvent",
        "Voxels",
        "from_json",
        "map_event",
    ],
    "arcloud.errors": [
        "ArcloudError",
        "DatasetError",
        "FrameGivenUp",
        "InvalidInput",
        "LockTimeout",
        "MapMismatch",
        "ModelError",
        "StaleLease",
        "StoreError",
        "StoreUnavailable",
        "TooManyCells",
    ],
}


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_exported_names_are_exactly_these(module: str) -> None:
    assert importlib.import_module(module).__all__ == PUBLIC[module]


@pytest.mark.parametrize("module", sorted(PUBLIC))
def test_every_exported_name_imports(module: str) -> None:
    namespace: dict[str, object] = {}
    exec(f"from {module} import *", namespace)
    assert sorted(set(namespace) - {"__builtins__"}) == sorted(PUBLIC[module])
    assert all(namespace[name] is not None for name in PUBLIC[module])


def test_errors_are_one_tree_with_the_client_error_in_it() -> None:
    from arcloud.client import ServiceError
    from arcloud.errors import ArcloudError

    errors = importlib.import_module("arcloud.errors")
    assert all(issubclass(getattr(errors, name), ArcloudError) for name in PUBLIC["arcloud.errors"])
    assert issubclass(ServiceError, ArcloudError)


def test_importing_arcloud_loads_nothing_else() -> None:
    code = "import sys, arcloud; print(sorted(n for n in sys.modules if n.startswith('arcloud')))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert done.stdout.strip() == "['arcloud']"


def test_lazy_dataset_exports_resolve() -> None:
    """``arcloud.datasets`` loads its modules on first use: every name in its ``__all__`` resolves."""
    datasets = importlib.import_module("arcloud.datasets")
    assert all(getattr(datasets, name) is not None for name in datasets.__all__)
    assert set(datasets.__all__) <= set(dir(datasets))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        datasets.nope  # noqa: B018 - the attribute access is the test
