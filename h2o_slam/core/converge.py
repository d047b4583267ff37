"""Convergence to the exact optimum beside H₂O's budgeted updates.

H₂O's single-edge updates give a new edge its first correction within a callback's budget,
but old nodes stiffen in ``B`` and the updates settle at their own fixed point, not at the
optimum (thesis 3.5). As Cartographer and ORB-SLAM run their global optimization beside the
real-time front end, this module solves a *snapshot* of the graph exactly (damped
Gauss–Newton with a sparse factorization,
:func:`~h2o_slam.core.exact.converge_exact`, the same code as ``--mode exact``) and merges
the answer back into the live tree in budgeted slices:

* the snapshot is the tree (parents and local transforms) and the edges so far; the
  solution is the world pose of every snapshot node;
* a merged node gets the local transform its solution gives relative to its parent, so
  every node added after the snapshot keeps its tree-relative pose and follows its parent;
* edges added after the snapshot are not in the solution: H₂O's revisits work on them (and
  only on them) until the next solution includes them.

Where the solve runs (:class:`Converger`):

* ``"process"`` — in a worker process (niced, so that on one core the callbacks still come
  first), through memory-mapped arrays: a callback only copies the tree in and the solution
  out, each a few memory copies predicted to fit before they start; it never waits.
* ``"inline"`` — in the calling step, when the whole solve is predicted to fit its budget
  (small graphs, huge budgets), and unconditionally in unbudgeted steps, where it follows a
  geometric schedule (whenever the edges outside the last solution reach ``growth`` times
  those in it, and whenever :meth:`OnlineH2O.converge` asks) so that replaying a bag costs
  a few exact solves in all and stays deterministic.

While the worker's job is out for much longer than its jobs take, idle steps run damped
Gauss–Newton on the live map themselves, phase by phase as each is predicted to fit
(:class:`LiveIterations`): a robot's CPU is busy with perception, and a niced worker can
starve for seconds (intel at 5 ms beside two CPU-bound processes: 181 idle steps left χ² at
5.5 times the optimum), while each phase of an iteration of a graph of a thousand poses
costs a millisecond or two.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import tempfile
import weakref
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.exact import (
    MAX_DAMPING,
    ExactSystem,
    WorldLinearization,
    WorldSystem,
    converge_exact,
    next_damping,
    scored_step,
    settled,
)
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH
from h2o_slam.core.robust import (
    RobustConfig,
    RobustOutcome,
    converge_robust,
    global_restart,
    lago_restart,
    odometry_edges,
    restarted_if_lower,
)
from h2o_slam.core.solver import H2OSolver, SolverConfig
from h2o_slam.core.timing import CostModel
from h2o_slam.core.tree import PoseTree

BACKGROUNDS = ("process", "inline", "off")

#: A worker's job out for longer than this many times the last one took (and at least
#: STARVED_MIN_S) is starved: idle steps iterate the live map themselves.
STARVED_FACTOR = 4.0
STARVED_MIN_S = 0.1


@dataclass(frozen=True)
class EdgeRows:
    """Edges ``first, first + 1, …`` as arrays (what a worker is sent to extend its copy)."""

    first: int
    kind: np.ndarray
    a: np.ndarray
    b: np.ndarray
    meas_R: Array
    meas_t: Array
    info: Array

    @classmethod
    def of(cls, solver: H2OSolver, first: int) -> EdgeRows:
        """The solver's edges from ``first`` on (copies)."""
        s = slice(first, solver.num_edges)
        return cls(first, solver.kind[s].copy(), solver.a[s].copy(), solver.b[s].copy(),
                   solver.meas_R[s].copy(), solver.meas_t[s].copy(),
                   solver.info[s].copy())


@dataclass
class Solution:
    """A solved snapshot.

    Attributes:
        nodes, edges: the snapshot held nodes ``0 … nodes-1`` and edges ``0 … edges-1``.
        generation: the live solver's generation at the snapshot (a subtree join or a GPS
            alignment moves whole subtrees and starts a new one; older solutions are dropped).
        R, t: world poses of the snapshot's nodes at the solution.
        chi2_start, chi2: χ² of the snapshot's edges before and after.
        iterations: Gauss–Newton iterations taken.
        converged: χ² stopped falling (relative tolerance), not an iteration cap.
        error: why the solve failed (empty when it did not).
        weights: robust solves: the weight of each of the snapshot's edges (0: dropped as an
            outlier); ``None`` otherwise.
    """

    nodes: int
    edges: int
    generation: int
    R: Array
    t: Array
    chi2_start: float
    chi2: float
    iterations: int
    converged: bool
    error: str = ""
    weights: Array | None = None


