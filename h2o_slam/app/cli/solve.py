"""``h2o-solve``: optimize a g2o pose graph with H₂O (or LAGO) and write the solution and a report.

    h2o-solve INPUT.g2o --output OUT.g2o [--mode exact|offline|online] [--passes N]
              [--tolerance T] [--init auto|tree|input|lago|chordal] [--solver h2o|lago] [--d-max N]
              [--budget-ms X] [--gps-batch-size N] [--gps-every K --gps-sigma S]
              [--metric h2o|gtsam|g2o] [--report REPORT.json] [--trace TRACE.json]
              [--idle-s S] [--samples N] [--period-ms P] [--robust auto|gnc|off]
              [--certify auto|on|off] [--staircase auto|off] [--quiet]

The work is :func:`solve_file`; this module's ``main`` only parses arguments, prints, and maps
errors to a one-line message and an exit code (2: the command line, 1: the input).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from contextlib import AbstractContextManager, nullcontext
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from h2o_slam.app.cli.common import (
    EXIT_INPUT,
    OneLineParser,
    ProgressLine,
    integer,
    number,
    unwritable_file,
    usage_error,
)
from h2o_slam.baselines.chi2_metrics import METRICS, all_chi2
from h2o_slam.core.errors import H2OError, InputError
from h2o_slam.core.graph import (
    INFO_EIG_FLOOR,
    PoseGraph,
    chi2,
    chi2_as_written,
    edge_chi2,
    has_global,
)
from h2o_slam.core.modes import (
    EXACT_ITERATIONS,
    INITS,
    Progress,
    SolveResult,
    sample_points,
    solve_exact,
    solve_lago,
    solve_offline,
    solve_online,
)
from h2o_slam.core.online import OnlineConfig
from h2o_slam.core.robust import (
    EdgeState,
    RobustConfig,
    closure_noise_scale,
    decided_thresholds,
    edge_states,
    loop_closures,
    odometry_edges,
    thresholds,
)
from h2o_slam.core.solver import SolverConfig
from h2o_slam.core.warmup import false_ring, load_closure_scoring, warm_up
from h2o_slam.io.g2o import read_g2o, write_g2o
from h2o_slam.io.synthetic import add_gps

MODES = ("exact", "offline", "online")
SOLVERS = ("h2o", "lago")
ROBUST = ("auto", "gnc", "off")
CERTIFY = ("auto", "on", "off")

#: Solves of a small ring before exact mode's clock starts (:func:`_load`).
INTERPRETER_WARMUP = 10

#: ``--staircase``: ``auto`` climbs when the certificate fails.
STAIRCASE = ("auto", "off")
DEFAULT_PASSES = {"offline": 10, "online": 0, "exact": EXACT_ITERATIONS}
PROG = "h2o-solve"

#: ``--init`` values: ``auto`` (:func:`default_init`) and the starts of :data:`INITS`.
INIT_CHOICES = ("auto", *INITS)


@dataclass(frozen=True)
class SolveOptions:
    """How :func:`solve_file` solves.

    Attributes:
        mode: ``exact`` (the default: Gauss–Newton to convergence after the tree start, the
            best map), ``offline`` or ``online``.
        passes: offline passes (offline mode), offline passes after the online pass (online),
            or the most Gauss–Newton iterations (exact); ``None`` takes the mode's default.
        tolerance: exact mode: stop when an iteration lowers χ² by less than this fraction.
        init: ``tree`` (the thesis' start: tree edges concatenated from the root), ``input``
            (the file's vertices, or its odometry chain) or ``lago`` (planar graphs); online
            mode grows its tree from the arriving edges instead.
        solver: ``h2o`` or ``lago`` (the linear approximation alone; ``mode`` is ignored).
        d_max: most nodes solved for per edge (interpolated solving); ``None``: unlimited.
        budget_ms: online mode: time per arriving pose; ``None``: relax every edge in full.
        gps_batch_size: GPS edges relaxed together.
        gps_every, gps_sigma_m: add a GPS edge every ``gps_every`` poses at the graph's exact
            optimum plus noise of ``gps_sigma_m`` (0: none).
        idle_s: online mode: seconds of budgeted idle steps after the last arrival (the
            robot stops; the exact solver beside the updates finishes its work).
        samples: online mode: sample χ² of the edges so far at this many poses spread over
            the stream and as many after loop closures (0: none).
        period_ms: online mode: one pose arrives every this many ms, with idle steps between
            (a robot's keyframe rate); 0: each as soon as the last callback returns.
        robust: ``auto`` (GNC-TLS in exact mode, none elsewhere), ``gnc`` or ``off``: loop
            closures and GPS fixes weighed as possible outliers, odometry trusted
            (:mod:`h2o_slam.core.robust`).
        certify: ``auto`` (the default: after exact-mode solves with the H₂O solver), ``on``
            (the same, refused elsewhere) or ``off``: test the solution's global optimality
            with SE-Sync's certificate (:mod:`h2o_slam.core.certificate`).
        staircase: ``auto`` (the default): when the certificate fails, climb SE-Sync's
            Riemannian staircase from the solution and solve again from its rounded point,
            keeping the answer that ends lower
            (:func:`~h2o_slam.core.staircase.staircase_solve`);
            ``off``: report the failure only.
    """

    mode: str = "exact"
    passes: int | None = None
    tolerance: float = SolverConfig.exact_tolerance
    init: str = "auto"
    solver: str = "h2o"
    d_max: int | None = None
    budget_ms: float | None = None
    gps_batch_size: int = 30
    gps_every: int = 0
    gps_sigma_m: float = 1.0
    idle_s: float = 1.0
    samples: int = 0
    period_ms: float = 0.0
    robust: str = "auto"
    certify: str = "auto"
    staircase: str = "auto"

    @property
    def robust_config(self) -> RobustConfig | None:
        """The robust estimation to run: GNC-TLS in H₂O's exact mode unless ``off``."""
        on = self.robust == "gnc" or (self.robust == "auto" and self.mode == "exact"
                                      and self.solver == "h2o")
        return RobustConfig() if on else None

    @property
    def certifies(self) -> bool:
        """Whether the solution's global optimality is tested (exact mode, H₂O solver)."""
        return self.certify != "off" and self.mode == "exact" and self.solver == "h2o"

    def __post_init__(self) -> None:
        for name, value, allowed in (("solver", self.solver, SOLVERS),
                                     ("mode", self.mode, MODES),
                                     ("init", self.init, INIT_CHOICES)):
            if value not in allowed:
                raise InputError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")
        if self.passes is not None and self.passes < 0:
            raise InputError("--passes must be non-negative")
        if not 0.0 <= self.tolerance < 1.0:
            raise InputError("--tolerance must be in [0, 1)")
        if self.d_max is not None and self.d_max < 1:
            raise InputError("--d-max must be at least 1")
        if self.budget_ms is not None and not self.budget_ms > 0.0:
            raise InputError("--budget-ms must be positive")
        if self.budget_ms is not None and self.mode != "online":
            raise InputError("--budget-ms applies to --mode online only")
        if self.gps_batch_size < 1:
            raise InputError("--gps-batch-size must be at least 1")
        if not 0.0 <= self.idle_s < math.inf:
            raise InputError("--idle-s must be a non-negative number of seconds")
        if self.samples < 0:
            raise InputError("--samples must be non-negative")
        if not 0.0 <= self.period_ms < math.inf:
            raise InputError("--period-ms must be a non-negative number of milliseconds")
        if self.robust not in ROBUST:
            raise InputError(f"unknown robust {self.robust!r}; choose one of {', '.join(ROBUST)}")
        if self.robust == "gnc" and (self.mode != "exact" or self.solver != "h2o"):
            raise InputError("--robust gnc applies to --mode exact with --solver h2o only")
        if self.period_ms and (self.mode != "online" or self.budget_ms is None):
            raise InputError("--period-ms applies to --mode online with --budget-ms only")
        if self.certify not in CERTIFY:
            raise InputError(f"unknown certify {self.certify!r}; choose one of "
                             f"{', '.join(CERTIFY)}")
        if self.certify == "on" and (self.mode != "exact" or self.solver != "h2o"):
            raise InputError("--certify on applies to --mode exact with --solver h2o only")
        if self.staircase not in STAIRCASE:
            raise InputError(f"unknown staircase {self.staircase!r}; choose one of "
                             f"{', '.join(STAIRCASE)}")


@dataclass
class SolveReport:
    """What ``--report`` writes (JSON)."""

    input: str
    solver: str
    mode: str
    init: str | None
    passes: int
    nodes: int
    edges: int
    chi2_initial: float
    chi2_final: float
    chi2_per_pass: list[float]
    wall_s: float
    load_s: float = 0.0
    metric: str = "h2o"
    chi2_metrics: dict[str, dict[str, float]] | None = None
    iterations: int | None = None
    max_iterations: int | None = None
    tolerance: float | None = None
    d_max: int | None = None
    budget_ms: float | None = None
    per_callback_ms: dict[str, float] | None = None
    overruns: int | None = None
    deferred_edges: int | None = None
    gps_edges_added: int = 0
    converged: bool | None = None
    chi2_end_of_stream: float | None = None
    chi2_after_idle: float | None = None
    idle_s: float | None = None
    idle_steps: int | None = None
    period_ms: float | None = None
    idle_steps_between: int | None = None
    updates: int | None = None
    exact: dict[str, Any] | None = None
    samples: list[list[float]] | None = None
    robust: dict[str, Any] | None = None
    certificate: dict[str, Any] | None = None
    staircase: dict[str, Any] | None = None
    conditioned: dict[str, Any] | None = None


def solve_file(
    input_path: Path, output_path: Path, options: SolveOptions | None = None,
    metric: str = "h2o", progress: Progress | None = None,
    solving: AbstractContextManager[object] | None = None,
) -> tuple[SolveReport, SolveResult]:
    """Read ``input_path``, solve it as ``options`` say, write the solution to ``output_path``.

    The report's ``chi2_initial``, ``chi2_final`` and ``chi2_per_pass`` are in ``metric``
    (see :mod:`h2o_slam.baselines.chi2_metrics`; the solvers minimize ``h2o``); ``chi2_metrics``
    carries the initial and final χ² in all three. ``progress(step, chi2)`` is called after
    each offline pass. ``solving`` is entered for the solve alone (the span of ``wall_s``):
    a progress line there does not count reading, warming up or writing.

    Raises:
        H2OError: the input cannot be read or solved (the message names file and line).
        OSError: the files cannot be read or written.
    """
    opt = options or SolveOptions()
    graph = read_g2o(input_path)
    added = 0
    if opt.gps_every:
        optimum = solve_exact(graph)
        before = graph.num_edges
        graph = add_gps(graph, optimum.t, opt.gps_every, opt.gps_sigma_m)
        added = graph.num_edges - before
    opt = replace(opt, init=default_init(graph) if opt.init == "auto" else opt.init)
    passes = DEFAULT_PASSES[opt.mode] if opt.passes is None else opt.passes
    load_s = _load(graph, opt)
    try:
        # The clock starts inside: the progress line's thread starts before it (0.1-0.4 ms,
        # a third of a 9-pose graph's solve).
        with solving or nullcontext():
            start = time.perf_counter()
            result = _solve(graph, opt, passes, progress)
            wall_s = time.perf_counter() - start
    except InputError as err:  # e.g. LAGO refusing a 3-D graph: say which file
        raise InputError(f"{input_path}: {err}") from None
    # Written before it is tested: whatever the test does, the solve's answer is saved.
    write_g2o(output_path, graph, result.R, result.t)
    certificate = _certificate(graph, result) if opt.certifies else None
    staircase = None
    if certificate is not None and not certificate["certified"] and opt.staircase == "auto":
        result, staircase = _climbed(graph, opt, passes, result)
        if staircase["adopted"]:
            # The written answer took the certificate and the climb too.
            wall_s += certificate["seconds"] + staircase["seconds"]
            certificate = _certificate(graph, result)
            write_g2o(output_path, graph, result.R, result.t)
    lago = opt.solver == "lago"
    online = not lago and opt.mode == "online"
    exact = not lago and opt.mode == "exact"
    # An infinite budget is no budget: reported as null (strict JSON has no Infinity).
    budget = opt.budget_ms if opt.budget_ms is not None and math.isfinite(opt.budget_ms) \
        else None
    start_R, start_t = _start(graph, result)
    metrics = {"initial": all_chi2(graph, start_R, start_t),
               "final": all_chi2(graph, result.R, result.t)}
    # The last entry is the reported solution's χ² in ``metric``; the others are the
    # solver's own (it minimizes h2o's).
    per_pass = result.chi2_per_pass[:-1] + [metrics["final"][metric]] \
        if result.chi2_per_pass else []
    report = SolveReport(
        input=str(input_path), solver=opt.solver,
        mode="lago" if lago else opt.mode,
        # LAGO needs no starting estimate; online mode grows its tree from the arrivals.
        init=None if lago else ("tree" if online else result.init or opt.init),
        passes=0 if lago else (len(result.chi2_per_pass) if exact else passes),
        nodes=graph.num_nodes, edges=graph.num_edges,
        chi2_initial=metrics["initial"][metric], chi2_final=metrics["final"][metric],
        chi2_per_pass=per_pass, wall_s=wall_s, load_s=load_s, metric=metric,
        chi2_metrics=metrics,
        iterations=len(result.chi2_per_pass) if exact else None,
        max_iterations=passes if exact else None, tolerance=opt.tolerance if exact else None,
        d_max=opt.d_max, budget_ms=budget,
        per_callback_ms=_percentiles(result.per_callback_ms) if online else None,
        overruns=(sum(t > budget for t in result.per_callback_ms)
                  if online and budget is not None else None),
        deferred_edges=result.deferred_edges if online else None,
        gps_edges_added=added, converged=result.converged,
        chi2_end_of_stream=result.chi2_end_of_stream, chi2_after_idle=result.chi2_after_idle,
        idle_s=opt.idle_s if online else None, idle_steps=result.idle_steps if online else None,
        period_ms=opt.period_ms if online else None,
        idle_steps_between=result.idle_steps_between if online else None,
        updates=result.updates if online else None,
        exact=asdict(result.exact) if result.exact is not None else None,
        samples=[list(sample) for sample in result.samples] if online else None,
        robust=_robust_summary(graph, result),
        certificate=certificate, staircase=staircase,
        conditioned=_conditioned(graph, result),
    )
    return report, result


def _certificate(graph: PoseGraph, result: SolveResult) -> dict[str, Any]:
    """The report's certificate: SE-Sync's test of the solution over the edges the solve
    kept (all of them without robust estimation; :mod:`h2o_slam.core.certificate`)."""
    # Imported here: scipy's eigensolvers add 0.1-0.2 s to every start-up otherwise.
    from h2o_slam.core.certificate import certify

    keep = None if result.weights is None else result.weights > 0.5
    return asdict(certify(graph, result.R, result.t, keep))


def _climbed(graph: PoseGraph, opt: SolveOptions, passes: int, result: SolveResult
             ) -> tuple[SolveResult, dict[str, Any]]:
    """Exact mode again from SE-Sync's staircase climbed from an uncertified ``result``; the
    answer that ends lower and the report's account of the climb."""
    # Imported here: scipy's eigensolvers add 0.1-0.2 s to every start-up otherwise.
    from h2o_slam.core.staircase import staircase_solve

    start = time.perf_counter()
    config = SolverConfig(gps_batch_size=opt.gps_batch_size, exact_tolerance=opt.tolerance)
    before = chi2(graph, result.R, result.t)
    try:
        answer, climb, adopted = staircase_solve(graph, result, passes, config,
                                                 opt.robust_config)
    except (H2OError, ArithmeticError, RuntimeError, ValueError) as err:
        # A second opinion that fails (a factorization, the eigensolver) costs the solve's
        # answer nothing: it is written as it stands.
        return result, {
            "adopted": False, "error": f"{type(err).__name__}: {err}", "rank": None,
            "relaxation_solved": None, "lambda_min": None, "relaxation_cost": None,
            "iterations": None, "climb_s": None, "chi2_before": before, "chi2_after": before,
            "seconds": time.perf_counter() - start,
        }
    return answer, {
        "adopted": adopted, "error": None, "rank": climb.rank,
        "relaxation_solved": climb.relaxation_solved,
        "lambda_min": climb.lambda_min, "relaxation_cost": climb.cost,
        "iterations": climb.iterations, "climb_s": climb.seconds,
        "chi2_before": before, "chi2_after": chi2(graph, answer.R, answer.t),
        "seconds": time.perf_counter() - start,
    }


def _conditioned(graph: PoseGraph, result: SolveResult) -> dict[str, Any] | None:
    """The report's account of the information matrices the reader eigen-clamped: how many,
    and χ² at the solution with the conditioned information (what was solved) and with the
    file's as written. ``None`` when none was."""
    count = len(graph.clamped_edges)
    if not count:
        return None
    solved = chi2(graph, result.R, result.t)
    written = chi2_as_written(graph, result.R, result.t)
    return {"edges": count, "clamped_edges": graph.clamped_edges.tolist(),
            "eigenvalue_floor": INFO_EIG_FLOOR, "chi2_conditioned": solved,
            "chi2_as_written": written, "chi2_difference": solved - written}


def _robust_summary(graph: PoseGraph, result: SolveResult) -> dict[str, Any] | None:
    """The report's account of a robust solve: what was weighed, kept and dropped, and χ²
    of the edges kept (what the solve minimized; ``chi2_final`` counts every edge)."""
    if result.weights is None:
        return None
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    states = edge_states(result.weights, trusted)
    kept = result.weights > 0.5
    config = RobustConfig()
    r2 = edge_chi2(graph, result.R, result.t)
    used = decided_thresholds(graph, trusted, config, result.weights, r2)
    plain = thresholds(graph.kind, graph.planar, config.inlier_probability)
    closures = loop_closures(graph.kind, trusted)
    return {
        "method": "gnc-tls", "inlier_probability": config.inlier_probability,
        "closure_noise_scale": closure_noise_scale(graph, trusted),
        "closure_threshold_scale": float(np.min(used[closures] / plain[closures],
                                                initial=1.0)),
        "weighed": int(np.count_nonzero(~trusted)),
        "accepted": int(np.count_nonzero(states == EdgeState.ACCEPTED)),
        "dropped": int(np.count_nonzero(states == EdgeState.DROPPED)),
        "dropped_edges": np.flatnonzero(states == EdgeState.DROPPED).tolist(),
        "chi2_accepted": float(np.sum(r2[kept])),
    }


def default_init(graph: PoseGraph) -> str:
    """``--init auto``: the chordal initialization for 3-D graphs of relative edges only, the
    spanning tree otherwise. Measured (bench/RESULTS.md, Solvers): from the chordal start
    exact mode ends at the same χ² as from the tree on 12 of 12 3-D graphs, in half the
    time on large-noise spheres (σ_R ≥ 0.2 rad: 46-55 s against 106-123 s); on planar
    graphs the robust solve already runs from the tree and from LAGO and keeps the better
    answer (from LAGO alone, intel with 10 false closures ends 14 m off)."""
    if graph.planar or has_global(graph):
        return "tree"
    return "chordal"


def _load(graph: PoseGraph, opt: SolveOptions) -> float:
    """Load the compiled kernels the solve uses before its clock starts (``load_s``: 0.3-0.5 s
    on two cores), so that ``wall_s`` is the solve's: the budgeted modes start as a node
    does, with every kernel (no callback pays for one), exact mode with what a solve of a
    graph of the same kind loads. LAGO uses none."""
    if opt.solver == "lago":
        return 0.0
    start = time.perf_counter()
    if opt.mode == "exact":
        # As GTSAM is loaded before its optimize() is timed: otherwise a solve of a
        # 125-pose graph counts 0.3-0.5 s of loading (numba's first kernel alone sets up its
        # code generator, ~0.2 s) against its tens of milliseconds of work. A start the
        # kind has no use for is the solve's error to report, not the load's.
        usable = opt.init in ("lago", "tree") if graph.planar else opt.init in ("chordal", "tree")
        init = opt.init if usable else "tree"
        solve_exact(false_ring(graph.planar), 5, init=init, robust=opt.robust_config)
        # Python's specializing interpreter (3.11+) adapts a function's bytecode once it has
        # run a few times: solves of a clean ring leave the code a solve runs once per call
        # adapted too (tinyGrid3D's least-squares solve 1.9 -> 1.4 ms; 20-30 ms of loading).
        ring = false_ring(graph.planar, false_closure=False)
        for _ in range(INTERPRETER_WARMUP):
            solve_exact(ring, 5, init=init, robust=opt.robust_config)
        if opt.robust_config is not None:
            load_closure_scoring()
    else:
        warm_up()
    return time.perf_counter() - start


def _start(graph: PoseGraph, result: SolveResult) -> tuple[np.ndarray, np.ndarray]:
    """The starting estimate the solve reported ``chi2_initial`` for."""
    return result.start if result.start is not None else (graph.R, graph.t)


def _solve(graph: PoseGraph, opt: SolveOptions, passes: int,
           progress: Progress | None) -> SolveResult:
    if opt.solver == "lago":
        return solve_lago(graph)
    config = SolverConfig(gps_batch_size=opt.gps_batch_size, exact_tolerance=opt.tolerance)
    if opt.mode == "offline":
        return solve_offline(graph, passes, config, init=opt.init, d_max=opt.d_max,
                             progress=progress)
    if opt.mode == "online":
        budget_s = None if opt.budget_ms is None else opt.budget_ms / 1e3
        # Unbudgeted, the exact solves run inline on their schedule: no worker is needed.
        background = "process" if budget_s is not None and budget_s < 1.0 else "inline"
        online = OnlineConfig(d_max=opt.d_max, background=background)
        return solve_online(graph, passes, config, budget_s, online,
                            trace_every=max(1, graph.num_nodes // 200), idle_s=opt.idle_s,
                            sample_nodes=sample_points(graph, opt.samples),
                            period_s=opt.period_ms / 1e3)
    return solve_exact(graph, passes, config, init=opt.init, robust=opt.robust_config)


def _percentiles(times_ms: list[float]) -> dict[str, float]:
    t = np.asarray(times_ms) if times_ms else np.zeros(1)
    return {"mean": float(t.mean()), "p99": float(np.percentile(t, 99)), "max": float(t.max())}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``h2o-solve``."""
    p = OneLineParser(
        prog=PROG,
        description="Optimize a g2o pose graph with H₂O (hybrid-Hessian SLAM) or LAGO.",
    )
    p.add_argument("input", type=Path, help="input graph (.g2o)")
    p.add_argument("--output", "-o", type=Path, required=True,
                   help="where to write the solution (.g2o, a VERTEX line per pose)")
    p.add_argument("--mode", choices=MODES, default="exact",
                   help="exact: damped Gauss-Newton on all edges to convergence, from the "
                        "tree start (the best map); offline: Algorithm 1 passes; online: "
                        "pose by pose (default: exact)")
    p.add_argument("--passes", type=integer(0), default=None,
                   help="exact: most iterations (default "
                        f"{EXACT_ITERATIONS}; a warning when reached); offline passes "
                        f"(default {DEFAULT_PASSES['offline']}); online: extra offline passes "
                        "after the online pass (default 0)")
    p.add_argument("--tolerance", type=number(0.0, 1.0), default=SolverConfig.exact_tolerance,
                   help="exact: converged when an iteration lowers chi2 by less than this "
                        f"fraction (default {SolverConfig.exact_tolerance:g})")
    p.add_argument("--solver", choices=SOLVERS, default="h2o",
                   help="h2o (default) or lago: the linear approximation alone "
                        "(planar graphs; --mode, --passes and --init are ignored)")
    p.add_argument("--init", choices=INIT_CHOICES, default="auto",
                   help="starting estimate: tree (tree edges concatenated from the root, as in "
                        "the thesis), input (the file's vertices, or its odometry chain when "
                        "it has none), lago (planar graphs) or chordal (3-D graphs: rotations "
                        "first); default auto: chordal for 3-D graphs without GPS or compass "
                        "edges, tree otherwise")
    p.add_argument("--d-max", type=integer(1), default=None,
                   help="most nodes solved for per edge (interpolated solving); default: all")
    p.add_argument("--budget-ms", type=number(0.0, math.inf, low_open=True, infinite=True),
                   default=None,
                   help="online mode: time per arriving pose in ms; default (and inf): no "
                        "limit")
    p.add_argument("--gps-batch-size", type=integer(1), default=30,
                   help="GPS edges relaxed together (default 30)")
    p.add_argument("--gps-every", type=integer(0), default=0,
                   help="add a GPS edge every K poses, at the graph's exact optimum plus noise")
    p.add_argument("--gps-sigma", type=number(0.0, math.inf), default=1.0,
                   help="noise (m, per axis) of the GPS edges --gps-every adds (default 1)")
    p.add_argument("--metric", choices=METRICS, default="h2o",
                   help="chi2 convention of chi2_initial, chi2_final and chi2_per_pass: h2o "
                        "(this package's [t; Log R]), gtsam (2 x GTSAM's graph error) or g2o "
                        "(g2o's chi2); chi2_metrics always has all three (default: h2o)")
    p.add_argument("--idle-s", type=number(0.0, math.inf), default=1.0,
                   help="online mode: seconds of budgeted idle steps after the last pose "
                        "(the robot stops; default 1)")
    p.add_argument("--samples", type=integer(0), default=0,
                   help="online mode: sample chi2 of the edges so far at N poses over the "
                        "stream and N after loop closures, into the report (default 0)")
    p.add_argument("--period-ms", type=number(0.0, math.inf), default=0.0,
                   help="online mode with --budget-ms: one pose arrives every this many ms, "
                        "idle steps between (a robot's keyframe rate); default 0: each pose "
                        "as soon as the last callback returns (the worst case)")
    p.add_argument("--robust", choices=ROBUST, default="auto",
                   help="loop closures and GPS fixes as possible outliers (GNC with a "
                        "truncated quadratic; odometry trusted): auto = in exact mode "
                        "(default), gnc, or off (plain least squares)")
    p.add_argument("--certify", choices=CERTIFY, default="auto",
                   help="test the solution's global optimality with SE-Sync's certificate "
                        "(auto = after exact-mode solves with h2o (default), on, or off); "
                        "the answer in one line on stderr and in the report")
    p.add_argument("--staircase", choices=STAIRCASE, default="auto",
                   help="when the certificate fails: climb SE-Sync's Riemannian staircase "
                        "from the solution and solve again from its rounded point, keeping "
                        "the lower answer (auto, the default), or off")
    p.add_argument("--report", type=Path, default=None, help="write a JSON report here")
    p.add_argument("--trace", type=Path, default=None,
                   help="online mode: write per-callback times and chi2 samples (JSON) here")
    p.add_argument("--quiet", "-q", action="store_true",
                   help="no progress line on stderr (printed once a second for solves "
                        "longer than a second)")
    return p


def _options(args: argparse.Namespace) -> SolveOptions:
    return SolveOptions(
        mode=args.mode, passes=args.passes, tolerance=args.tolerance, init=args.init,
        solver=args.solver, d_max=args.d_max, budget_ms=args.budget_ms,
        gps_batch_size=args.gps_batch_size, gps_every=args.gps_every,
        gps_sigma_m=args.gps_sigma, idle_s=args.idle_s, samples=args.samples,
        period_ms=args.period_ms, robust=args.robust, certify=args.certify,
        staircase=args.staircase,
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``h2o-solve``; returns the exit code (2: the command line, 1: the
    input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        options = _options(args)  # options that do not go together
    except InputError as err:
        return usage_error(PROG, str(err))
    # Every output is checked before the solve, which may take minutes.
    for option, path in (("--output", args.output), ("--report", args.report),
                         ("--trace", args.trace)):
        problem = unwritable_file(option, path)
        if problem is not None:
            return usage_error(PROG, problem)
    mode = "lago" if options.solver == "lago" else options.mode
    # Its clock runs from the solve's start: a fast solve in a slow start-up prints nothing.
    line = ProgressLine(PROG, enabled=not args.quiet)

    def progress(step: int, chi2: float) -> None:
        line.status = f"{mode}: pass {step}, chi2 {chi2:.6g}"

    line.status = f"{mode}: solving {args.input}"
    try:
        report, result = solve_file(args.input, args.output, options, args.metric,
                                    progress, solving=line.start())
    except H2OError as err:
        print(f"{PROG}: {err}", file=sys.stderr)
        return EXIT_INPUT
    except OSError as err:
        print(f"{PROG}: {err.filename or args.input}: {err.strerror or err}",
              file=sys.stderr)
        return EXIT_INPUT
    finally:
        line.close()  # where the solve was never reached (an unreadable input)
    if report.mode == "exact" and not result.converged and report.max_iterations:
        rate = _last_decrease(result)
        print(f"{PROG}: warning: exact mode stopped at its cap of {report.max_iterations} "
              f"iterations, chi2 still falling ({rate:.2g} of it in the last); raise "
              "--passes or --tolerance", file=sys.stderr)
    if report.robust is not None and report.robust["closure_threshold_scale"] < 1.0:
        agree = 1.0 / report.robust["closure_noise_scale"]
        print(f"{PROG}: robust: the loop closures agree {agree:.3g} times better than "
              "their information says (variance); their outlier "
              f"thresholds are scaled by {report.robust['closure_threshold_scale']:.3g}",
              file=sys.stderr)
    if report.robust is not None and report.robust["dropped"]:
        print(f"{PROG}: robust: dropped {report.robust['dropped']} of "
              f"{report.robust['weighed']} loop closures and fixes as outliers (listed in the "
              "report's robust.dropped_edges)", file=sys.stderr)
    if report.conditioned is not None:
        cond = report.conditioned
        rel = abs(cond["chi2_difference"]) / max(abs(cond["chi2_as_written"]), 1e-300)
        print(f"{PROG}: warning: {cond['edges']} singular or nearly singular information "
              f"matrices were conditioned (eigenvalues raised to {INFO_EIG_FLOOR:g} of the "
              f"largest; listed in the report's conditioned.clamped_edges); chi2 at the "
              f"solution is {cond['chi2_conditioned']:.9g} conditioned, "
              f"{cond['chi2_as_written']:.9g} as written (difference "
              f"{cond['chi2_difference']:.3g}, {rel:.2g} of it)", file=sys.stderr)
    if report.staircase is not None:
        print(f"{PROG}: {_staircase_line(report.staircase)}", file=sys.stderr)
    if report.certificate is not None:
        print(f"{PROG}: {report.certificate['message']}", file=sys.stderr)
    text = json.dumps(asdict(report), indent=2)
    if args.report is not None:
        args.report.write_text(text + "\n")
    if args.trace is not None:
        trace = {"callback_ms": result.per_callback_ms, "required_ms": result.required_ms,
                 "chi2_trace": [list(sample) for sample in result.chi2_trace]}
        args.trace.write_text(json.dumps(trace) + "\n")
    print(text)
    return 0


def _staircase_line(climb: dict[str, Any]) -> str:
    """The console's line on the staircase's outcome."""
    if climb["error"] is not None:
        return (f"not certified; SE-Sync's Riemannian staircase failed ({climb['error']}); "
                "the solution stands")
    outcome = (f"chi2 {climb['chi2_before']:.6g} -> {climb['chi2_after']:.6g}, written"
               if climb["adopted"] else "no lower answer; the solution stands")
    return (f"not certified; SE-Sync's Riemannian staircase (rank {climb['rank']}) and exact "
            f"mode from its rounded point: {outcome}")


def _last_decrease(result: SolveResult) -> float:
    """Relative χ² decrease of the last iteration."""
    chain = [result.chi2_initial, *result.chi2_per_pass]
    if len(chain) < 2 or chain[-2] <= 0.0:
        return 0.0
    return (chain[-2] - chain[-1]) / chain[-2]


if __name__ == "__main__":
    sys.exit(main())
