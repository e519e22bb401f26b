"""glibc's allocator kept from handing every step's large blocks back to the kernel.

torch allocates CPU tensors with ``malloc``. glibc serves blocks above its mmap threshold
(128 KiB, raised as blocks are freed, up to 32 MiB) with fresh ``mmap`` pages and returns
them on ``free``; a training step allocates tens of activations and gradients of 2-25 MB,
so each step page-faults and zeroes them again, in the kernel
(docs/performance.md#fused-layers-and-a-kept-heap). :func:`keep_freed_memory` asks glibc to serve
all blocks from its heap and to keep freed memory there: the next step reuses the pages.
The cost is memory that is not returned to the system until the process ends (the
training process's peak, which it reaches again every step anyway).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import sys

M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # glibc's mallopt parameters (malloc.h)
TRIM_THRESHOLD = 1 << 30  # keep up to 1 GiB of free memory at the top of the heap


@functools.lru_cache(maxsize=1)
def keep_freed_memory() -> bool:
    """Tell glibc to serve large blocks from its heap and keep freed memory (once per
    process; later allocations only). True where it took effect: Linux with glibc and
    neither ``MALLOC_MMAP_MAX_`` nor ``MALLOC_TRIM_THRESHOLD_`` chosen by the user."""
    import os

    if not sys.platform.startswith("linux") or {"MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_"} & set(os.environ):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
