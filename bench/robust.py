"""Benchmark: a back end robust to false loop closures. H₂O's GNC-TLS exact solve against
GTSAM Levenberg–Marquardt (plain, Cauchy, DCS) and GTSAM's GNC-TLS, on the public pose graphs
with planted false closures, and on one graph with GPS fixes and a multipath jump.

    .venv/bin/python bench/robust.py [--data DIR] [--graphs NAME ...] [--kinds KIND ...]
                                     [--counts N ...] [--solvers NAME ...] [--timeout S]
                                     [--plot-graph NAME] [--results FILE | --no-write]

Protocol, per graph:

1. The outlier-free graph is read (:func:`h2o_slam.io.g2o.read_g2o`); every solver solves it
   once: its *reference*. The χ² optimum ("opt") is the smallest χ² of the outlier-free
   graph that any reference, or H₂O's exact solve without a kernel, reached.
2. For every kind of :data:`h2o_slam.io.outliers.OUTLIER_KINDS` and every count of
   ``--counts`` the graph has at least as many true loop closures for (relative edges that
   are not odometry), :func:`h2o_slam.io.outliers.plant_outliers` appends that many false
   closures, seeded by ``crc32("<graph>/<kind>/<count>")``. Every solver solves the result.
3. Each map is compared with the *same* solver's reference: ATE = RMS of the position
   difference after a rigid best-fit alignment (:func:`h2o_slam.core.geometry.
   best_fit_transform`; node 0 is held by every solver, so the alignment is nearly the
   identity). χ²_true/opt = the outlier-free graph scored at the map
   (:func:`h2o_slam.core.graph.chi2`: the true edges only) over opt. An edge is accepted when
   its final weight is above 0.5; "false accepted" counts planted closures accepted, "true
   turned away" the true closures (and GPS fixes) that are not.

GPS multipath (``--gps-graph``, default intel, run when that graph is among those selected):
the graph's own least-squares optimum (``solve_exact`` without a kernel) stands in for the
truth; :func:`h2o_slam.io.synthetic.add_gps` adds a fix every 5th pose (sigma 0.5 m); the
jump-free graph is the reference case, and a multipath jump moves 20 consecutive fixes
(100 poses) by one seeded vector of 20–50 m, same covariance. GPS fixes set the world frame,
so there the ATE is not aligned, and the largest displacement of a pose is reported too.

Solvers (every one from the graph as :func:`read_g2o` returns it, except H₂O, which starts
from its spanning tree of odometry edges; odometry never gets a kernel):

- ``h2o``: :func:`h2o_slam.core.modes.solve_exact` with ``robust=RobustConfig()`` (GNC-TLS,
  ``c̄²`` the 0.999999 χ² quantile of the edge's degrees of freedom), what ``h2o-solve``
  runs by default. Time: the call.
- ``node``: the node's path, planar graphs only (:func:`mapper_stream.stream_graph`: the
  rclpy-free ``Mapper`` at a 5 ms budget with its worker process, odometry, closures and
  fixes in stream order, one pose per callback, 1 ms between callbacks, 1 s of idle steps,
  then ``~/exact_solve``),
  in a process that runs nothing else, as ``h2o_node``'s (:class:`Workers`).
  The node makes each odometry edge's information from its noise model (``odom_*``), which a
  robot sets to its own odometry: here it is set to the graph's
  (:func:`mapper_stream.fitted_odometry`), so that the node solves the edges GTSAM solves.
  Its rows are still compared with its own map of the outlier-free graph (χ²_true over that
  map's): a per-metre model is close to the file's information, not equal to it. The
  callback column gives the p99 and the largest callback time, the most CPU time one
  callback's thread spent, and how many callbacks took over 10 ms, with in parentheses
  those of them the hypervisor took CPU time from (on a shared virtual machine the host
  runs other work on its virtual CPUs for ms at a time, which no code inside can prevent):
  the steal counter advanced (:func:`mapper_stream.stolen_during`), or the callback is
  within 10 ms but for time in which its thread neither ran, nor waited for a core, nor
  blocked (``callback_off_ms``: the virtual CPU was paused; the steal counter misses
  pauses of a few ms). The guest may count much of a pause as its thread's CPU time, so
  the CPU column does not exclude it: an odometry sample's callback that takes 0.5 ms took
  28 ms, 19.4 ms of it counted as CPU, while steal advanced. Target: p99 ≤ 5 ms, and
  every callback over 10 ms one of those. Time: the whole stream.
- ``node_default`` (opt-in): the same with the mapper's default odometry model, as a robot
  whose ``odom_*`` were never set runs: it is 2-5 times tighter than some graphs' odometry
  (manhattan: σ 0.05 against 0.11 m per metre), so it shows what a mis-set model costs.
- ``lm``: GTSAM ``LevenbergMarquardtOptimizer``, factors as ``bench/solvers.py`` builds them
  (same information, Pose3 information permuted, node 0 held by a prior of sigma 1e-6), the
  same LM settings; every edge weight 1.
- ``cauchy``: the same with ``noiseModel.Robust`` / ``mEstimator.Cauchy`` k = 1 on the loop
  closures (and GPS fixes). GTSAM's kernels act on the whitened distance r (r² = the edge's
  χ²): ρ = ½k² log(1 + r²/k²), weight 1/(1 + r²/k²) — k = 1 is g2o's Cauchy kernel at its
  default width 1. A true closure with χ² > 1 then weighs under 0.5 and counts as turned
  away, although the kernel never drops an edge outright.
- ``dcs``: ``mEstimator.DCS`` with Φ = 1, the value Agarwal et al. (ICRA 2013) recommend;
  weight (2Φ / (Φ + r²))² above r² = Φ, so under 0.5 from χ² ≈ 1.83.
- ``gnc``: ``GncLMOptimizer`` with ``GncLossType.TLS`` and the same LM settings inside, known
  inliers = the odometry factors and the prior, inlier thresholds set with
  ``setInlierCostThresholdsAtProbability(0.999999)`` (GTSAM's default is 0.99) so that its
  ``c̄²`` is H₂O's; weights from ``getWeights()``.

The kernels' weights are taken at the solution, of the plain factor's whitened distance
(``sqrt(2 · error())``), which is what the optimizer saw. GTSAM times are ``optimize()`` only.
GPS fixes in GTSAM: ``PoseTranslationPrior2D`` (world-frame position of a Pose2; a
``PriorFactorPose2`` would also fix the heading) or ``GPSFactor`` in 3-D; the GPS graphs
need no prior on node 0 (the fixes set the gauge; a tight prior would fight the fix at node
0). Each solver runs in a worker process kept across runs and replaced on a ``--timeout``.

Output: the tables go to stdout and replace the section ``## Robust (bench/robust.py)`` of
``bench/RESULTS.md``; one map, ``bench/plots/robust_<graph>.png``, of H₂O's solution of
``--plot-graph`` (default intel) with ``--plot-kind``/``--plot-count`` (random, 100).
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import math
import multiprocessing as mp
import platform
import sys
import time
import zlib
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from mapper_stream import fitted_odometry, stream_graph
from results_md import (
    add_graph_arguments,
    command,
    publish,
    results_path,
    revision,
    run_graphs,
    select_graphs,
    table_head,
)
from solvers import (
    LM_ABSOLUTE_TOL,
    LM_MAX_ITERATIONS,
    LM_RELATIVE_TOL,
    PRIOR_SIGMA,
    _gtsam_graph,
    _poses,
)

from h2o_slam.core.geometry import best_fit_transform
from h2o_slam.core.graph import EdgeKind, PoseGraph, chi2
from h2o_slam.core.modes import solve_exact
from h2o_slam.core.robust import RobustConfig, odometry_edges
from h2o_slam.io.g2o import read_g2o
from h2o_slam.io.outliers import OUTLIER_KINDS, plant_outliers
from h2o_slam.io.synthetic import add_gps

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Robust (bench/robust.py)"
DEFAULT_PLOTS = REPO / "bench" / "plots"

SOLVERS = ("h2o", "node", "lm", "cauchy", "dcs", "gnc")
#: The node's path with the mapper's default odometry noise model, not the graph's (opt-in: a
#: second run of the slowest solver).
NODE_DEFAULTS = "node_default"
NODES = ("node", NODE_DEFAULTS)
#: The node path's per-callback budget (ms), as ``h2o_node``'s default.
NODE_BUDGET_MS = 5.0
#: H₂O's exact solve without a kernel: the outlier-free χ² optimum (not a table row).
LEAST_SQUARES = "ls"
COUNTS = (10, 100, 1000)

CAUCHY_K = 1.0
DCS_PHI = 1.0
#: GNC's inlier threshold as a χ² probability: H₂O's, so both truncate at the same ``c̄²``.
INLIER_PROBABILITY = RobustConfig().inlier_probability
#: An edge whose final weight is above this is accepted.
ACCEPT_WEIGHT = 0.5

#: Issue target for H₂O at these counts: ATE and χ²_true/opt at most these.
TARGET_COUNTS = (10, 100)
TARGET_ATE_M = 0.05
TARGET_CHI2 = 1.01

#: Longest a solver process may take to start (import, compile or load the kernels).
STARTUP_S = 300.0

GPS_EVERY = 5
GPS_SIGMA_M = 0.5
JUMP_FIXES = 20
JUMP_M = (20.0, 50.0)
#: Case kinds of the GPS run: the jump-free reference and the jump.
GPS_CLEAN, MULTIPATH = "gps", "multipath"


# --- cases: the graph each run solves ---------------------------------------------------------


@dataclass(frozen=True)
class Case:
    """One graph to solve: ``kind`` is "clean", an outlier kind, "gps" or "multipath"."""

    path: str
    kind: str
    count: int = 0

    @property
    def name(self) -> str:
        """The graph's file stem."""
        return Path(self.path).stem

    @property
    def seed(self) -> int:
        """Fixed per (graph, kind, count), the same in every process and run."""
        return zlib.crc32(f"{self.name}/{self.kind}/{self.count}".encode())

    @property
    def clean(self) -> Case:
        """The outlier-free case this one is compared with."""
        return Case(self.path, GPS_CLEAN if self.kind in (GPS_CLEAN, MULTIPATH) else "clean")


