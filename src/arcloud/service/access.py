"""Who may call a route, and how often: the dependency ``require(action)`` every map route declares.

In order, so that each answer tells no more than the caller may know:

1. 401 (``WWW-Authenticate: Bearer``) without a token, or with one no key has (auth ``keys``); 429 with
   ``Retry-After`` instead once the client's address failed more than ``auth_failure_burst`` times at
   ``auth_failure_rate_per_s`` (a bucket per address, in the rate limiter: shared by every API process), and
   then, for as long as ``Retry-After`` says, for every request from that address before its token is looked
   at: a spray of guessed tokens costs one refusal each, not a key lookup;
2. 422 for a malformed map id;
3. 403 when the key's role may not do ``action`` or the map is not one of its maps;
4. 429 with ``Retry-After`` when the key (with auth ``none``: the client's address) is over
   ``key_rate_per_s``, or, for an upload, the map is over ``map_frame_rate_per_s``.

A browser viewer authenticates with a viewer session instead (``VIEWER_COOKIE``, an HttpOnly cookie holding a pass
of ``Access.open_viewer_session``): it reads its one map while the key that drew its ticket may, as a reader key of
that map alone (``arcloud.access.viewer_key``); a session unknown or expired is a 401 like a wrong token.

The body of a request is read only after all four passed. Keys are looked up through a small cache
(``Settings.key_cache_s``, 5 s): a key created or revoked takes effect within that time in every API process.

Keys can be lost with the data (a Redis restarted without it, a FLUSHALL): then every request answers 401
while the service looks healthy. ``Access.keys_health`` (a check of ``/readyz``) reports a key store that
holds no key where this process saw some, and logs it once.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from arcloud.access import (
    ROLE_ACTIONS,
    Action,
    ApiKey,
    ViewerGrant,
    ViewerPassKind,
    new_viewer_pass,
    secret_digest,
    split_token,
    verify,
    viewer_key,
)
from arcloud.core.checks import check_map_id
from arcloud.errors import ArcloudError
from arcloud.ports import KeyStore, RateLimiter, ViewerPasses
from arcloud.service.settings import Settings

log = logging.getLogger(__name__)

KEY_CACHE_ENTRIES = 10_000  # lookups kept at most (cleared when full)
BARRED_ADDRESSES = 10_000  # addresses refused for failed authentications, kept at most (cleared when full)

#: The cookie of a viewer session (its path: the map's routes, ``/v1/maps/<map>``).
VIEWER_COOKIE = "arcloud_viewer"
#: What a viewer pass's secret looks like (``secrets.token_urlsafe(32)``); anything else is unknown, unlooked-up.
VIEWER_PASS = re.compile(r"[A-Za-z0-9_-]{43}")
HOW_TO_VIEW = "draw a viewer ticket (POST /v1/maps/{map}/viewer-tickets with the key) and open the viewer with it"

#: In the OpenAPI schema: the bearer token scheme (the check itself is ``require``'s).
bearer_scheme = HTTPBearer(auto_error=False, description="a token from `arcloud keys create` (auth keys)")


class Refused(Exception):
    """A request refused by access control or a rate limit: answered ``status`` with the usual JSON problem."""

    def __init__(self, status: int, detail: str, field: str | None = None, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.field = field
        self.headers = headers or {}


@dataclass(frozen=True, slots=True)
class Caller:
    """Who sent a request: a key (auth keys), or an address (auth none)."""

    key: ApiKey | None
    address: str

    def may(self, action: Action, map_id: str) -> bool:
        """Whether the caller may do ``action`` on ``map_id`` (anyone may, with auth none)."""
        return self.key is None or self.key.allows(action, map_id)

    @property
    def bucket(self) -> str:
        """The rate limit bucket of the caller."""
        return f"key:{self.key.id}" if self.key is not None else f"ip:{self.address}"


class KeyCache:
    """``KeyStore.find`` with its answers kept ``ttl_s`` (bounded; cleared when full)."""

    def __init__(self, keys: KeyStore, ttl_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.keys = keys
        self.ttl_s = ttl_s
        self.clock = clock
        self._lock = threading.Lock()
        self._found: dict[str, tuple[float, ApiKey | None]] = {}

    def find(self, key_id: str) -> ApiKey | None:
        now = self.clock()
        with self._lock:
            cached = self._found.get(key_id)
        if cached is not None and now - cached[0] < self.ttl_s:
            return cached[1]
        key = self.keys.find(key_id)
        with self._lock:
            if len(self._found) >= KEY_CACHE_ENTRIES:
                self._found.clear()
            self._found[key_id] = (now, key)
        return key


@dataclass(eq=False)
class Access:
    """What ``require`` checks against: the keys (None: auth none), the rate limiter (None: no limits), the viewer
    passes (None: none, as with auth none). ``clock``: monotonic seconds (how long an address stays barred);
    ``wall_clock``: Unix seconds (when viewer passes expire)."""

    settings: Settings
    keys: KeyCache | None
    limiter: RateLimiter | None
    passes: ViewerPasses | None = None
    clock: Callable[[], float] = time.monotonic
    wall_clock: Callable[[], float] = time.time
    _barred: dict[str, float] = field(default_factory=dict)  # address -> until when (clock) it is refused at once
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _keys_seen: int = 0  # the most keys this process saw in the key store (1: a lookup found one)
    _loss_logged: bool = False

    def keys_health(self) -> str:
        """``ok``, or what is wrong with the keys: the store unreachable, or ``lost``: it holds no key where this
        process saw some (Redis restarted without its data, a FLUSHALL, a deleted keys file; or every key
        revoked), logged once as an error when it begins."""
        if self.keys is None:
            return "ok"
        try:
            n_keys = self.keys.keys.count_keys()  # not list_keys: 80 ms for 10,000 keys, on an open route
        except ArcloudError as exc:
            return f"unreachable: {exc}"
        with self._lock:
            if n_keys:
                self._keys_seen, self._loss_logged = max(self._keys_seen, n_keys), False
                return "ok"
            if not self._keys_seen:
                return "ok"  # no key yet: a new deployment (`arcloud keys create`)
            seen, first = self._keys_seen, not self._loss_logged
            self._loss_logged = True
        detail = (
            f"lost: the key store holds no key where it held {seen}, so every request answers 401 (its Redis restarted "
            "without its data or was flushed, or every key was revoked? create or restore keys: docs/service.md, Recovery)"
        )
        if first:
            log.error("API keys %s", detail)
        return detail

    def authenticate(self, token: str | None, address: str, viewer_session: str | None = None) -> Caller:
        """Who sends ``token`` (a bearer token), or else ``viewer_session`` (the viewer's cookie)."""
        if self.keys is None:
            return Caller(None, address)
        self._refuse_if_barred(address)
        if token is None and viewer_session is not None:
            grant = self._viewer_pass(viewer_session, "session")
            if grant is None:
                raise self._failed(address, f"authorization: the viewer session is unknown or expired: {HOW_TO_VIEW}")
            key = self.keys.find(grant.key_id)
            if key is None:
                raise self._failed(address, f"authorization: the key of this viewer session was revoked: {HOW_TO_VIEW}")
            return Caller(viewer_key(key, grant.map_id), address)
        if token is None:
            raise self._failed(
                address, "authorization: expected `Authorization: Bearer TOKEN` (a token from `arcloud keys create`)"
            )
        parts = split_token(token)
        key = self.keys.find(parts[0]) if parts is not None else None
        if parts is None or key is None or not verify(key, parts[1]):
            raise self._failed(address, "authorization: the token is not a valid key (unknown, revoked, or mistyped)")
        if not self._keys_seen:
            self._keys_seen = 1
        return Caller(key, address)

    def issue_viewer_ticket(self, caller: Caller, map_id: str) -> tuple[str, ViewerGrant]:
        """(a new ticket's secret, its grant): one viewer session of ``map_id``, for the caller's key (which may read
        it: ``require("read")`` checked), within ``viewer_ticket_s``. 404 with auth none (no ticket needed)."""
        if self.passes is None or caller.key is None:
            raise _no_viewer_passes(map_id)
        grant, secret = new_viewer_pass(
            "ticket", map_id, caller.key.id, now_s=self.wall_clock(), ttl_s=self.settings.viewer_ticket_s
        )
        self.passes.put(secret_digest(secret), grant)
        return secret, grant

    def open_viewer_session(self, ticket: str, map_id: str, address: str) -> tuple[str, ViewerGrant]:
        """(a new session's secret, its grant) for a ticket of ``map_id``, which it uses up: 401 (counted as a
        failed authentication) for a ticket unknown, used or expired, or whose key was revoked; 403 for a ticket of
        another map."""
        if self.passes is None or self.keys is None:
            raise _no_viewer_passes(map_id)
        self._refuse_if_barred(address)
        grant = self._viewer_pass(ticket, "ticket", take=True)
        if grant is None:
            raise self._failed(
                address,
                f"viewer ticket: unknown, used or expired (each opens one session, within {self.settings.viewer_ticket_s:g} s "
                f"of being drawn): {HOW_TO_VIEW}",
            )
        if grant.map_id != map_id:
            raise Refused(403, f"viewer ticket: it is for map {grant.map_id!r}, not {map_id!r}", "ticket")
        key = self.keys.find(grant.key_id)
        if key is None or not key.allows("read", map_id):
            raise self._failed(address, f"viewer ticket: the key that drew it was revoked: {HOW_TO_VIEW}")
        session, secret = new_viewer_pass(
            "session", map_id, key.id, now_s=self.wall_clock(), ttl_s=self.settings.viewer_session_s
        )
        self.passes.put(secret_digest(secret), session)
        return secret, session

    def _viewer_pass(self, secret: str, kind: ViewerPassKind, *, take: bool = False) -> ViewerGrant | None:
        """The live pass of this kind whose secret this is; None for anything else."""
        if self.passes is None or not VIEWER_PASS.fullmatch(secret):
            return None
        digest = secret_digest(secret)
        grant = self.passes.take(digest) if take else self.passes.find(digest)
        if grant is None or grant.kind != kind or grant.expires_at_s <= self.wall_clock():
            return None
        return grant

    def _failed(self, address: str, detail: str) -> Refused:
        """A failed authentication from ``address``: 401, or 429 once the address is over its limit (then
        barred until its bucket has a token again)."""
        rate, burst = self.settings.auth_failure_rate_per_s, self.settings.auth_failure_burst
        if self.limiter is None or rate <= 0:
            return _unauthorized(detail)
        wait = self.limiter.take(f"auth-failures:{address}", rate_per_s=rate, burst=burst)
        if wait <= 0:
            return _unauthorized(detail)
        with self._lock:
            if len(self._barred) >= BARRED_ADDRESSES:
                self._barred.clear()
            self._barred[address] = self.clock() + wait
        return self._too_many_failures(address, wait)

    def _refuse_if_barred(self, address: str) -> None:
        with self._lock:
            until = self._barred.get(address)
            if until is None:
                return
            wait = until - self.clock()
            if wait <= 0:
                del self._barred[address]
                return
        raise self._too_many_failures(address, wait)

    def _too_many_failures(self, address: str, wait_s: float) -> Refused:
        settings = self.settings
        return _too_many(
            f"authorization: client {address} failed to authenticate more than {settings.auth_failure_burst} times at "
            f"more than {settings.auth_failure_rate_per_s:g} a second",
            wait_s,
            "authorization",
        )

    def authorize(self, caller: Caller, action: Action, map_id: str | None, *, listing: bool = False) -> None:
        """403 unless the caller may do ``action`` on ``map_id``; ``listing``: a route of no map that
        answers only what the key's maps allow (the role alone is checked here)."""
        key = caller.key
        if key is None or key.allows(action, map_id) or (listing and action in ROLE_ACTIONS[key.role]):
            return
        if action not in ROLE_ACTIONS[key.role]:
            raise Refused(403, f"authorization: a {key.role} key may not {action} (key {key.id})", "authorization")
        what = f"map {map_id!r}" if map_id is not None else "routes of every map"
        raise Refused(403, f"authorization: key {key.id} is not for {what} (its maps: {', '.join(key.maps)})", "authorization")

    def limit(self, caller: Caller, action: Action, map_id: str | None) -> None:
        if self.limiter is None:
            return
        settings = self.settings
        if settings.key_rate_per_s > 0:
            wait = self.limiter.take(caller.bucket, rate_per_s=settings.key_rate_per_s, burst=settings.key_burst)
            if wait > 0:
                who = f"key {caller.key.id}" if caller.key is not None else f"client {caller.address}"
                raise _too_many(f"rate limit: {who} sends more than {settings.key_rate_per_s:g} requests a second", wait)
        if action == "write" and map_id is not None and settings.map_frame_rate_per_s > 0:
            bucket = f"map:{map_id}:frames"
            wait = self.limiter.take(bucket, rate_per_s=settings.map_frame_rate_per_s, burst=settings.map_frame_burst)
            if wait > 0:
                raise _too_many(
                    f"rate limit: map {map_id!r} takes at most {settings.map_frame_rate_per_s:g} frames a second", wait
                )


def _no_viewer_passes(map_id: str) -> Refused:
    return Refused(
        404, f"viewer tickets: none with auth none (the viewer needs none): open /viewer?map={map_id}", "authorization"
    )


def _unauthorized(detail: str) -> Refused:
    return Refused(401, detail, "authorization", {"WWW-Authenticate": "Bearer"})


def _too_many(detail: str, wait_s: float, field_name: str | None = None) -> Refused:
    return Refused(429, f"{detail}; retry in {wait_s:.2f} s", field_name, {"Retry-After": str(max(1, math.ceil(wait_s)))})


def require(action: Action, *, listing: bool = False) -> Callable[..., Caller]:
    """The dependency of a route doing ``action`` (on the path's ``map_id``, when it has one; ``listing``:
    on the maps of the caller's key, which the route filters by ``Caller.may``)."""

    def check(request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]) -> Caller:
        access: Access = request.app.state.runtime.access
        address = request.client.host if request.client is not None else "unknown"
        token = credentials.credentials if credentials is not None else None
        caller = access.authenticate(token, address, request.cookies.get(VIEWER_COOKIE))
        map_id = request.path_params.get("map_id")
        if map_id is not None:
            check_map_id("map_id", map_id)
        access.authorize(caller, action, map_id, listing=listing)
        access.limit(caller, action, map_id)
        return caller

    return check


__all__ = ["VIEWER_COOKIE", "Access", "Caller", "KeyCache", "Refused", "bearer_scheme", "require"]
