"""Process settings every node applies at start-up, so that per-frame time goes to the stage's own work.

Measured on the graph (docs/ARCHITECTURE.md, "Timing"; FACTS "Measured on the graph"):

* numpy's OpenBLAS starts worker threads that spin while waiting for work; in five node processes
  on a small CPU they took about a third of the graph's CPU for matrix products of a few thousand
  rows. The stages run one frame at a time on one core each: one BLAS thread per process.
* glibc serves allocations above its mmap threshold (128 KiB at first) with fresh ``mmap`` pages,
  which the kernel zeroes on first touch and unmaps on free: every 640x480 image a node takes,
  converts or publishes paid for that again (about 2 ms of a 3 ms rgb8 take). Raising the mmap and
  trim thresholds lets freed image buffers be reused from the heap. The working set is a few
  frames, so the heap stays bounded (the load benchmark reports RSS per node over time).

Both are done through ctypes on the already-loaded libraries, so they apply however the node was
started (graph runner, launch file, a test); a node started with ``OPENBLAS_NUM_THREADS`` or
``MALLOC_*`` already set keeps those. Nothing here raises: on another platform it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
from typing import Dict

# glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # above a 1280x720 rgb8 frame (2.7 MB) and any point cloud of a frame
TRIM_THRESHOLD_BYTES = 64 * 1024 * 1024


def limit_blas_threads(threads: int = 1) -> bool:
    """Set numpy's OpenBLAS to ``threads`` threads (unless OPENBLAS_NUM_THREADS is set); True if done."""
    if os.environ.get("OPENBLAS_NUM_THREADS"):
        return False
    import numpy as np

    folders = [os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs"),
               os.path.join(os.path.dirname(np.__file__), ".libs")]
    for path in sorted(p for folder in folders for p in glob.glob(os.path.join(folder, "*openblas*.so*"))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for symbol in ("openblas_set_num_threads64_", "openblas_set_num_threads", "scipy_openblas_set_num_threads64_"):
            setter = getattr(lib, symbol, None)
            if setter is not None:
                setter(ctypes.c_int(int(threads)))
                return True
    return False


def keep_large_buffers_in_heap() -> bool:
    """Raise glibc's mmap and trim thresholds (unless MALLOC_MMAP_THRESHOLD_ is set); True if done."""
    if os.environ.get("MALLOC_MMAP_THRESHOLD_"):
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    return bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1 and ok)


def tune_node_process() -> Dict[str, bool]:
    """Apply every setting above; returns which took effect (for the node's start-up log)."""
    return {"blas_threads_1": limit_blas_threads(1), "large_buffers_in_heap": keep_large_buffers_in_heap()}
