"""API keys and what each role may do: pure functions, no I/O (the stores keep keys, the service checks them).

A token is ``arc_<id>_<secret>``: ``id`` (12 hex digits) names the key and is shown by ``arcloud keys
list``; ``secret`` (43 URL-safe characters, 256 random bits) is printed once at creation and stored only as
its SHA-256. A salted slow hash protects guessable passwords; a 256-bit random secret cannot be guessed,
so one SHA-256 is enough, and comparing digests in constant time leaks nothing.

A viewer pass (``ViewerGrant``) lets a browser read one map without the key in a URL: a key that may read the map
draws a ticket (``new_viewer_pass(kind="ticket")``, minutes long, used once), and the viewer trades it for a session
(an HttpOnly cookie, hours long). Only the pass's SHA-256 is stored, like a key's secret.

Roles, each on its maps (a list of map ids, or ``*`` for every map):

    reader   read: objects, stats, frame status
    device   read, and write: upload frames
    admin    read, write, and admin: delete maps
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from dataclasses import dataclass
from typing import Literal, cast

from arcloud.core.errors import InvalidInput

Role = Literal["device", "reader", "admin"]
Action = Literal["read", "write", "admin"]
ROLES: tuple[Role, ...] = ("device", "reader", "admin")
ALL_MAPS = "*"

#: What each role may do.
ROLE_ACTIONS: dict[str, frozenset[str]] = {
    "reader": frozenset({"read"}),
    "device": frozenset({"read", "write"}),
    "admin": frozenset({"read", "write", "admin"}),
}

TOKEN_PREFIX = "arc"
_TOKEN = re.compile(r"arc_([0-9a-f]{12})_([A-Za-z0-9_-]{43})")


@dataclass(frozen=True, slots=True)
class ApiKey:
    """A key as stored: never its secret, only the secret's SHA-256 (hex)."""

    id: str
    role: Role
    maps: tuple[str, ...]  # map ids, or (ALL_MAPS,)
    created_at_s: float
    secret_sha256: str
    name: str = ""

    def allows(self, action: Action, map_id: str | None) -> bool:
        """Whether this key may do ``action`` on ``map_id`` (None: a route of no map, allowed for ``*`` keys)."""
        if action not in ROLE_ACTIONS[self.role]:
            return False
        return ALL_MAPS in self.maps or (map_id is not None and map_id in self.maps)

    def to_record(self) -> dict[str, object]:
        """The key as a JSON-able dict (what the stores write)."""
        return {
            "id": self.id,
            "role": self.role,
            "maps": list(self.maps),
            "created_at_s": self.created_at_s,
            "secret_sha256": self.secret_sha256,
            "name": self.name,
        }

    @staticmethod
    def from_record(record: dict[str, object]) -> ApiKey:
        role = str(record["role"])
        if role not in ROLES:
            raise InvalidInput("role", f"one of {', '.join(ROLES)}", repr(role))
        maps = record["maps"]
        return ApiKey(
            id=str(record["id"]),
            role=role,
            maps=tuple(str(m) for m in maps) if isinstance(maps, list) else (),
            created_at_s=float(cast(float, record["created_at_s"])),
            secret_sha256=str(record["secret_sha256"]),
            name=str(record.get("name", "")),
        )


ViewerPassKind = Literal["ticket", "session"]


@dataclass(frozen=True, slots=True)
class ViewerGrant:
    """What a viewer pass lets its holder do: read map ``map_id`` while key ``key_id`` may, until ``expires_at_s``
    (Unix s). A ``ticket`` is traded once for a ``session``; only a ``session`` opens map routes."""

    kind: ViewerPassKind
    map_id: str
    key_id: str
    expires_at_s: float

    def to_record(self) -> dict[str, object]:
        return {"kind": self.kind, "map_id": self.map_id, "key_id": self.key_id, "expires_at_s": self.expires_at_s}

    @staticmethod
    def from_record(record: dict[str, object]) -> ViewerGrant:
        kind = str(record["kind"])
        if kind not in ("ticket", "session"):
            raise InvalidInput("kind", "ticket or session", repr(kind))
        return ViewerGrant(
            kind="ticket" if kind == "ticket" else "session",
            map_id=str(record["map_id"]),
            key_id=str(record["key_id"]),
            expires_at_s=float(cast(float, record["expires_at_s"])),
        )


def new_viewer_pass(kind: ViewerPassKind, map_id: str, key_id: str, *, now_s: float, ttl_s: float) -> tuple[ViewerGrant, str]:
    """A new viewer pass and its secret (256 random bits, shown once; stored as ``secret_digest``)."""
    return ViewerGrant(kind, map_id, key_id, now_s + ttl_s), secrets.token_urlsafe(32)


def viewer_key(key: ApiKey, map_id: str) -> ApiKey:
    """What a viewer session of ``key`` may do: read ``map_id`` (if the key may), nothing else."""
    maps = (map_id,) if key.allows("read", map_id) else ()
    return ApiKey(key.id, "reader", maps, key.created_at_s, key.secret_sha256, f"viewer session of key {key.id}")


def parse_maps(text: str) -> tuple[str, ...]:
    """``M1,M2`` or ``*`` -> the key's maps, each a valid map id (``InvalidInput`` otherwise)."""
    names = tuple(part.strip() for part in text.split(",") if part.strip())
    if not names:
        raise InvalidInput("maps", "a comma-separated list of map ids, or '*'", repr(text))
    from arcloud.core.checks import check_map_id  # here: the CLI imports this module and must not load numpy

    if ALL_MAPS in names:
        if len(names) > 1:
            raise InvalidInput("maps", "'*' alone, or map ids", repr(text))
        return (ALL_MAPS,)
    for name in names:
        check_map_id("maps", name)
    return tuple(dict.fromkeys(names))


def new_key(role: str, maps: tuple[str, ...], *, now_s: float, name: str = "") -> tuple[ApiKey, str]:
    """A new key and its token (the only time the token exists in clear)."""
    if role not in ROLES:
        raise InvalidInput("role", f"one of {', '.join(ROLES)}", repr(role))
    if not maps:
        raise InvalidInput("maps", "at least one map id, or '*'", "none")
    key_id = secrets.token_hex(6)
    secret = secrets.token_urlsafe(32)
    key = ApiKey(key_id, role, maps, now_s, secret_digest(secret), name)
    return key, f"{TOKEN_PREFIX}_{key_id}_{secret}"


def secret_digest(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def split_token(token: str) -> tuple[str, str] | None:
    """``arc_<id>_<secret>`` -> (id, secret); None for anything else."""
    found = _TOKEN.fullmatch(token)
    return (found.group(1), found.group(2)) if found else None


def verify(key: ApiKey, secret: str) -> bool:
    """Whether ``secret`` is the key's (constant time)."""
    return hmac.compare_digest(secret_digest(secret), key.secret_sha256)


__all__ = [
    "ALL_MAPS",
    "ROLES",
    "ROLE_ACTIONS",
    "Action",
    "ApiKey",
    "Role",
    "ViewerGrant",
    "ViewerPassKind",
    "new_key",
    "new_viewer_pass",
    "parse_maps",
    "secret_digest",
    "split_token",
    "verify",
    "viewer_key",
]
