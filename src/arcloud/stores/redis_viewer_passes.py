"""Viewer passes in Redis, shared by every API process: one STRING per pass, ``keys.viewer_pass_key(digest)`` ->
``ViewerGrant`` JSON, expiring with the pass (PX); ``take`` is one GETDEL, so a ticket is traded once."""

from __future__ import annotations

import json
import math
import time

from arcloud.access import ViewerGrant
from arcloud.stores.keys import viewer_pass_key
from arcloud.stores.redis import RedisSideStore


class RedisViewerPasses(RedisSideStore):
    """``ViewerPasses`` on Redis: on ``client`` (shared, not closed here), else on a new connection to ``url``."""

    REPLY_TIMEOUT_S = 5.0

    def put(self, digest: str, grant: ViewerGrant) -> None:
        ttl_ms = max(1, math.ceil((grant.expires_at_s - time.time()) * 1000))
        self._call("store the viewer pass", "set", viewer_pass_key(digest), json.dumps(grant.to_record()), px=ttl_ms)

    def find(self, digest: str) -> ViewerGrant | None:
        return _grant(self._call("look the viewer pass up", "get", viewer_pass_key(digest)))

    def take(self, digest: str) -> ViewerGrant | None:
        return _grant(self._call("take the viewer pass", "getdel", viewer_pass_key(digest)))


def _grant(raw: object) -> ViewerGrant | None:
    return ViewerGrant.from_record(json.loads(raw)) if isinstance(raw, (bytes, str)) else None
