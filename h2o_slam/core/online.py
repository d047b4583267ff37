"""H₂O online: edges as a robot produces them, and a per-call time budget.

:class:`OnlineH2O` wraps an :class:`~h2o_slam.core.solver.H2OSolver` with what running on a robot
needs (thesis 3.3.9–3.3.13):

* :meth:`OnlineH2O.add_edge` — Algorithm 2 (AddEdge): a new node joins the tree through its
  edge; a cross edge that leaves its deeper end more than one level below the other re-parents
  it and queues the breadth-first rebalancing (3.3.9); an edge between two separate trees
  merges them by growing the larger tree into the smaller one; a GPS edge waits until its
  subtree has ``gps_align_count`` of them, whose best fit then sets the subtree's global pose
  (3.3.10).
* :meth:`OnlineH2O.step` — one budgeted step: queued rebalancing first (bounded), then new
  edges in arrival order, each solved for as many nodes as the calibrated cost model says fit
  in the time left (interpolated solving below the domain size, a GPS edge with its upstream
  GPS edges in one batch); an edge that does not fit even at the smallest size waits for the
  next step. Time left over revisits old edges, highest residual first. Every update is
  guarded: one that raises the energy is undone and retried at half the step.

Work is never *started* when the cost model predicts it would overrun; the model is a linear
fit of the measured time of each update to ``(1, domain size, solved size)``, refitted by
recursive least squares as the robot runs.
"""

from __future__ import annotations

import functools
import gc
import itertools
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.blas import BlasLimit
from h2o_slam.core.capacity import Growable, GrowAhead, ensure
from h2o_slam.core.condensed import CondensedLoop, Reduced, planar_chi2, planar_poses
from h2o_slam.core.converge import BACKGROUNDS, Converger, Solution
from h2o_slam.core.errors import GraphError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, edge_chi2
from h2o_slam.core.heap import keep_freed_memory
from h2o_slam.core.loop_spread import LoopSolve, closure_moved, spread_loop
from h2o_slam.core.robust import RobustConfig
from h2o_slam.core.solver import H2OSolver, SolverConfig
from h2o_slam.core.timing import CostModel, UpdateCost
from h2o_slam.core.warmup import ensure_warm_up

#: Steps a queued spread that does not fit is tried in before it is given up.
SPREAD_TRIES = 8
#: A closure whose χ² at the current map is below this is not spread (measured on CSAIL:
#: nine in ten spreads of such closures were refused, at 1-2 ms each).
SPREAD_MIN_CHI2 = 10.0
#: χ² of a closure before its first correction above which (and above the map's own) a
#: solution without it is dropped rather than merged (:meth:`Converger.stale`).
BIG_CORRECTION_CHI2 = 100.0
#: Fewest poses after the newest tie inside a crossed loop for its tail to take the closure's
#: correction (:meth:`OnlineH2O._spread_tail`).
TAIL_MIN_POSES = 3
#: Most closures newer than a merged solution looked at again, the newest (a worker far
#: behind leaves thousands; each look is a residual inside a callback's budget: with 32,
#: intel's merges spent up to 1.2 ms on it, p99 0.24 ms, and queued none again).
RELAX_AGAIN_MAX = 8


@dataclass(frozen=True)
class OnlineConfig:
    """Online behaviour; defaults follow the thesis where it gives one.

    Attributes:
        d_max: most nodes solved for per edge (``None``: the whole domain when time allows).
        d_max_min: fewest nodes worth solving for; an edge that cannot fit this waits.
        balance: keep the tree balanced (3.3.9).
        balance_share: fraction of a budget the rebalancing queue may use before new edges.
        balance_max_subtree: largest subtree a rebalancing step re-parents; moving one costs
            time in its size (every path through it changes), and a budget cannot absorb
            thousands of nodes at once. ``None``: no limit.
        gps_align_count: GPS edges a subtree needs before its global pose is fitted (3.3.10).
        guard: undo updates that raise the energy, retrying at half the step.
        guard_retries: halvings tried before an update is skipped.
        safety: factor applied to predicted costs before comparing them with the time left
            (the cost model raises it when it sees larger misses).
        reserve: fraction of each budget held back for bookkeeping and timing jitter.
        freeze_gc: after each step, move every object alive into the garbage collector's
            permanent generation (``gc.freeze``), so that Python's full collections, which
            scan every tracked object, stay small. Process-wide; objects are still freed by
            reference counting and young cycles are collected before each freeze, but cycles
            among objects frozen earlier wait for ``gc.unfreeze()`` (``H2ONode.destroy_node``
            calls it).
        heap_reserve_mb: keep memory the process frees for its own reuse and touch this
            many MB of heap at construction (:func:`~h2o_slam.core.heap.keep_freed_memory`),
            so that a callback's arrays land on resident pages, not fresh ones (a page fault
            each: on a virtual machine up to 3 ms per MB). Process-wide; 0: leave ``malloc``
            as it is.
        blas_threads: threads of every BLAS the process has loaded while this solver runs
            (process-wide, :class:`h2o_slam.core.blas.BlasLimit`; restored by :meth:`close`;
            ``None`` leaves them): a budgeted step's linear algebra is small, and the extra
            threads of a BLAS spin after each call on the callbacks' core.
        background: where the exact solves that take the map to the optimum run
            (:mod:`h2o_slam.core.converge`): ``"process"`` (a worker process beside the steps),
            ``"inline"`` (within steps, when a whole solve fits the time left, and on a
            geometric schedule in unbudgeted steps) or ``"off"`` (H₂O's updates alone).
        merge_share: fraction of a budget a waiting exact solution may take to be merged
            before new edges are relaxed (the rest of it merges after them).
        exact_iterations: most Gauss–Newton iterations of one exact solve, as
            ``h2o-solve``'s: a robust solve's first least-squares solve from a map bent by
            false closures needs them (measured on manhattan with 100 false closures, the
            map as the stream left it: capped at 50, ``~/exact_solve`` kept 59 true closures
            out at a TLS cost of 7197; at 100, 5994, as ``h2o-solve`` on the same graph).
        exact_growth: unbudgeted steps solve exactly once the edges outside the last
            solution reach this many times those in it.
        unlimited_s: a budget this long or longer means no budget: nothing a robot runs
            per callback takes a second, and such a budget asks for the full solution, not
            for the step to spin through it.
        spread_loops: a new loop closure is first spread along its odometry chain
            (:mod:`h2o_slam.core.loop_spread`: the loop's own least-squares correction, kept
            only if the χ² of the edges it moves falls), then relaxed as any edge; so is one
            that a merged exact solution, older than it, left out.
        spread_steps: Gauss–Newton steps of a spread.
        solve_loops: with ``spread_loops``, the poses after a new closure's older end are
            first solved by Gauss–Newton with everything older held
            (:class:`~h2o_slam.core.loop_spread.LoopSolve`) wherever a few iterations fit the
            step's budget; the spread serves the loops too long for it.
        robust: the exact solves weigh loop closures and GPS fixes as possible outliers
            (:mod:`h2o_slam.core.robust`; odometry trusted) and each merged solution sets
            every edge's weight, so a decision is revised by every solve; ``None``: least
            squares.
    """

    d_max: int | None = None
    d_max_min: int = 2
    balance: bool = True
    balance_share: float = 0.3
    balance_max_subtree: int | None = 256
    gps_align_count: int = 3
    guard: bool = True
    guard_retries: int = 3
    safety: float = 1.2
    reserve: float = 0.1
    freeze_gc: bool = True
    heap_reserve_mb: int = 64
    blas_threads: int | None = 1
    background: str = "inline"
    merge_share: float = 0.3
    exact_iterations: int = 100
    exact_growth: float = 0.5
    unlimited_s: float = 1.0
    spread_loops: bool = True
    spread_steps: int = 2
    solve_loops: bool = True
    robust: RobustConfig | None = None

    def __post_init__(self) -> None:
        if self.d_max is not None and self.d_max < 1:
            raise ValueError("d_max must be at least 1")
        if self.d_max_min < 1:
            raise ValueError("d_max_min must be at least 1")
        if not 0.0 <= self.balance_share <= 1.0:
            raise ValueError("balance_share must be in [0, 1]")
        if not 0.0 <= self.reserve < 1.0:
            raise ValueError("reserve must be in [0, 1)")
        if self.heap_reserve_mb < 0:
            raise ValueError("heap_reserve_mb must be >= 0")
        if self.gps_align_count < 2:
            raise ValueError("gps_align_count must be at least 2")
        if self.background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)}")
        if not 0.0 <= self.merge_share <= 1.0:
            raise ValueError("merge_share must be in [0, 1]")
        if self.exact_iterations < 1:
            raise ValueError("exact_iterations must be at least 1")
        if not self.exact_growth > 0.0:
            raise ValueError("exact_growth must be positive")
        if not self.unlimited_s > 0.0:
            raise ValueError("unlimited_s must be positive")


