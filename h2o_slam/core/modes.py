"""The three ways to run H₂O over a whole pose graph: offline, online and exact.

* :func:`solve_offline` — the paper's Algorithm 1: grow a breadth-first spanning tree, sort the
  edges by increasing root depth (3.3.12), relax them one at a time, GPS edges in batches,
  for a number of passes with a cooling temperature.
* :func:`solve_online` — the thesis' Algorithm 1: poses arrive one at a time; at the arrival of
  pose ``k`` every edge whose newest pose is ``k`` is added (AddEdge) and relaxed. Per-callback
  wall times are recorded. Optional offline passes follow.
* :func:`solve_exact` — the batch of all edges (exact Gauss–Newton), damped when the energy
  would rise, iterated to convergence.

Each returns a :class:`SolveResult` with the final world poses and the χ² history, scored by
the one evaluator :func:`h2o_slam.core.graph.chi2`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.chordal import chordal
from h2o_slam.core.converge import ConvergeState
from h2o_slam.core.errors import InputError
from h2o_slam.core.exact import converge_exact
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, chi2, edge_chi2, has_global
from h2o_slam.core.online import OnlineConfig, OnlineH2O
from h2o_slam.core.robust import (
    RobustConfig,
    converge_robust,
    global_restart,
    lowest_cost,
    odometry_edges,
)
from h2o_slam.core.solver import H2OSolver, SolverConfig
from h2o_slam.core.tree import PoseTree, spanning_parents, tree_edges


@dataclass
class SolveResult:
    """Outcome of a solve.

    Attributes:
        R, t: world poses of the solution, ``(N, 3, 3)`` and ``(N, 3)``.
        chi2_initial: χ² of the starting estimate.
        chi2_per_pass: χ² after each pass (offline), iteration (exact), or the online pass
            followed by any offline passes.
        per_callback_ms: online mode: wall time of each pose's callback (ms).
        required_ms: online mode: the same without the spare-time revisits of old edges,
            i.e. what each callback had to spend (ms).
        chi2_trace: online mode: ``(cumulative callback seconds, χ²)`` samples.
        deferred_edges: online mode: edges still waiting when the last pose arrived.
        converged: exact mode: the relative χ² decrease fell to the tolerance (or no step
            lowered χ²) before the iteration cap.
        chi2_end_of_stream: online mode: χ² when the last pose's callback returned.
        chi2_after_idle: online mode: χ² after the idle steps that follow.
        idle_steps: online mode: idle steps run after the last arrival.
        idle_steps_between: online mode, paced: idle steps run between arrivals.
        updates: online mode: single-edge and GPS-batch updates run in the arrivals'
            callbacks (new edges, revisits, and updates the guard undid).
        exact: online mode: what the exact solves beside the updates did.
        samples: online mode: ``(poses so far, χ² of their edges at the estimate then)``
            after the callback of each pose in ``sample_nodes`` (see :func:`sample_points`).
        weights: robust exact mode: every edge's final weight (0: dropped as an outlier).
        init: robust exact mode: the start whose answer was kept.
        start: offline and exact modes: the starting estimate ``(R, t)`` (``chi2_initial``
            is its χ²); ``None``: the graph's own.
    """

    R: Array
    t: Array
    chi2_initial: float
    chi2_per_pass: list[float] = field(default_factory=list)
    per_callback_ms: list[float] = field(default_factory=list)
    required_ms: list[float] = field(default_factory=list)
    chi2_trace: list[tuple[float, float]] = field(default_factory=list)
    deferred_edges: int = 0
    converged: bool | None = None
    chi2_end_of_stream: float | None = None
    chi2_after_idle: float | None = None
    idle_steps: int = 0
    idle_steps_between: int = 0
    updates: int = 0
    samples: list[tuple[int, float]] = field(default_factory=list)
    exact: ConvergeState | None = None
    start: tuple[Array, Array] | None = None
    weights: Array | None = None
    init: str | None = None

    @property
    def chi2_final(self) -> float:
        """χ² after the last pass (the initial χ² when no pass ran)."""
        return self.chi2_per_pass[-1] if self.chi2_per_pass else self.chi2_initial


INITS = ("input", "tree", "lago", "chordal")

#: Most Gauss–Newton iterations of exact mode by default: a cap that converged graphs
#: never reach (they stop at ``SolverConfig.exact_tolerance``, typically within 10–30).
EXACT_ITERATIONS = 100

#: ``progress(step, chi2)``: called after each pass of a solve.
Progress = Callable[[int, float], None]


def build_solver(
    graph: PoseGraph, config: SolverConfig | None = None, init: str = "tree",
    regularizer: bool = True, trusted: np.ndarray | None = None,
) -> tuple[H2OSolver, PoseGraph]:
    """A solver over the whole graph on a breadth-first spanning tree of its relative edges.

    ``init="input"`` starts from the graph's estimate (its vertices, or the odometry chain);
    ``init="tree"`` starts, as the thesis does (3.4.2), from the tree edges' measurements
    concatenated down from the root, so that every tree edge starts with zero error;
    ``init="lago"`` starts from the LAGO linear approximation (planar graphs only);
    ``init="chordal"`` from the chordal initialization, rotations first (3-D graphs only:
    :mod:`h2o_slam.core.chordal`).
    ``regularizer=False`` skips building ``B`` (exact mode never reads it). ``trusted``: edges
    the spanning tree is grown from first (the odometry of a robust solve, so that a false
    loop closure never becomes a tree edge and places the start).

    Returns the solver and the graph holding the starting estimate.
    """
    if init not in INITS:
        raise ValueError(f"unknown init {init!r}; choose one of {', '.join(INITS)}")
    parents = _spanning_tree(graph, trusted)
    if init == "tree":
        graph = graph.with_estimate(*tree_estimate(graph, parents))
    elif init == "lago":
        from h2o_slam.core.lago import lago

        # LAGO starts from the relative edges; GPS edges are H₂O's to relax afterwards.
        start = lago(graph, ignore_global=True)
        graph = graph.with_estimate(start.R, start.t)
    elif init == "chordal":
        if graph.planar:
            raise InputError("the chordal initialization is for 3-D graphs; planar ones have LAGO")
        graph = graph.with_estimate(*chordal(graph))
    return H2OSolver.from_graph(graph, parents, config, regularizer), graph


def _spanning_tree(graph: PoseGraph, trusted: np.ndarray | None) -> np.ndarray:
    """Breadth-first spanning forest of the relative edges; of the ``trusted`` ones when
    they alone connect the graph."""
    rel = graph.kind == EdgeKind.RELATIVE
    if trusted is not None:
        use = rel & trusted
        parents = spanning_parents(graph.num_nodes, graph.a[use], graph.b[use])
        if np.count_nonzero(parents == EARTH) <= 1:
            return parents
    return spanning_parents(graph.num_nodes, graph.a[rel], graph.b[rel])


def tree_estimate(graph: PoseGraph, parents: np.ndarray) -> tuple[Array, Array]:
    """World poses from concatenating the tree edges' measurements down from the root.

    Subtree tops keep their estimate from ``graph``.
    """
    tree = PoseTree.from_parents(parents, graph.R, graph.t)
    edge, forward = tree_edges(graph, parents)
    ahead = np.flatnonzero((edge >= 0) & forward)
    back = np.flatnonzero((edge >= 0) & ~forward)
    tree.R[ahead], tree.t[ahead] = graph.meas_R[edge[ahead]], graph.meas_t[edge[ahead]]
    tree.R[back], tree.t[back] = geo.inverse(graph.meas_R[edge[back]], graph.meas_t[edge[back]])
    return tree.world_poses()


def offline_order(solver: H2OSolver) -> list[int]:
    """Edges by increasing root depth (3.3.12): relaxing an edge never moves nodes above its
    root, so this order does not undo work done higher in the tree."""
    depth = np.array([solver.root_depth(e) for e in range(solver.num_edges)])
    return [int(e) for e in np.argsort(depth, kind="stable")]


def offline_pass(solver: H2OSolver, order: list[int], d_max: int | None = None) -> None:
    """One pass of the paper's Algorithm 1 over ``order``: GPS edges are gathered and relaxed
    together in batches of ``gps_batch_size``; other edges one at a time, solving for at most
    ``d_max`` nodes each."""
    batch: list[int] = []
    size = solver.config.gps_batch_size
    for e in order:
        if len(batch) >= size:
            solver.relax_batch(batch)
            batch = []
        if solver.kind[e] == EdgeKind.POSITION:
            batch.append(e)
        else:
            solver.relax_batch(batch)
            batch = []
            solver.relax(e, d_max=d_max)
    solver.relax_batch(batch)
    solver.end_pass()


def solve_offline(
    graph: PoseGraph, passes: int = 10, config: SolverConfig | None = None, init: str = "tree",
    d_max: int | None = None, progress: Progress | None = None,
) -> SolveResult:
    """Relax the whole graph for ``passes`` passes (paper Algorithm 1); see
    :func:`build_solver` for ``init``; ``d_max`` bounds the nodes solved for per edge;
    ``progress`` is called after each pass."""
    solver, start = build_solver(graph, config, init)
    result = SolveResult(start.R.copy(), start.t.copy(), chi2(start), start=(start.R, start.t))
    order = offline_order(solver)
    best = _Best(solver, result.chi2_initial)
    for k in range(passes):
        offline_pass(solver, order, d_max)
        result.chi2_per_pass.append(solver.chi2(graph))
        best.offer(result.chi2_per_pass[-1])
        if progress is not None:
            progress(k + 1, result.chi2_per_pass[-1])
    result.R, result.t = best.poses()
    return result


class _Best:
    """The lowest-χ² map a run of passes has visited: the thesis' offline passes settle at
    a fixed point of their own, which can be worse than the map they started from
    (measured: ``--passes 10`` after an online run at the optimum took a KITTI graph from
    1.000 to 7.7 times it), so a run ends on the best map it saw, never a worse one."""

    def __init__(self, solver: H2OSolver, chi2_now: float) -> None:
        self.solver = solver
        self.chi2 = chi2_now
        self.R, self.t = solver.world_poses()

    def offer(self, chi2_now: float) -> None:
        """The solver's map after a pass, of χ² ``chi2_now``: kept if the best so far."""
        if chi2_now < self.chi2:
            self.chi2 = chi2_now
            self.R, self.t = self.solver.world_poses()

    def poses(self) -> tuple[Array, Array]:
        """World poses of the best map."""
        return self.R.copy(), self.t.copy()


