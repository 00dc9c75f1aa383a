"""Device alignments on Redis, shared by every API process: one HASH a map, ``keys.alignments_key`` (the
map's hash tag), device id -> its ``device_from_map`` as JSON (16 numbers, row-major). Every frame the API
takes reads its device's field (one HGET), so that an alignment set through any process applies to the next
frame of the device, whichever process takes it."""

from __future__ import annotations

import json

import numpy as np

from arcloud.errors import StoreError
from arcloud.stores.keys import alignments_key
from arcloud.stores.redis import RedisSideStore


class RedisDeviceAlignments(RedisSideStore):
    """``DeviceAlignments`` on Redis: on ``client`` (shared, not closed here), else on a new connection to ``url``."""

    def get(self, map_id: str, device_id: str) -> np.ndarray | None:
        raw = self._call(f"read the alignment of device {device_id}", "hget", alignments_key(map_id), device_id)
        return None if raw is None else _decode(raw, map_id, device_id)

    def put(self, map_id: str, device_id: str, device_from_map: np.ndarray) -> None:
        values = np.asarray(device_from_map, np.float64).reshape(16)
        encoded = json.dumps([float(v) for v in values])
        self._call(f"store the alignment of device {device_id}", "hset", alignments_key(map_id), device_id, encoded)

    def delete(self, map_id: str, device_id: str) -> bool:
        return bool(self._call(f"delete the alignment of device {device_id}", "hdel", alignments_key(map_id), device_id))

    def of_map(self, map_id: str) -> dict[str, np.ndarray]:
        raw = self._call("list the map's alignments", "hgetall", alignments_key(map_id))
        assert isinstance(raw, dict)  # HGETALL answers a dict
        found = {}
        for device, value in raw.items():
            device_id = device.decode() if isinstance(device, bytes) else str(device)
            found[device_id] = _decode(value, map_id, device_id)
        return found

    def forget_map(self, map_id: str) -> None:
        self._call("delete the map's alignments", "delete", alignments_key(map_id))


def _decode(raw: object, map_id: str, device_id: str) -> np.ndarray:
    """A stored value as (4, 4) float64; ``StoreError`` for one this module did not write."""
    try:
        values = np.array(json.loads(raw), dtype=np.float64)  # type: ignore[arg-type]  # bytes or str from redis-py
        return values.reshape(4, 4)
    except (TypeError, ValueError) as exc:
        raise StoreError(f"the alignment of device {device_id} in map {map_id} is not 16 numbers: {raw!r:.80}") from exc


__all__ = ["RedisDeviceAlignments"]
