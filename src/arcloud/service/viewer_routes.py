"""The web viewer: ``GET /viewer`` (``?map=M#ticket=T``) and its files, ``GET /viewer/<file>``, and its passes.

The page and its files hold no data, so they are open to anyone. No API key goes in a URL (URLs land in access logs,
browser history and proxies): ``/viewer?...&token=`` is refused (400, saying what to do instead). A key that may read
a map draws a viewer ticket (``POST /v1/maps/{map}/viewer-tickets``, ``Authorization: Bearer``): a random secret
good for one viewer session of that map, within ``viewer_ticket_s``; the page trades it (``POST
/v1/maps/{map}/viewer-session``) for an HttpOnly, SameSite=Strict cookie (``access.VIEWER_COOKIE``, path
``/v1/maps/{map}``) with which it reads the map's events and objects, and nothing else, for ``viewer_session_s``.
A ticket in the page's URL fragment (``#ticket=``) never reaches a server or its logs, and once used is worth
nothing. The page also takes a key typed into its form: it draws a ticket with it and forgets it.

The files ship in the package (``service/viewer/``): the page, its script and style, and three.js under
``vendor/`` (copied from npm by ``make web-vendor``, with its licence), so nothing is fetched from elsewhere when
the page runs.
"""

from __future__ import annotations

import re
from importlib import resources
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Path, Request
from fastapi.responses import Response
from fastapi.security import HTTPAuthorizationCredentials
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from arcloud.core.checks import check_map_id
from arcloud.service.access import VIEWER_COOKIE, Caller, Refused, bearer_scheme, require
from arcloud.service.app import MapId, RuntimeDep
from arcloud.service.schemas import PROBLEM_RESPONSES, Problem

VIEWER_PACKAGE = "arcloud.service"
VIEWER_FOLDER = "viewer"
MEDIA_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8"}
LICENSE_MEDIA_TYPE = "text/plain; charset=utf-8"
#: A file of the viewer: one or two path segments of safe characters (no "..", no hidden files).
FILE_NAME = re.compile(r"(?:vendor/)?[A-Za-z0-9][A-Za-z0-9_.-]*")
NO_CACHE = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}

router = APIRouter(tags=["viewer"])


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


class ViewerTicket(BaseModel):
    ticket: str = Field(description="the ticket: one viewer session of the map (POST .../viewer-session)")
    expires_in_s: float = Field(description="seconds left to use it")
    viewer_url: str = Field(description="the viewer with the ticket, relative to the service (the ticket in the fragment)")


class ViewerSessionIn(BaseModel):
    ticket: str = Field(max_length=128, description="a ticket of the map, from POST /v1/maps/{map}/viewer-tickets")


@router.post(
    "/v1/maps/{map_id}/viewer-tickets",
    status_code=201,
    response_model=ViewerTicket,
    responses=PROBLEM_RESPONSES,
    summary="A ticket for the web viewer: one session of the map, within viewer_ticket_s",
    description="Open `viewer_url` in a browser: the page trades the ticket (once) for a cookie that reads this map "
    "only, so the key never goes in a URL. Needs the key in the Authorization header (a viewer session draws none).",
)
async def draw_viewer_ticket(
    map_id: MapId,
    runtime: RuntimeDep,
    caller: Annotated[Caller, Depends(require("read"))],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)],
) -> ViewerTicket:
    if credentials is None and runtime.access.keys is not None:
        raise Refused(403, "viewer tickets: a viewer session draws none; send the key (Authorization: Bearer)", "authorization")
    secret, grant = await run_in_threadpool(runtime.access.issue_viewer_ticket, caller, map_id)
    return ViewerTicket(
        ticket=secret,
        expires_in_s=runtime.settings.viewer_ticket_s,
        viewer_url=f"/viewer?map={grant.map_id}#ticket={secret}",
    )


def checked_map_id(map_id: MapId) -> None:
    """422 for a malformed map id, before the body is read (as ``require`` does on the other map routes)."""
    check_map_id("map_id", map_id)


@router.post(
    "/v1/maps/{map_id}/viewer-session",
    status_code=204,
    dependencies=[Depends(checked_map_id)],
    responses={**PROBLEM_RESPONSES, 400: {"model": Problem, "description": "a body that is not JSON"}},
    summary="Trade a viewer ticket for a viewer session (an HttpOnly cookie that reads the map)",
    description="Uses the ticket up. The cookie (SameSite=Strict, path /v1/maps/{map_id}) opens the map's reads, "
    "the event stream included, for viewer_session_s, while the key that drew the ticket may read the map.",
)
async def open_viewer_session(map_id: MapId, body: ViewerSessionIn, request: Request, runtime: RuntimeDep) -> Response:
    address = request.client.host if request.client is not None else "unknown"
    secret, _ = await run_in_threadpool(runtime.access.open_viewer_session, body.ticket, map_id, address)
    response = Response(status_code=204, headers={"Cache-Control": "no-store"})
    response.set_cookie(
        VIEWER_COOKIE,
        secret,
        max_age=int(runtime.settings.viewer_session_s),
        path=f"/v1/maps/{map_id}",
        secure=request.url.scheme == "https",
        httponly=True,
        samesite="strict",
    )
    return response


@router.get("/viewer", include_in_schema=False)
def viewer_page(request: Request) -> Response:
    """The viewer page (``?map=M``, ``#ticket=T`` from a viewer ticket); 400 for a key in the URL."""
    if "token" in request.query_params:
        raise Refused(
            400,
            "token: an API key never goes in a URL (URLs are logged); revoke this key if the URL was shared "
            "(arcloud keys revoke), then draw a viewer ticket (POST /v1/maps/{map}/viewer-tickets with the key in "
            "the Authorization header) and open its viewer_url, or type the key into the viewer's form",
            "token",
        )
    content, media = viewer_file("index.html")
    return Response(content, media_type=media, headers={**NO_CACHE, "Referrer-Policy": "no-referrer"})


@router.get("/viewer/{name:path}", include_in_schema=False)
def viewer_asset(name: Annotated[str, Path(description="a file of the viewer, e.g. viewer.js")]) -> Response:
    content, media = viewer_file(name)
    return Response(content, media_type=media, headers=NO_CACHE)


__all__ = ["ViewerSessionIn", "ViewerTicket", "router", "viewer_file"]
