"""The warm-up: every compiled kernel loaded (or compiled) with the argument types the
solver passes, before the first timed update.

From the cache a warm-up takes a few hundred milliseconds; on the first run after the
kernel sources change it compiles everything, a minute or more on two cores. The package's
set-up runs it once (``make venv``, ``colcon build``: ``python -m h2o_slam.core.warmup``) so
that no command or node compiles on first use, and a node runs it beside its executor
(:func:`warm_up_in_background`) so that it answers while the kernels load.

Not imported by the modules whose kernels it warms, so that they do not import each other in
a circle.
"""

from __future__ import annotations

import compileall
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.condensed import Reduced, solve_loop
from h2o_slam.core.exact import converge_exact
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, make_graph
from h2o_slam.core.jacobians import chain_jacobians, endpoint_jacobians
from h2o_slam.core.loop_spread import dead_reckon, spread_loop
from h2o_slam.core.solver import H2OSolver
from h2o_slam.core.tree import PoseTree, spanning_parents

_lock = threading.Lock()
_started = False
_ready = threading.Event()


def warm_up() -> None:
    """Load or compile every kernel the solver's update paths use; returns when they are
    ready. Idempotent; a call while another thread warms up waits for it."""
    global _started
    with _lock:
        first = not _started
        _started = True
    if not first:
        _ready.wait()
        return
    try:
        _run_every_path()
    finally:
        _ready.set()  # a failure surfaces again at the kernel's first use, not as a hang


def ensure_warm_up() -> None:
    """:func:`warm_up` now, unless one is already under way or done: a node warms up in the
    background (:func:`warm_up_in_background`) and holds its inputs until :func:`is_ready`,
    so the solver it builds meanwhile must not wait for it."""
    with _lock:
        if _started:
            return
    warm_up()


def warm_up_in_background() -> threading.Thread | None:
    """Start :func:`warm_up` in a daemon thread (``None`` when it is already started);
    :func:`is_ready` says when it is done. numba holds the interpreter lock for much of a
    compile, so the caller's thread runs slower meanwhile, but it runs."""
    with _lock:
        if _started:
            return None
    thread = threading.Thread(target=warm_up, name="h2o-warm-up", daemon=True)
    thread.start()
    return thread


def is_ready() -> bool:
    """Every kernel is loaded: an update runs at its compiled speed."""
    return _ready.is_set()


def _run_every_path() -> None:
    """A tiny planar and a tiny 3-D problem through every update path."""
    geo.so3_exp(np.zeros(3))
    geo.so3_log(np.eye(3))
    geo.so3_right_jacobian_inv(np.zeros(3))
    geo.renormalize(np.eye(3))
    eye, zero = np.eye(3)[None], np.zeros((1, 3))
    endpoint_jacobians(np.zeros(1, dtype=np.int64), eye, zero, eye, zero, eye, zero)
    chain_jacobians(eye, eye, zero, zero[0])
    for planar in (True, False):
        solver = H2OSolver(planar=planar)
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
        tree.top(tree.n - 1)
        tree.world_pose(tree.n - 1)
        converge_exact(solver, 2)  # the sparse factorization's first uses
    spanning_parents(2, np.array([0]), np.array([1]))
    _condensed_loop()
    _robust_solve()


def _condensed_loop() -> None:
    """A loop of eight poses closed back to its start through the condensed solve."""
    inc = np.tile([1.0, 0.0, np.pi / 4], (8, 1))
    cov = np.tile(np.eye(3), (8, 1, 1))
    pose = np.vstack([np.zeros(3), dead_reckon(np.zeros(3), inc)[1:]])
    closure = Reduced(np.array([0]), np.array([8]), np.zeros((1, 3)), np.eye(3)[None],
                      np.empty(0, np.int64))
    solve_loop(pose, 0, inc, cov, closure, 2, 1e-6, lambda: False)
    R, t = geo.yaw_to_matrix(pose[:, 2]), np.column_stack([pose[:, :2], np.zeros(9)])
    for a, b in ((0, 8), (8, 0)):
        spread_loop(R, t, a, b, np.eye(3), np.zeros(3), np.eye(6), np.tile(np.eye(6), (8, 1, 1)),
                    geo.PLANAR_DOF, 1)
    Reduced(closure.a, closure.b, closure.meas, closure.info, np.array([8])).rotations_first(
        pose)


