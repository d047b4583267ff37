"""Compiled kernels: the decorator the hot paths use, and the warm-up that compiles them.

The per-edge hot paths (rotation exp/log, edge Jacobians along a tree path, the hybrid
solve, applying and distributing steps) are numba ``nopython`` functions. Each formula is
written once, as a kernel on one item; the batched numpy-facing functions loop over it, so
there is no second copy that can drift. Compiled code is cached on disk next to the modules
(``cache=True``); :func:`warm_up` loads or compiles every signature the solver uses, so that
a node calls it at start-up (``H2OSolver`` does on first construction) and no callback pays
for compilation.

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

F = TypeVar("F", bound=Callable[..., Any])

#: Modules whose kernels call one another. numba's cache checks only the source file of the
#: function it compiled, so a kernel inlined from another module would go stale when that
#: module changes: the cache folder is keyed by the sources of all of them.
_KERNEL_MODULES = ("compiled", "exact", "geometry", "jacobians", "hybrid", "interpolate",
                   "solver", "tree")


def _cache_dir() -> str:
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for name in _KERNEL_MODULES:
        digest.update((here / f"{name}.py").read_bytes())
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return str(base / "h2o_slam" / f"numba-{numba.__version__}-{digest.hexdigest()[:16]}")


if not os.environ.get("NUMBA_CACHE_DIR"):  # the user's choice wins
    setattr(numba.config, "CACHE_DIR", _cache_dir())  # noqa: B010 (untyped attribute)


def kernel(func: F) -> F:
    """Compile ``func`` in nopython mode, cached on disk, releasing the GIL."""
    return cast(F, numba.njit(cache=True, nogil=True)(func))


_warm = False


def warm_up() -> None:
    """Compile (or load from the on-disk cache) every kernel with the argument types the
    solver passes: a few hundred milliseconds from the cache, seconds on a first install.

    Idempotent; runs a tiny planar and a tiny 3-D problem through every update path.
    """
    global _warm
    if _warm:  # done, or under way (the solvers built below call this again)
        return
    _warm = True
    import numpy as np

    from h2o_slam.core import geometry as geo
    from h2o_slam.core.exact import converge_exact
    from h2o_slam.core.graph import EARTH, EdgeKind
    from h2o_slam.core.jacobians import chain_jacobians, endpoint_jacobians
    from h2o_slam.core.solver import H2OSolver
    from h2o_slam.core.tree import PoseTree, spanning_parents

    geo.so3_exp(np.zeros(3))
    geo.so3_log(np.eye(3))
    geo.so3_right_jacobian_inv(np.zeros(3))
    geo.renormalize(np.eye(3))
    eye, zero = np.eye(3)[None], np.zeros((1, 3))
    endpoint_jacobians(np.zeros(1, dtype=np.int64), eye, zero, eye, zero, eye, zero)
    chain_jacobians(eye, eye, zero, zero[0])
    for planar in (True, False):
        solver = H2OSolver(planar)
        solver.add_pose(np.eye(3), np.zeros(3))
        step = np.array([1.0, 0.0, 0.0])
        yaw = geo.yaw_to_matrix(np.array(0.1))
        for node in range(1, 6):
            solver.add_edge(EdgeKind.RELATIVE, node - 1, node, yaw, step, np.eye(6))
        loop = solver.add_edge(EdgeKind.RELATIVE, 0, 5, np.eye(3), step, np.eye(6))
        gps = solver.add_edge(EdgeKind.POSITION, EARTH, 5, np.eye(3), step, np.eye(6))
        solver.add_edge(EdgeKind.ORIENTATION, EARTH, 4, np.eye(3), step, np.eye(6))
        solver.relax(1)
        solver.relax(loop, guard=True)
        solver.relax(loop, d_max=2)
        solver.relax(loop, d_max=2, guard=True)
        solver.relax_batch([gps])
        tree = PoseTree.from_parents(solver.tree.parent[: solver.num_nodes],
                                     *solver.world_poses())
        tree.tops()
        tree.world_pose(tree.n - 1)
        converge_exact(solver, 2)  # the sparse factorization's first uses
    spanning_parents(2, np.array([0]), np.array([1]))
