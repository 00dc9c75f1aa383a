"""Frames of a dataset read on demand, so that long sequences need not fit in memory, what the readers'
sequences share (``FrameSequence``, ``GravityAlignedSequence``), and the colour camera of an unregistered
RGB-D pair."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from arcloud.core.types import Frame, Intrinsics

if TYPE_CHECKING:
    from arcloud.datasets.gt_boxes import GroundTruthBoxes

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


class FrameSequence:
    """What every reader's sequence shares (a mixin of its dataclass): ``frame_names`` in order, each read by
    ``load_frame``."""

    frame_names: tuple[str, ...]

    def load_frame(self, name: str, *, device_id: str | None = None) -> Frame:
        raise NotImplementedError

    @cached_property
    def _index(self) -> dict[str, int]:
        return {name: i for i, name in enumerate(self.frame_names)}

    @property
    def n_frames(self) -> int:
        return len(self.frame_names)

    def frames(self, *, stride: int = 1, limit: int | None = None) -> Iterator[Frame]:
        """Every ``stride``-th frame, in order, at most ``limit``."""
        for name in self.frame_names[:: max(1, int(stride))][:limit]:
            yield self.load_frame(name)


class GravityAlignedSequence(FrameSequence):
    """A sequence whose poses may be turned into a gravity-aligned world (7-Scenes, TUM): ``up_file`` (3,) unit
    up in the file's world (None: unknown), ``world2file`` (4, 4) output world to file world, and the
    ground truth (None without)."""

    up_file: np.ndarray | None
    world2file: np.ndarray
    ground_truth: GroundTruthBoxes | None

    @property
    def up(self) -> tuple[float, float, float]:
        """Up in the output world, for ``Params.up`` (+z once gravity-aligned; +z when unknown)."""
        if self.up_file is None:
            return (0.0, 0.0, 1.0)
        up = self.world2file[:3, :3].T @ self.up_file
        x, y, z = up / np.linalg.norm(up)
        return float(x), float(y), float(z)

    @property
    def world2gt(self) -> np.ndarray | None:
        """(4, 4) maps output-world points to the ground truth's aligned frame (None without ground truth)."""
        if self.ground_truth is None:
            return None
        return self.ground_truth.file2aligned @ self.world2file


@dataclass(frozen=True, eq=False)
class ColourCamera:
    """The colour camera of an unregistered RGB-D pair: its intrinsics (at the depth image's size) and
    ``depth2rgb`` (4, 4), depth camera coordinates to colour camera coordinates (see ``core.types.Frame``)."""

    intrinsics: Intrinsics
    depth2rgb: np.ndarray
