"""Memory of the object map against a dense reconstruction of the same frames (DESIGN.md, "Evaluation").

Frames: the real 7-Scenes redkitchen sequence (``../shared/data/7scenes-redkitchen``, 640x480; ``ARCLOUD_SHARED``
names another shared folder), read as ``arcloud eval 7scenes`` reads it (gravity-aligned world), every
``--stride``-th frame (default 1: all 1000), at most ``--frames``, in order. Each frame is read once and goes
both to the object map and to the dense reconstructions, so both see the same frames.

Object map: the centralized run, ``process_frame`` with the real YOLOv8n-seg (fp32, 640) on each frame, one after
another, into a ``RedisStore`` on a throwaway redis-server (default ``Params``: 5 cm voxels). Its size, two ways:
- codec payload: the bytes ``codec.encode_voxels`` and ``codec.encode_meta`` produce for every object (what
  the store writes for it; checked against ``HSTRLEN`` of the stored fields); the 48-byte bounds of the
  spatial index are listed apart;
- Redis: ``MEMORY USAGE key SAMPLES 0`` (exact, not sampled) summed over the map's keys (``arcloud.stores.keys``):
  the object hashes, the metadata and bounds hashes and the index's cell sets. The id counter and the
  processed-frames set are bookkeeping of the run, reported apart and not counted.

Dense reconstruction: a TSDF of the same depth and colour with the same intrinsics and poses (extrinsic =
world2cam, the inverse of the frame's cam2world: 7-Scenes poses are camera-to-world with OpenCV camera axes,
which Open3D's pinhole model uses too), depth cut at ``Params.depth_max_m``, at the pipeline's voxel size and
at 1 cm (``--dense-voxel-sizes``), sdf_trunc = 4 voxels, in blocks of 16^3 voxels. Open3D's
``ScalableTSDFVolume`` integrates nothing in the pinned Open3D 0.20.0 (any frame, even a flat wall, leaves it
empty), so its tensor successor ``t.geometry.VoxelBlockGrid`` holds the TSDF, and the mesh is extracted as
``ScalableTSDFVolume`` extracts it: marching cubes over the cubes whose corners were all observed
(weight > 0), vertex colours, no normals. Reported: vertices, triangles, the binary PLY file
``write_triangle_mesh`` writes (uncompressed: float64 xyz, uint8 RGB, int32 indices) and the mesh as
arrays (float32 xyz, uint8 RGB, int32 triangles).

Ratios: each mesh size over each object-map size. The map holds the objects of five classes only, the mesh
the whole room: that difference is what the comparison measures. Wall times of detection + step and of each
TSDF integration are recorded (single run, 2-core machine: context, not a timing benchmark).

    .venv/bin/python bench/bench_memory.py [--frames N] [--stride 1] [--out bench/results/memory.json]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import SHARED, Redis, environment, write_json

from arcloud.argtypes import positive_int
from arcloud.core.types import Frame, MapObject, Params
from arcloud.ports import Detector, ObjectStore
from arcloud.stores import codec, keys

if TYPE_CHECKING:
    import redis

    from arcloud.datasets.sevenscenes import SevenScenesSequence

SEQUENCE_DIR = SHARED / "data/7scenes-redkitchen"
MODEL = SHARED / "models/yolov8n-seg-fp32-640.onnx"
DENSE_VOXEL_SIZE_M = 0.01  # a typical dense-mesh voxel, besides the pipeline's own
SDF_TRUNC_VOXELS = 4.0
MESH_MIN_WEIGHT = 0.0  # a cube is meshed when all its corners were observed, as ScalableTSDFVolume does
BLOCK_RESOLUTION = 16  # voxels per block side, as ScalableTSDFVolume's volume units
INITIAL_BLOCKS = 10_000  # the grid's hash map grows past this


def missing_inputs() -> str | None:
    """Why the benchmark cannot run here, or None."""
    if not (SEQUENCE_DIR / "camera-intrinsics.txt").is_file():
        return f"7-Scenes redkitchen not found in {SEQUENCE_DIR} (set ARCLOUD_SHARED to the shared folder)"
    if not MODEL.is_file():
        return f"model {MODEL} not found (set ARCLOUD_SHARED to the shared folder)"
    if shutil.which("redis-server") is None:
        return "redis-server not found on PATH"
    return None


class DenseReconstruction:
    """A TSDF voxel-block grid (Open3D ``t.geometry.VoxelBlockGrid``: tsdf, weight, RGB) fed arcloud frames;
    records its integration time."""

    def __init__(self, voxel_size_m: float, depth_max_m: float) -> None:
        import open3d as o3d
        import open3d.core as o3c

        self.o3d, self.o3c = o3d, o3c
        self.voxel_size_m = voxel_size_m
        self.depth_max_m = depth_max_m
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=(1, 1, 3), voxel_size=voxel_size_m, block_resolution=BLOCK_RESOLUTION,
            block_count=INITIAL_BLOCKS, device=o3c.Device("CPU:0"),
        )  # fmt: skip
        self.integrate_s = 0.0

    def integrate(self, frame: Frame) -> None:
        """Integrate one frame: depth in metres, colour in [0, 1], extrinsic = world2cam."""
        o3d, o3c = self.o3d, self.o3c
        started = time.perf_counter()
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(frame.depth_m, np.float32)))
        colour = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(frame.rgb, np.float32) / 255.0))
        intrinsic = o3c.Tensor(frame.intrinsics.matrix(), o3c.float64)
        world2cam = o3c.Tensor(np.linalg.inv(frame.cam2world), o3c.float64)
        blocks = self.grid.compute_unique_block_coordinates(depth, intrinsic, world2cam, 1.0, self.depth_max_m, SDF_TRUNC_VOXELS)
        self.grid.integrate(blocks, depth, colour, intrinsic, intrinsic, world2cam, 1.0, self.depth_max_m, SDF_TRUNC_VOXELS)
        self.integrate_s += time.perf_counter() - started

    def mesh_figures(self, folder: Path) -> dict[str, Any]:
        """Extract the mesh as ``ScalableTSDFVolume`` does (marching cubes over cubes whose corners were all
        observed; vertex colours, no normals); its counts, binary PLY bytes and array bytes."""
        started = time.perf_counter()
        mesh = self.grid.extract_triangle_mesh(weight_threshold=MESH_MIN_WEIGHT).to_legacy()
        extract_s = time.perf_counter() - started
        mesh.vertex_normals = self.o3d.utility.Vector3dVector()  # ScalableTSDFVolume's mesh has none
        if mesh.has_vertex_colors():  # averaged colours overshoot 1 by float rounding; PLY stores uint8
            mesh.vertex_colors = self.o3d.utility.Vector3dVector(np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0))
        n_vertices, n_triangles = len(mesh.vertices), len(mesh.triangles)
        ply_bytes = None  # Open3D writes no PLY for an empty mesh (too few frames)
        if n_vertices:
            ply = folder / f"tsdf_{self.voxel_size_m * 1000:g}mm.ply"
            if not self.o3d.io.write_triangle_mesh(str(ply), mesh, write_ascii=False, compressed=False):
                raise RuntimeError(f"Open3D could not write {ply} ({n_vertices} vertices)")
            ply_bytes = ply.stat().st_size
        array_bytes = {
            "vertices_float32": n_vertices * 3 * 4,
            "colours_uint8": n_vertices * 3 if mesh.has_vertex_colors() else 0,
            "triangles_int32": n_triangles * 3 * 4,
        }
        return {
            "voxel_size_m": self.voxel_size_m,
            "sdf_trunc_m": round(SDF_TRUNC_VOXELS * self.voxel_size_m, 6),
            "depth_trunc_m": self.depth_max_m,
            "tsdf_blocks": int(self.grid.hashmap().size()),
            "vertices": n_vertices,
            "triangles": n_triangles,
            "has_colours": mesh.has_vertex_colors(),
            "ply_bytes": ply_bytes,
            "array_bytes": sum(array_bytes.values()),
            "array_bytes_by_part": array_bytes,
            "integrate_s": round(self.integrate_s, 2),
            "extract_s": round(extract_s, 2),
        }


def codec_figures(objects: list[MapObject]) -> dict[str, int]:
    """Bytes the store's codec writes for the objects: voxel blobs, metadata JSON, bounds."""
    voxels = [len(codec.encode_voxels(o.keys, o.weights, o.votes, seen=o.seen, colors=o.colors)) for o in objects]
    meta = [len(codec.encode_meta(o)) for o in objects]
    bounds = [len(codec.pack_box(o.bounds)) for o in objects if o.bounds is not None]
    return {
        "voxels_bytes": sum(voxels),
        "meta_bytes": sum(meta),
        "payload_bytes": sum(voxels) + sum(meta),
        "bounds_bytes": sum(bounds),
    }