@dataclass
class StepReport:
    """What one :meth:`OnlineH2O.step` did.

    Attributes:
        elapsed_s: wall time of the step.
        relaxed: new edges relaxed.
        revisited: old edges relaxed with the time left over.
        revisit_s: wall time spent on those (optional work: the step fills its budget with
            it, and would be just as correct without).
        deferred: new edges still waiting (they did not fit).
        undone: updates the guard undid (each retry counts).
        smallest_d_max: the smallest number of nodes solved for in an update (0 if none).
        balanced: the rebalancing queue is empty.
        merged: edges in the exact solution whose merge this step completed (0: none).
        predictions: ``(predicted_s, remaining_s)`` of every update started.
    """

    elapsed_s: float = 0.0
    relaxed: int = 0
    revisited: int = 0
    revisit_s: float = 0.0
    deferred: int = 0
    undone: int = 0
    smallest_d_max: int = 0
    balanced: bool = True
    merged: int = 0
    predictions: list[tuple[float, float]] = field(default_factory=list)


class OnlineH2O:
    """Incremental H₂O with a per-step time budget; see the module docstring.

    Nodes are numbered in the order they are added, from 0.
    """

    def __init__(
        self, *, planar: bool, config: SolverConfig | None = None,
        online: OnlineConfig | None = None,
    ) -> None:
        # Budgeted callbacks must not pay for loading kernels: all of them now, unless a
        # node is loading them beside its executor (it holds its inputs until they are).
        ensure_warm_up()
        self.solver = H2OSolver(planar=planar, config=config)
        self.online = online or OnlineConfig()
        if self.online.heap_reserve_mb:
            keep_freed_memory(self.online.heap_reserve_mb)
        self._blas = (None if self.online.blas_threads is None
                      else BlasLimit(self.online.blas_threads))
        self.cost = UpdateCost()
        self.pending: deque[int] = deque()
        #: The step at which each queued edge first did not fit (:attr:`steps` counts them).
        self.waiting: dict[int, int] = {}
        self.steps = 0
        self._forgotten = 0  # edges that :meth:`_forget_solved` took out of the queue
        self._balance_queue: deque[int] = deque()
        #: Cross edges whose re-parenting (3.3.9) waits for a step.
        self._hang_queue: deque[int] = deque()
        #: Seconds a re-parenting costs per moved or walked node (a moving average).
        self._hang_cost_per_node = 5e-6
        #: Odometry edge into each node (``k-1 → k``), -1 where there is none: the chains
        #: along which loops are spread.
        self._odometry_edge = np.full(64, -1, dtype=np.int64)
        #: Seconds a spread costs: fixed, per node of the map (its world poses gathered and
        #: written back), and per node and edge it moves (measured on kitti_00's first
        #: loop, 2.2 ms for 2900). By the map's size too: a tail spread moves a few poses
        #: of a map of thousands.
        self.spread_cost = CostModel((3e-4, 1.5e-7, 6e-7), (3000.0, 1000.0))
        #: The loop solved where it fits (before the spread is tried).
        self.loop_solve = LoopSolve()
        self.condensed_loop = CondensedLoop()
        #: Closures a merged solution left out, to spread again (:meth:`_after_merge`).
        self._respread: deque[int] = deque()
        self._spread_tries: dict[int, int] = {}
        self._spread_kept: set[int] = set()
        self.spreads = Counter[str]()
        #: Edges a solution must hold to be merged in this step: one past the newest
        #: closure whose correction this step kept (0: any).
        self._corrected = 0
        # Edges whose paths changed under re-parenting and whose contribution to B still
        # belongs to the old path; refreshed within budgets (relaxing one refreshes it too).
        self._stale: dict[int, None] = {}
        self._held_gps: dict[int, list[int]] = {}
        self._aligned: set[int] = set()
        self._priority = np.zeros(64)
        self._refresh_cursor = 0
        # GPS batches: domain size and number of edges.
        self.batch_cost = CostModel((2e-4, 3e-6, 3e-5), (50.0, 5.0))
        self._clock = time.perf_counter
        self._grow_ahead = GrowAhead()
        #: Tracked 99.5th percentile of a step's end past its planned deadline (seconds), and
        #: the extra time held back for it beyond ``reserve``; apart for steps with new input
        #: ([0]) and idle ones ([1]): idle steps, several between two arrivals and seldom
        #: late, held one shared quantile down, and the steps the robot waits on overran
        #: three times as often as it allows (manhattan at 5 ms: 1.6 % of them).
        self._late_q = [0.0, 0.0]
        self._late_s = [0.0, 0.0]
        self.converger = Converger(self.solver, self.online.background,
                                   self.online.exact_iterations, self.online.exact_growth,
                                   self.online.robust)
        #: Robust decisions the merged solutions changed: ``dropped`` (an accepted edge
        #: now out) and ``readmitted`` (an edge held or dropped now in).
        self.decisions: Counter[str] = Counter()
        self._arrived = False  # an edge or pose arrived since the last step

    def close(self) -> None:
        """Stop the exact solver's worker process, if any, and give the process's BLAS its
        threads back."""
        self.converger.close()
        if self._blas is not None:
            self._blas.restore()

    # -- adding -------------------------------------------------------------------------------

    @property
    def num_nodes(self) -> int:
        """Nodes added so far."""
        return self.solver.num_nodes

    def add_pose(self, R_world: Array, t_world: Array) -> int:
        """Add a node that starts a new subtree at a world pose."""
        self._arrived = True
        return self.solver.add_pose(R_world, t_world)

    def add_edge(
        self, kind: int, a: int, b: int, meas_R: Array, meas_t: Array, info: Array
    ) -> int:
        """Add an edge (Algorithm 2); it is relaxed by a later :meth:`step`."""
        solver = self.solver
        self._arrived = True
        n = solver.num_nodes
        merging = (kind == EdgeKind.RELATIVE and a < n and b < n
                   and self._top(a) != self._top(b))
        edge = solver.add_edge(kind, a, b, meas_R, meas_t, info, contribute=False)
        self._grow_priority()
        creates_node = solver.num_nodes > n
        if creates_node and kind == EdgeKind.RELATIVE and b == a + 1:
            self._note_odometry(b, edge)
        if creates_node:
            self._priority[edge] = solver.last_chi2
        else:  # linearized later, within a budget
            self._stale[edge] = None
            self._priority[edge] = np.inf
        if merging:
            self._merge(edge)
        elif kind == EdgeKind.RELATIVE and a < n and b < n and self.online.balance:
            self._maybe_rebalance(edge)
        if kind != EdgeKind.RELATIVE:
            self._add_global(edge)
        elif not (creates_node and solver.last_chi2 <= 1e-18):
            # A new node's own tree edge starts satisfied: relaxing it would change nothing.
            self.pending.append(edge)
            if self.online.spread_loops and abs(a - b) > 1:
                self._respread.append(edge)
        return edge

    def _note_odometry(self, node: int, edge: int) -> None:
        ensure([(self, "_odometry_edge", -1)], node + 1)
        self._odometry_edge[node] = edge

    def _grow_priority(self) -> None:
        ensure([(self, "_priority", 0.0)], self.solver.num_edges)

    def _growables(self) -> list[Growable]:
        """Every per-node and per-edge array of the solver and of this object."""
        s = self.solver
        n, m = s.num_nodes, s.num_edges
        nodes = s.node_arrays() + [(self, "_odometry_edge", -1)]
        edges = s.edge_arrays() + [(self, "_priority", 0.0)]
        return ([Growable(owner, name, fill, n) for owner, name, fill in nodes]
                + [Growable(owner, name, fill, m) for owner, name, fill in edges])

    def _top(self, node: int) -> int:
        return self.solver.tree.top(node)

    # -- tree balancing and merging (3.3.9) ---------------------------------------------------

    def _maybe_rebalance(self, edge: int) -> None:
        """Queue the re-parenting a cross edge calls for (3.3.9). It runs inside a later
        step's budget: moving a subtree costs time in its size, which AddEdge, outside any
        budget, cannot afford."""
        self._hang_queue.append(edge)

    def _hang_edge(self, edge: int, deadline: float) -> bool:
        """Re-parent the deeper end of a cross edge under the other end if it hangs more than
        one level lower; False if that would not fit before ``deadline``."""
        depth = self.solver.tree.depth
        a, b = int(self.solver.a[edge]), int(self.solver.b[edge])
        if depth[a] > depth[b]:
            a, b = b, a
        if depth[b] > depth[a] + 1:
            return self._hang(b, a, edge, deadline)
        return True

    def _hang(self, node: int, parent: int, edge: int, deadline: float = math.inf) -> bool:
        """Re-parent ``node`` and queue its whole subtree: every depth in it dropped, so any
        of their neighbours may now hang lower too (3.3.9's recursion).

        Returns False, moving nothing, when the move is predicted not to fit before
        ``deadline``. A subtree larger than ``balance_max_subtree`` is never moved (returns
        True).
        """
        tree = self.solver.tree
        limit = self.online.balance_max_subtree
        if limit is not None and tree.subtree_exceeds(node, limit):
            return True
        # The cost is the tree path from the new parent to the node (their relative pose)
        # plus the subtree.
        if deadline < math.inf:
            unit = self._hang_cost_per_node
            # The walk is left out: closing a long loop it would never fit, and the loop
            # would never be balanced.
            fits = int((deadline - self._clock()) / unit)
            if fits < 1 or tree.subtree_exceeds(node, fits):
                # Only moves that run give samples: a high estimate must not lock the queue.
                self._hang_cost_per_node = max(0.9 * unit, 1e-6)
                return False
        begin = self._clock()
        path = self.solver.tree_path(parent, node, edge)
        walk = len(path.a_chain) + len(path.b_chain)
        moved, affected = self.solver.reparent(node, parent, edge, refresh=False, path=path)
        sample = (self._clock() - begin) / (len(moved) + walk)
        self._hang_cost_per_node = max(0.8 * self._hang_cost_per_node + 0.2 * sample, 1e-6)
        self._stale.update(dict.fromkeys(affected))
        self._balance_queue.extend(moved)
        return True

    def balance(self, deadline: float = float("inf")) -> bool:
        """Work through the rebalancing queue (breadth-first from re-parented nodes), then
        refresh the regularizer contributions of edges whose paths changed, until both are
        done or ``deadline`` passes. Returns whether both are done."""
        return self._rebalance(deadline) and self._refresh_stale(deadline)

    def _rebalance(self, deadline: float) -> bool:
        solver = self.solver
        depth = solver.tree.depth
        while self._hang_queue and self._clock() < deadline:
            if not self._hang_edge(self._hang_queue[0], deadline):
                return False
            self._hang_queue.popleft()
        while self._balance_queue and self._clock() < deadline:
            u = self._balance_queue[0]
            for e in solver.incident(u):
                if solver.kind[e] != EdgeKind.RELATIVE:
                    continue
                n = int(solver.b[e]) if int(solver.a[e]) == u else int(solver.a[e])
                if depth[n] > depth[u] + 1 and not self._hang(n, u, e, deadline):
                    # Revisited from the start next time: the neighbours done so far no
                    # longer qualify, so nothing is moved twice.
                    return False
            self._balance_queue.popleft()
        return not (self._balance_queue or self._hang_queue)

    def _refresh_stale(self, deadline: float) -> bool:
        """Linearize edges whose contribution to ``B`` is missing or belongs to an old path,
        each only if the cost model says it fits (a refresh costs about what an update
        solving no node costs). Relaxing a stale edge refreshes it too."""
        misfits = 0
        # Oldest first; one that does not fit goes to the back. A few misfits end the call:
        # scanning thousands of stale edges for one that fits would itself cost the budget.
        while self._stale and misfits < 8:
            edge = next(iter(self._stale))
            del self._stale[edge]
            old = self.solver.contribution_size(edge)
            d = len(self.solver.path(edge).domain) + old
            # A refresh linearizes the path as a full update does, without the solve.
            if self.cost.predict_with_margin(d, d, self.online.safety) > deadline - self._clock():
                self._stale[edge] = None
                misfits += 1
                continue
            self.solver.refresh_edges([edge])
        return not self._stale

    def _merge(self, edge: int) -> None:
        """Join two trees through ``edge``: the smaller one is re-rooted at its endpoint and
        hung from the other endpoint, moved rigidly onto the edge's measurement unless GPS
        already placed it."""
        solver = self.solver
        a, b = int(solver.a[edge]), int(solver.b[edge])
        top_a, top_b = self._top(a), self._top(b)
        size_a = len(solver.tree.subtree(top_a))
        size_b = len(solver.tree.subtree(top_b))
        small, big = (a, b) if size_a <= size_b else (b, a)
        self.converger.generation += 1
        top_small = top_a if small == a else top_b
        if top_small not in self._aligned:
            self._move_onto_edge(edge, small, big, top_small)
        nodes = solver.tree.subtree(top_small)
        order, parents, via = self._bfs(small, set(nodes))
        affected = solver.reparent(small, big, edge, refresh=False)[1]
        for node, parent, e in zip(order[1:], parents[1:], via[1:], strict=True):
            affected |= solver.reparent(node, parent, e, refresh=False)[1]
        solver.refresh_edges(affected)
        if self.online.balance:
            self._balance_queue.extend(nodes)
        held = self._held_gps.pop(top_small, [])
        self._held_gps.setdefault(self._top(big), []).extend(held)
        self._release_gps(self._top(big))

    def _move_onto_edge(self, edge: int, small: int, big: int, top_small: int) -> None:
        solver = self.solver
        R_big, t_big = solver.world_pose(big)
        R_k, t_k = solver.meas_R[edge], solver.meas_t[edge]
        if int(solver.a[edge]) != big:
            R_k, t_k = geo.inverse(R_k, t_k)
        R_want, t_want = geo.compose(R_big, t_big, R_k, t_k)
        R_now, t_now = solver.world_pose(small)
        # T maps the small tree's world frame onto the big one's: T · now = want.
        R_T, t_T = geo.compose(R_want, t_want, *geo.inverse(R_now, t_now))
        tree = solver.tree
        R_top, tree.t[top_small] = geo.compose(R_T, t_T, tree.R[top_small], tree.t[top_small])
        tree.R[top_small] = geo.renormalize(R_top)

    def _bfs(self, start: int, allowed: set[int]) -> tuple[list[int], list[int], list[int]]:
        """Breadth-first order of ``allowed`` from ``start`` over relative edges, with each
        node's parent and the edge that reached it."""
        solver = self.solver
        order, parents, via = [start], [EARTH], [-1]
        seen = {start}
        i = 0
        while i < len(order):
            u = order[i]
            i += 1
            for e in solver.incident(u):
                if solver.kind[e] != EdgeKind.RELATIVE:
                    continue
                n = int(solver.b[e]) if int(solver.a[e]) == u else int(solver.a[e])
                if n in allowed and n not in seen:
                    seen.add(n)
                    order.append(n)
                    parents.append(u)
                    via.append(e)
        # Nodes the edges cannot reach (a subtree joined by GPS only) keep their parent.
        return order, parents, via

    # -- GPS (3.3.10) -------------------------------------------------------------------------

    def _add_global(self, edge: int) -> None:
        top = self._top(int(self.solver.b[edge]))
        if self.solver.kind[edge] != EdgeKind.POSITION or top in self._aligned:
            self.pending.append(edge)
            return
        self._held_gps.setdefault(top, []).append(edge)
        self._release_gps(top)

    def _release_gps(self, top: int) -> None:
        held = self._held_gps.get(top, [])
        if top in self._aligned or len(held) < self.online.gps_align_count:
            return
        self._align(top, held)
        self._aligned.add(top)
        self.pending.extend(self._held_gps.pop(top))

    def _align(self, top: int, edges: list[int]) -> None:
        """Best-fit rigid transform of a subtree onto its GPS fixes (weighted Kabsch; yaw only
        for planar graphs), applied to the subtree's top."""
        solver = self.solver
        nodes = [int(solver.b[e]) for e in edges]
        P = np.array([solver.world_pose(n)[1] for n in nodes])
        Q = solver.meas_t[edges]
        w = np.array([np.trace(solver.info[e][:3, :3]) for e in edges])
        R_T, t_T = geo.best_fit_transform(P, Q, w, planar=solver.planar)
        self.converger.generation += 1
        tree = solver.tree
        R_top, tree.t[top] = geo.compose(R_T, t_T, tree.R[top], tree.t[top])
        tree.R[top] = geo.renormalize(R_top)

    # -- stepping -----------------------------------------------------------------------------

    def step(self, budget_s: float | None = None) -> StepReport:
        """Relax new edges, merge or start exact solves, then revisit edges outside the last
        solution, within ``budget_s``.

        ``None`` (or a budget of ``unlimited_s`` or more): no limit; every new edge is solved
        in full, and the map exactly on the converger's schedule.

        Raises:
            ValueError: ``budget_s`` is negative or NaN.
        """
        if budget_s is not None and not budget_s >= 0.0:
            raise ValueError(f"budget_s must be >= 0 seconds or None, got {budget_s!r}")
        if budget_s is not None and budget_s >= self.online.unlimited_s:
            budget_s = None
        idle, self._arrived = not self._arrived, False
        start = self._clock()
        if budget_s is None:
            deadline = math.inf
        else:
            # Capped: on a starved CPU, holding back more only leaves new edges waiting.
            held = min(budget_s * self.online.reserve + self._late_s[idle],
                       max(0.3, self.online.reserve) * budget_s)
            deadline = start + budget_s - held
        report = StepReport()
        self._corrected = 0
        # New loop closures first: a long loop's own correction is worth more to the map
        # right after its closure than anything else a step can do.
        self._spread_queued(deadline)
        if budget_s is not None and not self._big_closure_queued():
            # Then a waiting solution, within a share: it moves the whole map to an
            # optimum, worth more than any one new edge's update, unless that edge is a
            # closure far off (its update comes first, and holds older solutions).
            self._converge_within(min(deadline, start + self.online.merge_share * budget_s),
                                  False, idle, report)
        self._relax_new(deadline, report)
        self._spread_queued(deadline)
        if self.online.balance:
            share = math.inf if budget_s is None else self.online.balance_share * budget_s
            self._rebalance(min(deadline, start + share))
        report.balanced = (self._refresh_stale(deadline) and not self._balance_queue
                           and not self._hang_queue)
        self._converge_within(deadline, budget_s is None, idle, report)
        # A solution merged just now put back the map without closures newer than it that
        # earlier steps corrected: their corrections again, while time is left.
        self._spread_queued(deadline)
        total = self.solver.num_nodes + self.solver.num_edges
        if budget_s is not None and self._grow_ahead.due(total):
            # Before the revisits, which would take the time to the deadline.
            self._grow_ahead.run(self._growables(), total, deadline, self._clock)
        self.steps += 1
        report.deferred = len(self.pending)
        if self.pending and report.relaxed == 0:
            # Nothing fit: the margin learnt from one slow sample must not lock the queue
            # for good, since only updates that run produce new samples.
            self.cost.relax_margins()
        if budget_s is not None and not self.pending and self.online.background != "process":
            # Revisits settle at H₂O's own fixed point, not at the optimum (thesis 3.5):
            # beside a worker's exact solves they only move the map away from the last
            # solution (measured on city10000 at 5 ms: median r 4.5 with them, 2.4 without).
            revisit_start = self._clock()
            self._revisit(deadline, report)
            report.revisit_s = self._clock() - revisit_start
        if self.online.freeze_gc:
            # Python's full collections scan every live object: on a graph of a few
            # thousand poses that is a 20–40 ms pause at an unpredictable step, which no
            # budget can absorb. Frozen objects are still freed by reference counting.
            # Young cycles are collected first, or every step would freeze some garbage
            # for good; the young generations only hold what this step allocated.
            gc.collect(1)
            gc.freeze()
        end = self._clock()
        report.elapsed_s = end - start
        if budget_s is not None:
            # Past the deadline actually used: measured against one that ignores what was
            # held back, the tracker would see its own correction and settle at half of it
            # (2 % overruns instead of 0.5 % in test_online).
            self._track_lateness(end - deadline, budget_s, idle)
        return report

    def _converge_within(self, deadline: float, unlimited: bool, idle: bool,
                         report: StepReport) -> None:
        # A solution older than a closure corrected in this step would put back the map
        # without that correction (measured on intel: r 2·10⁴ right after the closure's
        # callback): it waits for the next step, which merges it and corrects again.
        merged = self.converger.work(deadline, self._clock, unlimited=unlimited, idle=idle,
                                     safety=self.online.safety,
                                     hold_before=0 if unlimited else self._corrected)
        if merged is not None:
            self._after_merge(merged)
            report.merged = merged.edges
        self._forget_solved(self.converger.live_solved_edges)

    def converge(self) -> Solution | None:
        """Solve the map exactly now, in this call, and merge it: every edge so far at its
        optimum (None when there are no edges, or the solve failed)."""
        merged = self.converger.solve_now(self._clock)
        if merged is not None:
            self._after_merge(merged)
        return merged

    def _after_merge(self, sol: Solution) -> None:
        """Edges in a merged solution are solved: none of them waits any longer. A robust
        solution also sets their weights; the edges whose weight changed have stale
        contributions to ``B``."""
        solved = sol.edges
        self._forget_solved(solved)
        if self.online.spread_loops:
            # The solution placed the map without the closures newer than it: the
            # correction of those whose spread was kept went with the poses it replaced,
            # so they are spread again (measured on intel: the others were refused 97 % of
            # the time, a millisecond each).
            s = self.solver
            newer = np.arange(solved, s.num_edges)
            queued = set(self._respread)
            self._respread.extend(e for e in newer.tolist()
                                  if e in self._spread_kept and e not in queued)
            self._spread_kept = {e for e in self._spread_kept if e >= solved}
        self._relax_again(solved)
        if sol.weights is not None:
            old = self.solver.weight[:solved] > 0.5
            new = sol.weights[:solved] > 0.5
            self.decisions["dropped"] += int(np.count_nonzero(old & ~new))
            self.decisions["readmitted"] += int(np.count_nonzero(~old & new))
            changed = np.flatnonzero(self.solver.weight[:solved] != sol.weights[:solved])
            self.solver.set_weights(sol.weights[:solved], np.arange(solved))
            for edge in changed.tolist():
                self._stale[edge] = None

    def _relax_again(self, solved: int) -> None:
        """Closures newer than a merged solution, whose update an earlier step made (their
        spread did not fit), lost that correction with the poses the merge replaced
        (kitti_00, a closure 4,450 poses back: χ² 216 before the merge of a solution without
        it, 1.7·10⁵ after): those still far off are relaxed again, first in the queue."""
        s = self.solver
        m = s.num_edges
        if solved >= m:
            return
        kinds, a, b = s.kind[solved:m], s.a[solved:m], s.b[solved:m]
        closures = solved + np.flatnonzero((kinds == EdgeKind.RELATIVE) & (np.abs(a - b) > 1)
                                           & (s.weight[solved:m] > 0.0))
        again = [edge for edge in closures[-RELAX_AGAIN_MAX:].tolist()
                 if _chi2_of(s, edge) > SPREAD_MIN_CHI2]
        if again:  # the queue can hold thousands: looked at only when one is far off
            queued = set(self.pending)
            self.pending.extendleft(reversed([e for e in again if e not in queued]))

    def _forget_solved(self, solved: int) -> None:
        """The first ``solved`` edges were solved together, the map at their optimum or on
        its way there: a budgeted update of one of them now would pull the map away from it
        (measured on a 120-pose city: a pending closure's update after the live iterations
        settled left χ² at 1.09 × the optimum)."""
        if solved <= self._forgotten:
            return  # every step would otherwise scan the queue
        self._forgotten = solved
        self.pending = deque(e for e in self.pending if e >= solved)
        for edge in [e for e in self.waiting if e < solved]:
            del self.waiting[edge]

    def restore_weights(self, weights: Array) -> None:
        """Set every edge's robust weight (a saved map's decisions) before any solve; the
        edges at weight 0 leave the budgeted updates' queue."""
        self.solver.set_weights(np.asarray(weights, dtype=float))
        out = set(np.flatnonzero(self.solver.weight <= 0.0).tolist())
        self.pending = deque(e for e in self.pending if e not in out)
        for edge in out:
            self._stale[edge] = None

    def gps_aligned(self, node: int) -> bool:
        """The node's subtree has been placed in the world by its GPS fixes."""
        return self._top(node) in self._aligned

    def add_held_edge(
        self, kind: int, a: int, b: int, meas_R: Array, meas_t: Array, info: Array
    ) -> int:
        """Add an edge at weight 0 between existing nodes: in the graph, never relaxed by
        the budgeted updates, weighed again by every robust exact solve (a closure a cheap
        first filter doubts, kept so that it can be re-admitted)."""
        n = self.solver.num_nodes
        if not (a == EARTH or 0 <= a < n) or not 0 <= b < n:
            raise GraphError(f"held edge ({a}, {b}) must join existing nodes")
        self._arrived = True
        edge = self.solver.add_edge(kind, a, b, meas_R, meas_t, info, contribute=False)
        self.solver.set_weights(np.zeros(1), np.array([edge]))
        self._grow_priority()
        self._priority[edge] = 0.0
        return edge

    def _track_lateness(self, late_s: float, budget_s: float, idle: bool = False) -> None:
        """Follow the 99.5th percentile of how far steps (``idle`` ones apart) end past the
        deadline they worked to (stochastic quantile tracking) and hold back what the fixed
        reserve does not cover.

        Predictions miss by more than any fixed margin now and then (a cache-cold update, a
        busy CPU); what matters for the robot is that those misses stay rarer than 1 in 100.
        """
        k = int(idle)
        q = self._late_q[k]
        step = 0.02 * budget_s
        q = q + step if late_s > q else q - step / 199.0
        self._late_q[k] = max(q, 0.0)
        self._late_s[k] = max(self._late_q[k] - budget_s * self.online.reserve, 0.0)

    def _relax_new(self, deadline: float, report: StepReport, skips: int = 8) -> None:
        """New edges in arrival order. One that does not fit stays queued (in order) and the
        next ones are tried, so a long loop closure cannot hold up the cheap edges behind it;
        after ``skips`` misfits in a row the rest waits too."""
        kept: deque[int] = deque()
        misses = 0
        while self.pending and misses < skips and self._clock() < deadline:
            edge = self.pending.popleft()
            if self._relax_within(edge, deadline, report):
                self.waiting.pop(edge, None)
                report.relaxed += 1
                misses = 0
            else:
                kept.append(edge)
                self.waiting.setdefault(edge, self.steps)
                misses += 1
        # Put back in front, in order: O(misses), where rebuilding the queue cost O(queue)
        # per step (thousands of edges on city10000 while the worker's solves lagged).
        self.pending.extendleft(reversed(kept))

    def _revisit(self, deadline: float, report: StepReport) -> None:
        """Spend the time left on old edges, highest residual first.

        Residuals go stale as other updates move nodes, so each call first re-measures a
        few edges in round-robin order; a revisited edge drops to half its new residual so
        that one stubborn edge cannot take every spare millisecond.
        """
        waiting = set(self.pending)
        # Edges in the last merged exact solution are at its optimum: relaxing one toward
        # its own measurement would only move the map away from it.
        lo = self.converger.state.solution_edges
        m = self.solver.num_edges
        self._refresh_priorities(min(m - lo, 16), deadline, lo)
        tried = 0
        while self._clock() < deadline and tried < m - lo:
            edge = lo + int(np.argmax(self._priority[lo:m]))
            tried += 1
            if edge in waiting or self._priority[edge] <= 0.0:
                break
            if not self._relax_within(edge, deadline, report):
                break
            self._priority[edge] *= 0.5
            report.revisited += 1

    def _refresh_priorities(self, count: int, deadline: float, lo: int = 0) -> None:
        m = self.solver.num_edges
        for _ in range(count):
            if self._clock() >= deadline:
                return
            e = lo + self._refresh_cursor % (m - lo)
            self._refresh_cursor += 1
            self._priority[e] = _chi2_of(self.solver, e)

    def _relax_within(self, edge: int, deadline: float, report: StepReport) -> bool:
        """Relax ``edge`` if it fits before ``deadline``; False if it must wait.

        A GPS edge goes with its upstream GPS edges in one batch when that fits, and alone
        (interpolated if need be) otherwise.
        """
        solver = self.solver
        if solver.kind[edge] == EdgeKind.POSITION and self._relax_gps(edge, deadline, report):
            return True
        d = len(solver.path(edge).domain)
        cap = d if self.online.d_max is None else min(d, self.online.d_max)
        remaining = deadline - self._clock()
        s = self.cost.largest_fitting(d, cap, remaining, self.online.safety)
        if s < min(self.online.d_max_min, cap):
            return False
        report.predictions.append(
            (self.cost.predict_with_margin(d, s, self.online.safety), remaining))
        report.smallest_d_max = s if report.smallest_d_max == 0 else min(report.smallest_d_max, s)
        scale: float | None = None
        for _ in range(self.online.guard_retries + 1):
            begin = self._clock()
            outcome = solver.relax(edge, d_max=s if s < d else None, scale=scale,
                                   guard=self.online.guard)
            self._stale.pop(edge, None)
            self.cost.update(d, s, self._clock() - begin)
            if outcome.accepted:
                self._priority[edge] = min(outcome.energy_after, outcome.chi2_before)
                if solver.kind[edge] == EdgeKind.RELATIVE:
                    self._mark_big(edge, outcome.chi2_before)
                return True
            report.undone += 1
            scale = 0.5 * (solver.temperature if scale is None else scale)
            if deadline - self._clock() < self.cost.predict_with_margin(d, s, self.online.safety):
                break
        # Nothing it tried helped: leave the edge be until the rest of the graph moves.
        self._priority[edge] = 0.0
        return True

    def _spread_queued(self, deadline: float) -> None:
        """Spread the queued closures in order while they fit; one that does not waits
        (with the rest) for a later step."""
        while self._respread and self._clock() < deadline:
            edge = self._respread[0]
            if not self._spread(edge, deadline):
                # A loop too long for any step's budget must not hold the others back.
                self._spread_tries[edge] = self._spread_tries.get(edge, 0) + 1
                if self._spread_tries[edge] < SPREAD_TRIES:
                    return
            self._spread_tries.pop(edge, None)
            self._respread.popleft()

    def _spread(self, edge: int, deadline: float) -> bool:
        """The first correction of a loop closure (:mod:`h2o_slam.core.loop_spread`): the
        poses after its older end solved by Gauss–Newton where a few iterations fit
        (counted ``solved`` in :attr:`spreads`), else its error spread along its odometry
        chain when the chain is whole (``kept``), along the chain after the newest pose
        another edge ties where others cross the loop (``crossed``, and ``tail`` where
        kept); ``refused`` when the χ² of the edges it moves did not fall. False, doing
        nothing, when neither is predicted to fit before ``deadline`` (counted ``late``)."""
        solver = self.solver
        if not _live_closure(solver, edge):
            return True
        a, b = int(solver.a[edge]), int(solver.b[edge])
        chi2_before = _chi2_of(solver, edge)
        if chi2_before < SPREAD_MIN_CHI2:
            return True  # the tree path's update is enough
        done = self._spread_or_solve(edge, min(a, b), max(a, b), deadline)
        if edge in self._spread_kept:
            self._mark_big(edge, chi2_before)
        return done

    def _big_closure_queued(self, look: int = 8) -> bool:
        """One of the first ``look`` queued edges is a closure whose χ² is above what
        :meth:`_mark_big` calls big: merging a solution older than it first took the
        step's time from its update (manhattan, two closures with χ² 3.7·10⁴ and 3.9·10⁵
        waited a callback behind a merge slice of 2,690 nodes: r 162 after it)."""
        s, big = self.solver, self._big_chi2()
        return any(_live_closure(s, edge) and _chi2_of(s, edge) > big
                   for edge in itertools.islice(self.pending, look))

    def _big_chi2(self) -> float:
        """A closure's χ² above which it is far off: above :data:`BIG_CORRECTION_CHI2` and
        the map's converged χ²."""
        ref = self.converger.state.converged_chi2
        return max(BIG_CORRECTION_CHI2, ref if math.isfinite(ref) else 0.0)

    def _mark_big(self, edge: int, chi2_before: float) -> None:
        """A closure whose first correction took its χ² down from more than the whole map's
        (converged) χ²: a solution solved without it must not be merged over it."""
        if chi2_before > self._big_chi2():
            self.converger.stale(edge + 1)
            # And a merge under way waits for the next step, which corrects it again.
            self._corrected = max(self._corrected, edge + 1)

    def _spread_or_solve(self, edge: int, lo: int, hi: int, deadline: float) -> bool:
        """:meth:`_spread` of a closure far enough off to be worth it."""
        solver = self.solver
        if self.online.solve_loops:
            # The condensed solve first (where it applies), then the loop solve from its
            # answer where that fits: the condensed problem's optimum is the loop's to
            # first order only (MIT: 1.12 times the optimum's χ²).
            # Both solve the same poses and edges: gathered once, when first needed.
            problem = functools.cache(lambda: self.loop_solve.problem(solver, lo))
            first = self._solve_condensed(lo, problem, deadline) if solver.planar else None
            then = self._solve_loop(lo, problem, deadline)
            if first is not None or then is not None:
                kept = any(run is not None and run[0] for run in (first, then))
                self._count_spread(edge, kept, "solved")
                return (then or first or (False, False))[1]
        return self._spread_chain(edge, lo, hi, deadline)

    def _solve_condensed(self, lo: int, problem: Problem, deadline: float
                         ) -> tuple[bool, bool] | None:
        """The loop solve of the poses after ``lo`` condensed to their junctions
        (:mod:`h2o_slam.core.condensed`) where that is much smaller than the loop solve and
        fits (``None`` if not): whether it was kept (χ² of the edges it moves fell) and
        whether it converged. ``problem()``: :meth:`LoopSolve.problem` of ``lo``."""
        solver, n = self.solver, self.solver.num_nodes
        clock, safety = self._clock, self.online.safety
        chain = self._odometry_edge[lo + 1: n]
        # The chain alone bounds the work from below: refused before the edges are gathered.
        if (n - lo < CONDENSE_MIN_POSES or len(chain) < n - lo - 1 or np.any(chain < 0)
                or not self.condensed_loop.fits(len(chain), 0, deadline, clock, safety)):
            return None
        free, edges = problem()
        others = np.zeros(solver.num_edges, dtype=bool)
        others[edges] = True
        others[chain] = False
        cross = np.flatnonzero(others)
        if (len(free) != n - lo - 1 or np.any(solver.kind[cross] != EdgeKind.RELATIVE)
                or CONDENSE_SHARE * len(cross) > len(free)
                # Each other edge brings up to two junctions, so two chain edges.
                or not self.condensed_loop.fits(len(chain), 3 * len(cross), deadline, clock,
                                                safety)):
            return None
        R, t = solver.world_poses()
        pose = planar_poses(R, t)
        weight = solver.weight
        reduced = Reduced(solver.a[cross], solver.b[cross], solver.planar_meas[cross],
                          weight[cross, None, None] * solver.planar_info[cross],
                          np.empty(0, np.int64))
        solved, converged = self.condensed_loop.run(
            pose, lo, solver.planar_meas[chain], solver.planar_cov[chain], reduced, deadline,
            clock, safety, solver.config.exact_tolerance)
        kept = _planar_chi2(solver, edges, solved) < _planar_chi2(solver, edges, pose)
        if kept:
            t_new = t.copy()
            t_new[:, :2] = solved[:, :2]
            solver.tree.set_world_poses(geo.yaw_to_matrix(solved[:, 2]), t_new)
        return kept, converged

    def _solve_loop(self, lo: int, problem: Problem, deadline: float
                    ) -> tuple[bool, bool] | None:
        """The loop solve of the poses after ``lo`` if it fits (``None`` if not): whether it
        was kept and whether it converged (else it goes on in the next step, from the poses
        it reached). ``problem()``: :meth:`LoopSolve.problem` of ``lo``."""
        solver, loop = self.solver, self.loop_solve
        clock, safety = self._clock, self.online.safety
        # The newer poses and their odometry bound the work from below: a long loop on a
        # large map is refused before its edges are gathered.
        if not loop.fits(2 * (solver.num_nodes - lo - 1), deadline, clock, safety):
            return None
        free, edges = problem()
        if not loop.fits(len(free) + len(edges), deadline, clock, safety):
            return None
        return loop.run(solver, free, edges, deadline, clock, safety)

    def _ties_inside(self, edge: int, lo: int, hi: int) -> np.ndarray:
        """Poses in ``lo < k ≤ hi`` at which a closure or GPS fix other than ``edge`` ends
        (not dropped): where there are any the loop is crossed, and the spread, which solves
        the loop as if nothing else tied it, would bend them (kitti_00, a closure 2,055
        poses back across 20 older ones: r 932 after the spread, 5.8 after the tree path's
        update alone)."""
        s, m = self.solver, self.solver.num_edges
        others = s.weight[:m] > 0.0
        others[edge] = False
        chain = self._odometry_edge[lo + 1: s.num_nodes]
        others[chain[chain >= 0]] = False
        ends = np.concatenate([s.a[:m][others], s.b[:m][others]])
        return ends[(ends > lo) & (ends <= hi)]

    def _spread_chain(self, edge: int, lo: int, hi: int, deadline: float) -> bool:
        """The spread of ``edge`` along its odometry chain (see :meth:`_spread`); where
        other edges end inside the loop, along the chain after the newest of them
        (:meth:`_spread_tail`)."""
        solver = self.solver
        chain = self._odometry_edge[lo + 1: hi + 1]
        if len(chain) < hi - lo or np.any(chain < 0):
            return True
        ties = self._ties_inside(edge, lo, hi)
        if len(ties):
            self.spreads["crossed"] += 1
            return self._spread_tail(edge, lo, hi, ties, deadline)
        return self._spread_along(edge, int(solver.a[edge]), int(solver.b[edge]),
                                  solver.meas_R[edge], solver.meas_t[edge], solver.info[edge],
                                  deadline, "kept")

    def _spread_tail(self, edge: int, lo: int, hi: int, ties: np.ndarray, deadline: float
                     ) -> bool:
        """A closure across older ones spread over the poses after the newest pose another
        edge ties (``ties``: :meth:`_ties_inside`), the rest of the map held: with ``lo`` and
        that pose fixed, the closure is one between that pose and ``hi``
        (:func:`~h2o_slam.core.loop_spread.closure_moved`), and the stretch after it, which
        nothing else holds, takes the correction that the map, stiffened by the closures
        inside the loop, mostly does not (manhattan, the first closure of a revisit 3,000
        poses back: the tree path's short update left 46 times the optimum's χ² for seven
        callbacks, until a background solution)."""
        solver = self.solver
        before_hi = ties[ties < hi]
        tie = int(before_hi.max()) if len(before_hi) else lo
        if hi - tie < TAIL_MIN_POSES:
            return True
        forward = int(solver.a[edge]) == lo
        C_R, C_t = solver.relative_pose(lo, tie)
        meas_R, meas_t, info = closure_moved(C_R, C_t, solver.meas_R[edge],
                                             solver.meas_t[edge], solver.info[edge], forward)
        a, b = (tie, hi) if forward else (hi, tie)
        return self._spread_along(edge, a, b, meas_R, meas_t, info, deadline, "tail")

    def _spread_along(self, edge: int, a: int, b: int, meas_R: Array, meas_t: Array,
                      info: Array, deadline: float, how: str) -> bool:
        """``edge``'s error, as a closure ``a → b`` measured ``(meas_R, meas_t)`` with
        ``info``, spread along the odometry chain between them; kept where the χ² of the
        edges it moves fell."""
        solver = self.solver
        lo, hi = min(a, b), max(a, b)
        chain = self._odometry_edge[lo + 1: hi + 1]
        m = solver.num_edges
        touched = (solver.a[:m] > lo) | (solver.b[:m] > lo)
        work = (solver.num_nodes, (solver.num_nodes - lo) + int(np.count_nonzero(touched)))
        if not self.spread_cost.fits(deadline - self._clock(), self.online.safety, *work):
            self.spreads["late"] += 1
            return False
        begin = self._clock()
        R, t = solver.world_poses()
        R_new, t_new = spread_loop(R, t, a, b, meas_R, meas_t, solver.weight[edge] * info,
                                   solver.info[chain], solver.dof, self.online.spread_steps)
        edges = np.flatnonzero(touched)
        before = _moved_chi2(solver, edges, R, t)
        after = _moved_chi2(solver, edges, R_new, t_new)
        if after < before:
            solver.tree.set_world_poses(R_new, t_new)
        self._count_spread(edge, after < before, how)
        self.spread_cost.update(self._clock() - begin, *work)
        return True

    def _count_spread(self, edge: int, kept: bool, how: str) -> None:
        if kept:
            self._corrected = max(self._corrected, edge + 1)
            self._spread_kept.add(edge)
            self.spreads[how] += 1
        else:
            self._spread_kept.discard(edge)
            self.spreads["refused"] += 1

    def _relax_gps(self, edge: int, deadline: float, report: StepReport) -> bool:
        solver = self.solver
        # Building the batch walks the whole path to the earth (O(depth)), so a refused attempt
        # must be refused before it: the edge's own path is a lower bound on the batch's domain.
        fewest = int(solver.tree.depth[solver.b[edge]])
        if self.batch_cost.predict(fewest, 1) * self.batch_cost.margin(
                self.online.safety) > deadline - self._clock():
            return False
        batch = solver.upstream_gps(int(solver.b[edge]), solver.config.gps_batch_size)
        if edge not in batch:
            batch.append(edge)
        nodes = np.unique(np.concatenate([solver.path(e).domain for e in batch]))
        d = len(nodes)
        remaining = deadline - self._clock()
        predicted = self.batch_cost.predict(d, len(batch)) * self.batch_cost.margin(
            self.online.safety)
        if predicted > remaining:
            return False
        report.predictions.append((predicted, remaining))
        begin = self._clock()
        solver.relax_batch(batch)
        self.batch_cost.update(self._clock() - begin, d, len(batch))
        for e in batch:
            self._priority[e] = 0.0
        return True


