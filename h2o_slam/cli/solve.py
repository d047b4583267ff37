"""``h2o-solve``: optimize a g2o pose graph with H₂O (or LAGO) and write the solution and a report.

    h2o-solve INPUT.g2o --output OUT.g2o [--mode offline|online|exact] [--passes N]
              [--init tree|input|lago] [--solver h2o|lago] [--d-max N] [--budget-ms X]
              [--gps-batch-size N] [--gps-every K --gps-sigma S] [--report REPORT.json]
              [--trace TRACE.json] [--idle-s S] [--samples N] [--period-ms P]

The work is :func:`solve_file`; this module's ``main`` only parses arguments, prints, and maps
errors to a one-line message and a non-zero exit code.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from h2o_slam.compiled import warm_up
from h2o_slam.errors import H2OError, InputError
from h2o_slam.g2o import read_g2o, write_g2o
from h2o_slam.graph import PoseGraph
from h2o_slam.modes import (
    INITS,
    SolveResult,
    sample_points,
    solve_exact,
    solve_lago,
    solve_offline,
    solve_online,
)
from h2o_slam.online import OnlineConfig
from h2o_slam.solver import SolverConfig
from h2o_slam.synthetic import add_gps

MODES = ("offline", "online", "exact")
SOLVERS = ("h2o", "lago")
DEFAULT_PASSES = {"offline": 10, "online": 0, "exact": 20}


@dataclass(frozen=True)
class SolveOptions:
    """How :func:`solve_file` solves.

    Attributes:
        mode: ``offline``, ``online`` or ``exact``.
        passes: offline passes (offline mode), offline passes after the online pass (online),
            or the most Gauss–Newton iterations (exact); ``None`` takes the mode's default.
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
    """

    mode: str = "offline"
    passes: int | None = None
    init: str = "tree"
    solver: str = "h2o"
    d_max: int | None = None
    budget_ms: float | None = None
    gps_batch_size: int = 30
    gps_every: int = 0
    gps_sigma_m: float = 1.0
    idle_s: float = 1.0
    samples: int = 0
    period_ms: float = 0.0

    def __post_init__(self) -> None:
        for name, value, allowed in (("solver", self.solver, SOLVERS),
                                     ("mode", self.mode, MODES), ("init", self.init, INITS)):
            if value not in allowed:
                raise InputError(f"unknown {name} {value!r}; choose one of {', '.join(allowed)}")
        if self.passes is not None and self.passes < 0:
            raise InputError("--passes must be non-negative")
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
        if self.period_ms and (self.mode != "online" or self.budget_ms is None):
            raise InputError("--period-ms applies to --mode online with --budget-ms only")


@dataclass
class SolveReport:
    """What ``--report`` writes (JSON)."""

    input: str
    solver: str
    mode: str
    init: str
    passes: int
    nodes: int
    edges: int
    chi2_initial: float
    chi2_final: float
    chi2_per_pass: list[float]
    wall_s: float
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
    exact: dict[str, Any] | None = None
    samples: list[list[float]] | None = None


def solve_file(
    input_path: Path, output_path: Path, options: SolveOptions | None = None
) -> tuple[SolveReport, SolveResult]:
    """Read ``input_path``, solve it as ``options`` say, write the solution to ``output_path``.

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
    passes = DEFAULT_PASSES[opt.mode] if opt.passes is None else opt.passes
    # Start-up, as a node's: the compiled kernels load from their cache (or compile) before
    # the clock starts, so wall_s is the solve (0.5 s of loading on the 2-core machine).
    warm_up()
    start = time.perf_counter()
    try:
        result = _solve(graph, opt, passes)
    except InputError as err:  # e.g. LAGO refusing a 3-D graph: say which file
        raise InputError(f"{input_path}: {err}") from None
    wall_s = time.perf_counter() - start
    write_g2o(output_path, graph, result.R, result.t)
    online = opt.solver == "h2o" and opt.mode == "online"
    budget = opt.budget_ms
    report = SolveReport(
        input=str(input_path), solver=opt.solver,
        mode="lago" if opt.solver == "lago" else opt.mode,
        init="input" if opt.solver == "lago" else ("tree" if online else opt.init),
        passes=0 if opt.solver == "lago" else passes,
        nodes=graph.num_nodes, edges=graph.num_edges,
        chi2_initial=result.chi2_initial, chi2_final=result.chi2_final,
        chi2_per_pass=result.chi2_per_pass, wall_s=wall_s, d_max=opt.d_max, budget_ms=budget,
        per_callback_ms=_percentiles(result.per_callback_ms) if online else None,
        overruns=(sum(t > budget for t in result.per_callback_ms)
                  if online and budget is not None else None),
        deferred_edges=result.deferred_edges if online else None,
        gps_edges_added=added, converged=result.converged,
        chi2_end_of_stream=result.chi2_end_of_stream, chi2_after_idle=result.chi2_after_idle,
        idle_s=opt.idle_s if online else None, idle_steps=result.idle_steps if online else None,
        period_ms=opt.period_ms if online else None,
        idle_steps_between=result.idle_steps_between if online else None,
        exact=asdict(result.exact) if result.exact is not None else None,
        samples=[list(sample) for sample in result.samples] if online else None,
    )
    return report, result


