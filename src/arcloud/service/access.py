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

The body of a request is read only after all four passed. Keys are looked up through a small cache
(``Settings.key_cache_s``, 5 s): a key created or revoked takes effect within that time in every API process.

Keys can be lost with the data (a Redis restarted without it, a FLUSHALL): then every request answers 401
while the service looks healthy. ``Access.keys_health`` (a check of ``/readyz``) reports a key store that
holds no key where this process saw some, and logs it once.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from arcloud.access import ROLE_ACTIONS, Action, ApiKey, split_token, verify
from arcloud.core.checks import check_map_id
from arcloud.errors import ArcloudError
from arcloud.ports import KeyStore, RateLimiter
from arcloud.service.settings import Settings

log = logging.getLogger(__name__)

KEY_CACHE_ENTRIES = 10_000  # lookups kept at most (cleared when full)
BARRED_ADDRESSES = 10_000  # addresses refused for failed authentications, kept at most (cleared when full)

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
    """What ``require`` checks against: the keys (None: auth none), the rate limiter (None: no limits).
    ``clock``: monotonic seconds (how long an address stays barred)."""

    settings: Settings
    keys: KeyCache | None
    limiter: RateLimiter | None
    clock: Callable[[], float] = time.monotonic
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
            n_keys = len(self.keys.keys.list_keys())
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
            "without its data or was flushed? restore the keys: docs/service.md, Recovery)"
        )
        if first:
            log.error("API keys %s", detail)
        return detail

    def authenticate(self, token: str | None, address: str) -> Caller:
        if self.keys is None:
            return Caller(None, address)
        self._refuse_if_barred(address)
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
        caller = access.authenticate(credentials.credentials if credentials is not None else None, address)
        map_id = request.path_params.get("map_id")
        if map_id is not None:
            check_map_id("map_id", map_id)
        access.authorize(caller, action, map_id, listing=listing)
        access.limit(caller, action, map_id)
        return caller

    return check


__all__ = ["Access", "Caller", "KeyCache", "Refused", "bearer_scheme", "require"]
