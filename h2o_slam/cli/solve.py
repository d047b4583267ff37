"""``h2o-solve``: optimize a g2o pose graph with H₂O and write the solution and a report.

    h2o-solve INPUT.g2o --output OUT.g2o [--mode offline|online|exact] [--passes N]
              [--report REPORT.json]

The work is :func:`solve_file`; this module's ``main`` only parses arguments, prints, and maps
errors to a one-line message and a non-zero exit code.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from h2o_slam.errors import H2OError
from h2o_slam.g2o import read_g2o, write_g2o
from h2o_slam.graph import PoseGraph
from h2o_slam.modes import (
    INITS,
    SolveResult,
    solve_exact,
    solve_lago,
    solve_offline,
    solve_online,
)

MODES = ("offline", "online", "exact")
SOLVERS = ("h2o", "lago")
DEFAULT_PASSES = {"offline": 10, "online": 0, "exact": 20}


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
    per_callback_ms: dict[str, float] | None = None


def solve_file(
    input_path: Path,
    output_path: Path,
    mode: str = "offline",
    passes: int | None = None,
    init: str = "tree",
    solver: str = "h2o",
) -> SolveReport:
    """Read ``input_path``, solve it in ``mode``, write the solution to ``output_path``.

    ``passes``: offline passes (offline mode), offline passes after the online pass (online
    mode), or the most Gauss–Newton iterations (exact mode); ``None`` takes the mode's default.
    ``init``: ``tree`` (the thesis' start: tree edges concatenated from the root), ``input``
    (the file's vertices, or its odometry chain) or ``lago`` (planar graphs); online mode
    always grows its tree from the arriving edges. ``solver="lago"`` runs LAGO alone.

    Raises:
        H2OError: the input cannot be read or solved (the message names file and line).
        OSError: the files cannot be read or written.
    """
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose one of {', '.join(MODES)}")
    passes = DEFAULT_PASSES[mode] if passes is None else passes
    graph = read_g2o(input_path)
    start = time.perf_counter()
    if solver == "lago":
        mode, init, passes = "lago", "input", 0
        result = solve_lago(graph)
    else:
        result = _solve(graph, mode, passes, init)
    wall_s = time.perf_counter() - start
    write_g2o(output_path, graph, result.R, result.t)
    return SolveReport(
        input=str(input_path), solver=solver, mode=mode, init="tree" if mode == "online" else init,
        passes=passes,
        nodes=graph.num_nodes, edges=graph.num_edges,
        chi2_initial=result.chi2_initial, chi2_final=result.chi2_final,
        chi2_per_pass=result.chi2_per_pass, wall_s=wall_s,
        per_callback_ms=_percentiles(result.per_callback_ms) if mode == "online" else None,
    )


def _solve(graph: PoseGraph, mode: str, passes: int, init: str) -> SolveResult:
    if mode == "offline":
        return solve_offline(graph, passes, init=init)
    if mode == "online":
        return solve_online(graph, passes)
    return solve_exact(graph, passes, init=init)


def _percentiles(times_ms: list[float]) -> dict[str, float]:
    t = np.asarray(times_ms) if times_ms else np.zeros(1)
    return {"mean": float(t.mean()), "p99": float(np.percentile(t, 99)), "max": float(t.max())}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``h2o-solve``."""
    parser = argparse.ArgumentParser(
        prog="h2o-solve",
        description="Optimize a g2o pose graph with H₂O (hybrid-Hessian SLAM).",
    )
    parser.add_argument("input", type=Path, help="input graph (.g2o)")
    parser.add_argument("--output", "-o", type=Path, required=True,
                        help="where to write the solution (.g2o, a VERTEX line per pose)")
    parser.add_argument("--mode", choices=MODES, default="offline",
                        help="offline: Algorithm 1 passes; online: pose by pose; "
                             "exact: damped Gauss-Newton (default: offline)")
    parser.add_argument("--passes", type=int, default=None,
                        help="offline passes (default 10); online: extra offline passes "
                             "after the online pass (default 0); exact: most iterations "
                             "(default 20)")
    parser.add_argument("--solver", choices=SOLVERS, default="h2o",
                        help="h2o (default) or lago: the linear approximation alone "
                             "(planar graphs; --mode, --passes and --init are ignored)")
    parser.add_argument("--init", choices=INITS, default="tree",
                        help="starting estimate: tree (tree edges concatenated from the root, "
                             "as in the thesis) or input (the file's vertices, or its odometry "
                             "chain when it has none) or lago (planar graphs); default: tree")
    parser.add_argument("--report", type=Path, default=None, help="write a JSON report here")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``h2o-solve``."""
    args = build_parser().parse_args(argv)
    if args.passes is not None and args.passes < 0:
        print("h2o-solve: --passes must be non-negative", file=sys.stderr)
        return 2
    try:
        report = solve_file(
            args.input, args.output, args.mode, args.passes, args.init, args.solver
        )
    except H2OError as err:
        print(f"h2o-solve: {err}", file=sys.stderr)
        return 1
    except OSError as err:
        print(f"h2o-solve: {err.filename or args.input}: {err.strerror or err}", file=sys.stderr)
        return 1
    text = json.dumps(asdict(report), indent=2)
    if args.report is not None:
        args.report.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
