"""Device alignments in this process's memory (the embedded service): map id -> device id -> (4, 4)."""

from __future__ import annotations

import threading

import numpy as np


class MemoryDeviceAlignments:
    """``DeviceAlignments`` in memory; every value handed in or out is a copy. Thread-safe."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._maps: dict[str, dict[str, np.ndarray]] = {}

    def close(self) -> None:
        return None

    def get(self, map_id: str, device_id: str) -> np.ndarray | None:
        with self._lock:
            found = self._maps.get(map_id, {}).get(device_id)
        return None if found is None else found.copy()

    def put(self, map_id: str, device_id: str, device_from_map: np.ndarray) -> None:
        value = np.array(device_from_map, dtype=np.float64).reshape(4, 4)
        with self._lock:
            self._maps.setdefault(map_id, {})[device_id] = value

    def delete(self, map_id: str, device_id: str) -> bool:
        with self._lock:
            devices = self._maps.get(map_id, {})
            found = devices.pop(device_id, None) is not None
            if not devices:
                self._maps.pop(map_id, None)
        return found

    def of_map(self, map_id: str) -> dict[str, np.ndarray]:
        with self._lock:
            return {device: value.copy() for device, value in self._maps.get(map_id, {}).items()}

    def forget_map(self, map_id: str) -> None:
        with self._lock:
            self._maps.pop(map_id, None)


__all__ = ["MemoryDeviceAlignments"]