@functools.lru_cache(maxsize=2)
def read_graph(path: str) -> PoseGraph:
    """The graph file, read once per process."""
    return read_g2o(path)


@functools.lru_cache(maxsize=1)
def gps_graph(path: str) -> PoseGraph:
    """The graph with a GPS fix every ``GPS_EVERY`` poses around its least-squares optimum."""
    graph = read_graph(path)
    truth = solve_exact(graph)
    return add_gps(graph, truth.t, GPS_EVERY, GPS_SIGMA_M, seed=Case(path, GPS_CLEAN).seed)


def plant_jump(graph: PoseGraph, seed: int) -> tuple[PoseGraph, np.ndarray]:
    """A copy of ``graph`` with ``JUMP_FIXES`` consecutive GPS fixes moved by one vector of
    ``JUMP_M`` metres (a multipath jump), and the mask of the moved fixes."""
    fixes = np.flatnonzero(graph.kind == EdgeKind.POSITION)
    rng = np.random.default_rng(seed)
    first = int(rng.integers(0, len(fixes) - JUMP_FIXES + 1))
    jumped = fixes[first:first + JUMP_FIXES]
    if graph.planar:
        angle = rng.uniform(-np.pi, np.pi)
        direction = np.array([np.cos(angle), np.sin(angle), 0.0])
    else:
        direction = rng.standard_normal(3)
        direction /= np.linalg.norm(direction)
    out = graph.copy()
    out.meas_t[jumped] += rng.uniform(*JUMP_M) * direction
    mask = np.zeros(graph.num_edges, dtype=bool)
    mask[jumped] = True
    return out, mask


