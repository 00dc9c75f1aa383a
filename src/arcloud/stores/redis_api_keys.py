"""API keys in Redis, shared by every API process: one HASH ``arcloud:keys``, key id -> the key's JSON
record (``ApiKey.to_record``: the secret's SHA-256, never the secret). ``revoke`` deletes the field, so
a revoked key fails at the next lookup of every process."""

from __future__ import annotations

import json

from arcloud.access import ApiKey
from arcloud.stores.keys import API_KEYS
from arcloud.stores.redis import RedisSideStore


class RedisKeyStore(RedisSideStore):
    """``KeyStore`` on Redis: on ``client`` (shared, not closed here), else on a new connection to ``url``."""

    REPLY_TIMEOUT_S = 5.0

    def add(self, key: ApiKey) -> None:
        self._call("store the key", "hset", API_KEYS, key.id, json.dumps(key.to_record()))

    def find(self, key_id: str) -> ApiKey | None:
        raw = self._call("look the key up", "hget", API_KEYS, key_id)
        return ApiKey.from_record(json.loads(raw)) if isinstance(raw, (bytes, str)) else None

    def list_keys(self) -> list[ApiKey]:
        raw = self._call("list the keys", "hgetall", API_KEYS)
        keys = [ApiKey.from_record(json.loads(v)) for v in raw.values()]  # type: ignore[attr-defined]  # HGETALL answers a dict
        return sorted(keys, key=lambda k: (k.created_at_s, k.id))

    def count_keys(self) -> int:
        count = self._call("count the keys", "hlen", API_KEYS)
        return count if isinstance(count, int) else 0

    def revoke(self, key_id: str) -> bool:
        return bool(self._call("revoke the key", "hdel", API_KEYS, key_id))
