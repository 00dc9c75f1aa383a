"""The devices a map heard from lately: each one's last accepted frame pose, for viewers to draw its camera.

Kept by the ingest of this API process when it queues a frame (no store or queue holds poses): in the
embedded deployment that is every frame; with several API processes behind a balancer, each knows the
devices whose uploads it took. Bounded: ``max_maps`` maps and ``max_devices`` devices a map, the least
recently heard dropped first.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from arcloud.core.types import Frame

MAX_MAPS = 1024
MAX_DEVICES_PER_MAP = 64


@dataclass(frozen=True, slots=True)
class DevicePose:
    """A device's last accepted frame: its camera (OpenCV axes: x right, y down, z forward) and when it came."""

    device_id: str
    frame_id: str
    cam2world: tuple[float, ...]  # 16 numbers, row-major 4x4: camera points to world points
    intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy in pixels
    width: int
    height: int
    received_at_s: float  # this process's wall clock (Unix seconds)


class RecentDevices:
    """Map id -> device id -> ``DevicePose``, bounded (see the module docstring). Thread-safe."""

    def __init__(
        self, max_maps: int = MAX_MAPS, max_devices: int = MAX_DEVICES_PER_MAP, clock: Callable[[], float] = time.time
    ) -> None:
        self.max_maps = max_maps
        self.max_devices = max_devices
        self.clock = clock
        self._lock = threading.Lock()
        self._maps: OrderedDict[str, OrderedDict[str, DevicePose]] = OrderedDict()

    def record(self, frame: Frame) -> DevicePose:
        """Remember ``frame``'s pose as its device's last."""
        height, width = frame.shape
        i = frame.intrinsics
        pose = DevicePose(
            frame.device_id,
            frame.frame_id,
            tuple(float(v) for v in frame.cam2world.reshape(16)),
            (float(i.fx), float(i.fy), float(i.cx), float(i.cy)),
            int(width),
            int(height),
            self.clock(),
        )
        with self._lock:
            devices = self._maps.setdefault(frame.map_id, OrderedDict())
            self._maps.move_to_end(frame.map_id)
            devices[frame.device_id] = pose
            devices.move_to_end(frame.device_id)
            while len(devices) > self.max_devices:
                devices.popitem(last=False)
            while len(self._maps) > self.max_maps:
                self._maps.popitem(last=False)
        return pose

    def of_map(self, map_id: str, *, within_s: float) -> list[DevicePose]:
        """The map's devices heard from in the last ``within_s`` seconds, by device id."""
        since = self.clock() - within_s
        with self._lock:
            devices = list(self._maps.get(map_id, {}).values())
        return sorted((d for d in devices if d.received_at_s >= since), key=lambda d: d.device_id)

    def forget_map(self, map_id: str) -> None:
        with self._lock:
            self._maps.pop(map_id, None)


__all__ = ["DevicePose", "RecentDevices"]
