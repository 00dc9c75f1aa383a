"""The paper's multi-user protocol: one map built from a sequence by one ordered user (centralized) or by
K users fed concurrently (distributed), and Table 1 (mean and variance of mAP over Monte-Carlo runs).

Distributed run: the trajectory is cut into K contiguous segments, one per user; the segments are
shuffled; the users stream concurrently (a seeded random interleaving of their frames, each user's frames
in order) into a pool of worker threads that share one store. Only the order and the device ids change
between runs: a frame's detections depend on its frame id alone, so they are computed once and replayed.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

import numpy as np

from arcloud.core.step import integrate_frame
from arcloud.core.types import Detection, Frame, LabelledBox, MapObject, Params
from arcloud.eval.metrics import evaluate, variance
from arcloud.ports import Detector, ObjectStore

Progress = Callable[[int], None]


class StoreFactory(Protocol):
    """Makes the empty store of one run (``arcloud.stores.memory.MemoryStore`` is one): the caller picks
    the adapter, the protocol only talks to the port."""

    def __call__(self, *, cell_m: float) -> ObjectStore: ...


class CachedDetector:
    """Runs a detector once per frame id and replays its detections (thread-safe)."""

    def __init__(self, detector: Detector) -> None:
        self.detector = detector
        self._cache: dict[str, list[Detection]] = {}
        self._lock = threading.Lock()

    def detect(self, frame: Frame) -> list[Detection]:
        with self._lock:
            cached = self._cache.get(frame.frame_id)
        if cached is None:
            cached = self.detector.detect(frame)
            with self._lock:
                self._cache[frame.frame_id] = cached
        return cached


def user_streams(n_frames: int, users: int, rng: np.random.Generator) -> list[list[int]]:
    """Frame indices per user: ``users`` contiguous segments of nearly equal length, shuffled."""
    if not 1 <= users <= n_frames:
        raise ValueError(f"users must be in 1..{n_frames} (the number of frames), got {users}")
    segments = [list(part) for part in np.array_split(np.arange(n_frames), users)]
    order = rng.permutation(users)
    return [segments[i] for i in order]


def interleave(streams: Sequence[Sequence[int]], rng: np.random.Generator) -> list[tuple[int, int]]:
    """A random arrival order of (user, frame index) pairs that keeps each user's frames in order:
    at each step the next frame comes from a user drawn with probability proportional to what it has left."""
    remaining = np.array([len(s) for s in streams], np.float64)
    cursor = [0] * len(streams)
    arrivals = []
    while remaining.sum() > 0:
        user = int(rng.choice(len(streams), p=remaining / remaining.sum()))
        arrivals.append((user, streams[user][cursor[user]]))
        cursor[user] += 1
        remaining[user] -= 1
    return arrivals


def run_map(
    frames: Sequence[Frame],
    detector: Detector,
    params: Params,
    *,
    new_store: StoreFactory,
    users: int = 1,
    seed: int = 0,
    workers: int = 1,
    map_id: str | None = None,
    progress: Progress | None = None,
) -> list[MapObject]:
    """Build a map from ``frames`` in a store from ``new_store(cell_m=params.index_cell_m)`` and return
    its objects.

    users == 1: the centralized run, frames in order on one worker (``workers`` is ignored).
    users > 1: the distributed run described in the module docstring, on ``workers`` threads."""
    store = new_store(cell_m=params.index_cell_m)
    map_id = map_id or f"run-{users}-{seed}"
    rng = np.random.default_rng(seed)
    if users == 1:
        arrivals = [(0, i) for i in range(len(frames))]
        workers = 1
    else:
        arrivals = interleave(user_streams(len(frames), users, rng), rng)

    def process(user: int, index: int) -> None:
        frame = dataclasses.replace(frames[index], map_id=map_id, device_id=f"user-{user:03d}")
        integrate_frame(frame, detector.detect(frame), store, params)
        if progress is not None:
            progress(1)

    if workers == 1:
        for user, index in arrivals:
            process(user, index)
    else:
        pending: queue.Queue[tuple[int, int]] = queue.Queue()
        for arrival in arrivals:
            pending.put(arrival)

        def work() -> None:
            while True:
                try:
                    user, index = pending.get_nowait()
                except queue.Empty:
                    return
                process(user, index)

        with ThreadPoolExecutor(max_workers=workers) as pool:
            for future in [pool.submit(work) for _ in range(workers)]:
                future.result()
    return store.list_objects(map_id)


def object_boxes(objects: Sequence[MapObject]) -> list[LabelledBox]:
    """The objects as scored axis-aligned boxes for evaluation."""
    return [LabelledBox.from_aabb(o.label, o.aabb, o.score) for o in objects if o.aabb is not None and o.label]


def table1(
    frames: Sequence[Frame],
    detector: Detector,
    ground_truth: Sequence[LabelledBox],
    params: Params,
    *,
    new_store: StoreFactory,
    users: Sequence[int] = (10, 50, 100),
    runs: int = 10,
    seed: int = 0,
    workers: int = 4,
    scene: str = "scene",
    progress: Progress | None = None,
    on_run: Callable[[str, int, int, list[MapObject]], None] | None = None,
) -> dict[str, object]:
    """The paper's Table 1 on one sequence: the centralized run (deterministic, so one run) and
    ``runs`` distributed runs for each K in ``users``, each in a store from ``new_store``; mean and
    variance (ddof=0) of mAP@0.25 / 0.5.

    ``on_run(approach, users, run, objects)`` sees every run's map (to export or draw it)."""
    cached = CachedDetector(detector)
    rows: list[dict[str, object]] = []
    plan = [("centralized", 1, 1)] + [("distributed", k, runs) for k in users]
    for approach, k, n_runs in plan:
        scores25, scores50 = [], []
        for run in range(n_runs):
            objects = run_map(
                frames,
                cached,
                params,
                new_store=new_store,
                users=k,
                seed=seed * 1000 + run,
                workers=workers,
                map_id=f"{scene}-{k}-{run}",
                progress=progress,
            )
            if on_run is not None:
                on_run(approach, k, run, objects)
            result = evaluate({scene: object_boxes(objects)}, {scene: list(ground_truth)})
            scores25.append(result.map_at(0.25))
            scores50.append(result.map_at(0.5))
        rows.append(
            {
                "approach": approach,
                "users": k,
                "runs": n_runs,
                "map25_mean": float(np.mean(scores25)),
                "map25_var": variance(scores25),
                "map50_mean": float(np.mean(scores50)),
                "map50_var": variance(scores50),
            }
        )
    return {"table1": rows}
