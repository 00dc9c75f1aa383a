"""Every error answer of the service, built in one place: an RFC 9457 problem (``application/problem+json``).

    {"type": "/problems/invalid-input", "title": "Invalid input", "status": 422,
     "detail": "cam2world: expected a proper rotation (det +1), got a reflection (det -1)", "field": "cam2world"}

``type`` names the kind of problem (``PROBLEM_TYPES``): a URI reference relative to the service, which answers it
with the type's description (``GET /problems/{name}``); ``title`` is the type's, the same for every occurrence;
``status`` the HTTP status; ``detail`` what was wrong this time, naming the input at fault first when there is one;
``field`` (an extension member, kept from the body of before: clients that read ``detail`` and ``field`` go on
working) the input at fault, or null. Problems may carry more extension members (``/readyz``: ``checks``).

The app's exception handlers (``app``), its body limit (``app.BodyLimit``), the probes and uvicorn's protocol for
requests it cannot parse (``http_protocol``) all answer through ``problem_body``, so no error has another shape.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any

from starlette.responses import JSONResponse

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_PREFIX = "/problems/"  # the type URIs' path on the service (relative references: resolved against its URL)


@dataclass(frozen=True, slots=True)
class ProblemType:
    """A kind of problem: ``name`` (its URI is ``TYPE_PREFIX + name``), a ``title`` that never changes between
    occurrences, the ``statuses`` it comes with, and what it means for a client (``description``)."""

    name: str
    title: str
    statuses: tuple[int, ...]
    description: str

    @property
    def uri(self) -> str:
        return TYPE_PREFIX + self.name


#: Every kind of problem the service answers, by name. A status's first type is its default (``type_for``).
PROBLEM_TYPES: dict[str, ProblemType] = {
    t.name: t
    for t in (
        ProblemType(
            "bad-request",
            "Malformed request",
            (400, 431),
            "The request could not be read: a malformed HTTP request, multipart body or Content-Length, a JSON body "
            "that is not JSON, or a body the client stopped sending (400); a request line and headers over 64 kB "
            "(431). Fix the request; sending it again as it is fails the same way.",
        ),
        ProblemType(
            "unauthorized",
            "Authentication required",
            (401,),
            "No bearer token, or one that no key has (WWW-Authenticate: Bearer). Send `Authorization: Bearer TOKEN` "
            "with a token from `arcloud keys create`.",
        ),
        ProblemType(
            "forbidden",
            "Not allowed",
            (403,),
            "The key's role or maps do not allow this request (reader keys read, device keys read and upload, admin "
            "keys do all three, each on its maps).",
        ),
        ProblemType("not-found", "Not found", (404,), "No such route, map, object, frame or file."),
        ProblemType(
            "method-not-allowed",
            "Method not allowed",
            (405,),
            "The route exists but not with this method; the Allow header lists those it takes.",
        ),
        ProblemType(
            "too-slow",
            "Body too slow",
            (408,),
            "The body did not arrive whole within ARCLOUD_BODY_TIMEOUT_S of its first byte; `field` is `body`. Send it "
            "again at a steadier rate. Or the request line and headers did not within 10 s; `field` is null.",
        ),
        ProblemType(
            "map-mismatch",
            "Map of other settings",
            (409,),
            "The map was written under other settings (voxel size, up, ...) than this service's: its data would mean "
            "something else here.",
        ),
        ProblemType(
            "map-deleting",
            "Map being deleted",
            (409,),
            "The map's deletion is under way: its frames and reads are refused until it is done. GET "
            "/v1/maps/{map_id}/deletion says how far it got (admin keys); a deletion long without progress stopped "
            "half way, and DELETE goes on with it.",
        ),
        ProblemType(
            "too-large",
            "Body too large",
            (413,),
            "The body is larger than the service takes (ARCLOUD_MAX_FRAME_BYTES); `field` is `body`.",
        ),
        ProblemType(
            "unsupported-media-type",
            "Unsupported content type",
            (415,),
            "The body's Content-Type is not one the route takes (frames: application/x-protobuf or multipart/form-data).",
        ),
        ProblemType(
            "invalid-input",
            "Invalid input",
            (422,),
            "A value is not one the service takes: `field` names it, `detail` says what was expected and what came. "
            "Sending it again as it is fails the same way.",
        ),
        ProblemType(
            "rate-limited",
            "Too many requests",
            (429,),
            "Over the key's, the map's or the address's rate, or too many of its uploads or of the process's exports "
            "in progress (or the address failed authentication too often): try again after Retry-After seconds.",
        ),
        ProblemType(
            "internal-error",
            "Internal error",
            (500,),
            "Something unexpected went wrong in the service; its log has the details. Nothing of the cause is told.",
        ),
        ProblemType("not-implemented", "Not implemented", (501,), "This service was started without what the route needs."),
        ProblemType(
            "unavailable",
            "Unavailable for now",
            (503,),
            "The service cannot take the request now (shutting down, too many event streams): try again after "
            "Retry-After seconds.",
        ),
        ProblemType(
            "queue-full",
            "Queue full",
            (503,),
            "The frame queue, or the map's share of it, is at a limit that `detail` names: try again after Retry-After "
            "seconds (workers are behind).",
        ),
        ProblemType(
            "store-unavailable",
            "Store unavailable",
            (503,),
            "The store (Redis) does not answer, or answers busy: try again after Retry-After seconds.",
        ),
        ProblemType(
            "not-ready",
            "Not ready",
            (503,),
            "GET /readyz: this process cannot take or answer requests now; `checks` says which check failed.",
        ),
        ProblemType(
            "workers-unavailable",
            "Workers unavailable",
            (503,),
            "GET /healthz/workers: frames are accepted but not all the workers that should process them do; `checks` "
            "says what is wrong. The API still answers.",
        ),
    )
}
_BY_STATUS: dict[int, ProblemType] = {}
for _type in PROBLEM_TYPES.values():
    for _status in _type.statuses:
        _BY_STATUS.setdefault(_status, _type)


def type_for(status: int) -> ProblemType | None:
    """The default problem type of an HTTP status; None for a status the service never answers (then the type is
    ``about:blank`` and the title the status's phrase, as RFC 9457 says)."""
    return _BY_STATUS.get(status)


def problem_body(
    status: int, detail: str, field: str | None = None, *, kind: str | None = None, extra: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The problem document: ``kind`` a name of ``PROBLEM_TYPES`` (default: the status's), ``extra`` extension
    members (never one of the standard ones)."""
    found = PROBLEM_TYPES[kind] if kind is not None else type_for(status)
    if found is not None:
        type_uri, title = found.uri, found.title
    else:
        type_uri, title = "about:blank", _phrase(status)
    body: dict[str, Any] = {"type": type_uri, "title": title, "status": status, "detail": detail, "field": field}
    for name, value in (extra or {}).items():
        if name in body:
            raise ValueError(f"problem extension: {name!r} is a standard member")
        body[name] = value
    return body


def problem_response(
    status: int,
    detail: str,
    field: str | None = None,
    *,
    kind: str | None = None,
    headers: Mapping[str, str] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> JSONResponse:
    """``problem_body`` as an ``application/problem+json`` answer."""
    return JSONResponse(
        problem_body(status, detail, field, kind=kind, extra=extra),
        status_code=status,
        headers=dict(headers or {}),
        media_type=PROBLEM_MEDIA_TYPE,
    )


def problem_openapi(spec: dict[str, Any], problem_schema: str = "Problem") -> dict[str, Any]:
    """``spec`` (an OpenAPI document, changed in place) with every 4xx/5xx response as the service sends it:
    ``application/problem+json`` (FastAPI documents a response model under the route's media type), and FastAPI's
    default 422 body (``HTTPValidationError``, which the service never sends) replaced by ``problem_schema``."""
    problem_ref = {"$ref": f"#/components/schemas/{problem_schema}"}
    for operations in spec.get("paths", {}).values():
        for operation in operations.values():
            for code, response in operation.get("responses", {}).items():
                if not (code.isdigit() and int(code) >= 400) or "content" not in response:
                    continue
                content = response["content"]
                media = content.pop("application/json", None) or content.pop(PROBLEM_MEDIA_TYPE, None) or {}
                if media.get("schema", {}).get("$ref", "").endswith("/HTTPValidationError"):
                    media = {**media, "schema": problem_ref}
                    response["description"] = "invalid input"
                content[PROBLEM_MEDIA_TYPE] = media
    schemas = spec.get("components", {}).get("schemas", {})
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    return spec


def validation_wording(error: Mapping[str, Any]) -> str:
    """What a pydantic validation error expected, worded as a problem's detail says it after "expected": its
    message without pydantic's "Input should be", and a missing or unknown field said as such."""
    kind, message = error.get("type"), str(error.get("msg", "a valid value"))
    if kind == "missing":
        return "a value (the field is required)"
    if kind == "extra_forbidden":
        return "no such field"
    return message.removeprefix("Input should be ").removeprefix("Value error, ")


def first_error(errors: Sequence[Mapping[str, Any]]) -> Mapping[str, Any]:
    """The pydantic error to report: the first, or, among the errors of the same field, the one that reached deepest
    into its value (a ``cam2world`` of 4 rows with one wrong number: the rows' branch names the number, where the flat
    list's names the whole first row)."""
    field = errors[0]["loc"][:1]
    return max((e for e in errors if e["loc"][:1] == field), key=lambda e: len(e["loc"]))


def validation_location(loc: Sequence[Any]) -> str:
    """A pydantic error's location as a field path (``cam2world.3``), without the union branches it names
    (``list[float]``: a ``cam2world`` of 16 numbers or of 4 rows)."""
    return ".".join(str(part) for part in loc if not (isinstance(part, str) and part.startswith("list[")))


def _phrase(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


__all__ = [
    "PROBLEM_MEDIA_TYPE",
    "PROBLEM_TYPES",
    "TYPE_PREFIX",
    "ProblemType",
    "problem_body",
    "problem_openapi",
    "problem_response",
    "type_for",
    "first_error",
    "validation_location",
    "validation_wording",
]
