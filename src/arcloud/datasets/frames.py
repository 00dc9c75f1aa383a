"""Frames of a dataset read on demand, so that long sequences need not fit in memory, and the colour camera
of an unregistered RGB-D pair."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from arcloud.core.types import Frame, Intrinsics

#: Frames kept in memory when a sequence has at most this many (about 2.2 MB each at 640x480).
CACHE_FRAMES_UP_TO = 1500


class LazyFrames(Sequence[Frame]):
    """Frames of a dataset by index, read on first access (and kept when ``cache``). Thread-safe."""

    def __init__(self, names: Sequence[str], load: Callable[[str], Frame], *, cache: bool) -> None:
        self.names = tuple(names)
        self._load = load
        self._cache: dict[int, Frame] | None = {} if cache else None
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: int) -> Frame:  # type: ignore[override]  # Sequence's slice overload: refused below
        if isinstance(index, slice):
            raise TypeError("LazyFrames does not slice; pick names and build another")
        if self._cache is None:
            return self._load(self.names[index])
        with self._lock:
            frame = self._cache.get(index)
        if frame is None:
            frame = self._load(self.names[index])
            with self._lock:
                self._cache[index] = frame
        return frame

    def __iter__(self) -> Iterator[Frame]:
        return (self[i] for i in range(len(self)))


@dataclass(frozen=True, eq=False)
class ColourCamera:
    """The colour camera of an unregistered RGB-D pair: its intrinsics (at the depth image's size) and
    ``depth2rgb`` (4, 4), depth camera coordinates to colour camera coordinates (see ``core.types.Frame``)."""

    intrinsics: Intrinsics
    depth2rgb: np.ndarray