@functools.lru_cache(maxsize=2)
def build_case(case: Case) -> tuple[PoseGraph, np.ndarray]:
    """The graph of ``case`` and its mask of false edges (deterministic: the worker and this
    process build the same)."""
    if case.kind in ("clean", GPS_CLEAN):
        graph = read_graph(case.path) if case.kind == "clean" else gps_graph(case.path)
        return graph, np.zeros(graph.num_edges, dtype=bool)
    if case.kind == MULTIPATH:
        return plant_jump(gps_graph(case.path), case.seed)
    planted = plant_outliers(read_graph(case.path), case.kind, case.count, case.seed)
    return planted.graph, planted.outlier


def true_closures(graph: PoseGraph) -> int:
    """Relative edges that are not odometry."""
    odometry = odometry_edges(graph.kind, graph.a, graph.b)
    return int(np.count_nonzero((graph.kind == EdgeKind.RELATIVE) & ~odometry))


# --- solvers (run in the worker process) ------------------------------------------------------


@dataclass
class Outcome:
    """One solver run: the map, every edge's final weight and the solve time."""

    status: str  # "ok", "timeout …" or "failed: <message>"
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    weights: np.ndarray | None = None
    seconds: float = float("nan")
    p99_ms: float = float("nan")  # node path: callback time percentile and maximum
    max_ms: float = float("nan")
    max_cpu_ms: float = float("nan")  # the most CPU time one callback's thread spent
    over: int = 0  # callbacks over 2× the budget
    over_host: int = 0  # of those, the host's (steal counted, or the virtual CPU paused)


def solve_node(graph: PoseGraph, defaults: bool = False) -> Outcome:
    """The node's path (:func:`mapper_stream.stream_graph`: the rclpy-free ``Mapper`` at a
    5 ms budget, poses, closures and fixes in stream order, 1 s of idle steps, then its
    exact solve), its odometry model the graph's (``defaults``: the mapper's); planar graphs
    only."""
    if not graph.planar:
        return Outcome("skipped: 3-D (the node is planar)")
    out = stream_graph(graph, NODE_BUDGET_MS,
                       odometry_model=None if defaults else fitted_odometry(graph))
    over = out.callback_ms > 2 * NODE_BUDGET_MS
    # The host's: steal counted, or within 2× the budget but for the time the virtual CPU
    # was paused while the thread neither blocked nor waited for a core.
    paused = out.callback_ms - out.callback_off_ms <= 2 * NODE_BUDGET_MS
    host = over & (out.callback_stolen | paused)
    return Outcome("ok", out.R, out.t, out.weights, out.seconds,
                   float(np.percentile(out.callback_ms, 99)), float(out.callback_ms.max()),
                   float(out.callback_cpu_ms.max()), int(np.count_nonzero(over)),
                   int(np.count_nonzero(host)))


def solve_h2o(graph: PoseGraph, robust: bool) -> Outcome:
    """H₂O's exact solve, GNC-TLS weighted when ``robust``."""
    start = time.perf_counter()
    result = solve_exact(graph, robust=RobustConfig() if robust else None)
    seconds = time.perf_counter() - start
    weights = result.weights if result.weights is not None else np.ones(graph.num_edges)
    return Outcome("ok", result.R, result.t, weights, seconds)


def subgraph(graph: PoseGraph, keep: np.ndarray) -> PoseGraph:
    """The graph with only the edges ``keep`` (same nodes and estimate)."""
    return PoseGraph(graph.planar, graph.ids, graph.R, graph.t, graph.kind[keep], graph.a[keep],
                     graph.b[keep], graph.meas_R[keep], graph.meas_t[keep], graph.info[keep])


def position_factor(graph: PoseGraph, k: int, noise: Any) -> Any:
    """GPS edge ``k`` as a GTSAM factor on the world-frame position of its pose."""
    import gtsam

    if graph.planar:
        return gtsam.PoseTranslationPrior2D(int(graph.b[k]), graph.meas_t[k, :2], noise)
    return gtsam.GPSFactor(int(graph.b[k]), graph.meas_t[k], noise)


def plain_factors(graph: PoseGraph) -> tuple[list[Any], Any]:
    """A Gaussian GTSAM factor per edge, in edge order, and the start ``Values``: relative
    edges by ``bench/solvers.py``, GPS fixes by :func:`position_factor`."""
    import gtsam

    if np.any(graph.kind == EdgeKind.ORIENTATION):
        raise ValueError("orientation edges are not supported by this benchmark")
    relative = graph.kind == EdgeKind.RELATIVE
    between, initial = _gtsam_graph(subgraph(graph, relative))
    factors: list[Any] = [None] * graph.num_edges
    for j, k in enumerate(np.flatnonzero(relative)):
        factors[k] = between.at(j)
    rows = np.arange(2 if graph.planar else 3)
    for k in np.flatnonzero(~relative):
        noise = gtsam.noiseModel.Gaussian.Information(graph.info[k][np.ix_(rows, rows)])
        factors[k] = position_factor(graph, k, noise)
    return factors, initial


def kernel(solver: str) -> Any:
    """The M-estimator of a GTSAM solver (None: least squares or GNC)."""
    import gtsam

    if solver == "cauchy":
        return gtsam.noiseModel.mEstimator.Cauchy.Create(CAUCHY_K)
    if solver == "dcs":
        return gtsam.noiseModel.mEstimator.DCS.Create(DCS_PHI)
    return None


