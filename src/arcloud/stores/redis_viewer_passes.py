"""Viewer passes in Redis, shared by every API process: one STRING per pass, ``keys.viewer_pass_key(digest)`` ->
``ViewerGrant`` JSON, expiring with the pass (PX); ``take`` is one GETDEL, so a ticket is traded once. Each key's
live passes are also listed, by expiry, in a sorted set (``keys.viewer_key_passes_key``) that bounds them
(``MAX_VIEWER_PASSES_PER_KEY``). The set and the passes are separate keys (other hash slots in a cluster), so two
passes drawn by one key at the same instant may leave it one over the bound for a while: a bound, not a count."""

from __future__ import annotations

import json
import math
import time
from typing import cast

from arcloud.access import ViewerGrant
from arcloud.ports import MAX_VIEWER_PASSES_PER_KEY
from arcloud.stores.keys import viewer_key_passes_key, viewer_pass_key
from arcloud.stores.redis import RedisSideStore


class RedisViewerPasses(RedisSideStore):
    """``ViewerPasses`` on Redis: on ``client`` (shared, not closed here), else on a new connection to ``url``."""

    REPLY_TIMEOUT_S = 5.0

    def put(self, digest: str, grant: ViewerGrant) -> None:
        now = time.time()
        ttl_ms = max(1, math.ceil((grant.expires_at_s - now) * 1000))
        now_ms = math.floor(now * 1000)
        expires_ms = now_ms + ttl_ms
        listed = viewer_key_passes_key(grant.key_id)
        self._call("drop the key's expired viewer passes", "zremrangebyscore", listed, "-inf", now_ms)
        held = cast(int, self._call("count the key's viewer passes", "zcard", listed))
        if held >= MAX_VIEWER_PASSES_PER_KEY:  # those of the key's that would end first end now: never another key's
            oldest = cast(
                list[tuple[bytes | str, float]],
                self._call("end the key's oldest viewer passes", "zpopmin", listed, held - MAX_VIEWER_PASSES_PER_KEY + 1),
            )
            for member, _ in oldest:
                self._call("end a viewer pass", "delete", viewer_pass_key(_text(member)))
        self._call("store the viewer pass", "set", viewer_pass_key(digest), json.dumps(grant.to_record()), px=ttl_ms)
        self._call("list the viewer pass", "zadd", listed, {digest: expires_ms})
        if cast(int, self._call("read the list's expiry", "pttl", listed)) < ttl_ms:
            self._call("keep the list while its passes live", "pexpire", listed, ttl_ms)

    def find(self, digest: str) -> ViewerGrant | None:
        return _grant(self._call("look the viewer pass up", "get", viewer_pass_key(digest)))

    def take(self, digest: str) -> ViewerGrant | None:
        grant = _grant(self._call("take the viewer pass", "getdel", viewer_pass_key(digest)))
        if grant is not None:
            self._call("unlist the viewer pass", "zrem", viewer_key_passes_key(grant.key_id), digest)
        return grant


def _grant(raw: object) -> ViewerGrant | None:
    return ViewerGrant.from_record(json.loads(raw)) if isinstance(raw, (bytes, str)) else None


def _text(member: bytes | str) -> str:
    return member.decode() if isinstance(member, bytes) else str(member)
