"""Would batching the detector over queued frames raise frames per second? (issue 12, item 2)

The shipped YOLOv8n-seg export (``../shared/models/yolov8n-seg-fp32-640.onnx``) takes batch 1 only: its
input says ``[1, 3, 640, 640]`` and five reshapes of its head name batch 1 in their target shapes
(``/model.22/dfl/Reshape`` to ``[1, 4, 16, 8400]`` and the like). This benchmark makes a batch-capable
copy in a temporary folder (the input's and outputs' first dimension symbolic; those five shapes' first
entry 0, which ONNX Reshape reads as "the input's"; nothing else changed, checked by ``onnx.checker``),
checks that a batch gives each frame exactly the outputs it gets alone, then times ``session.run`` on
batches of real 7-Scenes frames (letterboxed as the detector does) for each ``--batches`` size, in
interleaved rounds (each round times every size once, so the machine's drift falls on all sizes alike),
with onnxruntime's own thread count and with one thread (as the service's one-thread workers run it).
Reported per size: frames/s (median over rounds) and its ratio to batch 1. Nothing is written into the
repository but ``--out``.

    .venv/bin/python bench/bench_batch.py [--batches 1,2,4,8] [--rounds 5] [--out bench/results/batch.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_detector import MODELS, SHARED, read_frames
from common import cores, environment, write_json

from arcloud.argtypes import positive_int
from arcloud.detectors.onnx_yolo import Letterbox, letterbox_tensor

MODEL = MODELS["yolov8n-seg-fp32-640"]
HEAD_PREFIX = "/model.22/"  # the detect/segment head, whose reshapes name the batch


def batch_capable_copy(source: Path, target: Path) -> int:
    """Write ``source`` with a symbolic batch dimension to ``target``; returns how many reshape shapes
    named batch 1 (now 0: copied from the input)."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(source))
    graph = model.graph
    shape_inputs = {node.input[1] for node in graph.node if node.op_type == "Reshape" and node.name.startswith(HEAD_PREFIX)}
    patched = 0
    for initializer in graph.initializer:
        if initializer.name in shape_inputs:
            shape = numpy_helper.to_array(initializer).copy()
            if shape.ndim == 1 and shape.size >= 3 and shape[0] == 1:
                shape[0] = 0
                initializer.CopyFrom(numpy_helper.from_array(shape, initializer.name))
                patched += 1
    for value in (*graph.input, *graph.output):
        value.type.tensor_type.shape.dim[0].dim_param = "batch"
    del graph.value_info[:]  # inferred shapes of batch 1; onnxruntime infers them again
    onnx.checker.check_model(model)
    onnx.save(model, str(target))
    return patched


def session(path: Path, threads: int | None) -> Any:
    import onnxruntime

    options = onnxruntime.SessionOptions()
    if threads is not None:
        options.intra_op_num_threads = threads
    return onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def check_exact(batched: Any, single: Any, tensors: np.ndarray) -> None:
    """A batch's outputs are, frame by frame, the outputs of the frame alone (bit for bit)."""
    together = batched.run(None, {"images": tensors})
    for i in range(tensors.shape[0]):
        alone = single.run(None, {"images": tensors[i : i + 1]})
        for name, a, b in zip(("output0", "output1"), together, alone):
            if not np.array_equal(a[i : i + 1], b):
                raise SystemExit(f"batched {name} of frame {i} differs from the frame alone: batching is not exact here")


def frames_per_s(run: Any, batch: np.ndarray) -> float:
    started = time.perf_counter()
    run.run(None, {"images": batch})
    return batch.shape[0] / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", default="1,2,4,8", help="batch sizes (default 1,2,4,8)")
    parser.add_argument("--rounds", type=positive_int, default=5, help="timed rounds, each every size once (default 5)")
    parser.add_argument("--calls", type=positive_int, default=4, help="session calls per size and round (default 4)")
    parser.add_argument("--out", type=Path, default=Path("bench/results/batch.json"))
    args = parser.parse_args()
    if not MODEL.is_file():
        print(f"skipped: model {MODEL} not found (the real models must be in {SHARED / 'models'})")
        return
    sizes = [int(v) for v in args.batches.split(",")]
    images = read_frames(list(range(0, 1000, 1000 // max(sizes))))[: max(sizes)]
    box = Letterbox.fit(images[0].shape[:2], 640)
    tensors = np.concatenate([letterbox_tensor(image, box) for image in images])
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="arcloud-batch-") as folder:
        batch_model = Path(folder) / "batch.onnx"
        patched = batch_capable_copy(MODEL, batch_model)
        check_exact(session(batch_model, None), session(MODEL, None), tensors[:3])
        for label, threads in (("threads_default", None), ("threads_1", 1)):
            run = session(batch_model, threads)
            for size in sizes:  # warm-up: onnxruntime plans each new shape on its first call
                run.run(None, {"images": tensors[:size]})
            rates: dict[int, list[float]] = {size: [] for size in sizes}
            for _ in range(args.rounds):
                for size in sizes:
                    rates[size] += [frames_per_s(run, tensors[:size]) for _ in range(args.calls)]
            base = statistics.median(rates[sizes[0]])
            results[label] = {
                str(size): {
                    "frames_per_s": round(statistics.median(rates[size]), 3),
                    "p10_frames_per_s": round(float(np.percentile(rates[size], 10)), 3),
                    "over_first_size": round(statistics.median(rates[size]) / base, 3),
                }
                for size in sizes
            }
            print(label, {size: results[label][str(size)]["over_first_size"] for size in sizes}, "x the first size's frames/s")
    write_json(
        args.out,
        {
            "benchmark": "detector session frames/s by batch size",
            "model": str(MODEL.relative_to(SHARED)),
            "batch_capable_copy": {"reshape_shapes_patched": patched, "exact": True},
            "frames": "7-Scenes redkitchen, letterboxed to 640",
            "rounds": args.rounds,
            "calls_per_round": args.calls,
            "cores": cores(),
            "results": results,
            **environment(("arcloud", "numpy", "onnxruntime", "onnx")),
        },
    )


if __name__ == "__main__":
    main()