class ExactProblem:
    """A copy of the edges and solves of tree snapshots: the side that runs beside the
    callbacks (in a worker process, or inline)."""

    def __init__(self, planar: bool, config: SolverConfig | None = None,
                 robust: RobustConfig | None = None) -> None:
        self.solver = H2OSolver(planar=planar, config=config)
        self.robust = robust
        # The last solution: the next solve starts from it (Gauss–Newton carried on, as
        # iSAM2 carries its linearization point), not from the live map, which the
        # single-edge updates have moved meanwhile.
        self._last: tuple[int, Array, Array] | None = None
        #: Robust solves: the last solution's decisions, carried on by the next solve.
        self._weights: Array | None = None

    def add_edges(self, rows: EdgeRows) -> None:
        """Extend the copy by edges ``rows.first …`` (ones it already holds are skipped)."""
        solver = self.solver
        for i in range(solver.num_edges - rows.first, len(rows.kind)):
            solver._append_edge(int(rows.kind[i]), int(rows.a[i]), int(rows.b[i]),
                                rows.meas_R[i], rows.meas_t[i], rows.info[i])

    def solve(self, parent: np.ndarray, R: Array, t: Array, edges: int, generation: int,
              iterations: int, regraduate: bool = False, from_global: bool = False
              ) -> Solution:
        """Solve the snapshot ``(parent, R, t)`` (tree-local transforms) over its first
        ``edges`` edges; ``regraduate``: a robust solve also graduates afresh
        (:func:`~h2o_slam.core.robust.converge_robust`); ``from_global``: the answer is
        solved again from the start that needs no guess (LAGO, or chordal in 3-D:
        :func:`~h2o_slam.core.robust.global_restart`) and kept where χ² ends lower."""
        n = len(parent)
        solver = self.solver
        full = solver._edges.m
        solver._edges.m = edges  # the copy may already hold edges newer than the snapshot
        try:
            solver.tree = self._seed(parent, R, t, generation)
            history, converged, weights = self._converge(iterations, regraduate)
            if from_global:
                history, converged = self._from_global(history, converged, weights,
                                                       iterations)
            R_w, t_w = solver.world_poses()
        except Exception as exc:  # noqa: BLE001 - reported to the live side, which goes on
            self._last = None
            return Solution(n, edges, generation, np.zeros((0, 3, 3)), np.zeros((0, 3)),
                            math.nan, math.nan, 0, False, f"{type(exc).__name__}: {exc}")
        finally:
            solver._edges.m = full
        self._last = (generation, R_w, t_w)
        return Solution(n, edges, generation, R_w, t_w, history[0], history[-1],
                        len(history) - 1, converged, weights=weights)

    def _converge(self, iterations: int, regraduate: bool
                  ) -> tuple[list[float], bool, Array | None]:
        """Gauss–Newton, or the robust solve carried on from the last decisions."""
        solver = self.solver
        if self.robust is None:
            return (*converge_exact(solver, iterations), None)
        m = solver.num_edges
        start = np.full(m, np.nan)
        if self._weights is not None:
            k = min(m, len(self._weights))
            start[:k] = self._weights[:k]
        trusted = odometry_edges(solver.kind, solver.a, solver.b)
        restart = lago_restart(solver.graph(copy=False)) if solver.planar else None
        outcome = converge_robust(solver, iterations, trusted, self.robust, weights=start,
                                  restart=restart, regraduate=regraduate)
        self._weights = outcome.weights.copy()
        return outcome.history, outcome.converged, outcome.weights


    def _from_global(self, history: list[float], converged: bool, weights: Array | None,
                     iterations: int) -> tuple[list[float], bool]:
        """The answer solved again from the global start of its decisions, kept where χ²
        ends lower: the live map the solves start from can lie in a basin of its own (a
        2,200-pose sphere with 0.3 rad of rotation noise, streamed: 1.068 times the optimum
        the chordal start reaches, and least squares from it stays there)."""
        solver = self.solver
        restart = global_restart(solver.graph(copy=False))
        if restart is None:
            return history, converged
        w = np.ones(solver.num_edges) if weights is None else weights
        outcome = RobustOutcome(w, history, 0, converged)
        restarted_if_lower(solver, outcome, restart, iterations)
        return outcome.history, outcome.converged

    def _seed(self, parent: np.ndarray, R: Array, t: Array, generation: int) -> PoseTree:
        """The snapshot's tree, its nodes of the last solution placed where that solution
        put them and newer nodes following their parents in tree coordinates."""
        tree = PoseTree.from_local(parent, R, t)
        if self._last is None or self._last[0] != generation:
            return tree  # none, or the live side has moved whole subtrees since
        _, R_old, t_old = self._last
        k = min(len(R_old), len(parent))
        R_w, t_w = np.empty((tree.n, 3, 3)), np.empty((tree.n, 3))
        R_w[:k], t_w[:k] = R_old[:k], t_old[:k]
        tree.compose_below(R_w, t_w, k)
        return PoseTree.from_parents(parent, R_w, t_w)


# -- the worker process ---------------------------------------------------------------------

class SharedArrays:
    """Named arrays in one memory-mapped file that two processes open by path."""

    def __init__(self, path: Path, shapes: dict[str, tuple[tuple[int, ...], Any]],
                 create: bool) -> None:
        self.path = path
        offsets, size = {}, 0
        for name, (shape, dtype) in shapes.items():
            offsets[name] = size
            size += int(np.prod(shape)) * np.dtype(dtype).itemsize
        self._buf = np.memmap(path, dtype=np.uint8, mode="w+" if create else "r+",
                              shape=(max(size, 1),))
        self.arrays = {
            name: np.ndarray(shape, dtype=dtype, buffer=self._buf, offset=offsets[name])
            for name, (shape, dtype) in shapes.items()
        }

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]


def _layout(capacity: int, edge_capacity: int, p: int) -> dict[str, tuple[tuple[int, ...], Any]]:
    return {
        "parent": ((capacity,), np.int64),
        "R": ((capacity, 3, 3), np.float64), "t": ((capacity, 3), np.float64),
        "R_out": ((capacity, 3, 3), np.float64), "t_out": ((capacity, 3), np.float64),
        "kind": ((edge_capacity,), np.int64), "a": ((edge_capacity,), np.int64),
        "b": ((edge_capacity,), np.int64), "meas_R": ((edge_capacity, 3, 3), np.float64),
        "meas_t": ((edge_capacity, 3), np.float64), "info": ((edge_capacity, p, p), np.float64),
        "w_out": ((edge_capacity,), np.float64),
    }