def _robust_solve() -> None:
    """A robust solve's first use imports scipy.special and scipy.sparse.csgraph (the
    module defers them to keep every command's start short) and runs LAGO's kernels: 0.15 s
    that the first inline solve of a node paid inside one callback."""
    from scipy.sparse.csgraph import connected_components

    from h2o_slam.core.robust import chdtri, lago_restart

    chdtri(np.array([3.0]), 0.01)
    connected_components(np.eye(2), directed=False)
    graph = false_ring(True)
    lago_restart(graph)(np.ones(graph.num_edges))
    load_closure_scoring()


def load_closure_scoring() -> None:
    """The kernels that weigh a robust solve's loop closures on graphs of about a thousand
    poses and more (a small graph's solve, as on :func:`false_ring`, takes neither path):
    the selected inverse's, and the neighbourhood bounds on drop candidates."""
    import scipy.sparse as sp

    from h2o_slam.core.neighbourhood import deletion_bounds
    from h2o_slam.core.selinv import selected_inverse
    from h2o_slam.core.spd import upper

    A = sp.diags([np.ones(2), np.full(3, 4.0), np.ones(2)], [-1, 0, 1], format="csc")
    selected = selected_inverse(upper(A), np.array([[0, 2]]))
    if selected is not None:  # without CHOLMOD no robust solve has one either
        selected.blocks(np.array([[0, 2, -1]]))
    for planar in (True, False):
        ring = false_ring(planar)
        solver = H2OSolver.from_graph(ring, np.arange(-1, ring.num_nodes - 1),
                                      regularizer=False)
        deletion_bounds(solver, [np.array([0])], 1)


def false_ring(planar: bool, n: int = 12, false_closure: bool = True) -> PoseGraph:
    """``n`` poses on a circle of 1 m steps, each joined to the next (the last to the
    first: the true loop closure), and a false closure across the ring (5 m straight
    ahead, where the two poses, 3.9 m apart, face opposite ways): a robust exact solve of
    it runs every path a solve of a graph of the same kind runs (``h2o-solve`` loads exact
    mode's kernels with it before its clock starts). ``false_closure=False``: the ring
    alone, a graph without outliers."""
    yaw = np.arange(n, dtype=np.float64) * (2.0 * np.pi / n)
    radius = 0.5 / np.sin(np.pi / n)  # 1 m steps
    # Off the measurements' ring a little (3-D: out of its plane too), so that every
    # residual and Jacobian path runs.
    wobble = 0.05 * np.sin(3.0 * yaw)
    tilt = np.zeros(n) if planar else wobble
    t = np.column_stack([radius * np.sin(yaw) + wobble, radius * (1.0 - np.cos(yaw)), tilt])
    R = geo.so3_exp(np.column_stack([tilt, -tilt, yaw + wobble]))
    a = np.array([*range(n), 3])
    b = np.array([*range(1, n), 0, 3 + n // 2])
    turn = geo.yaw_to_matrix(np.full(n + 1, 2.0 * np.pi / n))
    turn[-1] = np.eye(3)
    step = np.tile([1.0, 0.0, 0.0], (n + 1, 1))
    step[-1] = [5.0, 0.0, 0.0]
    info = np.tile(100.0 * np.eye(6), (n + 1, 1, 1))
    m = n + 1 if false_closure else n
    return make_graph(planar, np.arange(n), R, t, np.full(m, EdgeKind.RELATIVE), a[:m], b[:m],
                      turn[:m], step[:m], info[:m])


def byte_compile() -> None:
    """Write the bytecode of the package's modules now, as pip does for what it installs:
    with ``PYTHONDONTWRITEBYTECODE`` set (or an install step that skips it) every command
    would compile them again at each start (~0.1 s)."""
    root = Path(__file__).resolve().parents[2]
    for package in PACKAGES:
        if (root / package).is_dir() and os.access(root / package, os.W_OK):
            compileall.compile_dir(root / package, quiet=1)


#: The packages of this distribution (see setup.py).
PACKAGES = ("h2o_slam", "hybrid_vo", "msg_adapters")


def main() -> int:
    """``python -m h2o_slam.core.warmup``: compile the kernels into the cache now, and the
    modules' bytecode (the set-up's last step), saying how long it took."""
    start = time.perf_counter()
    print("h2o_slam: loading or compiling the solver kernels (a minute or more the first "
          "time)...", file=sys.stderr, flush=True)
    byte_compile()
    warm_up()
    print(f"h2o_slam: kernels ready in {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
