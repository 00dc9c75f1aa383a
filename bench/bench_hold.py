"""How long a frame holds its objects' locks: what bounds one hot map's rate (docs/scaling.md).

Frames of one map lock the objects they see, and in a room most frames see the same few (a table), so one
map integrates about one frame per hold, whatever the workers: its rate is at most 1 / (hold + the hand-over
to the next holder). This times the step after detection (``integrate_frame``) on a throwaway redis-server,
one frame at a time: every ``--stride``-th of the first redkitchen frames with the real model's detections
(computed once, beforehand, as ``bench_scaling``'s waiting detector replays them), ``--passes`` times over (as
other devices: the map grows on). Per frame, each lap of the step (``StepResult.timings_s``) and ``hold``: from
the locks taken to the commit that releases them (the laps after ``lock``), and Redis commands a frame.

``--busy N`` runs N one-thread sessions of the model beside it (``bench_scaling``'s ceiling processes): the hold
on cores the detectors keep busy, as the service's are.

    .venv/bin/python bench/bench_hold.py [--busy 1] [--out bench/results/hold.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from bench_scaling import MODEL, SEQUENCE, WaitingReplayDetector, _session_process, precompute_detections
from common import Redis, environment, summary_ms, write_json

OUT = Path(__file__).parent / "results" / "hold.json"
HELD_LAPS = ("associate_fuse", "create_refine", "write")  # after the locks are taken, until the commit releases them


def busy_sessions(n: int, frames: list[Any], seconds: float) -> list[Any]:
    """``n`` processes running the model's one-thread session for ``seconds`` once all are ready (started, not
    joined; returned with what they share, which must outlive them)."""
    import numpy as np

    from arcloud.detectors.onnx_yolo import Letterbox, YoloSegDetector, letterbox_tensor

    size = YoloSegDetector(str(MODEL), intra_op_threads=1).input_size_px
    tensors = np.stack([letterbox_tensor(f.rgb, Letterbox.fit(f.rgb.shape[:2], size))[0] for f in frames[:4]])
    folder = tempfile.TemporaryDirectory(prefix="arcloud-bench-")
    path = str(Path(folder.name) / "tensors.npy")
    np.save(path, tensors)
    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(n + 1), context.Queue()
    processes = [context.Process(target=_session_process, args=(str(MODEL), path, seconds, barrier, results)) for _ in range(n)]
    for process in processes:
        process.start()
    barrier.wait(timeout=120)  # every session loaded: they start now
    return [processes, folder, barrier, results]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--stride", type=int, default=10)
    parser.add_argument("--passes", type=int, default=2)
    parser.add_argument("--busy", type=int, default=0, help="one-thread sessions running beside it (default 0)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if not MODEL.is_file() or not SEQUENCE.is_dir():
        raise SystemExit(f"needs {MODEL} and {SEQUENCE} (the real assets in ../shared, or ARCLOUD_SHARED)")
    from arcloud.core.step import integrate_frame
    from arcloud.core.types import Params
    from arcloud.datasets.sevenscenes import load_seven_scenes
    from arcloud.stores.redis import RedisStore

    frames = list(load_seven_scenes(SEQUENCE, align_gravity=True).frames(stride=args.stride, limit=args.frames))
    with tempfile.TemporaryDirectory(prefix="arcloud-bench-") as folder:
        path = Path(folder) / "detections.npz"
        precomputed = precompute_detections(frames, MODEL, path)
        detector = WaitingReplayDetector(str(path), 0.0)()
    busy: list[Any] | None = None
    if args.busy:
        busy = busy_sessions(args.busy, frames, seconds=30.0 + 2.0 * len(frames) * args.passes)
    redis = Redis()
    store = RedisStore(redis.url)
    laps: dict[str, list[float]] = {}
    commands = []
    try:
        for n in range(args.passes):
            for frame in frames:
                detections = detector.detect(frame)
                before = redis.client.info("stats")["total_commands_processed"]
                result = integrate_frame(
                    dataclasses.replace(frame, map_id="hold", device_id=f"pass-{n}"), detections, store, Params()
                )
                commands.append(redis.client.info("stats")["total_commands_processed"] - before - 1)  # less the INFO
                for name, seconds in result.timings_s.items():
                    laps.setdefault(name, []).append(seconds)
                laps.setdefault("hold", []).append(sum(result.timings_s.get(name, 0.0) for name in HELD_LAPS))
    finally:
        store.close()
        redis.stop()
        if busy is not None:
            for process in busy[0]:
                process.terminate()
                process.join()
            busy[1].cleanup()
    summary = {name: summary_ms(times) for name, times in laps.items()}
    for name, row in summary.items():
        print(f"{name:16s} median {row['median_ms']:7.2f} ms  p90 {row['p90_ms']:7.2f} ms")
    print(f"Redis commands a frame: median {statistics.median(commands)}")
    write_json(
        args.out,
        {
            "benchmark": "hold",
            **environment(),
            "setup": {
                **vars(args),
                "out": str(args.out),
                "model": MODEL.name,
                "precomputed": precomputed,
                "redis": redis.version,
            },
            "laps": summary,
            "redis_commands_per_frame_median": statistics.median(commands),
        },
    )


if __name__ == "__main__":
    main()
