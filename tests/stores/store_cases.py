"""Objects, frames, snapshot files and thread runners shared by the store tests (and by the child processes they start,
and the chaos tests)."""

from __future__ import annotations

import io
import json
import threading
import zipfile

import numpy as np

from arcloud.core.checks import make_frame
from arcloud.core.header import MapHeader
from arcloud.core.step import integrate_frame
from arcloud.core.types import AABB, N_CLASSES, OBB, Detection, MapObject, Params
from arcloud.core.voxels import keys_bounds, pack_keys
from arcloud.stores import codec
from arcloud.stores.cells import MAX_OBJECT_CELLS
from arcloud.stores.snapshot import FORMAT

VOXEL_M = 0.05
MAP = "map-a"
EDGE = round(MAX_OBJECT_CELLS ** (1 / 3))  # index cells along each axis of an object at the limit: 16


class Clock:
    """Unix seconds that tests move on by hand (the stores' and queues' ``clock``)."""

    def __init__(self, now_s: float = 1_700_000_000.0) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        return self.now_s


def make_object(
    object_id: int, lo_m: tuple[float, float, float], size_m: float = 0.3, *, version: int = 1, seed: int = 0
) -> MapObject:
    """An object filling a cube of voxels from ``lo_m``, with random weights and votes and every derived field set."""
    rng = np.random.default_rng(seed)
    n = max(1, round(size_m / VOXEL_M))
    start = np.floor(np.asarray(lo_m) / VOXEL_M).astype(np.int64)
    grid = np.stack(np.meshgrid(*(np.arange(s, s + n) for s in start), indexing="ij"), axis=-1).reshape(-1, 3)
    keys = np.sort(pack_keys(grid))
    votes = np.zeros((keys.size, N_CLASSES), np.float32)
    votes[:, 0] = rng.random(keys.size, np.float32)
    votes[:, 2] = rng.random(keys.size, np.float32) * 0.1
    b_lo, b_hi = keys_bounds(keys, VOXEL_M)
    yaw = float(rng.uniform(-np.pi, np.pi))
    rotation = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    return MapObject(
        id=object_id,
        keys=keys,
        weights=rng.random(keys.size, np.float32) * 5,
        votes=votes,
        seen=rng.random(keys.size, np.float32) * 5 + 5,
        n_frames=int(rng.integers(1, 50)),
        devices=frozenset({"dev-1", f"dev-{seed}"}),
        score_sum=float(rng.random() * 10),
        version=version,
        created_at_s=1_700_000_000.123456,
        updated_at_s=1_700_000_123.654321 + seed,
        label="chair",
        score=float(rng.random()),
        aabb=AABB(b_lo + 0.05, b_hi - 0.05),
        obb=OBB(center=(b_lo + b_hi) / 2, size=b_hi - b_lo, rotation=rotation, yaw_rad=yaw),
        bounds=AABB(b_lo, b_hi),
        colors=rng.integers(0, 256, (keys.size, 3), dtype=np.uint8),  # drawn last: the other fields stay as they were
    )


def assert_same_object(got: MapObject, want: MapObject) -> None:
    np.testing.assert_array_equal(got.keys, want.keys)
    np.testing.assert_array_equal(got.weights, want.weights)
    np.testing.assert_array_equal(got.votes, want.votes)
    np.testing.assert_array_equal(got.seen_counts, want.seen_counts)
    assert got.keys.dtype == np.int64 and got.weights.dtype == np.float32 and got.votes.dtype == np.float32
    assert (got.colors is None) == (want.colors is None)
    if want.colors is not None:
        np.testing.assert_array_equal(got.colors, want.colors)
        assert got.colors.dtype == np.uint8
    for name in ("id", "n_frames", "devices", "score_sum", "version", "created_at_s", "updated_at_s", "label", "score"):
        assert getattr(got, name) == getattr(want, name), name
    for name in ("aabb", "bounds"):
        np.testing.assert_array_equal(getattr(got, name).min, getattr(want, name).min)
        np.testing.assert_array_equal(getattr(got, name).max, getattr(want, name).max)
    for name in ("center", "size", "rotation", "yaw_rad"):
        np.testing.assert_array_equal(getattr(got.obb, name), getattr(want.obb, name))


