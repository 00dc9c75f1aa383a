"""The API docs from files in the package, so that they work with no internet: ``GET /docs`` (Swagger UI),
``/docs/oauth2-redirect``, ``/redoc`` (ReDoc) and their files, ``GET /docs/ui/<file>``.

FastAPI's own pages load Swagger UI and ReDoc from a CDN (and ReDoc's fonts from Google): without internet
``/docs`` is a blank page. These are FastAPI's pages with local URLs; the files under ``docs_ui/`` are
copied from npm by ``make web-vendor`` (the versions ``web/package-lock.json`` pins), with their licences.
Open to anyone, as ``/openapi.json`` is: they hold no data. The pages' Content-Security-Policy lets them load
from this service only: ReDoc would fetch its logo from cdn.redoc.ly (it hides it when it cannot).
"""

from __future__ import annotations

from importlib import resources
from typing import Annotated

from fastapi import APIRouter, HTTPException, Path, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, Response

DOCS_PACKAGE = "arcloud.service"
DOCS_FOLDER = "docs_ui"
DOCS_URL, REDOC_URL, OAUTH2_REDIRECT_URL, FILES_URL = "/docs", "/redoc", "/docs/oauth2-redirect", "/docs/ui"
_TEXT = "text/plain; charset=utf-8"
#: Every file served, with its media type: nothing else under the folder is.
FILES = {
    "swagger-ui-bundle.js": "text/javascript; charset=utf-8",
    "swagger-ui.css": "text/css; charset=utf-8",
    "favicon-32x32.png": "image/png",
    "redoc.standalone.js": "text/javascript; charset=utf-8",
    "SWAGGER-UI-LICENSE": _TEXT,
    "SWAGGER-UI-NOTICE": _TEXT,
    "swagger-ui-bundle.js.LICENSE.txt": _TEXT,
    "REDOC-LICENSE": _TEXT,
    "redoc.standalone.js.LICENSE.txt": _TEXT,
}
#: Swagger UI's settings: FastAPI's, and no validator badge (it would fetch validator.swagger.io).
SWAGGER_UI_PARAMETERS = {"validatorUrl": None}
CACHE = {"Cache-Control": "public, max-age=86400", "X-Content-Type-Options": "nosniff"}
#: The pages load from this service only (inline: the pages' own script and style, and ReDoc's styles).
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'"
)

router = APIRouter(include_in_schema=False)


def docs_file(name: str) -> tuple[bytes, str]:
    """(content, media type) of a file of the docs; ``HTTPException`` 404 for any other name."""
    media = FILES.get(name)
    if media is None:
        raise HTTPException(404, f"docs file {name!r} not found: expected one of {', '.join(sorted(FILES))}")
    return resources.files(DOCS_PACKAGE).joinpath(DOCS_FOLDER, name).read_bytes(), media


def _openapi_url(request: Request) -> str:
    return str(request.scope.get("root_path", "")) + str(request.app.openapi_url)


def _local_only(page: HTMLResponse) -> HTMLResponse:
    page.headers["Content-Security-Policy"] = CONTENT_SECURITY_POLICY
    return page


@router.get(DOCS_URL)
def swagger_ui(request: Request) -> HTMLResponse:
    root = str(request.scope.get("root_path", ""))
    page = get_swagger_ui_html(
        openapi_url=_openapi_url(request),
        title=f"{request.app.title} - Swagger UI",
        swagger_js_url=f"{root}{FILES_URL}/swagger-ui-bundle.js",
        swagger_css_url=f"{root}{FILES_URL}/swagger-ui.css",
        swagger_favicon_url=f"{root}{FILES_URL}/favicon-32x32.png",
        oauth2_redirect_url=f"{root}{OAUTH2_REDIRECT_URL}",
        swagger_ui_parameters=SWAGGER_UI_PARAMETERS,
    )
    return _local_only(page)


@router.get(OAUTH2_REDIRECT_URL)
def swagger_ui_oauth2_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


@router.get(REDOC_URL)
def redoc(request: Request) -> HTMLResponse:
    root = str(request.scope.get("root_path", ""))
    page = get_redoc_html(
        openapi_url=_openapi_url(request),
        title=f"{request.app.title} - ReDoc",
        redoc_js_url=f"{root}{FILES_URL}/redoc.standalone.js",
        redoc_favicon_url=f"{root}{FILES_URL}/favicon-32x32.png",
        with_google_fonts=False,
    )
    return _local_only(page)


@router.get(FILES_URL + "/{name}")
def docs_asset(name: Annotated[str, Path(description="a file of the docs, e.g. swagger-ui.css")]) -> Response:
    content, media = docs_file(name)
    return Response(content, media_type=media, headers=CACHE)


__all__ = ["FILES", "docs_file", "router"]