def redis_figures(client: redis.Redis, map_id: str, object_ids: list[int]) -> dict[str, Any]:
    """``MEMORY USAGE`` (exact) of the map's keys by kind, and the stored payload (``HSTRLEN``)."""
    prefix = keys.map_prefix(map_id) + ":"
    names = sorted(k.decode() for k in client.scan_iter(match=keys.map_pattern(map_id), count=1000))
    with client.pipeline(transaction=False) as pipe:
        for name in names:
            pipe.memory_usage(name, samples=0)
        usage = pipe.execute()

    def kind(name: str) -> str:
        rest = name[len(prefix) :]
        if rest.startswith(keys.OBJECT + ":"):
            return "objects"
        if rest.startswith(keys.CELL + ":"):
            return "index_cells"
        bookkeeping = (keys.IDS, keys.PROCESSED, f"{keys.PROCESSED}:count")
        return {keys.META: "meta", keys.BOUNDS: "bounds", **dict.fromkeys(bookkeeping, "bookkeeping")}.get(rest, "other")

    by_kind: Counter[str] = Counter()
    key_counts: Counter[str] = Counter()
    for name, used in zip(names, usage):
        by_kind[kind(name)] += int(used or 0)
        key_counts[kind(name)] += 1
    with client.pipeline(transaction=False) as pipe:
        for object_id in object_ids:
            pipe.hstrlen(keys.object_key(map_id, object_id), "voxels")
            pipe.hstrlen(keys.meta_key(map_id), str(object_id))
        stored = pipe.execute()
    map_kinds = ("objects", "meta", "bounds", "index_cells")
    return {
        "object_map_bytes": sum(by_kind[k] for k in map_kinds),
        "bytes_by_kind": {k: by_kind[k] for k in (*map_kinds, "bookkeeping", "other")},
        "keys_by_kind": {k: key_counts[k] for k in (*map_kinds, "bookkeeping", "other")},
        "stored_payload_bytes": sum(stored),
        "used_memory_bytes": int(client.info("memory")["used_memory"]),
    }