def robust_factor(graph: PoseGraph, k: int, factor: Any, estimator: Any) -> Any:
    """The factor of edge ``k`` with its Gaussian noise wrapped in ``estimator``."""
    import gtsam

    noise = gtsam.noiseModel.Robust.Create(estimator, factor.noiseModel())
    if graph.kind[k] == EdgeKind.POSITION:
        return position_factor(graph, k, noise)
    return type(factor)(*factor.keys(), factor.measured(), noise)


def gauge_prior(graph: PoseGraph, initial: Any) -> Any:
    """Node 0 held at its start pose, as ``bench/solvers.py`` holds it."""
    import gtsam

    if graph.planar:
        return gtsam.PriorFactorPose2(0, initial.atPose2(0),
                                      gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA))
    return gtsam.PriorFactorPose3(0, initial.atPose3(0),
                                  gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA))


def lm_params() -> Any:
    """``bench/solvers.py``'s LM settings."""
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(LM_MAX_ITERATIONS)
    params.setRelativeErrorTol(LM_RELATIVE_TOL)
    params.setAbsoluteErrorTol(LM_ABSOLUTE_TOL)
    return params


def optimize(factors: Any, initial: Any, solver: str, inliers: list[int]
             ) -> tuple[Any, np.ndarray | None, float]:
    """Run LM (or GNC over LM); return the values, GNC's weights per factor and the time."""
    import gtsam

    if solver == "gnc":
        params = gtsam.GncLMParams(lm_params())
        params.setLossType(gtsam.GncLossType.TLS)
        params.setKnownInliers(inliers)
        optimizer = gtsam.GncLMOptimizer(factors, initial, params)
        optimizer.setInlierCostThresholdsAtProbability(INLIER_PROBABILITY)
    else:
        optimizer = gtsam.LevenbergMarquardtOptimizer(factors, initial, lm_params())
    start = time.perf_counter()
    values = optimizer.optimize()
    seconds = time.perf_counter() - start
    weights = np.ravel(optimizer.getWeights()) if solver == "gnc" else None
    return values, weights, seconds


def solve_gtsam(graph: PoseGraph, solver: str) -> Outcome:
    """One GTSAM variant (``lm``, ``cauchy``, ``dcs`` or ``gnc``) on ``graph``."""
    import gtsam

    plain, initial = plain_factors(graph)
    estimator = kernel(solver)
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    factors = gtsam.NonlinearFactorGraph()
    for k, factor in enumerate(plain):  # factor k is edge k
        use_kernel = estimator is not None and not trusted[k]
        factors.add(robust_factor(graph, k, factor, estimator) if use_kernel else factor)
    inliers = [int(k) for k in np.flatnonzero(trusted)]
    if not np.any(graph.kind == EdgeKind.POSITION):
        inliers.append(factors.size())
        factors.add(gauge_prior(graph, initial))
    values, gnc_weights, seconds = optimize(factors, initial, solver, inliers)
    R, t = _poses(graph, values)
    weights = np.ones(graph.num_edges)
    if gnc_weights is not None:
        weights = gnc_weights[:graph.num_edges].copy()
    elif estimator is not None:
        for k in np.flatnonzero(~trusted):
            weights[k] = estimator.weight(math.sqrt(2.0 * plain[k].error(values)))
    return Outcome("ok", R, t, weights, seconds)


def run_solver(case: Case, solver: str) -> Outcome:
    """Solve ``case`` with ``solver`` (one of :data:`SOLVERS` or :data:`LEAST_SQUARES`)."""
    graph, _ = build_case(case)
    if solver in ("h2o", LEAST_SQUARES):
        return solve_h2o(graph, robust=solver == "h2o")
    if solver in NODES:
        return solve_node(graph, defaults=solver == NODE_DEFAULTS)
    return solve_gtsam(graph, solver)


def _serve(conn: Any) -> None:
    """The worker's loop: a ``(path, kind, count, solver)`` in, an outcome's fields out."""
    from h2o_slam.core import warmup

    warmup.warm_up()  # load the kernels now, so that no timed solve pays for it
    conn.send("ready")
    while True:
        task = conn.recv()
        if task is None:
            return
        path, kind, count, solver = task
        try:
            out = run_solver(Case(path, kind, count), solver)
        except Exception as err:  # reported in the table, not raised
            out = Outcome(f"failed: {type(err).__name__}: {err}")
        # Plain fields: a class of the spawned child's __mp_main__ would not unpickle here.
        conn.send((out.status, out.R, out.t, out.weights, out.seconds, out.p99_ms,
                   out.max_ms, out.max_cpu_ms, out.over, out.over_host))


class Worker:
    """A spawned solver process kept across runs (start-up and kernel loading paid once),
    replaced after a run that timed out or killed it."""

    def __init__(self) -> None:
        self.proc: Any = None
        self.conn: Any = None

    def start(self) -> None:
        """Spawn the process and wait until it has loaded its kernels (outside any run's
        time limit)."""
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve, args=(child,), daemon=True)
        self.proc.start()
        child.close()
        if not self.conn.poll(STARTUP_S) or self.conn.recv() != "ready":
            self.stop(kill=True)
            raise RuntimeError(f"the solver process did not start within {STARTUP_S:g} s")

    def run(self, case: Case, solver: str, timeout_s: float) -> Outcome:
        """``solver`` on ``case``, given at most ``timeout_s``."""
        if self.proc is None:
            self.start()
        self.conn.send((case.path, case.kind, case.count, solver))
        try:
            if not self.conn.poll(timeout_s):
                self.stop(kill=True)
                return Outcome(f"timeout ({timeout_s:g} s)")
            return Outcome(*self.conn.recv())
        except EOFError:
            self.proc.join(5.0)
            code = self.proc.exitcode
            self.stop(kill=True)
            return Outcome(f"failed: solver process died (exit code {code})")

    def stop(self, kill: bool = False) -> None:
        """End the process (asking it to return first, unless ``kill``)."""
        if self.proc is None:
            return
        if not kill:
            try:
                self.conn.send(None)
                self.proc.join(10.0)
            except OSError:
                pass
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join()
        self.conn.close()
        self.proc = self.conn = None


