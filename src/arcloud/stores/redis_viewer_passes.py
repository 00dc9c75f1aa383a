"""Viewer passes in Redis, shared by every API process: one STRING per pass, ``keys.viewer_pass_key(digest)`` ->
``ViewerGrant`` JSON, expiring with the pass (PX); ``take`` is one GETDEL, so a ticket is traded once."""

from __future__ import annotations

import json
import math
import time

from arcloud.access import ViewerGrant
from arcloud.stores.keys import viewer_pass_key
from arcloud.stores.redis import RedisClient, connect_redis, where
from arcloud.stores.redis_errors import redis_errors


class RedisViewerPasses:
    """``ViewerPasses`` on Redis: on ``client`` (shared, not closed here), else on a new connection to ``url``."""

    def __init__(self, url: str = "", *, client: RedisClient | None = None, reply_timeout_s: float = 5.0) -> None:
        self._owns_client = client is None
        self.client = client if client is not None else connect_redis(url, reply_timeout_s=reply_timeout_s)

    def close(self) -> None:
        if self._owns_client:
            self.client.close()

    def _call(self, doing: str, method: str, *args: object, **options: object) -> object:
        with redis_errors(doing, lambda: where(self.client)):
            return getattr(self.client, method)(*args, **options)

    def put(self, digest: str, grant: ViewerGrant) -> None:
        ttl_ms = max(1, math.ceil((grant.expires_at_s - time.time()) * 1000))
        self._call("store the viewer pass", "set", viewer_pass_key(digest), json.dumps(grant.to_record()), px=ttl_ms)

    def find(self, digest: str) -> ViewerGrant | None:
        return _grant(self._call("look the viewer pass up", "get", viewer_pass_key(digest)))

    def take(self, digest: str) -> ViewerGrant | None:
        return _grant(self._call("take the viewer pass", "getdel", viewer_pass_key(digest)))


def _grant(raw: object) -> ViewerGrant | None:
    return ViewerGrant.from_record(json.loads(raw)) if isinstance(raw, (bytes, str)) else None
