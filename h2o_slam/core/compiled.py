"""Compiled kernels: the decorator the hot paths use, and where their machine code is cached.

The per-edge hot paths (rotation exp/log, edge Jacobians along a tree path, the hybrid
solve, applying and distributing steps) are numba ``nopython`` functions. Each formula is
written once, as a kernel on one item; the batched numpy-facing functions loop over it, so
there is no second copy that can drift. Compiled code is cached on disk (``cache=True``) in
a folder keyed by the kernel sources, shared by every install of them;
:mod:`h2o_slam.core.warmup` loads or compiles every signature the solver uses.

Measured on the shared two-core machine (see ``bench/README.md``): a tree-edge update
(d = 1) went from ~300 µs of interpreter overhead to ~20 µs.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, cast

import numba
from numba.core import caching

F = TypeVar("F", bound=Callable[..., Any])

#: Modules whose kernels call one another. numba's cache checks only the source file of the
#: function it compiled, so a kernel inlined from another module would go stale when that
#: module changes: the cache folder is keyed by the sources of all of them.
_KERNEL_MODULES = ("compiled", "condensed", "exact", "geometry", "jacobians", "hybrid",
                   "interpolate", "loop_spread", "solver", "tree")


def _cache_dir() -> str:
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for name in _KERNEL_MODULES:
        digest.update((here / f"{name}.py").read_bytes())
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return str(base / "h2o_slam" / f"numba-{numba.__version__}-{digest.hexdigest()[:16]}")


if not os.environ.get("NUMBA_CACHE_DIR"):  # the user's choice wins
    numba.config.CACHE_DIR = _cache_dir()  # type: ignore[attr-defined]


class _ContentLocator(caching.UserProvidedCacheLocator):
    """Where numba caches this package's kernels: ``CACHE_DIR/<package folder>``, whatever
    path the package is installed at.

    numba's own locator puts each source folder's kernels under a hash of its absolute path,
    so every new install tree (a ``colcon build``, a fresh venv) compiled everything again on
    first use: over a minute on two cores. Here the cache folder is already keyed by the
    kernel sources' digest (:func:`_cache_dir`) and numba checks each file's content hash,
    so one compile serves every install of the same sources.
    """

    def __init__(self, py_func: Any, py_file: str) -> None:
        super().__init__(py_func, py_file)
        self._cache_path = os.path.join(_CONFIG.CACHE_DIR, Path(py_file).parent.name)

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> Any:
        if not _CONFIG.CACHE_DIR or Path(py_file).resolve().parent not in _KERNEL_FOLDERS:
            return None
        return super().from_function(py_func, py_file)


_HERE = Path(__file__).resolve().parent
#: The folders whose kernels are cached by content: the core's, and the baselines' (TORO),
#: which use this decorator too.
_KERNEL_FOLDERS = (_HERE, _HERE.parent / "baselines")
_CONFIG: Any = numba.config
# Older numba names the class _CacheImpl; without either, numba's own locators serve.
_LOCATORS: Any = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
if _LOCATORS is not None and _ContentLocator not in _LOCATORS._locator_classes:
    _LOCATORS._locator_classes.insert(0, _ContentLocator)


def kernel(func: F) -> F:
    """Compile ``func`` in nopython mode, cached on disk, releasing the GIL."""
    return cast(F, numba.njit(cache=True, nogil=True)(func))