# --- scoring -----------------------------------------------------------------------------------


@dataclass
class Row:
    """One (graph, case, solver) of the tables."""

    graph: str
    kind: str
    count: int
    solver: str
    status: str
    planted: int = 0
    true_edges: int = 0  # untrusted true edges: loop closures (and GPS fixes)
    ate_m: float = float("nan")
    max_shift_m: float = float("nan")
    chi2_ratio: float = float("nan")
    false_accepted: int = 0
    true_dropped: int = 0
    seconds: float = float("nan")
    p99_ms: float = float("nan")
    max_ms: float = float("nan")
    max_cpu_ms: float = float("nan")
    over: int = 0
    over_host: int = 0

    @property
    def ok(self) -> bool:
        """The run finished and was scored."""
        return self.status == "ok"


def displacement(planar: bool, t: np.ndarray, ref: np.ndarray, align: bool) -> np.ndarray:
    """Distance of each position of ``t`` from ``ref``, after a rigid best fit if ``align``."""
    if align:
        R, shift = best_fit_transform(t, ref, np.ones(len(t)), planar)
        t = t @ R.T + shift
    return np.linalg.norm(t - ref, axis=1)


def score(case: Case, solver: str, out: Outcome, ref: Outcome, opt: float) -> Row:
    """Compare a run with the same solver's outlier-free reference."""
    graph, outlier = build_case(case)
    untrusted = ~odometry_edges(graph.kind, graph.a, graph.b)
    row = Row(case.name, case.kind, case.count, solver, out.status,
              planted=int(np.count_nonzero(outlier)),
              true_edges=int(np.count_nonzero(untrusted & ~outlier)))
    if not row.ok:
        return row
    if ref.status != "ok":
        row.status = f"failed: no outlier-free reference ({ref.status})"
        return row
    accepted = out.weights > ACCEPT_WEIGHT
    row.false_accepted = int(np.count_nonzero(outlier & accepted))
    row.true_dropped = int(np.count_nonzero(untrusted & ~outlier & ~accepted))
    # GPS fixes the world frame: a shift of the whole map is damage, not a gauge choice.
    align = case.kind not in (GPS_CLEAN, MULTIPATH)
    dist = displacement(graph.planar, out.t, ref.t, align)
    row.ate_m = float(np.sqrt(np.mean(dist**2)))
    row.max_shift_m = float(dist.max())
    clean_graph, _ = build_case(case.clean)
    if solver in NODES:  # its own odometry noise model: its own outlier-free map is its opt
        opt = chi2(clean_graph, ref.R, ref.t)
    row.chi2_ratio = chi2(clean_graph, out.R, out.t) / opt
    row.seconds = out.seconds
    row.p99_ms, row.max_ms, row.max_cpu_ms = out.p99_ms, out.max_ms, out.max_cpu_ms
    row.over, row.over_host = out.over, out.over_host
    return row


def optimum(clean: Case, refs: dict[str, Outcome]) -> float:
    """The smallest χ² of the outlier-free graph any reference reached."""
    graph, _ = build_case(clean)
    values = [chi2(graph, o.R, o.t) for o in refs.values() if o.status == "ok"]
    return min(values) if values else float("nan")


@dataclass
class CaseSet:
    """What one graph (or the GPS run) is put through."""

    clean: Case
    cases: list[Case]
    solvers: list[str]
    timeout_s: float
    keep: Case | None = None  # the case whose H₂O outcome is kept (for the plot)


class Workers:
    """The node's path in a process of its own, as ``h2o_node`` runs: in a process that has
    just run an exact solve, numpy's second BLAS thread spins on after it for a while, on the
    callbacks' core (measured on CSAIL: callbacks of 12-21 ms at a 5 ms budget, the main
    thread waiting 10-18 ms of them while that thread ran). Every other solver shares the
    second process."""

    def __init__(self) -> None:
        self.node = Worker()
        self.other = Worker()

    def run(self, case: Case, solver: str, timeout_s: float) -> Outcome:
        """:meth:`Worker.run` in the solver's process."""
        return (self.node if solver in NODES else self.other).run(case, solver, timeout_s)

    def stop(self) -> None:
        """End both processes."""
        self.node.stop()
        self.other.stop()


def bench_cases(todo: CaseSet, worker: Workers) -> tuple[list[Row], Outcome | None]:
    """References first, then every case with every solver; the rows (references included)
    and H₂O's outcome of ``todo.keep``."""

    def log(msg: str) -> None:
        print(f"[{todo.clean.name}] {msg}", file=sys.stderr, flush=True)

    refs = {}
    for solver in (*todo.solvers, LEAST_SQUARES):
        refs[solver] = worker.run(todo.clean, solver, todo.timeout_s)
        log(f"{todo.clean.kind} {solver}: {refs[solver].status}")
    opt = optimum(todo.clean, refs)
    rows = [score(todo.clean, s, refs[s], refs[s], opt) for s in todo.solvers]
    kept = None
    for case in todo.cases:
        for solver in todo.solvers:
            out = worker.run(case, solver, todo.timeout_s)
            rows.append(score(case, solver, out, refs[solver], opt))
            log(f"{case.kind} {case.count} {solver}: {out.status}, {out.seconds:.3g} s")
            if case == todo.keep and solver == "h2o" and out.status == "ok":
                kept = out
    return rows, kept