def moved(obj: MapObject, lo_m: tuple[float, float, float], seed: int = 7) -> MapObject:
    """The object rebuilt at another place, one version later."""
    return make_object(obj.id, lo_m, version=obj.version + 1, seed=seed)


H, W = 120, 160
INTRINSICS = (130.0, 130.0, 80.0, 60.0)


CHAIR_RGB, TABLE_RGB = (200, 60, 40), (40, 90, 210)


def step_frame(device: int, index: int) -> tuple:
    """A frame of a wall at 3 m with a chair-plane at 2 m and a table-plane at 2.5 m (coloured
    ``CHAIR_RGB`` and ``TABLE_RGB``), from a slightly moved camera, and the two rectangular detections."""
    depth = np.full((H, W), 3.0, np.float32)
    depth[25:75, 25:75] = 2.0
    depth[50:100, 100:150] = 2.5
    chair = np.zeros((H, W), bool)
    chair[25:75, 25:75] = True
    table = np.zeros((H, W), bool)
    table[50:100, 100:150] = True
    cam2world = np.eye(4)
    cam2world[0, 3] = 0.004 * index + 0.001 * device
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[chair] = CHAIR_RGB
    rgb[table] = TABLE_RGB
    frame = make_frame(
        rgb,
        depth,
        INTRINSICS,
        cam2world,
        timestamp_s=float(index),
        map_id=MAP,
        device_id=f"dev-{device}",
        frame_id=f"f{index}",
    )
    return frame, [Detection("chair", 0.9, chair), Detection("table", 0.8, table)]


def run_steps_in_threads(store, jobs_per_thread: list[list[tuple]], params: Params) -> None:
    """Each thread runs its frames through ``integrate_frame``; all start together. Fails on any error
    or on a thread still running after 45 s (a deadlock)."""
    barrier = threading.Barrier(len(jobs_per_thread))
    errors: list[BaseException] = []

    def work(jobs: list[tuple]) -> None:
        try:
            barrier.wait(timeout=10)
            for frame, detections in jobs:
                integrate_frame(frame, detections, store, params)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(jobs,)) for jobs in jobs_per_thread]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=45)
    assert not any(t.is_alive() for t in threads), "deadlock: a step did not finish"
    assert errors == []


def spread_object(object_id: int, lo_m: tuple[float, float, float], cells_per_axis: int, *, version: int = 1) -> MapObject:
    """An object of two voxels at opposite corners of a box touching ``cells_per_axis`` ** 3 index cells of 1 m
    (``lo_m`` on a cell's corner): as small as an object gets in bytes, as large as it gets in index cells."""
    base = make_object(object_id, lo_m, version=version, seed=object_id)
    first = np.floor(np.asarray(lo_m) / VOXEL_M).astype(np.int64)
    last = first + round(cells_per_axis / VOXEL_M) - 2  # its upper corner a voxel short of the last cell's end
    keys_ = np.sort(pack_keys(np.stack([first, last])))
    lo, hi = keys_bounds(keys_, VOXEL_M)
    return base.replace(
        keys=keys_,
        weights=base.weights[:2],
        votes=base.votes[:2],
        seen=base.seen[:2],
        colors=base.colors[:2] if base.colors is not None else None,
        bounds=AABB(lo, hi),
        aabb=AABB(lo, hi),
        obb=OBB(center=(lo + hi) / 2, size=hi - lo, rotation=np.eye(3), yaw_rad=0.0),
    )


def snapshot_of(objects: list[MapObject]) -> bytes:
    """A snapshot file holding ``objects`` as they are (a store would refuse some of them: a crafted file)."""
    archive = io.BytesIO()
    header = MapHeader.from_params(Params(), codec_version=codec.FORMAT_VERSION, created_at_s=1.0)
    with zipfile.ZipFile(archive, "w") as out:
        document = {"format": FORMAT, "map_id": MAP, "header": header.to_record(), "objects": len(objects)}
        out.writestr("snapshot.json", json.dumps(document))
        for obj in objects:
            out.writestr(f"objects/{obj.id}.meta", codec.encode_meta(obj))
            out.writestr(
                f"objects/{obj.id}.voxels",
                codec.encode_voxels(obj.keys, obj.weights, obj.votes, seen=obj.seen, colors=obj.colors),
            )
    return archive.getvalue()
