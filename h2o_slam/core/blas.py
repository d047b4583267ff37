"""The process's BLAS threads, held to what budgeted callbacks can live with.

numpy and scipy each bring an OpenBLAS that starts a thread per core (cvxopt's is
single-threaded). After a call that used them, the extra threads spin for a while waiting
for the next one, on the cores the callbacks and the background solver run on. On two cores,
the node's path on CSAIL with planted false closures had 18 callbacks over 7 ms at a 5 ms
budget (up to 14 ms, 7-12 ms of them waiting for the CPU, read from
``/proc/thread-self/schedstat``), the spinning BLAS thread of the same process taking 60 % of
the callbacks' core; with one BLAS thread, none. A budgeted step's linear algebra is small,
so the extra threads never paid for themselves.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Modules with a BLAS of their own that the back end loads on first use (scipy's sparse
#: fallback and LAGO): loaded before the limit is set, or their BLAS would start with a thread
#: per core when they load (25 ms of import).
LAZY_BLAS = ("scipy.linalg",)


class BlasLimit:
    """At most ``threads`` BLAS threads in every BLAS the process has loaded, until
    :meth:`restore` (process-wide: libraries loaded later than the limit are not held)."""

    def __init__(self, threads: int) -> None:
        for name in LAZY_BLAS:
            try:
                importlib.import_module(name)
            except ImportError:
                pass
        from threadpoolctl import threadpool_limits  # on use: 20 ms of import

        self._limits: Any = threadpool_limits(limits=threads, user_api="blas")

    def restore(self) -> None:
        """Give the BLAS libraries back the thread counts they had before the limit."""
        if self._limits is not None:
            self._limits.restore_original_limits()
            self._limits = None


def blas_threads() -> list[int]:
    """Threads of each multi-threaded BLAS the process has loaded."""
    from threadpoolctl import threadpool_info

    return [int(lib["num_threads"]) for lib in threadpool_info()
            if lib["user_api"] == "blas" and lib.get("threading_layer") != "disabled"]
