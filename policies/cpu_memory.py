"""Keep freed memory inside the process for CPU training loops (glibc malloc settings).

An update that allocates and frees the same multi-megabyte tensors every step (a batched VPACE update:
2.6 MB activations and gradients per layer) otherwise hands them back to the kernel on free (glibc
serves blocks above its mmap threshold with mmap, and trims the heap top) and faults them in again,
zero-filled, on the next allocation: about 1300 page faults and 2-4 ms of system time per update on
the development machine, 10 % of the update (docs/vpace.md). Raising glibc's mmap and trim thresholds
keeps those blocks for reuse, which is what PyTorch's CPU tuning guide gets from jemalloc or tcmalloc.
The cost: up to `trim_threshold` of freed memory stays with the process.
"""

from __future__ import annotations

import ctypes
import functools
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # mallopt parameter numbers (glibc malloc.h)


@functools.cache
def keep_freed_memory(mmap_threshold: int = 32 << 20, trim_threshold: int = 256 << 20) -> bool:
    """Serve blocks below `mmap_threshold` bytes from the heap and keep up to `trim_threshold` bytes
    of freed heap; process-wide, applied once. Returns whether the C library took the settings (glibc
    on Linux; elsewhere nothing changes). 32 MiB is the ceiling of glibc's own adaptive threshold."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(M_TRIM_THRESHOLD, trim_threshold))
