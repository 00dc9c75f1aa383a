"""Rate limits on Redis, shared by every API process: one GCRA step per request in ``lua/rate_limit.lua``
(one key per bucket, ``keys.rate_key``, expiring once the bucket is full again)."""

from __future__ import annotations

from arcloud.stores.keys import rate_key
from arcloud.stores.redis import RedisClient, RedisSideStore, lua_source, where
from arcloud.stores.redis_errors import redis_errors


class RedisRateLimiter(RedisSideStore):
    """``RateLimiter`` on Redis: on ``client`` (shared, not closed here), else on a new connection to ``url``."""

    def __init__(self, url: str = "", *, client: RedisClient | None = None, reply_timeout_s: float | None = None) -> None:
        super().__init__(url, client=client, reply_timeout_s=reply_timeout_s)
        self._script = self.client.register_script(lua_source("rate_limit"))

    def take(self, bucket: str, *, rate_per_s: float, burst: int) -> float:
        with redis_errors(f"take from rate bucket {bucket}", lambda: where(self.client)):
            wait = self._script(keys=[rate_key(bucket)], args=[repr(float(rate_per_s)), int(burst)])
        return float(wait)