# --- plot --------------------------------------------------------------------------------------


def _segments(t: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([t[a, :2], t[b, :2]], axis=1)


def plot_map(case: Case, out: Outcome, row: Row, path: Path) -> Path:
    """H₂O's map of ``case``: odometry gray, accepted closures green, dropped false closures
    red, dropped true closures orange (false closures accepted: purple); ``row`` its scores."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    graph, outlier = build_case(case)
    odometry = odometry_edges(graph.kind, graph.a, graph.b)
    closure = (graph.kind == EdgeKind.RELATIVE) & ~odometry
    accepted = out.weights > ACCEPT_WEIGHT
    # (edges, colour, width, alpha, label, z-order): the false closures span the map, so
    # they go underneath, faint; the failures (orange, purple) go on top.
    layers = [
        (odometry, "0.35", 0.8, 1.0, "odometry", 2),
        (closure & ~outlier & accepted, "tab:green", 0.6, 0.7, "closures accepted", 3),
        (closure & outlier & ~accepted, "tab:red", 0.5, 0.35, "false closures dropped", 1),
        (closure & ~outlier & ~accepted, "tab:orange", 1.5, 1.0, "true closures dropped", 4),
        (closure & outlier & accepted, "tab:purple", 1.5, 1.0, "false closures accepted", 5),
    ]
    fig, ax = plt.subplots(figsize=(11, 8))
    handles = []
    for mask, colour, width, alpha, label, z in layers:
        if np.any(mask):
            ax.add_collection(LineCollection(
                _segments(out.t, graph.a[mask], graph.b[mask]), colors=colour,
                linewidths=width, alpha=alpha, zorder=z))
            handles.append(Line2D([], [], color=colour, linewidth=2.0,
                                  label=f"{label} ({np.count_nonzero(mask)})"))
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{case.name}: H₂O robust exact, {case.count} false closures ({case.kind})\n"
                 f"ATE {row.ate_m:.3g} m against its outlier-free map, "
                 f"χ²_true/opt {row.chi2_ratio:.4g}", fontsize=11)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")  # the legend sits outside the axes
    plt.close(fig)
    return path


# --- tables -------------------------------------------------------------------------------------


def _num(x: float, fmt: str) -> str:
    return format(x, fmt) if np.isfinite(x) else "—"


def _status(row: Row) -> str:
    return row.status.split(":")[0]


def target(row: Row) -> str:
    """The issue's target for H₂O at :data:`TARGET_COUNTS` (empty for other rows)."""
    if (row.solver not in ("h2o", *NODES) or row.count not in TARGET_COUNTS
            or row.kind not in OUTLIER_KINDS or row.status.startswith("skipped")):
        return ""  # skipped: the node on a 3-D graph
    if not row.ok:
        return "missed (" + _status(row) + ")"
    misses = []
    if not row.ate_m <= TARGET_ATE_M:
        misses.append(f"ATE {row.ate_m:.3g} m")
    if not row.chi2_ratio <= TARGET_CHI2:
        misses.append(f"χ² {row.chi2_ratio:.4g}")
    if row.solver in NODES and not (row.p99_ms <= NODE_BUDGET_MS
                                     and row.over == row.over_host):
        misses.append(f"callbacks p99 {row.p99_ms:.2f} ms, "
                      f"{row.over - row.over_host} over {2 * NODE_BUDGET_MS:g} ms")
    return "met" if not misses else "missed: " + ", ".join(misses)


def _cells(row: Row, shift: bool) -> list[str]:
    if not row.ok:
        return [_status(row)] + ["—"] * (5 + shift)
    cells = [_num(row.ate_m, ".3g")]
    if shift:
        cells.append(_num(row.max_shift_m, ".3g"))
    callbacks = "—" if not np.isfinite(row.p99_ms) else (
        f"{row.p99_ms:.2f} / {row.max_ms:.2f} / {row.max_cpu_ms:.2f}; {row.over} "
        f"({row.over_host})")
    return cells + [_num(row.chi2_ratio, ".6f"), f"{row.false_accepted} / {row.planted}",
                    f"{row.true_dropped} / {row.true_edges}", _num(row.seconds, ".3g"),
                    callbacks]


def outlier_table(rows: list[Row]) -> list[str]:
    """The false-closure rows, with the target column."""
    lines = table_head("| graph | false closures | count | solver | ATE (m) | χ²_true/opt "
                       "| false accepted | true turned away | time (s) "
                       "| callback p99 / max / max CPU (ms); over 2× budget (host) | target |")
    for r in rows:
        cells = [r.graph, r.kind, str(r.count), r.solver, *_cells(r, False), target(r)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def gps_table(rows: list[Row]) -> list[str]:
    """The GPS rows: the jump-free references and the multipath jump."""
    lines = table_head("| graph | case | solver | ATE (m) | max shift (m) | χ²_true/opt "
                       "| false accepted | true turned away | time (s) "
                       "| callback p99 / max / max CPU (ms); over 2× budget (host) |")
    for r in rows:
        cells = _cells(r, True)
        case = f"multipath, {r.planted} fixes"
        if r.kind == GPS_CLEAN:  # the reference itself: no displacement to report
            case = "jump-free"
            cells[:2] = ["ref", "ref"] if r.ok else cells[:2]
        lines.append("| " + " | ".join([r.graph, case, r.solver, *cells]) + " |")
    return lines


def reference_table(rows: list[Row]) -> list[str]:
    """The outlier-free references: how far each solver's own reference is from opt."""
    lines = table_head("| graph | solver | χ²/opt | true turned away | time (s) |")
    for r in rows:
        cells = [_num(r.chi2_ratio, ".6f"), f"{r.true_dropped} / {r.true_edges}",
                 _num(r.seconds, ".3g")] if r.ok else [_status(r), "—", "—"]
        if r.solver in NODES and r.ok:
            cells[0] = "own"  # the node's map without outliers is what its rows compare with
        lines.append("| " + " | ".join([r.graph, r.solver, *cells]) + " |")
    return lines


def target_summary(rows: list[Row]) -> str:
    """One line: on how many of H₂O's target rows the target is met."""
    checked = [target(r) for r in rows if target(r)]
    met = sum(t == "met" for t in checked)
    return (f"H₂O target (ATE ≤ {TARGET_ATE_M:g} m and χ²_true/opt ≤ {TARGET_CHI2:g} at "
            f"{' and '.join(map(str, TARGET_COUNTS))} false closures): met on {met} of "
            f"{len(checked)} rows.")


#: GTSAM's robust solvers, against which the issue holds H₂O's rows ("at least as good as
#: GTSAM's best kernel in every row").
KERNELS = ("cauchy", "dcs", "gnc")
#: Differences below these are noise, not a better map: 1 mm of ATE, 1e-4 of χ²_true/opt.
BEAT_ATE_M = 1e-3
BEAT_CHI2 = 1e-4


def beaten_by(row: Row, rows: list[Row]) -> list[str]:
    """The GTSAM kernels whose map of ``row``'s case is better on both counts: ATE lower by
    more than :data:`BEAT_ATE_M` and χ²_true/opt lower by more than :data:`BEAT_CHI2` (a
    map that is only better on one of them trades, it does not beat)."""
    return [r.solver for r in rows
            if r.solver in KERNELS and r.ok and (r.graph, r.kind, r.count) == (
                row.graph, row.kind, row.count)
            and r.ate_m < row.ate_m - BEAT_ATE_M and r.chi2_ratio < row.chi2_ratio - BEAT_CHI2]


def kernel_summary(rows: list[Row]) -> list[str]:
    """H₂O's rows (exact and the node's, every count) that a GTSAM kernel beats, one line
    each, after a count line."""
    ours = [r for r in rows if r.solver in ("h2o", *NODES) and r.ok and r.kind in OUTLIER_KINDS]
    beaten = [(r, b) for r in ours if (b := beaten_by(r, rows))]
    lines = [f"H₂O rows that a GTSAM kernel in the same case beats on both ATE (by > "
             f"{BEAT_ATE_M * 1e3:g} mm) and χ²_true/opt (by > {BEAT_CHI2:g}): {len(beaten)} of "
             f"{len(ours)}."]
    lines += [f"- {r.graph}, {r.kind} {r.count}, {r.solver} (ATE {r.ate_m:.3g} m, χ² "
              f"{r.chi2_ratio:.6f}): beaten by {', '.join(b)}" for r, b in beaten]
    return lines


def format_tables(rows: list[Row]) -> str:
    """Every table of the section, and the failures."""
    refs = [r for r in rows if r.kind == "clean"]
    planted = [r for r in rows if r.kind in OUTLIER_KINDS]
    gps = [r for r in rows if r.kind in (GPS_CLEAN, MULTIPATH)]
    lines = [*outlier_table(planted), "", target_summary(planted), "",
             *kernel_summary(planted), "",
             "Outlier-free references (each solver's own map of the graph without false "
             "closures; χ²/opt as above):", "", *reference_table(refs)]
    if gps:
        lines += ["", f"GPS multipath (fixes every {GPS_EVERY}th pose, sigma {GPS_SIGMA_M:g} m; "
                  f"{JUMP_FIXES} consecutive fixes moved {JUMP_M[0]:g}–{JUMP_M[1]:g} m; ATE "
                  "not aligned):", "", *gps_table(gps)]
    failures = [r for r in rows if not r.ok and not r.status.startswith("skipped")]
    if failures:
        lines += ["", "Failures:", ""]
        lines += [f"- {r.graph}, {r.kind} {r.count}, {r.solver}: {r.status}" for r in failures]
    return "\n".join(lines)


NOTES = f"""\
Notes:

- ATE: RMS position difference between a solver's map and the *same* solver's map of the
  outlier-free graph, after a rigid best fit (none for GPS). χ²_true/opt: the outlier-free
  graph (true edges only) scored by `h2o_slam.core.graph.chi2` at the map, over the smallest
  such χ² of any outlier-free run (H₂O exact without a kernel included).
- Accepted = final weight > {ACCEPT_WEIGHT:g}. "true turned away" counts true loop closures (GPS:
  and true fixes) under it, out of all of them; odometry is trusted by every robust solver.
  Plain LM keeps every edge at weight 1. Cauchy (k = {CAUCHY_K:g}) and DCS (Φ = {DCS_PHI:g})
  weights are the kernel's at the plain factor's whitened distance r at the solution:
  1/(1 + r²) and min(1, (2Φ/(Φ + r²))²), under 0.5 from χ² = 1 and ≈ 1.83, so true closures
  a little off the map count as turned away although they still pull on it.
- GNC: `GncLMOptimizer`, TLS, known inliers = odometry and the prior, thresholds at χ²
  probability {INLIER_PROBABILITY:g} (H₂O's; GTSAM's default is 0.99).
- Seeds: `crc32("<graph>/<kind>/<count>")`. Counts above the graph's number of true loop
  closures are not run. H₂O's time is `solve_exact` (building its solver included); GTSAM's
  is `optimize()` (building factors excluded). H₂O starts from its odometry spanning tree,
  GTSAM from the file's vertices.
- GPS in GTSAM: `PoseTranslationPrior2D` (`GPSFactor` in 3-D), no prior on node 0.
"""


def render_section(rows: list[Row], skipped: list[str], plot: Path | None,
                   wall_s: float) -> str:
    """The ``## Robust`` section of RESULTS.md."""
    try:
        gtsam_version = metadata.version("gtsam")
    except metadata.PackageNotFoundError:
        gtsam_version = "not installed"
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    extra = "".join(f"- not run: {s}\n" for s in skipped) + ("\n" if skipped else "")
    if plot is not None:
        shown = plot.relative_to(REPO) if plot.is_relative_to(REPO) else plot
        extra += f"H₂O's map of the plotted case: `{shown}`.\n\n"
    return (f"{SECTION}\n\nCommand (from the repo root): `{command(REPO)}`\n\n"
            f"Date: {when}. Machine: {platform.machine()}, Python "
            f"{platform.python_version()}, gtsam {gtsam_version}, repo at {revision(REPO)}. "
            f"Wall time {wall_s:.0f} s. Timings are indicative (shared machine).\n\n"
            f"{format_tables(rows)}\n\n{extra}{NOTES}")


# --- driver -------------------------------------------------------------------------------------


@dataclass
class Options:
    """The command line, as the driver uses it."""

    kinds: list[str]
    counts: list[int]
    solvers: list[str]
    timeout_s: float
    plot_case: tuple[str, str, int]  # graph, kind, count
    plots: Path
    gps_graph: str | None


def graph_cases(path: Path, opts: Options, skipped: list[str]) -> CaseSet:
    """The cases of one graph file: each kind at each count it has closures for."""
    closures = true_closures(read_graph(str(path)))
    counts = [c for c in opts.counts if c <= closures]
    skipped += [f"{path.stem}, {c} false closures ({closures} true closures)"
                for c in opts.counts if c > closures]
    cases = [Case(str(path), kind, count) for kind in opts.kinds for count in counts]
    name, kind, count = opts.plot_case
    keep = Case(str(path), kind, count) if name == path.stem else None
    return CaseSet(Case(str(path), "clean"), cases, opts.solvers, opts.timeout_s, keep)


def run(paths: list[Path], opts: Options, results: Path | None) -> int:
    """Benchmark ``paths``; publish the section; return an exit code."""
    start = time.perf_counter()
    worker = Workers()
    skipped: list[str] = []
    plot: Path | None = None

    def bench_one(path: Path, _folder: Path) -> list[Row]:
        nonlocal plot
        todo = graph_cases(path, opts, skipped)
        rows, kept = bench_cases(todo, worker)
        if kept is not None and todo.keep is not None:
            row = next(r for r in rows if r.solver == "h2o" and r.kind == todo.keep.kind
                       and r.count == todo.keep.count)
            plot = plot_map(todo.keep, kept, row, opts.plots / f"robust_{path.stem}.png")
            print(f"map: {plot}", file=sys.stderr)
        if path.stem == opts.gps_graph:
            gps = CaseSet(Case(str(path), GPS_CLEAN), [Case(str(path), MULTIPATH)],
                          opts.solvers, opts.timeout_s)
            rows += bench_cases(gps, worker)[0]
        return rows

    try:
        per_graph, unread = run_graphs("robust.py", paths, None, bench_one)
    finally:
        worker.stop()
    rows = [r for graph_rows in per_graph for r in graph_rows]
    section = render_section(rows, skipped + unread, plot, time.perf_counter() - start)
    publish(section, results, SECTION)
    print(f"wall time {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_graph_arguments(parser)
    parser.add_argument("--no-write", dest="no_results", action="store_true",
                        help="print the section only (same as --no-results)")
    parser.add_argument("--kinds", nargs="+", choices=OUTLIER_KINDS, default=list(OUTLIER_KINDS),
                        metavar="KIND", help=f"false-closure kinds (default: all of "
                        f"{' '.join(OUTLIER_KINDS)})")
    parser.add_argument("--counts", nargs="+", type=int, default=list(COUNTS), metavar="N",
                        help="false closures per case, where the graph has as many true ones "
                        f"(default {' '.join(map(str, COUNTS))})")
    parser.add_argument("--solvers", nargs="+", choices=(*SOLVERS, NODE_DEFAULTS),
                        default=list(SOLVERS), metavar="NAME",
                        help=f"subset of {' '.join(SOLVERS)} {NODE_DEFAULTS} (default: all "
                        f"but {NODE_DEFAULTS})")
    parser.add_argument("--timeout", type=float, default=600.0, metavar="S",
                        help="limit per solver run in seconds (default 600)")
    parser.add_argument("--plot-graph", default="intel", metavar="NAME",
                        help="graph whose H₂O map is plotted (default intel)")
    parser.add_argument("--plot-kind", choices=OUTLIER_KINDS, default="random", metavar="KIND",
                        help="case plotted: its kind (default random) ...")
    parser.add_argument("--plot-count", type=int, default=100, metavar="N",
                        help="... and count (default 100); a case not run is not plotted")
    parser.add_argument("--plots", type=Path, default=DEFAULT_PLOTS, metavar="DIR",
                        help=f"folder of the PNG (default {DEFAULT_PLOTS})")
    parser.add_argument("--gps-graph", default="intel", metavar="NAME",
                        help="graph of the GPS multipath case, run when it is selected")
    parser.add_argument("--no-gps", action="store_true", help="skip the GPS multipath case")
    args = parser.parse_args(argv)
    paths = select_graphs("robust.py", args.data, args.graphs)
    if isinstance(paths, int):
        return paths
    opts = Options(args.kinds, args.counts, args.solvers, args.timeout,
                   (args.plot_graph, args.plot_kind, args.plot_count), args.plots,
                   None if args.no_gps else args.gps_graph)
    return run(paths, opts, results_path(args))


if __name__ == "__main__":
    sys.exit(main())