def run_frames(
    sequence: SevenScenesSequence,
    names: tuple[str, ...],
    detector: Detector,
    store: ObjectStore,
    params: Params,
    dense: list[DenseReconstruction],
) -> dict[str, float]:
    """Each frame, in order: ``process_frame`` into the store, then into every dense reconstruction.
    Returns the seconds spent in ``process_frame`` and, of those, in detection."""
    from tqdm import tqdm

    from arcloud.core.step import process_frame

    seconds = {"detect_and_step": 0.0, "detect": 0.0}
    for name in tqdm(names, unit="frame", leave=False, disable=not sys.stderr.isatty()):
        frame = sequence.load_frame(name)
        started = time.perf_counter()
        result = process_frame(frame, detector, store, params)
        seconds["detect_and_step"] += time.perf_counter() - started
        seconds["detect"] += result.timings_s.get("detect", 0.0)
        for reconstruction in dense:
            reconstruction.integrate(frame)
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--frames", type=positive_int, default=None, help="at most this many frames (after the stride; default all)"
    )
    parser.add_argument("--stride", type=positive_int, default=1, help="every S-th frame (default 1)")
    parser.add_argument(
        "--dense-voxel-sizes",
        type=float,
        nargs="+",
        default=None,
        help=f"TSDF voxel sizes in metres (default: the pipeline's and {DENSE_VOXEL_SIZE_M})",
    )
    parser.add_argument("--out", type=Path, default=Path("bench/results/memory.json"))
    args = parser.parse_args()
    from arcloud.allocator import keep_freed_memory

    keep_freed_memory()  # as the CLI's commands and the worker processes do
    reason = missing_inputs()
    if reason is not None:
        print(f"skipped: {reason}")
        return

    from arcloud.datasets.export import objects_json
    from arcloud.datasets.sevenscenes import load_seven_scenes
    from arcloud.detectors.factory import make_detector
    from arcloud.stores.redis import RedisStore

    started = time.perf_counter()
    params = Params()
    sequence = load_seven_scenes(SEQUENCE_DIR, align_gravity=True)  # as `arcloud eval 7scenes`
    names = sequence.frame_names[:: args.stride][: args.frames]
    detector = make_detector(f"onnx:{MODEL}")
    voxel_sizes = args.dense_voxel_sizes or [params.voxel_size_m, DENSE_VOXEL_SIZE_M]
    dense = [DenseReconstruction(size, params.depth_max_m) for size in voxel_sizes]

    server = Redis()
    try:
        store = RedisStore(server.url, cell_m=params.index_cell_m)
        map_id = sequence.name
        step_s = run_frames(sequence, names, detector, store, params, dense)
        objects = store.list_objects(map_id)
        n_voxels = sum(o.n_voxels for o in objects)
        payload = codec_figures(objects)
        in_redis = redis_figures(store.client, map_id, [o.id for o in objects])
        store.close()
        redis_version = server.version
    finally:
        server.stop()
    if in_redis["stored_payload_bytes"] != payload["payload_bytes"]:
        print(
            f"warning: Redis holds {in_redis['stored_payload_bytes']} payload bytes, the codec gives {payload['payload_bytes']}"
        )

    with tempfile.TemporaryDirectory(prefix="arcloud-bench-mesh-") as folder:
        meshes = [reconstruction.mesh_figures(Path(folder)) for reconstruction in dense]

    map_bytes = {"codec_payload": payload["payload_bytes"], "redis_memory_usage": in_redis["object_map_bytes"]}
    ratios = {
        f"{mesh['voxel_size_m'] * 100:g}cm": {
            f"{mesh_kind}_over_{map_kind}": round(mesh[f"{mesh_kind}_bytes"] / size, 2)
            if size and mesh[f"{mesh_kind}_bytes"]
            else None
            for mesh_kind in ("ply", "array")
            for map_kind, size in map_bytes.items()
        }
        for mesh in meshes
    }
    out = {
        "benchmark": "object map bytes against a dense TSDF mesh of the same frames",
        "setup": {
            "sequence": str(SEQUENCE_DIR.name),
            "frames": len(names),
            "stride": args.stride,
            "first_frame": names[0] if names else None,
            "last_frame": names[-1] if names else None,
            "detector": MODEL.name,
            "voxel_size_m": params.voxel_size_m,
            "index_cell_m": params.index_cell_m,
            "depth_max_m": params.depth_max_m,
            "dense_voxel_sizes_m": voxel_sizes,
            "sdf_trunc_voxels": SDF_TRUNC_VOXELS,
            "redis_version": redis_version,
        },
        "object_map": {
            "objects": len(objects),
            "labels": dict(Counter(o.label or "" for o in objects)),
            "voxels": n_voxels,
            "codec": payload,
            "redis": in_redis,
            "codec_voxels_bytes_per_voxel": round(payload["voxels_bytes"] / n_voxels, 3) if n_voxels else None,
            "codec_payload_bytes_per_voxel": round(payload["payload_bytes"] / n_voxels, 3) if n_voxels else None,
            "redis_bytes_per_voxel": round(in_redis["object_map_bytes"] / n_voxels, 3) if n_voxels else None,
            "boxes": objects_json(objects),
        },
        "tsdf_meshes": meshes,
        "ratios_mesh_over_map": ratios,
        "wall_s": {
            **{stage: round(seconds, 2) for stage, seconds in step_s.items()},
            "tsdf_integrate": {f"{d.voxel_size_m * 100:g}cm": round(d.integrate_s, 2) for d in dense},
            "total": round(time.perf_counter() - started, 2),
        },
        **environment(("arcloud", "numpy", "open3d", "onnxruntime", "redis")),
    }
    write_json(args.out, out)
    print(
        f"{len(names)} frames: {len(objects)} objects, {n_voxels} voxels; object map {payload['payload_bytes']} B codec payload "
        f"({out['object_map']['codec_payload_bytes_per_voxel']} B/voxel), {in_redis['object_map_bytes']} B in Redis "
        f"({out['object_map']['redis_bytes_per_voxel']} B/voxel)"
    )
    for mesh in meshes:
        label = f"{mesh['voxel_size_m'] * 100:g}cm"
        print(
            f"TSDF {label}: {mesh['vertices']} vertices, {mesh['triangles']} triangles, PLY {mesh['ply_bytes']} B, "
            f"arrays {mesh['array_bytes']} B; mesh/map {ratios[label]}"
        )
    print(f"wall {out['wall_s']}")


if __name__ == "__main__":
    main()