def _edge_rows(shared: SharedArrays, first: int, end: int) -> EdgeRows:
    """Edges ``first … end-1`` as the live side wrote them into ``shared`` (views)."""
    s = slice(first, end)
    return EdgeRows(first, shared["kind"][s], shared["a"][s], shared["b"][s],
                    shared["meas_R"][s], shared["meas_t"][s], shared["info"][s])


def _worker_main(conn: Connection, reply: Connection) -> None:
    """The worker: extend the edge copy, solve each snapshot, write the world poses back."""
    try:
        planar, config, robust = conn.recv()
    except (EOFError, OSError):
        return
    problem = ExactProblem(planar, config, robust)
    shared: SharedArrays | None = None
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return  # the live side is gone
        if message is None:
            return
        path, layout, n, edges, generation, iterations, from_global = message
        if shared is None or str(shared.path) != path:
            shared = SharedArrays(Path(path), _layout(*layout), create=False)
        problem.add_edges(_edge_rows(shared, problem.solver.num_edges, edges))
        sol = problem.solve(shared["parent"][:n].copy(), shared["R"][:n].copy(),
                            shared["t"][:n].copy(), edges, generation, iterations,
                            from_global=from_global)
        if not sol.error:
            shared["R_out"][:n] = sol.R
            shared["t_out"][:n] = sol.t
            if sol.weights is not None:
                shared["w_out"][:edges] = sol.weights
        sol.R, sol.t = np.zeros((0, 3, 3)), np.zeros((0, 3))  # sent through the arrays
        sol.weights = None if sol.weights is None else np.zeros(0)
        try:
            reply.send(sol)
        except (EOFError, OSError):
            return


#: The worker's interpreter: SIGINT ignored before the first import (a second of numpy and
#: numba), so a Ctrl-C sent to the worker itself cannot end it with a traceback either.
# Niced before anything is imported: Linux's nice is per thread, and a thread takes its
# creator's, so the BLAS library's threads, started when numpy loads, would otherwise run at
# the callbacks' priority (measured: the node's callbacks up to 14 ms at a 5 ms budget).
# And SCHED_IDLE where there is one: at nice 19 the scheduler still gives the worker a slice
# of a core it shares with the callbacks every ~200 ms of contention, and on two cores it
# shared one for 10 ms at a time while the other was idle (the callbacks waiting 8-12 ms,
# /proc/<tid>/schedstat); an idle-class task gets the CPU only when nothing else wants it.
_WORKER_CODE = ("import os\ntry:\n    os.nice(19)\nexcept OSError:\n    pass\n"
                "try:\n    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\n"
                "except (AttributeError, OSError):\n    pass\n"
                "import signal; signal.signal(signal.SIGINT, signal.SIG_IGN); import sys; "
                "from h2o_slam.core.converge import worker_main; worker_main(sys.argv[1:])")