def solve_exact(
    graph: PoseGraph, iterations: int = EXACT_ITERATIONS, config: SolverConfig | None = None,
    init: str = "tree", robust: RobustConfig | None = None,
) -> SolveResult:
    """Gauss–Newton on the batch of all edges, with Levenberg damping when χ² would rise,
    until the relative χ² decrease falls to ``config.exact_tolerance`` or no step helps
    (``result.converged``), or ``iterations`` run out; see :func:`build_solver` for ``init``.

    ``result.chi2_per_pass`` holds the χ² after each iteration run (its length is the
    iteration count).

    ``robust``: loop closures and GPS fixes weighed by GNC-TLS (:mod:`h2o_slam.core.robust`),
    odometry trusted; ``result.weights`` holds every edge's final weight and the χ² entries
    are of the weighted graph. With ``init="tree"`` a robust solve runs from the odometry's
    own tree and, for a planar graph, from LAGO too, and keeps the answer of lower TLS cost:
    least squares over every edge (GNC's first solve) has local minima, and which start
    avoids them depends on the graph (measured: from LAGO, MIT without outliers reaches the
    optimum where the odometry start ends at 18.7x it; intel with 10 false closures ends
    14 m off from LAGO and on the outlier-free map from the odometry).
    """
    if robust is None:
        solver, start = build_solver(graph, config, init, regularizer=False)
        history, converged = converge_exact(solver, iterations)
        return _exact_result(solver, start, history, converged, None)
    starts = [init] if init != "tree" else (
        ["tree", "lago"] if graph.planar and not has_global(graph) else ["tree"])
    results = [_solve_robust(graph, iterations, config, name, robust) for name in starts]
    return results[0] if len(results) == 1 else results[lowest_result(graph, robust, results)]