def _solve(graph: PoseGraph, opt: SolveOptions, passes: int) -> SolveResult:
    if opt.solver == "lago":
        return solve_lago(graph)
    config = SolverConfig(gps_batch_size=opt.gps_batch_size)
    if opt.mode == "offline":
        return solve_offline(graph, passes, config, init=opt.init, d_max=opt.d_max)
    if opt.mode == "online":
        budget_s = None if opt.budget_ms is None else opt.budget_ms / 1e3
        # Unbudgeted, the exact solves run inline on their schedule: no worker is needed.
        background = "process" if budget_s is not None and budget_s < 1.0 else "inline"
        online = OnlineConfig(d_max=opt.d_max, background=background)
        return solve_online(graph, passes, config, budget_s, online,
                            trace_every=max(1, graph.num_nodes // 200), idle_s=opt.idle_s,
                            sample_nodes=sample_points(graph, opt.samples),
                            period_s=opt.period_ms / 1e3)
    return solve_exact(graph, passes, config, init=opt.init)


def _percentiles(times_ms: list[float]) -> dict[str, float]:
    t = np.asarray(times_ms) if times_ms else np.zeros(1)
    return {"mean": float(t.mean()), "p99": float(np.percentile(t, 99)), "max": float(t.max())}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``h2o-solve``."""
    p = argparse.ArgumentParser(
        prog="h2o-solve",
        description="Optimize a g2o pose graph with H₂O (hybrid-Hessian SLAM) or LAGO.",
    )
    p.add_argument("input", type=Path, help="input graph (.g2o)")
    p.add_argument("--output", "-o", type=Path, required=True,
                   help="where to write the solution (.g2o, a VERTEX line per pose)")
    p.add_argument("--mode", choices=MODES, default="offline",
                   help="offline: Algorithm 1 passes; online: pose by pose; "
                        "exact: damped Gauss-Newton (default: offline)")
    p.add_argument("--passes", type=int, default=None,
                   help="offline passes (default 10); online: extra offline passes after the "
                        "online pass (default 0); exact: most iterations (default 20)")
    p.add_argument("--solver", choices=SOLVERS, default="h2o",
                   help="h2o (default) or lago: the linear approximation alone "
                        "(planar graphs; --mode, --passes and --init are ignored)")
    p.add_argument("--init", choices=INITS, default="tree",
                   help="starting estimate: tree (tree edges concatenated from the root, as in "
                        "the thesis), input (the file's vertices, or its odometry chain when "
                        "it has none) or lago (planar graphs); default: tree")
    p.add_argument("--d-max", type=int, default=None,
                   help="most nodes solved for per edge (interpolated solving); default: all")
    p.add_argument("--budget-ms", type=float, default=None,
                   help="online mode: time per arriving pose in ms; default: no limit")
    p.add_argument("--gps-batch-size", type=int, default=30,
                   help="GPS edges relaxed together (default 30)")
    p.add_argument("--gps-every", type=int, default=0,
                   help="add a GPS edge every K poses, at the graph's exact optimum plus noise")
    p.add_argument("--gps-sigma", type=float, default=1.0,
                   help="noise (m, per axis) of the GPS edges --gps-every adds (default 1)")
    p.add_argument("--idle-s", type=float, default=1.0,
                   help="online mode: seconds of budgeted idle steps after the last pose "
                        "(the robot stops; default 1)")
    p.add_argument("--samples", type=int, default=0,
                   help="online mode: sample χ² of the edges so far at N poses over the stream "
                        "and N after loop closures, into the report (default 0)")
    p.add_argument("--period-ms", type=float, default=0.0,
                   help="online mode with --budget-ms: one pose arrives every this many ms, "
                        "idle steps between (a robot's keyframe rate); default 0: each pose "
                        "as soon as the last callback returns (the worst case)")
    p.add_argument("--report", type=Path, default=None, help="write a JSON report here")
    p.add_argument("--trace", type=Path, default=None,
                   help="online mode: write per-callback times and χ² samples (JSON) here")
    return p


def _unwritable(option: str, path: Path | None) -> str | None:
    """Why ``path`` (given as ``option``) cannot be written, or ``None`` when it can."""
    if path is None:
        return None
    folder = path.parent
    if path.is_dir():
        return f"{option} {path}: is a folder, not a file"
    if not folder.is_dir():
        return f"{option} {path}: folder {folder} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK) or (path.exists()
                                                    and not os.access(path, os.W_OK)):
        return f"{option} {path}: not writable"
    return None


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``h2o-solve``."""
    args = build_parser().parse_args(argv)
    # Every output is checked before the solve, which may take minutes.
    for option, path in (("--output", args.output), ("--report", args.report),
                         ("--trace", args.trace)):
        problem = _unwritable(option, path)
        if problem is not None:
            print(f"h2o-solve: {problem}", file=sys.stderr)
            return 2
    try:
        options = SolveOptions(
            mode=args.mode, passes=args.passes, init=args.init, solver=args.solver,
            d_max=args.d_max, budget_ms=args.budget_ms, gps_batch_size=args.gps_batch_size,
            gps_every=args.gps_every, gps_sigma_m=args.gps_sigma, idle_s=args.idle_s,
            samples=args.samples, period_ms=args.period_ms,
        )
        report, result = solve_file(args.input, args.output, options)
    except H2OError as err:
        print(f"h2o-solve: {err}", file=sys.stderr)
        return 1
    except OSError as err:
        print(f"h2o-solve: {err.filename or args.input}: {err.strerror or err}", file=sys.stderr)
        return 1
    text = json.dumps(asdict(report), indent=2)
    if args.report is not None:
        args.report.write_text(text + "\n")
    if args.trace is not None:
        trace = {"callback_ms": result.per_callback_ms, "required_ms": result.required_ms,
                 "chi2_trace": [list(sample) for sample in result.chi2_trace]}
        args.trace.write_text(json.dumps(trace) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
