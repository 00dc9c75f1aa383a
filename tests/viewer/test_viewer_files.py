"""The viewer's files: three.js vendored at the version web/package-lock.json pins, with its licence; the
page loads nothing from elsewhere; the files ship in the wheel; ``/viewer/<file>`` serves those files only."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import pytest
from svc_helpers import AppClient

from arcloud.service.settings import Settings
from arcloud.service.viewer_routes import viewer_file
from arcloud.tools.wiring import create_app

PROJECT_ROOT = Path(__file__).resolve().parents[2]
VIEWER = PROJECT_ROOT / "src" / "arcloud" / "service" / "viewer"
VENDORED = ("three.module.js", "three.core.js", "OrbitControls.js", "CSS2DRenderer.js", "THREE-LICENSE")


def test_vendored_three_is_the_version_package_lock_pins_with_its_licence() -> None:
    lock = json.loads((PROJECT_ROOT / "web" / "package-lock.json").read_text())
    pinned = lock["packages"]["node_modules/three"]["version"]  # "0.187.0": three's REVISION is the minor
    assert json.loads((PROJECT_ROOT / "web" / "package.json").read_text())["dependencies"]["three"] == pinned
    revision = re.search(r"const REVISION = '(\d+)';", (VIEWER / "vendor" / "three.core.js").read_text())
    assert revision is not None and revision.group(1) == pinned.split(".")[1]
    for name in VENDORED:
        assert (VIEWER / "vendor" / name).is_file(), f"vendor/{name} missing: run `make web-vendor`"
    assert (VIEWER / "vendor" / "THREE-LICENSE").read_text().startswith("The MIT License")


def test_the_page_loads_only_files_of_this_service() -> None:
    """No URL with a scheme or a host in what the page loads (the vendored files are three's own)."""
    for name in ("index.html", "viewer.js", "viewer.css"):
        text = (VIEWER / name).read_text()
        loads = re.findall(
            r"""(?:src|href)=["']([^"']+)|import[^;]*?from\s+["']([^"']+)|@import\s+["']([^"']+)|url\(([^)]+)\)""", text
        )
        for found in (next(filter(None, groups)) for groups in loads):
            assert found.startswith(("viewer/", "./", "three", "data:")), f"{name} loads {found!r}"
    for name in VENDORED[:-1]:
        imports = re.findall(r"""^import[^;]*?from\s+['"]([^'"]+)['"]""", (VIEWER / "vendor" / name).read_text(), re.M)
        assert all(i == "three" or i.startswith("./") for i in imports), (name, imports)


def test_the_viewer_files_ship_in_the_package() -> None:
    package_data = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["arcloud"]
    assert "service/viewer/*" in package_data and "service/viewer/vendor/*" in package_data
    dev = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["dev"]
    assert any(r.startswith("playwright") for r in dev)


@pytest.mark.parametrize(
    "name", ["../app.py", "vendor/../../app.py", ".hidden.js", "vendor/x/y.js", "app.py", "nope.js", "viewer.JS"]
)
def test_only_the_viewers_files_are_served(name: str) -> None:
    from fastapi import HTTPException

    with pytest.raises(HTTPException) as refused:
        viewer_file(name)
    assert refused.value.status_code == 404


def test_the_page_and_its_files_are_open_and_the_events_are_not(tmp_path: Path) -> None:
    from viewer_helpers import make_keys

    keys_file = tmp_path / "keys.json"
    make_keys(keys_file, device=("device", "*"))
    with AppClient(create_app(Settings(detector="sim:0", workers=1, keys_file=str(keys_file)))) as api:
        page = api.get("/viewer")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert page.headers["referrer-policy"] == "no-referrer"
        for name, media in (("viewer.js", "text/javascript"), ("viewer.css", "text/css"), ("vendor/THREE-LICENSE", "text/plain")):
            answer = api.get(f"/viewer/{name}")
            assert answer.status_code == 200 and answer.headers["content-type"].startswith(media), name
        assert api.get("/viewer/vendor/three.module.js").content == (VIEWER / "vendor" / "three.module.js").read_bytes()
        assert api.get("/viewer/%2e%2e/app.py").status_code == 404
        assert api.get("/v1/maps/m/events").status_code == 401
        assert "/viewer" not in api.get("/openapi.json").json()["paths"]
        assert "/v1/maps/{map_id}/events" in api.get("/openapi.json").json()["paths"]