def lowest_result(graph: PoseGraph, robust: RobustConfig | None,
                  results: list[SolveResult]) -> int:
    """Which of ``results`` ends lowest: in χ² over every edge, or robustly in the truncated
    cost of each one's own decisions (:func:`~h2o_slam.core.robust.lowest_cost`)."""
    if robust is None:
        return int(np.argmin([chi2(graph, result.R, result.t) for result in results]))
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    scored = [(_weights(result), edge_chi2(graph, result.R, result.t)) for result in results]
    return lowest_cost(graph, trusted, robust, scored)


def _weights(result: SolveResult) -> Array:
    assert result.weights is not None, "a robust solve sets every edge's weight"
    return result.weights


def _solve_robust(graph: PoseGraph, iterations: int, config: SolverConfig | None, init: str,
                  robust: RobustConfig) -> SolveResult:
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    solver, start = build_solver(graph, config, init, regularizer=False, trusted=trusted)
    restart = global_restart(graph)
    outcome = converge_robust(solver, iterations, trusted, robust, restart=restart)
    return _exact_result(solver, start, outcome.history, outcome.converged, init)


def _exact_result(solver: H2OSolver, start: PoseGraph, history: list[float], converged: bool,
                  robust_init: str | None) -> SolveResult:
    result = SolveResult(start.R.copy(), start.t.copy(), history[0], history[1:],
                         start=(start.R, start.t))
    result.converged = converged
    if robust_init is not None:
        result.weights = solver.weight.copy()
        result.init = robust_init
    result.R, result.t = solver.world_poses()
    return result


