"""glibc's allocator kept from handing gtgen's grid-sized temporaries back to the kernel.

Every stage works on whole grids (a 500 x 500 float64 grid is 2 MB), and NumPy makes a new
array for most steps. With glibc's defaults such arrays are mapped afresh and returned to
the kernel when freed, so each step pays its page faults again: a 500 x 500 floor-and-cast
took 1.5 ms, 0.4 ms with the memory kept. Arrays under ``MMAP_THRESHOLD_B`` come from the
heap, and up to ``TRIM_THRESHOLD_B`` of freed heap stays with the process: memory bounded by
those constants, whatever the drive's length (peak RSS of each stage unchanged,
docs/performance.md). The CLI and every pool worker apply it; elsewhere (another C library)
nothing changes. A user's own ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` wins.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

MMAP_THRESHOLD_B = 32 << 20  # allocations below this come from the heap [bytes]
TRIM_THRESHOLD_B = 128 << 20  # freed heap kept before it is returned to the kernel [bytes]
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt's parameters (malloc.h)


def keep_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds for this process (see the module); return
    whether they were set (False: not glibc, or the user set them in the environment)."""
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_B)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_B))
