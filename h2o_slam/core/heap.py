"""Memory the callbacks reuse instead of faulting in fresh (glibc's ``malloc``).

glibc gives each large block (above 128 KB, a threshold it raises as blocks are freed) its
own ``mmap`` and returns freed memory to the kernel (``munmap``, trimming the heap's top),
so an array a callback allocates often lands on pages never touched before: a page fault
each, and on a virtual machine whose host takes back the guest's free memory, measured here
at about 3 ms per MB (the first touch of a 40 MB array: 134 ms; 15 MB: 5-11 ms; the same
sizes once recycled: 3.5 and 1 ms). The node's path at a 5 ms budget had one callback per
stream of 36-46 ms, almost all of it charged as CPU, on rows that moved from run to run.

The real-time remedy ROS 2's real-time demos use (``lock_and_prefault_dynamic``): keep
freed memory in the process (no ``mmap`` for large blocks, no trimming) and touch a reserve
once at start, so that later allocations reuse resident pages. Memory is not locked
(``mlockall`` needs a privilege a robot's user rarely has). The cost: the process keeps its
peak heap resident.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading

import numpy as np

#: ``mallopt`` parameters (glibc's ``malloc.h``).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
#: Trim only when this much is free at the heap's top: never, in practice.
_NO_TRIM = (1 << 31) - 1

_lock = threading.Lock()
_kept: bool | None = None  # None: not tried yet (a C library without mallopt stays False)
_reserved_mb = 0


def keep_freed_memory(reserve_mb: int) -> bool:
    """Keep freed memory in this process and touch ``reserve_mb`` MB of heap now (at most
    once per size: a later call touches only what a larger reserve adds). Process-wide, in
    the calling thread's ``malloc`` arena. False where the C library has no ``mallopt``
    (not glibc), doing nothing."""
    global _kept, _reserved_mb
    if reserve_mb < 0:
        raise ValueError(f"reserve_mb must be >= 0, got {reserve_mb}")
    with _lock:
        if _kept is None:
            _kept = _set_malloc_options()
        if not _kept:
            return False
        if reserve_mb > _reserved_mb:
            _touch(reserve_mb)
            _reserved_mb = reserve_mb
    return True


def _set_malloc_options() -> bool:
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, _NO_TRIM))


def _touch(reserve_mb: int) -> None:
    """Fault in ``reserve_mb`` MB of heap and free it (it stays in the heap, resident)."""
    block = np.empty(reserve_mb << 17)  # 8-byte floats: 2**17 of them per MB
    block[::512] = 0.0  # one write per 4 KB page
    del block