def solve_lago(graph: PoseGraph) -> SolveResult:
    """LAGO as a solver of its own: one linear solve, one χ² entry (planar graphs only)."""
    from h2o_slam.core.lago import lago_estimate

    R, t = lago_estimate(graph)
    return SolveResult(R, t, chi2(graph), [chi2(graph, R, t)])


def solve_online(
    graph: PoseGraph,
    passes: int = 0,
    config: SolverConfig | None = None,
    budget_s: float | None = None,
    online: OnlineConfig | None = None,
    trace_every: int = 0,
    idle_s: float = 0.0,
    sample_nodes: Collection[int] = (),
    period_s: float = 0.0,
) -> SolveResult:
    """Feed the graph pose by pose (thesis Algorithm 1), let the robot stand for ``idle_s``
    seconds, then run ``passes`` offline passes.

    ``period_s`` paces the arrivals: pose ``k`` arrives ``k * period_s`` seconds after the
    first (a robot's keyframe rate; 0: each as soon as the last callback returns, the worst
    case). Between arrivals, idle steps run as in ``h2o_node``'s idle timer.

    Each arriving pose is one callback: its edges are added (AddEdge, with tree balancing)
    and one :meth:`~h2o_slam.core.online.OnlineH2O.step` runs in what is left of ``budget_s``
    (``None``: no limit). The wall time of every callback is recorded; with
    ``trace_every > 0`` the χ² is sampled every that many callbacks, outside the timed
    region, against the cumulative callback time. After the callback of each node in
    ``sample_nodes``, ``(nodes so far, χ² of their edges)`` goes to ``result.samples``.

    Idle steps (no new edge) run with the same budget, one per budget period (the robot's
    other work keeps the rest of the CPU); unbudgeted, a single idle step solves the map
    exactly.
    """
    h2o = OnlineH2O(planar=graph.planar, config=config, online=online)
    try:
        result = SolveResult(graph.R.copy(), graph.t.copy(), chi2(graph))
        spent = _stream(h2o, graph, budget_s, trace_every, set(sample_nodes), result,
                        period_s)
        result.deferred_edges = len(h2o.pending)
        result.chi2_end_of_stream = h2o.solver.chi2(graph)
        spent += _idle(h2o, budget_s, idle_s, result)
        result.chi2_after_idle = h2o.solver.chi2(graph)
        result.chi2_per_pass.append(result.chi2_after_idle)
        if trace_every and result.idle_steps:
            result.chi2_trace.append((spent, result.chi2_after_idle))
        order = offline_order(h2o.solver)
        best = _Best(h2o.solver, result.chi2_after_idle)
        for _ in range(passes):
            start = time.perf_counter()
            offline_pass(h2o.solver, order, h2o.online.d_max)
            spent += time.perf_counter() - start
            result.chi2_per_pass.append(h2o.solver.chi2(graph))
            best.offer(result.chi2_per_pass[-1])
            if trace_every:
                result.chi2_trace.append((spent, result.chi2_per_pass[-1]))
        result.R, result.t = best.poses()
        result.exact = h2o.converger.state
    finally:
        h2o.close()
    return result