#: The worker's BLAS and OpenMP run on its one thread: it is the background helper of the
#: callbacks, and threads of its own would take the cores they and the robot's perception
#: need (measured on two cores: the node's robust path on intel ran 37 s with them, 16 s
#: without, and its callbacks' max fell from 6.5-8 to 4.6-4.7 ms).
WORKER_THREADS = {name: "1" for name in (
    "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}


def worker_main(fds: list[str]) -> None:
    """The worker process's entry: the two pipe ends (read, write) it was started with."""
    _worker_main(Connection(int(fds[0]), writable=False),
                 Connection(int(fds[1]), readable=False))


class WorkerProcess:
    """A worker process solving snapshots; every call returns at once."""

    #: Nodes and edges the first shared file holds. Its pages are only touched as the map
    #: grows, so a large file costs nothing up front, and a robot rarely pays for the copy
    #: into a larger one (page faults on a fresh file: about 1 ms per 10k nodes).
    FIRST_CAPACITY = 1 << 16

    def __init__(self, planar: bool, config: SolverConfig | None, info_dim: int,
                 robust: RobustConfig | None = None) -> None:
        self._info_dim = info_dim
        # A fresh interpreter running this module: forking a process that holds DDS threads
        # is unsafe, and multiprocessing's spawn would re-run the user's main script.
        child_in, to_child = os.pipe()
        to_parent, child_out = os.pipe()
        package_root = str(Path(__file__).resolve().parents[1])
        env = dict(os.environ) | WORKER_THREADS
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (package_root, env.get("PYTHONPATH", "")) if p)
        # Its own session: a terminal's Ctrl-C signals the foreground process group, and
        # the worker is not in it; the live side stops the worker (_shutdown).
        self._process = subprocess.Popen(
            [sys.executable, "-c", _WORKER_CODE, str(child_in), str(child_out)],
            pass_fds=(child_in, child_out), env=env, stdin=subprocess.DEVNULL,
            start_new_session=True)
        os.close(child_in)
        os.close(child_out)
        self._conn = Connection(to_child, readable=False)
        self._reply = Connection(to_parent, writable=False)
        self._conn.send((planar, config, robust))
        self._shape = (0, 0, info_dim)
        self._dir = Path(tempfile.mkdtemp(prefix="h2o-exact-", dir=_shm_dir()))
        self._finalizer = weakref.finalize(self, _shutdown, self._conn, self._reply,
                                           self._process, self._dir)
        self.shared: SharedArrays | None = None
        self._serial = 0
        self.busy = False

    def ensure_capacity(self, n: int, m: int) -> bool:
        """Arrays for at least ``n`` nodes and ``m`` edges (a new file, doubled, when they
        outgrow it); True when a new file was made (its edges must all be written again)."""
        shared = self.shared
        if shared is not None and len(shared["parent"]) >= n and len(shared["kind"]) >= m:
            return False
        capacity = max(self.FIRST_CAPACITY, 2 * n)
        edge_capacity = max(2 * self.FIRST_CAPACITY, 2 * m)
        self._serial += 1
        self._shape = (capacity, edge_capacity, self._info_dim)
        self.shared = SharedArrays(self._dir / f"snapshot{self._serial}.bin",
                                   _layout(*self._shape), create=True)
        if shared is not None:
            shared.path.unlink(missing_ok=True)  # the worker's mapping stays valid
        return True

    def submit(self, n: int, edges: int, generation: int, iterations: int,
               from_global: bool = False) -> None:
        """Start solving the snapshot and edges already written to :attr:`shared`: only a
        small message goes through the pipe, so sending never waits for the worker.
        ``from_global``: :meth:`ExactProblem.solve`'s."""
        assert self.shared is not None and not self.busy
        self._conn.send((str(self.shared.path), self._shape, n, edges, generation,
                         iterations, from_global))
        self.busy = True

    def poll(self) -> Solution | None:
        """The finished solution (poses in :attr:`shared`), or None while it runs."""
        if not self.busy:
            return None
        try:
            ready = self._reply.poll()
            sol: Solution | None = self._reply.recv() if ready else None
        except (EOFError, OSError):
            sol = None
            ready = False
        if ready:
            self.busy = False
            return sol
        if self.alive:
            return None
        self.busy = False
        return Solution(0, 0, -1, np.zeros((0, 3, 3)), np.zeros((0, 3)), math.nan,
                        math.nan, 0, False, "the exact solver's process died")

    @property
    def alive(self) -> bool:
        """The worker process runs."""
        return self._process.poll() is None

    def close(self) -> None:
        """Stop the worker and remove its files."""
        self._finalizer()


def _shm_dir() -> str | None:
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


def _shutdown(conn: Connection, reply: Connection, process: subprocess.Popen[bytes],
              folder: Path) -> None:
    try:
        conn.send(None)
    except (OSError, ValueError):
        pass
    conn.close()
    try:
        process.wait(timeout=1.0)
    except subprocess.TimeoutExpired:
        process.kill()
        try:  # SIGKILL ends it; a starved machine may take a while to schedule the exit
            process.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            pass  # abandoned rather than raised into a node's or a solve's shutdown
    reply.close()
    shutil.rmtree(folder, ignore_errors=True)


# -- the live side ---------------------------------------------------------------------------

@dataclass
class ConvergeState:
    """What the live side knows about its solutions (reported in ``/diagnostics``).

    Attributes:
        solution_edges: edges in the solution merged last (all of them are at its optimum
            when it converged); H₂O revisits only edges from here on.
        converged_edges: edges in the last converged solution merged.
        converged_chi2: χ² of that solution (its optimum).
        solves, merges, dropped, failures: solutions computed, merged, dropped as stale,
            and solves that failed.
        last_error: why the last failed solve failed.
    """

    solution_edges: int = 0
    converged_edges: int = 0
    converged_chi2: float = math.nan
    solves: int = 0
    merges: int = 0
    dropped: int = 0
    failures: int = 0
    last_error: str = ""


def merge_solution(tree: PoseTree, sol: Solution) -> None:
    """Write the whole solution into the live tree at once (:class:`StagedMerge` in one
    slice): every snapshot node at its solved pose, every node added after the snapshot
    at its tree-relative pose under its parent."""
    staged = StagedMerge(sol)
    staged.stage(tree.parent, 0, sol.nodes)
    staged.commit(tree)


def solved_locals(parent: np.ndarray, sol: Solution, idx: np.ndarray
                  ) -> tuple[np.ndarray, Array, Array]:
    """The local transforms the solution gives the snapshot nodes ``idx`` under ``parent``
    (theirs): which of them it places (tops, and children of snapshot nodes) and, for
    those, the transforms."""
    top = parent == EARTH
    placed = top | (parent < sol.nodes)
    i, p, top = idx[placed], parent[placed], top[placed]
    R = np.empty((len(i), 3, 3))
    t = np.empty((len(i), 3))
    R[top], t[top] = sol.R[i[top]], sol.t[i[top]]
    R[~top], t[~top] = geo.between(sol.R[p[~top]], sol.t[p[~top]], sol.R[i[~top]],
                                   sol.t[i[~top]])
    return placed, geo.renormalize(R), t


class StagedMerge:
    """A solution's local transforms, computed in slices beside the live tree and written
    into it at once (:meth:`commit`): a map left half merged at a callback's end is part
    solution, part the poses from before, neither of which its edges agree with (manhattan:
    χ² 15.7 times the optimum after a callback that ended with 2,426 of 4,253 nodes
    merged)."""

    def __init__(self, sol: Solution) -> None:
        self.sol = sol
        self.parent = np.empty(sol.nodes, dtype=np.int64)
        self.placed = np.zeros(sol.nodes, dtype=bool)
        self.R = np.empty((sol.nodes, 3, 3))
        self.t = np.empty((sol.nodes, 3))

    def stage(self, tree_parent: np.ndarray, lo: int, hi: int) -> None:
        """The local transforms of snapshot nodes ``lo … hi-1`` under their parents now."""
        idx = np.arange(lo, hi)
        self.parent[lo:hi] = tree_parent[lo:hi]
        placed, R, t = solved_locals(self.parent[lo:hi], self.sol, idx)
        self.placed[lo:hi] = placed
        self.R[idx[placed]], self.t[idx[placed]] = R, t

    def commit(self, tree: PoseTree) -> None:
        """Write the staged transforms into ``tree``: every snapshot node at its solved
        pose. Nodes re-parented since they were staged, and nodes hung under a node newer
        than the snapshot (by a rebalancing), get theirs under the parent they have now;
        newer nodes keep their local transforms."""
        n = self.sol.nodes
        keep = (tree.parent[:n] == self.parent) & self.placed
        tree.R[:n][keep] = self.R[keep]
        tree.t[:n][keep] = self.t[keep]
        rest = np.flatnonzero(~keep)
        if not len(rest):
            return
        # Where every pose will be: the snapshot's solved, the newer ones under their parents.
        R = np.empty((tree.n, 3, 3))
        t = np.empty((tree.n, 3))
        R[:n], t[:n] = self.sol.R, self.sol.t
        tree.compose_below(R, t, n)
        parent = tree.parent[rest]
        top = parent == EARTH
        under = np.where(top, 0, parent)
        R_loc, t_loc = geo.between(R[under], t[under], R[rest], t[rest])
        tree.R[rest] = geo.renormalize(np.where(top[:, None, None], R[rest], R_loc))
        tree.t[rest] = np.where(top[:, None], t[rest], t_loc)


class LiveIterations:
    """Damped Gauss–Newton on the live map itself, in phases that each fit an idle step of a
    few milliseconds: no whole iteration does on a graph of a few thousand edges (intel,
    2,512 edges: linearizing 1.4 ms, the factorization and solve 1.0, scoring the step's
    poses 1.4, the tree taking them 1.3).

    The phases, each run when its cost model predicts it fits the time left: the system of
    the edges and free nodes (once per ``key``), the linearization at the tree's poses, the
    damped step solved and scored at its poses with the tree untouched, and the tree taking
    a step that lowered χ² (whose linearization is the next step's). A step that raises χ²
    is never seen by the map: its damping is raised for the next try. A phase left half-way
    is dropped when the key (edges, generation, merges) or a world pose changed in between.
    """

    def __init__(self, solver: H2OSolver) -> None:
        self.system = ExactSystem(solver)
        self.damping = 0.0
        self.iterations = 0
        #: Edges in the system of the last step the map took: a budgeted update of any of
        #: them after it would move the map away from that step's better χ².
        self.solved_edges = 0
        self._key: tuple[int, int, int] | None = None
        self._settled: tuple[int, int, int] | None = None
        self._world: WorldSystem | None = None
        self._lin: WorldLinearization | None = None
        self._trial: WorldLinearization | None = None  # a step that lowered χ², not taken
        # Seconds by edges (system, linearization, solve and score) and by nodes (taking a
        # step); priors from intel's numbers above.
        self.system_cost = CostModel((2e-4, 1e-6), (3000.0,))
        self.lin_cost = CostModel((2e-4, 6e-7), (3000.0,))
        self.solve_cost = CostModel((3e-4, 1e-6), (3000.0,))
        self.take_cost = CostModel((1e-4, 8e-7), (3000.0,))

    @property
    def settled(self) -> bool:
        """No step helps the map of the current key (set by :meth:`run`)."""
        return self._settled is not None and self._settled == self._key

    def run(self, key: tuple[int, int, int], deadline: float, clock: Any,
            safety: float) -> None:
        """The phases that fit before ``deadline`` for the map of ``key``."""
        if key == self._settled:
            return
        if key != self._key:
            self._key, self._world, self._lin, self._trial = key, None, None, None
        elif not self._poses_kept():
            self._lin, self._trial = None, None
        solver = self.system.solver
        m, n = solver.num_edges, solver.num_nodes
        while True:
            if self._world is None:
                if not self.system_cost.fits(deadline - clock(), safety, m):
                    return
                begin = clock()
                self._world = self.system.system()
                self.system_cost.update(clock() - begin, m)
            elif self._lin is None:
                if not self.lin_cost.fits(deadline - clock(), safety, m):
                    return
                begin = clock()
                self._lin = self.system.linearize(self._world)
                self.lin_cost.update(clock() - begin, m)
            elif self._trial is None:
                if not self.solve_cost.fits(deadline - clock(), safety, m):
                    return
                begin = clock()
                first = not self._lin.system.factor_ready
                self._try(self._lin)
                if not first:
                    # A system's first solve runs the factorization's symbolic analysis
                    # too (intel: 2.9 ms against 1.0): as a sample it would keep every
                    # later solve from fitting, and none would run to correct it.
                    self.solve_cost.update(clock() - begin, m)
                if self.damping > MAX_DAMPING:  # no step helps: at a minimum
                    self._settle(key)
                    return
            else:
                if not self.take_cost.fits(deadline - clock(), safety, n):
                    return
                begin = clock()
                solver.tree.set_world_poses(self._trial.R, self._trial.x)
                self.take_cost.update(clock() - begin, n)
                self.iterations += 1
                self.solved_edges = key[0]
                before, self._lin, self._trial = self._lin.chi2, self._trial, None
                # converge_exact's test, so that the iterations are its own
                if settled(before, self._lin.chi2, solver.config.exact_tolerance):
                    self._settle(key)
                    return

    def _try(self, lin: WorldLinearization) -> None:
        """Solve the damped step from ``lin`` and score it at its poses."""
        self._trial = scored_step(self.system, lin, self.damping)
        self.damping = next_damping(self.damping, self._trial is not None)

    def _settle(self, key: tuple[int, int, int]) -> None:
        self._settled, self._lin, self._trial, self.damping = key, None, None, 0.0

    def _poses_kept(self) -> bool:
        """The map's world poses are those the linearization was taken at: nothing moved a
        pose since (a re-parenting by the balancing moves none, a merge or a spread does)."""
        if self._lin is None:
            return True
        R, x = self.system.solver.world_poses()
        lin = self._lin
        return (len(x) == len(lin.x) and np.allclose(x, lin.x, rtol=0.0, atol=POSE_KEPT_M)
                and np.allclose(R, lin.R, rtol=0.0, atol=POSE_KEPT_M))


#: World poses this close (metres, and rotation-matrix entries) to a linearization's are the
#: same poses: a re-parenting recomposes them to within rounding.
POSE_KEPT_M = 1e-9


class Converger:
    """Keeps the live solver's map converging to the optimum of the edges so far; see the
    module docstring. :meth:`work` is called from every step with that step's deadline."""

    def __init__(self, solver: H2OSolver, background: str = "inline",
                 iterations: int = 50, growth: float = 0.5,
                 robust: RobustConfig | None = None) -> None:
        if background not in BACKGROUNDS:
            raise ValueError(
                f"unknown background {background!r}; choose one of {', '.join(BACKGROUNDS)}")
        self.solver = solver
        self.background = background
        self.iterations = iterations
        self.growth = growth
        self.robust = robust
        self.job_iterations = 5
        self.state = ConvergeState()
        #: Bumped when the live side moves whole subtrees (a join, a GPS alignment): a
        #: solution of an older snapshot would undo the move and is dropped.
        self.generation = 0
        self._inline = ExactProblem(solver.planar, solver.config, robust)
        self._worker: WorkerProcess | None = None
        if background == "process":
            self._worker = WorkerProcess(solver.planar, solver.config, solver.info.shape[-1],
                                         robust)
        self._sent = 0  # edges the worker holds
        self._written = 0  # edges written to the worker's shared file
        self._failed_at = -1  # edges when the last solve failed: retried once more arrive
        self._global_at = -1  # edges when the map was last solved from the global start
        self._merging: Solution | None = None
        self._staged: StagedMerge | None = None  # its local transforms so far
        self._cursor = 0  # nodes of it staged
        #: A solution of fewer edges than this is dropped, unless its merge has begun: it
        #: was solved without a closure whose first correction it would undo (:meth:`stale`).
        self._stale_before = 0
        # Seconds: an inline solve by edges × linearizations; a merge slice by its nodes, its
        # commit by the tree's; a snapshot by nodes (memory copies: 5 ns a node on 10k).
        # A robust solve has a fixed cost the per-edge slope cannot learn from a first
        # sample it was not predicted to have: 9.5 ms on a 2-node graph (1.2 ms without a
        # kernel), which the first callback of a node beside a worker paid (11.7 ms at a
        # 5 ms budget). Without a worker the inline solves are the only ones, so the prior
        # stays the plain one there and the model learns from what they cost.
        fixed_s = 8e-3 if robust is not None and background == "process" else 1e-3
        self.inline_cost = CostModel((fixed_s, 4e-6), (30000.0,))
        self.merge_cost = CostModel((2e-5, 2e-7), (1000.0,))
        self.commit_cost = CostModel((5e-5, 1e-7), (3000.0,))
        self.copy_cost = CostModel((5e-5, 2e-8), (1000.0,))
        self._live: LiveIterations | None = None
        self._submitted_at = 0.0
        self._job_s = 0.0  # how long the last job took, submitted to collected

    @property
    def enabled(self) -> bool:
        """The mechanism runs at all (``background`` is not ``"off"``)."""
        return self.background != "off"

    @property
    def busy(self) -> bool:
        """A solve runs in the worker or a solution is being merged."""
        return self._merging is not None or (self._worker is not None and self._worker.busy)

    def outside(self) -> int:
        """Edges not in the last converged solution merged."""
        return self.solver.num_edges - self.state.converged_edges

    def work(self, deadline: float, clock: Any, unlimited: bool, idle: bool,
             safety: float, hold_before: int = 0) -> Solution | None:
        """Merge, solve or dispatch what fits before ``deadline``; returns a solution whose
        merge this call completed.

        ``unlimited``: no budget (merge whole, solve inline on the geometric schedule);
        ``idle``: no edge arrived since the last step (solve inline whenever it fits);
        ``hold_before``: a solution of fewer edges waits, also one whose merge has begun:
        the rest of its merge, after a closure's correction in the same step, would put back
        the poses from before it (kitti_00, closure 4,455 → 5: r 1,899 right after its
        callback); the next step merges it and corrects the closure again.
        """
        if not self.enabled:
            return None
        self._collect(clock)
        self._stream_edges()
        if self._merging is None and not self.busy and self._wanted(unlimited, idle):
            if unlimited or self._inline_fits(deadline - clock(), safety, idle):
                # Budgeted, a few iterations at a time as the worker's jobs: the cost of a
                # solve to convergence depends on iterations no model can foresee (an idle
                # step of 10 ms ran 24 ms).
                self._solve_inline(clock, self.iterations if unlimited else self.job_iterations)
            elif self._worker is not None:
                self._dispatch(deadline, clock, safety)
        elif idle and not unlimited and self._merging is None and self._global_due():
            self._dispatch(deadline, clock, safety, from_global=True)
        elif idle and not unlimited and self._merging is None and self._starved(clock):
            self._iterate_live(deadline, clock, safety)
        sol = self._merging
        if sol is None or sol.edges < hold_before:
            return None
        return self._merge(math.inf if unlimited else deadline, clock, safety)

    def _global_due(self) -> bool:
        """The map is converged at every edge and has not been solved from the global start
        at this many (:meth:`ExactProblem.solve`'s ``from_global``): the robot stopped, so
        the worker tries once whether a start that needs no guess reaches a lower χ² than
        the live map's basin. Beside a worker only: a whole solve does not fit a callback."""
        m = self.solver.num_edges
        return (self._worker is not None and not self.busy and m > 0
                and m == self.state.converged_edges and self._global_at != m
                and m != self._failed_at)

    def _starved(self, clock: Any) -> bool:
        """The worker's job is out for much longer than jobs take: on an idle machine the
        worker's answers keep the map converging and live iterations would only repeat its
        work in the callbacks."""
        return (self._worker is not None and self._worker.busy and clock() - self._submitted_at
                > max(STARVED_FACTOR * self._job_s, STARVED_MIN_S))

    def _iterate_live(self, deadline: float, clock: Any, safety: float) -> None:
        """Damped Gauss–Newton on the live map, as many of its phases as are predicted to
        fit before ``deadline`` (:class:`LiveIterations`). The worker's solution still
        merges over it: solved from an earlier snapshot to convergence, it is at least as
        good on the edges it holds."""
        if self._live is None:
            self._live = LiveIterations(self.solver)
        self._live.run((self.solver.num_edges, self.generation, self.state.merges),
                       deadline, clock, safety)

    @property
    def live_solved_edges(self) -> int:
        """Edges the live map's last Gauss–Newton step solved together (0: none yet)."""
        return 0 if self._live is None else self._live.solved_edges

    @property
    def live_iterations(self) -> int:
        """Steps the live map took in idle steps while the worker starved."""
        return 0 if self._live is None else self._live.iterations

    def _wanted(self, unlimited: bool, idle: bool) -> bool:
        m = self.solver.num_edges
        if m == 0 or m == self._failed_at:
            return False
        if m > self.state.converged_edges and (idle or not unlimited):
            return True
        # Unbudgeted: solve when the edges outside the solution have grown enough, so that
        # replaying a long bag costs a few solves in all.
        return m - self.state.converged_edges > self.growth * self.state.converged_edges

    def _inline_fits(self, remaining: float, safety: float, idle: bool) -> bool:
        work = self.solver.num_edges * (self.job_iterations + 1)
        if not (idle or self._worker is None or self.state.converged_edges == 0):
            # Beside a worker, inline solves are for the small graphs it is not needed for.
            return self.inline_cost.predict(work) * 4.0 < remaining
        return self.inline_cost.predict(work) * self.inline_cost.margin(safety) < remaining

    def _snapshot(self) -> tuple[np.ndarray, Array, Array]:
        n = self.solver.num_nodes
        tree = self.solver.tree
        return tree.parent[:n], tree.R[:n], tree.t[:n]

    def _solve_inline(self, clock: Any, iterations: int, regraduate: bool = False) -> None:
        """Solve here and now, ``iterations`` at most; the cost model learns seconds per
        edge and linearization (one per iteration, and the start), except from a solve that
        also graduated afresh (``regraduate``), which is not the budgeted solves' kind."""
        begin = clock()
        solver = self._inline.solver
        self._inline.add_edges(EdgeRows.of(self.solver, solver.num_edges))
        parent, R, t = self._snapshot()
        sol = self._inline.solve(parent.copy(), R.copy(), t.copy(), self.solver.num_edges,
                                 self.generation, iterations, regraduate)
        if not regraduate:
            self.inline_cost.update(clock() - begin,
                                    self.solver.num_edges * (sol.iterations + 1))
        self._received(sol)

    #: Most edges one step writes to the worker's file (a few hundred microseconds): new
    #: edges stream there as they arrive, so a snapshot only copies the tree.
    STREAM_CHUNK = 1024

    def _stream_edges(self) -> None:
        worker = self._worker
        m = self.solver.num_edges
        if worker is None or self._written >= m:
            return
        # A new file only between jobs: a running job and a merge read the current one.
        if not self.busy and worker.ensure_capacity(self.solver.num_nodes, m):
            self._written = self._sent  # the worker holds the older edges
        shared = worker.shared
        if shared is None:
            return
        hi = min(m, self._written + self.STREAM_CHUNK, len(shared["kind"]))
        s = slice(self._written, hi)
        for name in ("kind", "a", "b", "meas_R", "meas_t", "info"):
            shared[name][s] = getattr(self.solver, name)[s]
        self._written = hi

    def _dispatch(self, deadline: float, clock: Any, safety: float,
                  from_global: bool = False) -> None:
        worker = self._worker
        assert worker is not None
        n, m = self.solver.num_nodes, self.solver.num_edges
        if self._written < m:
            return  # the backlog of a new file or a restarted worker streams first
        if not self.copy_cost.fits(deadline - clock(), safety, n):
            self.copy_cost.forget()
            return
        # A fresh file's first touches fault its pages in: no sample for the model.
        fresh = worker.ensure_capacity(n, m)
        if fresh:
            self._written = self._sent
            return
        begin = clock()
        shared = worker.shared
        assert shared is not None
        parent, R, t = self._snapshot()
        shared["parent"][:n], shared["R"][:n], shared["t"][:n] = parent, R, t
        # A few iterations per job: each answer is merged as it comes (the map improves
        # while the robot drives) and the next job takes in the edges that arrived meanwhile.
        # From the global start, a whole solve: its answer is compared with the live one's.
        iterations = self.iterations if from_global else min(self.iterations,
                                                             self.job_iterations)
        worker.submit(n, m, self.generation, iterations, from_global)
        if from_global:
            self._global_at = m
        self._submitted_at = clock()
        self._sent = m
        self.copy_cost.update(clock() - begin, n)

    def _collect(self, clock: Any) -> None:
        if self._worker is None:
            return
        sol = self._worker.poll()
        if sol is None:
            return
        self._job_s = clock() - self._submitted_at
        if not sol.error:
            assert self._worker.shared is not None
            # Views: no new snapshot is written until this one is merged.
            sol.R = self._worker.shared["R_out"][: sol.nodes]
            sol.t = self._worker.shared["t_out"][: sol.nodes]
            if sol.weights is not None:
                sol.weights = self._worker.shared["w_out"][: sol.edges].copy()
        elif not self._worker.alive:
            # Started again; the new worker holds no edges yet.
            self._worker.close()
            self._worker = WorkerProcess(self.solver.planar, self.solver.config,
                                         self.solver.info.shape[-1], self.robust)
            self._sent = self._written = 0
        self._received(sol)

    def _received(self, sol: Solution) -> None:
        self.state.solves += 1
        if sol.error:
            self.state.failures += 1
            self.state.last_error = sol.error
            self._failed_at = self.solver.num_edges
        elif sol.generation != self.generation or sol.edges < self._stale_before:
            self.state.dropped += 1
        else:
            self._merging, self._cursor = sol, 0

    def stale(self, edges: int) -> None:
        """Solutions of fewer than ``edges`` edges are not merged (one whose merge has begun
        still finishes): the newest of them changed the map so much that a solution without
        it would put back the map from before (kitti_00, a closure 4,450 poses back: χ² 216
        after its first correction, 1.7·10⁵ after the merge of a solution solved just before
        it). The next snapshot holds it; a worker costs one job per such edge."""
        self._stale_before = max(self._stale_before, edges)

    def _merge(self, deadline: float, clock: Any, safety: float) -> Solution | None:
        sol = self._merging
        assert sol is not None
        if sol.generation != self.generation or (self._cursor == 0
                                                 and sol.edges < self._stale_before):
            self.state.dropped += 1
            self._merging = self._staged = None
            return None
        staged = self._staged_for(sol)
        while self._cursor < sol.nodes:
            c0, c1 = self.merge_cost.coef
            room = (deadline - clock()) / self.merge_cost.margin(safety) - c0
            count = sol.nodes - self._cursor if deadline == math.inf else int(room / c1)
            if count < min(256, sol.nodes - self._cursor):
                self.merge_cost.forget()
                return None  # slices too small cost more in overhead than they move
            begin = clock()
            hi = min(sol.nodes, self._cursor + count)
            staged.stage(self.solver.tree.parent, self._cursor, hi)
            self.merge_cost.update(clock() - begin, hi - self._cursor)
            self._cursor = hi
        # The commit is a pass over the whole tree, priced on its own: folded into the last
        # slice's sample, it taught the slices' model a cost they do not have.
        tree = self.solver.tree
        if deadline != math.inf and not self.commit_cost.fits(deadline - clock(), safety,
                                                              tree.n):
            self.commit_cost.forget()
            return None
        begin = clock()
        staged.commit(tree)
        self.commit_cost.update(clock() - begin, tree.n)
        self._merging = self._staged = None
        state = self.state
        state.merges += 1
        state.solution_edges = sol.edges
        if sol.converged:
            state.converged_edges, state.converged_chi2 = sol.edges, sol.chi2
        return sol

    def _staged_for(self, sol: Solution) -> StagedMerge:
        """The staging of ``sol``'s merge, begun afresh when it is not the one under way."""
        if self._staged is None or self._staged.sol is not sol:
            self._staged, self._cursor = StagedMerge(sol), 0
        return self._staged

    def solve_now(self, clock: Any) -> Solution | None:
        """Solve inline and merge whole, dropping any solution still under way (it is older).
        A robust solve here is the robust optimum: the carried decisions and a graduation
        afresh, the lower TLS cost kept.

        Returns the merged solution (None without edges, or when the solve failed)."""
        self.generation += 1
        self._merging = self._staged = None
        if self.solver.num_edges == 0:
            return None
        self._solve_inline(clock, self.iterations, regraduate=True)
        if self._merging is None:
            return None
        return self._merge(math.inf, clock, 1.0)

    def close(self) -> None:
        """Stop the worker process, if any."""
        if self._worker is not None:
            self._worker.close()

