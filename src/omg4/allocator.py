"""Keep freed memory in the process: a hot path allocates the same large tensors every step.

glibc serves allocations above its (adaptive) mmap threshold with fresh ``mmap`` pages and
returns freed heap tops to the system, so each training step on the CPU faults in and zeroes
tens of megabytes again (system time reached half the CPU time in a demo run). Raising the
mmap threshold to its maximum (32 MiB on 64-bit) and the trim threshold to 1 GiB lets the
heap reuse those blocks: about 8 % off a demo training step here
(``benchmarks/speed/train_step.py``). Called by the ``omg4`` command; library users may call it too.
"""

from __future__ import annotations

import ctypes
import ctypes.util

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 * 2**20
TRIM_THRESHOLD = 2**30


def keep_freed_memory() -> bool:
    """Tune glibc's ``malloc`` as above; False where the C library is not glibc (nothing changed)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))


__all__ = ["keep_freed_memory"]
