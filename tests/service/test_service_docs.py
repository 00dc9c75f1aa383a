"""``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) from the package's files: their pages load nothing from
elsewhere, the files are the versions web/package-lock.json pins and ship in the wheel, and in headless
Chromium with every request off this service refused (no network), both pages render the API."""

from __future__ import annotations

import json
import re
import shutil
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
from fastapi import HTTPException
from svc_helpers import AppClient, UvicornThread

from arcloud.service.docs_routes import FILES, docs_file
from arcloud.service.settings import Settings
from arcloud.tools.wiring import create_app

PROJECT_ROOT = Path(__file__).resolve().parents[2]
DOCS_UI = PROJECT_ROOT / "src" / "arcloud" / "service" / "docs_ui"
#: The version string each vendored bundle carries, and the npm package it comes from.
BUNDLES = {
    "swagger-ui-bundle.js": ("swagger-ui-dist", r'PACKAGE_VERSION:"([\d.]+)"'),
    "redoc.standalone.js": ("redoc", r'ReDoc Version: ","([\d.]+)"'),
}
WAIT_MS = 15_000


@pytest.fixture(scope="module")
def api() -> Iterator[AppClient]:
    with AppClient(create_app(Settings(detector="sim:0", workers=1))) as client:
        yield client


def loaded_urls(html: str) -> list[str]:
    """What a page loads: src and href attributes, and the spec-url / url it hands the UI."""
    return re.findall(r"""(?:src|href|spec-url)=["']([^"']+)""", html) + re.findall(r"""\burl: ?['"]([^'"]+)""", html)


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_the_docs_pages_load_only_files_of_this_service(api: AppClient, page: str) -> None:
    answer = api.get(page)
    assert answer.status_code == 200 and answer.headers["content-type"].startswith("text/html")
    urls = loaded_urls(answer.text)
    assert "/openapi.json" in urls and len(urls) >= 3, urls
    for url in urls:
        assert not urlsplit(url).scheme and not urlsplit(url).netloc and url.startswith("/"), f"{page} loads {url!r}"
        assert api.get(url).status_code == 200, url
    assert "googleapis" not in answer.text and "cdn." not in answer.text
    assert answer.headers["content-security-policy"].startswith("default-src 'self';")


def test_the_docs_files_are_served_with_their_types_and_nothing_else(api: AppClient) -> None:
    for name, media in FILES.items():
        answer = api.get(f"/docs/ui/{name}")
        assert answer.status_code == 200 and answer.headers["content-type"] == media, name
        assert answer.content == (DOCS_UI / name).read_bytes()
    assert api.get("/docs/oauth2-redirect").status_code == 200
    for name in ("swagger-ui-bundle.js.map", "../app.py", "%2e%2e%2fapp.py", "index.html"):
        assert api.get(f"/docs/ui/{name}").status_code == 404, name
    with pytest.raises(HTTPException, match="expected one of"):
        docs_file("../docs_routes.py")
    assert "/docs" not in json.dumps(api.get("/openapi.json").json()["paths"])  # not API routes


def test_the_vendored_files_are_the_pinned_versions_and_ship_in_the_wheel() -> None:
    lock = json.loads((PROJECT_ROOT / "web" / "package-lock.json").read_text())
    pins = json.loads((PROJECT_ROOT / "web" / "package.json").read_text())["dependencies"]
    for name, (package, version_pattern) in BUNDLES.items():
        pinned = lock["packages"][f"node_modules/{package}"]["version"]
        assert pins[package] == pinned
        found = re.search(version_pattern, (DOCS_UI / name).read_text())
        assert found is not None and found.group(1) == pinned, f"{name} is not {package} {pinned}: run `make web-vendor`"
    assert set(FILES) == {p.name for p in DOCS_UI.iterdir()}
    assert (DOCS_UI / "SWAGGER-UI-LICENSE").read_text().startswith("\n                                 Apache License")
    assert (DOCS_UI / "REDOC-LICENSE").read_text().startswith("The MIT License")
    package_data = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["arcloud"]
    assert "service/docs_ui/*" in package_data


# --- in a browser, offline -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.skip("chromium not found on PATH (scripts/bootstrap.sh --test installs Debian's chromium)")
    playwright_api = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra (make installs it)")
    with playwright_api.sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=chromium)
        yield launched
        launched.close()


@pytest.fixture(scope="module")
def served() -> Iterator[str]:
    with UvicornThread(create_app(Settings(detector="sim:0", workers=1))) as server:
        yield server.url


def open_offline(browser: Any, url: str) -> tuple[Any, Any, list[str], list[str]]:
    """(context, page, requests refused, page errors) of a page at ``url`` where nothing but ``url``'s host answers."""
    context = browser.new_context()
    refused: list[str] = []
    errors: list[str] = []
    host = urlsplit(url).netloc

    def only_this_service(route: Any) -> None:
        if urlsplit(route.request.url).netloc == host:
            route.continue_()
        else:
            refused.append(route.request.url)
            route.abort("internetdisconnected")

    context.route("**/*", only_this_service)
    page = context.new_page()
    page.set_default_timeout(WAIT_MS)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("console", lambda message: print(f"console {message.type}: {message.text}"))
    page.goto(url)
    return context, page, refused, errors


def test_swagger_ui_renders_the_api_offline(browser: Any, served: str) -> None:
    context, page, refused, errors = open_offline(browser, f"{served}/docs")
    try:
        page.wait_for_selector(".swagger-ui .information-container h1.title")
        assert "arcloud" in page.inner_text(".swagger-ui .information-container h1.title")
        page.wait_for_selector(".opblock-summary-path")
        paths = page.locator(".opblock-summary-path").all_inner_texts()
        assert any("/v1/maps/{map_id}/frames" in p for p in paths), paths
    finally:
        context.close()
    assert refused == [] and errors == [], (refused, errors)


def test_redoc_renders_the_api_offline(browser: Any, served: str) -> None:
    context, page, refused, errors = open_offline(browser, f"{served}/redoc")
    try:
        page.wait_for_selector("h1")
        assert page.inner_text("h1").startswith("arcloud")
        page.wait_for_selector(".menu-content")
        assert {"frames", "objects", "maps"} <= set(page.inner_text(".menu-content").split("\n"))
        page.locator("h2", has_text="The map's objects").first.wait_for()  # an operation, from /openapi.json
    finally:
        context.close()
    assert refused == [] and errors == [], (refused, errors)
