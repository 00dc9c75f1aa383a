"""keep_freed_memory: frame-sized arrays allocated and freed again stop faulting pages in."""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import resource, sys
import numpy as np
if sys.argv[1] == "kept":
    from arcloud.allocator import keep_freed_memory
    assert keep_freed_memory()
def frame_work():  # what a VGA frame allocates and frees: colour, depth, metres, a float64 copy (~6 MB)
    rgb = np.ones((480, 640, 3), np.uint8); depth = np.ones((480, 640), np.float32); metres = depth * 2
    points = metres.astype(np.float64)
    del rgb, depth, metres, points
for _ in range(3):
    frame_work()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    frame_work()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 20)
"""


def faults_per_frame(mode: str) -> float:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True)
    return float(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_frame_arrays_reuse_the_heap_instead_of_faulting_pages_in_again() -> None:
    default, kept = faults_per_frame("default"), faults_per_frame("kept")
    # glibc's dynamic thresholds let the heap grow to twice the largest block freed, then trim it back:
    # ~6 MB handed back and faulted in again (4 KiB pages) every frame.
    assert default > 500
    assert kept < 50