#: ``() -> (free poses, edges)`` of a loop solve (:meth:`LoopSolve.problem`), gathered once.
Problem = Callable[[], tuple[np.ndarray, np.ndarray]]
#: Fewest poses after a closure's older end for which the loop solve is condensed.
CONDENSE_MIN_POSES = 50
#: The loop solve is condensed only where its poses are at least this many times the
#: other edges (each adds up to two junctions): kitti_00's last loop, 4,450 poses and 90
#: edges, condenses about 25-fold; city10000's loops hardly do.
CONDENSE_SHARE = 4


def _planar_chi2(solver: H2OSolver, edges: np.ndarray, pose: Array) -> float:
    """Σ wᵢ χ²ᵢ over a planar solver's relative ``edges`` at world ``(x, y, yaw)`` rows
    ``pose``: the condensed solve's check, from the edge table's planar copies."""
    return planar_chi2(solver.a, solver.b, solver.planar_meas, solver.planar_info,
                       solver.weight, pose, rows=edges)


def _live_closure(solver: H2OSolver, edge: int) -> bool:
    """``edge`` is a loop closure (a relative edge between poses not in sequence) that is
    not dropped as an outlier."""
    return bool(solver.kind[edge] == EdgeKind.RELATIVE
                and abs(int(solver.a[edge]) - int(solver.b[edge])) > 1
                and solver.weight[edge] > 0.0)


def _chi2_of(solver: H2OSolver, edge: int) -> float:
    """One edge's χ² at the current map (its whitened residual's square)."""
    r = solver.residual(edge)
    return float(r @ r)


def _moved_chi2(solver: H2OSolver, edges: np.ndarray, R: Array, t: Array) -> float:
    """Σ wᵢ χ²ᵢ over the solver's ``edges`` at world poses ``(R, t)``; a planar solver's
    relative edges by :func:`_planar_chi2` (a fifth of the general path's time: the spread's
    check runs inside a callback's budget)."""
    total, weight = 0.0, solver.weight
    if solver.planar:
        relative = solver.kind[edges] == EdgeKind.RELATIVE
        total += _planar_chi2(solver, edges[relative], planar_poses(R, t))
        edges = edges[~relative]
    if len(edges):
        graph = solver.graph(copy=False)
        sub = PoseGraph(graph.planar, graph.ids, R, t, graph.kind[edges], graph.a[edges],
                        graph.b[edges], graph.meas_R[edges], graph.meas_t[edges],
                        graph.info[edges])
        total += float(np.sum(weight[edges] * edge_chi2(sub)))
    return total
