"""The web viewer: ``GET /viewer`` (``?map=M&token=T``) and its files, ``GET /viewer/<file>``.

The page and its files hold no data, so they are open to anyone; the page calls the map routes with the
token it was given (``Authorization: Bearer``). The files ship in the package (``service/viewer/``):
the page, its script and style, and three.js under ``vendor/`` (copied from npm by ``make web-vendor``,
with its licence), so nothing is fetched from elsewhere when the page runs.
"""

from __future__ import annotations

import re
from importlib import resources
from typing import Annotated

from fastapi import APIRouter, HTTPException, Path
from fastapi.responses import Response

VIEWER_PACKAGE = "arcloud.service"
VIEWER_FOLDER = "viewer"
MEDIA_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8"}
LICENSE_MEDIA_TYPE = "text/plain; charset=utf-8"
#: A file of the viewer: one or two path segments of safe characters (no "..", no hidden files).
FILE_NAME = re.compile(r"(?:vendor/)?[A-Za-z0-9][A-Za-z0-9_.-]*")
NO_CACHE = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}

router = APIRouter(tags=["viewer"], include_in_schema=False)


def viewer_file(name: str) -> tuple[bytes, str]:
    """(content, media type) of a file of the viewer; ``HTTPException`` 404 for anything else."""
    suffix = name[name.rfind(".") :] if "." in name else ""
    media = MEDIA_TYPES.get(suffix) or (LICENSE_MEDIA_TYPE if name.endswith("LICENSE") else None)
    if media is None or not FILE_NAME.fullmatch(name) or ".." in name:
        raise HTTPException(404, f"viewer file {name!r} not found")
    path = resources.files(VIEWER_PACKAGE).joinpath(VIEWER_FOLDER, *name.split("/"))
    if not path.is_file():
        raise HTTPException(404, f"viewer file {name!r} not found")
    return path.read_bytes(), media


@router.get("/viewer")
def viewer_page() -> Response:
    """The viewer page (``?map=M``, and ``&token=T`` once: the page keeps it in sessionStorage)."""
    content, media = viewer_file("index.html")
    return Response(content, media_type=media, headers={**NO_CACHE, "Referrer-Policy": "no-referrer"})


@router.get("/viewer/{name:path}")
def viewer_asset(name: Annotated[str, Path(description="a file of the viewer, e.g. viewer.js")]) -> Response:
    content, media = viewer_file(name)
    return Response(content, media_type=media, headers=NO_CACHE)


__all__ = ["router", "viewer_file"]
