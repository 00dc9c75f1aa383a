"""Time the ONNX YOLO-seg detector on real 7-Scenes frames: session.run against our pre/post-processing.

For each model (640 fp32 and 320 int8 from ../shared/models), ``detect(frame)`` runs on real
redkitchen frames (640x480), cycling through them: warm-up calls first, then ``--repeats`` timed calls.
The detector's own split (``last_timing``: letterbox + tensor, ``session.run``, decode + NMS + masks) is
recorded per call; the JSON holds median, p10 and p90 of each, the detections per frame, the share of
pre+post-processing in session time (target: <= 15%), versions and machine. onnxruntime uses
``--threads`` intra-op threads (default: its own choice, one per core); nothing is pinned.

    .venv/bin/python bench/bench_detector.py [--repeats 40] [--out bench/results/detector.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import SHARED, environment, summary_ms, write_json

from arcloud.detectors.onnx_yolo import YoloSegDetector

MODELS = {
    "yolov8n-seg-fp32-640": SHARED / "models/yolov8n-seg-fp32-640.onnx",
    "yolov8n-seg-int8-320": SHARED / "models/yolov8n-seg-int8-320.onnx",
}
FRAMES_DIR = SHARED / "data/7scenes-redkitchen"
TARGET_PRE_POST_FRACTION = 0.15


def read_frames(indices: list[int]) -> list[np.ndarray]:
    """RGB (480, 640, 3) uint8 images of the given 7-Scenes frames."""
    images = []
    for index in indices:
        path = FRAMES_DIR / f"frame-{index:06d}.color.jpg"
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SystemExit(f"cannot read {path}: the real data must be in {SHARED} (see its README)")
        images.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return images


def bench_model(path: Path, images: list[np.ndarray], *, warmup: int, repeats: int, threads: int | None) -> dict[str, object]:
    detector = YoloSegDetector(path, intra_op_threads=threads)
    for i in range(warmup):
        detector.detect_image(images[i % len(images)])
    parts: dict[str, list[float]] = {"preprocess_s": [], "session_s": [], "postprocess_s": [], "total_s": []}
    n_detections = []
    for i in range(repeats):
        started = time.perf_counter()
        detections = detector.detect_image(images[i % len(images)])
        parts["total_s"].append(time.perf_counter() - started)
        for key, value in detector.last_timing.items():
            parts[key].append(value)
        n_detections.append(len(detections))
    pre_post = [a + b for a, b in zip(parts["preprocess_s"], parts["postprocess_s"])]
    fraction = statistics.median(pre_post) / statistics.median(parts["session_s"])
    return {
        "model": str(path.relative_to(SHARED)) if path.is_relative_to(SHARED) else str(path),
        "input_size_px": detector.input_size_px,
        "preprocess": summary_ms(parts["preprocess_s"]),
        "session": summary_ms(parts["session_s"]),
        "postprocess": summary_ms(parts["postprocess_s"]),
        "pre_plus_post": summary_ms(pre_post),
        "total": summary_ms(parts["total_s"]),
        "pre_post_fraction_of_session": round(fraction, 4),
        "meets_target": fraction <= TARGET_PRE_POST_FRACTION,
        "detections_per_frame": {"mean": round(float(np.mean(n_detections)), 2), "max": int(np.max(n_detections))},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=40, help="timed calls per model (>= 20)")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--frames", default="0,100,200,300,400,500,600,700,800,900", help="7-Scenes frame indices")
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: its own)")
    parser.add_argument("--models", default=",".join(MODELS), help=f"comma-separated, of: {', '.join(MODELS)}")
    parser.add_argument("--out", type=Path, default=Path("bench/results/detector.json"))
    args = parser.parse_args()
    from arcloud.allocator import keep_freed_memory

    keep_freed_memory()  # as the CLI's commands and the worker processes do
    if args.repeats < 20:
        parser.error("--repeats must be >= 20 for a median and spread worth reporting")
    indices = [int(i) for i in args.frames.split(",")]
    images = read_frames(indices)
    results = {}
    for name in args.models.split(","):
        if name not in MODELS:
            parser.error(f"--models: expected names from {', '.join(MODELS)}, got {name!r}")
        if not MODELS[name].is_file():
            raise SystemExit(f"model {MODELS[name]} not found: the real models must be in {SHARED / 'models'}")
        results[name] = bench_model(MODELS[name], images, warmup=args.warmup, repeats=args.repeats, threads=args.threads)
        r = results[name]
        print(
            f"{name}: session {r['session']['median_ms']:.1f} ms (p10 {r['session']['p10_ms']:.1f}, "
            f"p90 {r['session']['p90_ms']:.1f}); pre {r['preprocess']['median_ms']:.2f} ms, "
            f"post {r['postprocess']['median_ms']:.2f} ms; pre+post = "
            f"{100 * r['pre_post_fraction_of_session']:.1f}% of session (target <= {100 * TARGET_PRE_POST_FRACTION:.0f}%)"
        )
    payload = {
        "benchmark": "detector",
        "description": __doc__.splitlines()[0],
        "frames": {"dataset": "7scenes-redkitchen", "indices": indices, "shape": list(images[0].shape)},
        "warmup": args.warmup,
        "repeats": args.repeats,
        "intra_op_threads": args.threads,
        "target_pre_post_fraction_of_session": TARGET_PRE_POST_FRACTION,
        "results": results,
        **environment(("arcloud", "numpy", "onnxruntime", "opencv-python-headless")),
    }
    write_json(args.out, payload)


if __name__ == "__main__":
    main()