def _stream(h2o: OnlineH2O, graph: PoseGraph, budget_s: float | None, trace_every: int,
            sample_nodes: set[int], result: SolveResult, period_s: float = 0.0) -> float:
    """Run every arrival's callback (pose ``k`` at ``k * period_s``, idle steps between);
    returns the seconds the callbacks took."""
    spent = 0.0
    first = time.perf_counter()
    for node, edges in enumerate(arrivals(graph)):
        if period_s > 0.0 and node > 0:
            result.idle_steps_between += _idle_until(h2o, budget_s, first + node * period_s)
        start = time.perf_counter()
        add_arrival(h2o, graph, node, edges)
        left = None if budget_s is None else budget_s - (time.perf_counter() - start)
        report = h2o.step(None if left is None else max(left, 0.0))
        elapsed = time.perf_counter() - start
        result.updates += report.relaxed + report.revisited + report.undone
        spent += elapsed
        result.per_callback_ms.append(1e3 * elapsed)
        result.required_ms.append(1e3 * (elapsed - report.revisit_s))
        if trace_every and (node % trace_every == 0 or node == graph.num_nodes - 1):
            result.chi2_trace.append((spent, _partial_chi2(h2o, graph)))
        if node in sample_nodes:
            result.samples.append((node + 1, _partial_chi2(h2o, graph)))
    return spent


def _idle_until(h2o: OnlineH2O, budget_s: float | None, until: float) -> int:
    """Idle steps of ``budget_s`` each, one per two budgets (as ``_idle``), while one still
    ends before ``until``; then wait for ``until``. Returns the steps run."""
    steps = 0
    while budget_s is not None and time.perf_counter() + budget_s <= until:
        h2o.step(budget_s)
        steps += 1
        time.sleep(max(0.0, min(budget_s, until - time.perf_counter())))
    time.sleep(max(0.0, until - time.perf_counter()))
    return steps


def _idle(h2o: OnlineH2O, budget_s: float | None, idle_s: float, result: SolveResult) -> float:
    """Idle steps for ``idle_s`` seconds of wall time; returns the seconds they took."""
    if idle_s <= 0.0:
        return 0.0
    spent = 0.0
    end = time.perf_counter() + idle_s
    while True:
        start = time.perf_counter()
        h2o.step(budget_s)
        spent += time.perf_counter() - start
        result.idle_steps += 1
        if budget_s is None or time.perf_counter() + budget_s > end:
            return spent
        time.sleep(budget_s)


