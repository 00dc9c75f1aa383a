"""Keep freed memory in the process instead of handing it back to the kernel after every frame.

A frame allocates a few megabytes of arrays (decoded images, depth in metres, masks, points) and frees
them when it is done. With glibc's defaults those pages go back to the kernel and the next frame faults
them in again: about 1,400 page faults per frame of VGA arrays. On the virtual machines this was measured
on, that cost a worker process about 15 % of its CPU (161 against 139 ms of CPU per simulated frame). So
long-running processes (the CLI's commands, worker processes) serve buffers up to ``MMAP_THRESHOLD``
from the heap and keep up to ``TRIM_THRESHOLD`` freed at its top; memory use stays at the high-water
mark of a frame's work instead of falling back between frames.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger(__name__)

MMAP_THRESHOLD = 32 << 20  # bytes (glibc's ceiling): larger blocks are still mapped and unmapped on their own
TRIM_THRESHOLD = 256 << 20  # bytes freed at the heap's top kept before trimming
_M_TRIM_THRESHOLD = -1  # mallopt parameters (glibc's malloc.h)
_M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Set glibc malloc's thresholds (see the module docstring) for this process. Returns whether they
    were set: False where the C library is not glibc (nothing changes there)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        log.debug("no mallopt in this C library (%s): allocator left as it is", name)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
