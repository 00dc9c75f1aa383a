"""Time the per-frame step without detection: 640x480 frames, 10 detections, 20 visible objects.

The scene: 20 rectangular surfaces at 1.5-4 m in front of a wall, each an object of the map (built by a
few warm-up frames that detect all 20). Each timed frame moves the camera a little and detects 10 of
the 20 (the other 10 are visible but undetected), so the step voxelizes 10 masks, finds 20 objects in
its frustum, locks, associates, fuses, refines and writes to the embedded store. Pinned to one core.
In the same run, on the same frames and core: Open3D's VoxelBlockGrid TSDF integration at the same voxel
size (``tsdf``) and the real model's session (``detector``; skipped without ../shared).

    .venv/bin/python bench/bench_step.py [--repeats 200] [--out bench/results/step.json]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import environment, pin_to_one_core, summary_ms, time_calls, write_json

from arcloud.core.checks import make_frame
from arcloud.core.step import integrate_frame
from arcloud.core.types import CLASSES, Detection, Frame, Params
from arcloud.stores.memory import MemoryStore

HEIGHT, WIDTH = 480, 640
INTRINSICS = (525.0, 525.0, 319.5, 239.5)


def make_scene(rng: np.random.Generator) -> tuple[np.ndarray, list[np.ndarray], list[str]]:
    """Depth (H, W) of a wall with 20 patches in a 5x4 grid, their masks and labels."""
    depth = np.full((HEIGHT, WIDTH), 4.5, np.float32)
    masks, labels = [], []
    for row in range(4):
        for col in range(5):
            r0, c0 = 20 + row * 115, 15 + col * 125
            h, w = int(rng.integers(60, 100)), int(rng.integers(70, 110))
            mask = np.zeros((HEIGHT, WIDTH), bool)
            mask[r0 : r0 + h, c0 : c0 + w] = True
            # A slanted surface, so each object spans several voxel layers like real furniture.
            slope = np.linspace(0, 0.3, w, dtype=np.float32)
            depth[r0 : r0 + h, c0 : c0 + w] = float(rng.uniform(1.5, 4.0)) + slope
            masks.append(mask)
            labels.append(CLASSES[(row * 5 + col) % len(CLASSES)])
    return depth, masks, labels


def scene_steps(n: int) -> tuple[MemoryStore, Params, list[Frame], list[list[Detection]]]:
    """The scene's map built (all 20 objects, in the embedded store) and ``n`` frames to step, each with the 10
    detections it brings (the camera moved a little, the depth noisy, every random draw seeded)."""
    rng = np.random.default_rng(0)
    depth, masks, labels = make_scene(rng)
    rgb = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
    params, store = Params(), MemoryStore()

    def frame_at(i: int) -> Frame:
        pose = np.eye(4)
        pose[:3, 3] = rng.normal(0, 0.01, 3)
        noisy = depth + rng.normal(0, 0.005, depth.shape).astype(np.float32)
        return make_frame(rgb, noisy, INTRINSICS, pose, timestamp_s=i / 30, map_id="bench", device_id="d", frame_id=f"f{i}")

    for i in range(3):  # build the map: all 20 objects
        integrate_frame(frame_at(i), [Detection(label, 0.9, m) for label, m in zip(labels, masks)], store, params)
    assert len(store.list_objects("bench")) == 20, len(store.list_objects("bench"))
    frames = [frame_at(10 + i) for i in range(n)]
    subsets = [rng.choice(20, 10, replace=False) for _ in frames]
    return store, params, frames, [[Detection(labels[j], 0.8, masks[j]) for j in subset] for subset in subsets]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path("bench/results/step.json"))
    args = parser.parse_args()
    from arcloud.allocator import keep_freed_memory

    keep_freed_memory()  # as the CLI's commands and the worker processes do
    core = pin_to_one_core()
    store, params, frames, detections = scene_steps(args.warmup + args.repeats)
    stages: dict[str, list[float]] = {}
    visible: list[int] = []

    def step(i: int) -> None:
        result = integrate_frame(frames[i], detections[i], store, params)
        visible.append(result.n_visible)
        for name, seconds in result.timings_s.items():
            stages.setdefault(name, []).append(seconds)

    times = time_calls(step, warmup=args.warmup, repeats=args.repeats)
    stage_ms = {name: round(float(np.median(v[args.warmup :])) * 1000, 3) for name, v in stages.items()}
    tsdf = time_tsdf(frames, params.voxel_size_m, warmup=args.warmup, repeats=args.repeats)
    detector = time_detector(frames, warmup=min(args.warmup, 5), repeats=min(args.repeats, 30))
    payload = {
        "benchmark": "per-frame step without detection (embedded store)",
        "frame": f"{WIDTH}x{HEIGHT}",
        "detections": 10,
        "visible_objects_median": int(np.median(visible)),
        "objects_in_map": len(store.list_objects("bench")),
        "pinned_core": core,
        "step": summary_ms(times),
        "stages_median_ms": stage_ms,
        "target_median_ms": 15.0,
        "tsdf": tsdf,
        "detector": detector,
        "step_over_tsdf": round(summary_ms(times)["median_ms"] / tsdf["median_ms"], 3),
        "step_over_detector": None if detector is None else round(summary_ms(times)["median_ms"] / detector["median_ms"], 4),
        **environment(),
    }
    write_json(args.out, payload)
    print(
        f"step median {payload['step']['median_ms']:.2f} ms (p10 {payload['step']['p10_ms']:.2f}, "
        f"p90 {payload['step']['p90_ms']:.2f}); stages {stage_ms}; TSDF {tsdf['median_ms']:.2f} ms "
        f"(step x{payload['step_over_tsdf']}); detector session "
        + ("n/a" if detector is None else f"{detector['median_ms']:.1f} ms (step x{payload['step_over_detector']})")
    )


def time_tsdf(frames: list, voxel_size_m: float, *, warmup: int, repeats: int) -> dict[str, float]:
    """Open3D's VoxelBlockGrid TSDF integration (what a user would run to map a room densely) of the same
    frames at the same voxel size, on the same pinned core: median and spread of one frame."""
    from bench_memory import DenseReconstruction

    dense = DenseReconstruction(voxel_size_m, depth_max_m=Params().depth_max_m)
    return summary_ms(time_calls(lambda i: dense.integrate(frames[i]), warmup=warmup, repeats=repeats))


def time_detector(frames: list, *, warmup: int, repeats: int) -> dict[str, float] | None:
    """The real YOLOv8n-seg session (``session.run`` only) on the same frames' colour, one thread on the
    pinned core; None when the model is not in ../shared."""
    model = Path(__file__).resolve().parents[1].parent / "shared/models/yolov8n-seg-fp32-640.onnx"
    if not model.is_file():
        return None
    from arcloud.detectors.onnx_yolo import Letterbox, YoloSegDetector, letterbox_tensor

    detector = YoloSegDetector(model, intra_op_threads=1)
    session = detector._session  # the bare session: the step's cost is compared with the model's
    outputs = [o.name for o in session.get_outputs()]
    tensors = [
        letterbox_tensor(f.rgb, Letterbox.fit(f.rgb.shape[:2], detector.input_size_px)) for f in frames[: warmup + repeats]
    ]
    return summary_ms(
        time_calls(lambda i: session.run(outputs, {detector.input_name: tensors[i]}), warmup=warmup, repeats=repeats)
    )


if __name__ == "__main__":
    main()
