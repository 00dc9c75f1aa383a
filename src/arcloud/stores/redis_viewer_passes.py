"""Viewer passes in Redis, shared by every API process: one STRING per pass, ``keys.viewer_pass_key(digest)`` ->
``ViewerGrant`` JSON, expiring with the pass (PX); ``take`` is one GETDEL, so a ticket is traded once. Each key's
live passes are also listed, by expiry, in a sorted set (``keys.viewer_key_passes_key``) that bounds them
(``MAX_VIEWER_PASSES_PER_KEY``), kept in one step (``lua/viewer_passes.lua``). The list and the passes are separate
keys (other hash slots in a cluster): a pass the list ended is deleted just after, and a pass is stored just after it
is listed."""

from __future__ import annotations

import json
import math
import time
from typing import cast

from arcloud.access import ViewerGrant
from arcloud.ports import MAX_VIEWER_PASSES_PER_KEY
from arcloud.stores.keys import viewer_key_passes_key, viewer_pass_key
from arcloud.stores.redis import RedisClient, RedisSideStore, lua_source, where
from arcloud.stores.redis_errors import redis_errors


class RedisViewerPasses(RedisSideStore):
    """``ViewerPasses`` on Redis: on ``client`` (shared, not closed here), else on a new connection to ``url``."""

    REPLY_TIMEOUT_S = 5.0

    def __init__(self, url: str = "", *, client: RedisClient | None = None, reply_timeout_s: float | None = None) -> None:
        super().__init__(url, client=client, reply_timeout_s=reply_timeout_s)
        self._listed = self.client.register_script(lua_source("viewer_passes"))

    def put(self, digest: str, grant: ViewerGrant) -> None:
        now = time.time()
        ttl_ms = max(1, math.ceil((grant.expires_at_s - now) * 1000))
        now_ms = math.floor(now * 1000)
        listed = viewer_key_passes_key(grant.key_id)
        with redis_errors("list the viewer pass", lambda: where(self.client)):
            ended = self._listed(keys=[listed], args=[now_ms, digest, now_ms + ttl_ms, MAX_VIEWER_PASSES_PER_KEY])
        for member in cast(list[bytes | str], ended):  # those of the key's that would end first: never another key's
            self._call("end a viewer pass", "delete", viewer_pass_key(_text(member)))
        self._call("store the viewer pass", "set", viewer_pass_key(digest), json.dumps(grant.to_record()), px=ttl_ms)

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
