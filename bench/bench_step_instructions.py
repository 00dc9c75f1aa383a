"""Count the instructions of the per-frame step (``bench_step``'s scene): a figure that does not move with the load.

``bench_step`` times the step in milliseconds, and on a shared machine its medians move by tens of per cent from
one run to the next (the same code read 10.5 and 17.6 ms within minutes, November 28), too much to tell a 15 %
change. This runs the same scene's step under valgrind's callgrind, counting the instructions executed by the
timed frames' ``integrate_frame`` calls alone (collection is on only inside ``operator.call``, through which
they are made): the same code and scene give the same count within 0.1 %, whatever else the machine runs.
Instructions are not time (numpy's memory traffic and the cache are not in them), so a change is judged by both.

Compare two checkouts by the ``arcloud`` each imports:

    .venv/bin/python bench/bench_step_instructions.py [--frames 30] [--out bench/results/step_instructions.json]
    PYTHONPATH=OTHER_TREE/src .venv/bin/python bench/bench_step_instructions.py --out /tmp/other.json

Needs ``valgrind`` (Debian: ``apt-get install valgrind``); about a minute for 30 frames.
"""

from __future__ import annotations

import argparse
import operator
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from common import environment, write_json

#: The C function through which the counted calls are made; callgrind collects only inside it.
COUNTED_CALL = "_operator_call"


def run_frames(frames: int, warmup: int) -> None:
    """The step of ``bench_step``'s scene: the map built, ``warmup`` frames uncounted, then ``frames`` counted."""
    from bench_step import scene_steps

    from arcloud.core.step import integrate_frame

    store, params, steps, detections = scene_steps(warmup + frames)
    for i in range(warmup):
        integrate_frame(steps[i], detections[i], store, params)
    for i in range(warmup, warmup + frames):
        operator.call(integrate_frame, steps[i], detections[i], store, params)  # counted


def arcloud_source() -> dict[str, object]:
    """Where the ``arcloud`` measured comes from, and that checkout's commit (a ``PYTHONPATH`` may name another)."""
    import arcloud

    folder = Path(arcloud.__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=folder
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = None
    return {"package": str(folder), "commit": commit}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("bench/results/step_instructions.json"))
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)  # the run under valgrind
    args = parser.parse_args()
    if args.inner:
        run_frames(args.frames, args.warmup)
        return
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        raise SystemExit("needs valgrind on the PATH (Debian: apt-get install valgrind)")
    with tempfile.TemporaryDirectory(prefix="arcloud-bench-") as folder:
        command = [
            valgrind, "--tool=callgrind", f"--toggle-collect={COUNTED_CALL}", f"--callgrind-out-file={folder}/callgrind.out",
            sys.executable, __file__, "--inner", "--frames", str(args.frames), "--warmup", str(args.warmup),
        ]  # fmt: skip
        single = {var: "1" for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
        done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, **single})
    collected = re.search(r"Collected : (\d+)", done.stderr)
    if done.returncode != 0 or collected is None:
        raise SystemExit(f"the counted run failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    per_frame = int(collected.group(1)) / args.frames
    payload = {
        "benchmark": "instructions of the per-frame step (bench_step's scene, embedded store)",
        "frames": args.frames,
        "warmup": args.warmup,
        "instructions_per_frame": round(per_frame),
        "measured": arcloud_source(),
        **environment(),
    }
    write_json(args.out, payload)
    print(
        f"step: {per_frame / 1e6:.2f} M instructions a frame ({args.frames} frames; arcloud from {payload['measured']['package']})"
    )


if __name__ == "__main__":
    main()