def sample_points(graph: PoseGraph, count: int) -> list[int]:
    """Poses after whose callback to sample the map: ``count`` spread evenly over the stream,
    and up to ``count`` among those that bring a loop closure (an edge to a pose other than
    the one before), spread evenly over them."""
    if count <= 0 or graph.num_nodes == 0:
        return []
    n = graph.num_nodes
    spread = np.linspace(0, n - 1, min(count, n)).round().astype(int)
    rel = graph.kind == EdgeKind.RELATIVE
    newest = np.maximum(graph.a, graph.b)
    gap = np.abs(graph.a - graph.b)
    closing = np.unique(newest[rel & (gap > 1)])
    picked = closing[np.linspace(0, len(closing) - 1, min(count, len(closing))).round()
                     .astype(int)] if len(closing) else closing
    return sorted({int(k) for k in np.concatenate([spread, picked])})


def prefix_graph(graph: PoseGraph, nodes: int) -> PoseGraph:
    """The first ``nodes`` nodes of ``graph`` and the edges among them: what a robot fed
    the graph pose by pose holds after pose ``nodes - 1``."""
    newest = np.where(graph.a == EARTH, graph.b, np.maximum(graph.a, graph.b))
    keep = newest < nodes
    return PoseGraph(graph.planar, graph.ids[:nodes], graph.R[:nodes], graph.t[:nodes],
                     graph.kind[keep], graph.a[keep], graph.b[keep], graph.meas_R[keep],
                     graph.meas_t[keep], graph.info[keep])


def _partial_chi2(h2o: OnlineH2O, graph: PoseGraph) -> float:
    """χ² of the edges added so far, at the current estimate of the nodes added so far."""
    n, m = h2o.num_nodes, h2o.solver.num_edges
    R, t = h2o.solver.world_poses()
    full_R = np.concatenate([R, np.broadcast_to(np.eye(3), (graph.num_nodes - n, 3, 3))])
    full_t = np.concatenate([t, np.zeros((graph.num_nodes - n, 3))])
    added = _added_edges(graph, h2o)
    return float(np.sum(edge_chi2(graph, full_R, full_t)[added])) if m else 0.0


def _added_edges(graph: PoseGraph, h2o: OnlineH2O) -> np.ndarray:
    newest = np.where(graph.a == EARTH, graph.b, np.maximum(graph.a, graph.b))
    return np.flatnonzero(newest < h2o.num_nodes)


def arrivals(graph: PoseGraph) -> list[np.ndarray]:
    """For each pose ``k``, the edges whose newest pose is ``k``, odometry-like edges (to the
    most recent earlier pose) first."""
    newest = np.where(graph.a == EARTH, graph.b, np.maximum(graph.a, graph.b))
    other = np.where(graph.a == EARTH, -1, np.minimum(graph.a, graph.b))
    order = np.lexsort((-other, newest))
    bounds = np.searchsorted(newest[order], np.arange(graph.num_nodes + 1))
    return [order[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]


def add_arrival(h2o: OnlineH2O, graph: PoseGraph, node: int, edges: np.ndarray) -> list[int]:
    """Add pose ``node`` of ``graph`` and its edges (relative ones first) to ``h2o``; returns
    the graph's edges in the order they were added.

    A pose with no relative edge to an earlier pose starts a new subtree at its estimate.
    """
    rel = [int(e) for e in edges if graph.kind[e] == EdgeKind.RELATIVE]
    if not rel:
        h2o.add_pose(graph.R[node], graph.t[node])
    added = rel + [int(e) for e in edges if graph.kind[e] != EdgeKind.RELATIVE]
    for e in added:
        h2o.add_edge(int(graph.kind[e]), int(graph.a[e]), int(graph.b[e]),
                     graph.meas_R[e], graph.meas_t[e], graph.info[e])
    return added
