"""Benchmark: our LAGO (full 3×3 information) against GTSAM's LAGO and Levenberg–Marquardt
on the public planar pose graphs, and LAGO as the warm start of H₂O's offline mode.

    .venv/bin/python bench/lago.py [--data DIR] [--graphs NAME ...] [--passes P]
                                   [--repeats R] [--results FILE]

For every planar ``*.g2o`` in ``--data`` (default ``$H2O_POSEGRAPHS``; neither: exit 2; a
missing folder is reported and the script exits 0):

- our LAGO, :func:`h2o_slam.core.lago.lago_estimate`, timed in-process (median of ``--repeats``
  runs after one warm-up; file reading excluded), with ``jacobian="estimate"`` (the
  default, eq. (12)) and ``"measurement"`` (Theorem 1's exact GN step); and once through
  the real command line, ``h2o-solve IN --output OUT --solver lago --report R.json``;
- GTSAM's ``gtsam.lago.initialize`` (median of ``--repeats`` calls; building the factor
  graph excluded). It refuses full information matrices ("assumes diagonal noise model"),
  so it gets the diagonal of each one; its answer is scored on the real problem;
- GTSAM's Levenberg–Marquardt from the graph's own estimate (as ``bench/solvers.py``) and
  from our LAGO;
- H₂O offline (:func:`h2o_slam.core.modes.solve_offline`) for ``--passes`` passes from
  ``init="tree"`` (the default start) and ``init="lago"``: the first pass whose χ² is within
  1.05 × the optimum;
- H₂O's exact mode (Gauss–Newton on our χ²) from our LAGO, for the optimum of our metric;
- the sparse factorizations :func:`h2o_slam.core.lago.solve_spd` offers, timed on the phase-3
  system ``Ω_x`` (the larger of LAGO's two) and over a whole LAGO run.

Every χ² is :func:`h2o_slam.core.graph.chi2` on the input graph. The optimum is the smallest χ²
any run reached on that graph. The tables go to stdout and replace the section
``## LAGO (bench/lago.py)`` of ``bench/RESULTS.md`` (other sections are kept).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from results_md import (
    add_graph_arguments,
    command,
    publish,
    results_path,
    revision,
    select_graphs,
    table_head,
)

from h2o_slam.core import geometry as geo
from h2o_slam.core import lago as lago_mod
from h2o_slam.core import spd
from h2o_slam.core.graph import PoseGraph, chi2
from h2o_slam.core.lago import lago, lago_estimate, solve_spd
from h2o_slam.core.modes import solve_exact, solve_offline
from h2o_slam.io.g2o import read_g2o

REPO = Path(__file__).resolve().parents[1]
SECTION = "## LAGO (bench/lago.py)"

LM_MAX_ITERATIONS = 100
LM_TOL = 1e-10
PRIOR_SIGMA = 1e-6  # gauge prior on node 0 for LM (as bench/solvers.py)
#: GTSAM's LAGO anchors the graph through a prior factor; without one its orientation
#: system has no reference. Pose 0 at the origin, as our LAGO fixes it.
LAGO_PRIOR_SIGMA = 1e-3
EXACT_ITERATIONS = 30
TARGET = 1.05  # "reaches the optimum": χ² within this factor


@dataclass
class Row:
    """Everything measured on one graph."""

    name: str
    nodes: int
    edges: int
    ours: float = float("nan")
    ours_ms: float = float("nan")
    ours_gn: float = float("nan")  # jacobian="measurement"
    cli: float = float("nan")
    cli_wall_s: float = float("nan")
    gtsam_lago: float = float("nan")
    gtsam_lago_ms: float = float("nan")
    gtsam_full_refusal: str = ""
    lm_input: float = float("nan")
    lm_input_iters: int = 0
    lm_ours: float = float("nan")
    lm_ours_iters: int = 0
    exact: float = float("nan")  # H₂O exact mode (GN on our χ²) from our LAGO
    exact_iters: int = 0
    h2o: dict[str, list[float]] = field(default_factory=dict)  # init → χ² per pass (0: start)
    factor_ms: dict[str, float] = field(default_factory=dict)  # method → Ω_x solve ms
    lago_ms: dict[str, float] = field(default_factory=dict)  # method → whole-LAGO ms
    omega_x: tuple[int, int] = (0, 0)  # size, nnz
    notes: list[str] = field(default_factory=list)

    @property
    def optimum(self) -> float:
        """Smallest χ² of any run on this graph."""
        values = [self.ours, self.ours_gn, self.cli, self.gtsam_lago, self.lm_input,
                  self.lm_ours, self.exact] + [v for h in self.h2o.values() for v in h]
        finite = [v for v in values if np.isfinite(v)]
        return min(finite) if finite else float("nan")


def timed(fn: Callable[[], Any], repeats: int) -> tuple[Any, float]:
    """``fn()``'s result and its median wall time in ms over ``repeats`` runs (one warm-up)."""
    out = fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return out, 1e3 * statistics.median(times)


# --- GTSAM -------------------------------------------------------------------------------------


def gtsam_factors(graph: PoseGraph, diagonal: bool) -> Any:
    """BetweenFactorPose2 of every edge; information diagonal only if ``diagonal``."""
    import gtsam

    factors = gtsam.NonlinearFactorGraph()
    dof = geo.PLANAR_DOF  # (x, y, yaw): GTSAM's Pose2 tangent order as well
    yaw = geo.matrix_to_yaw(graph.meas_R)
    for k in range(graph.num_edges):
        info = graph.info[k][np.ix_(dof, dof)]
        if diagonal:
            noise = gtsam.noiseModel.Diagonal.Precisions(np.diag(info).copy())
        else:
            noise = gtsam.noiseModel.Gaussian.Information(info)
        meas = gtsam.Pose2(graph.meas_t[k, 0], graph.meas_t[k, 1], yaw[k])
        factors.add(gtsam.BetweenFactorPose2(int(graph.a[k]), int(graph.b[k]), meas, noise))
    return factors


def poses_of(values: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
    p2 = [values.atPose2(i) for i in range(n)]
    t = np.array([[p.x(), p.y(), 0.0] for p in p2])
    return geo.yaw_to_matrix(np.array([p.theta() for p in p2])), t


def values_of(R: np.ndarray, t: np.ndarray) -> Any:
    import gtsam

    values = gtsam.Values()
    yaw = geo.matrix_to_yaw(R)
    for i in range(len(t)):
        values.insert(i, gtsam.Pose2(t[i, 0], t[i, 1], yaw[i]))
    return values


def run_gtsam_lago(graph: PoseGraph, row: Row, repeats: int) -> None:
    import gtsam

    # Full information first, to record GTSAM's own refusal.
    full = gtsam_factors(graph, diagonal=False)
    full.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(0, 0, 0),
                                    gtsam.noiseModel.Isotropic.Sigma(3, LAGO_PRIOR_SIGMA)))
    try:
        gtsam.lago.initialize(full)
        row.gtsam_full_refusal = "accepted"
    except (RuntimeError, ValueError) as err:
        row.gtsam_full_refusal = str(err).strip().splitlines()[-1]
    factors = gtsam_factors(graph, diagonal=True)
    factors.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(0, 0, 0),
                                       gtsam.noiseModel.Isotropic.Sigma(3, LAGO_PRIOR_SIGMA)))
    values, row.gtsam_lago_ms = timed(lambda: gtsam.lago.initialize(factors), repeats)
    row.gtsam_lago = chi2(graph, *poses_of(values, graph.num_nodes))


def run_lm(graph: PoseGraph, R: np.ndarray, t: np.ndarray) -> tuple[float, int]:
    """GTSAM LM (full information) from ``(R, t)``, node 0 held by a tight prior."""
    import gtsam

    factors = gtsam_factors(graph, diagonal=False)
    initial = values_of(R, t)
    factors.add(gtsam.PriorFactorPose2(0, initial.atPose2(0),
                                       gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(LM_MAX_ITERATIONS)
    params.setRelativeErrorTol(LM_TOL)
    params.setAbsoluteErrorTol(LM_TOL)
    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, initial, params)
    result = optimizer.optimize()
    return chi2(graph, *poses_of(result, graph.num_nodes)), optimizer.iterations()


# --- ours --------------------------------------------------------------------------------------


def run_cli(path: Path, out_dir: Path, row: Row) -> None:
    """``h2o-solve --solver lago`` as a subprocess; its output file rescored."""
    out, report = out_dir / f"{path.stem}.lago.g2o", out_dir / f"{path.stem}.lago.json"
    cmd = [sys.executable, "-m", "h2o_slam.app.cli.solve", str(path), "--output", str(out),
           "--solver", "lago", "--report", str(report)]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        row.notes.append(f"h2o-solve --solver lago failed: {proc.stderr.strip()}")
        return
    graph = read_g2o(path)
    solved = read_g2o(out)
    row.cli = chi2(graph, solved.R, solved.t)
    row.cli_wall_s = float(json.loads(report.read_text())["wall_s"])


def factorization_methods() -> list[str]:
    return [m for m in lago_mod.FACTORIZATIONS[1:] if m not in spd.PACKAGES or spd.available(m)]


def run_factorizations(graph: PoseGraph, row: Row, repeats: int) -> None:
    omega_x = lago(graph).information
    row.omega_x = (omega_x.shape[0], omega_x.nnz)
    rhs = np.ones(omega_x.shape[0])
    for method in factorization_methods():
        _, row.factor_ms[method] = timed(lambda m=method: solve_spd(omega_x, rhs, m), repeats)
        _, row.lago_ms[method] = timed(lambda m=method: lago(graph, factorization=m), repeats)


def bench_graph(path: Path, out_dir: Path, passes: int, repeats: int) -> Row:
    graph = read_g2o(path)

    def log(msg: str) -> None:
        print(f"[{path.stem}] {msg}", file=sys.stderr, flush=True)

    row = Row(path.stem, graph.num_nodes, graph.num_edges)
    log(f"{graph.num_nodes} nodes, {graph.num_edges} edges; our LAGO ...")
    (R, t), row.ours_ms = timed(lambda: lago_estimate(graph), repeats)
    row.ours = chi2(graph, R, t)
    gn = lago(graph, jacobian="measurement")
    row.ours_gn = chi2(graph, gn.R, gn.t)
    log("h2o-solve --solver lago ...")
    run_cli(path, out_dir, row)
    log("GTSAM LAGO ...")
    run_gtsam_lago(graph, row, repeats)
    log("GTSAM LM (from the input estimate, from our LAGO) ...")
    row.lm_input, row.lm_input_iters = run_lm(graph, graph.R, graph.t)
    row.lm_ours, row.lm_ours_iters = run_lm(graph, R, t)
    log("H₂O exact from our LAGO ...")
    exact = solve_exact(graph, EXACT_ITERATIONS, init="lago")
    row.exact, row.exact_iters = exact.chi2_final, len(exact.chi2_per_pass)
    log("factorizations ...")
    run_factorizations(graph, row, repeats)
    for init in ("tree", "lago"):
        log(f"H₂O offline, {passes} passes, init={init} ...")
        result = solve_offline(graph, passes, init=init)
        row.h2o[init] = [result.chi2_initial, *result.chi2_per_pass]
    return row


# --- tables ------------------------------------------------------------------------------------


def _num(x: float, fmt: str) -> str:
    return format(x, fmt) if np.isfinite(x) else "—"


def _passes_to_target(history: list[float], optimum: float) -> str:
    for p, value in enumerate(history):
        if value <= TARGET * optimum:
            return str(p)
    return f"not within {len(history) - 1}"


def format_tables(rows: list[Row], passes: int) -> str:
    head = ("| graph | nodes | edges | ours χ² | ours / opt | ours ms "
            "| GTSAM LAGO (diag) χ² | GTSAM / opt | GTSAM ms | time ours / GTSAM "
            "| ours χ² (J at Δ̄) | CLI χ² | CLI wall s "
            "| LM χ² (input start) | LM iters | LM χ² (our start) | LM iters "
            "| H₂O exact χ² (our start) | iters | optimum |")
    lines = table_head(head)
    for r in rows:
        opt = r.optimum
        lines.append("| " + " | ".join([
            r.name, str(r.nodes), str(r.edges),
            _num(r.ours, ".6g"), _num(r.ours / opt, ".5f"), _num(r.ours_ms, ".3g"),
            _num(r.gtsam_lago, ".6g"), _num(r.gtsam_lago / opt, ".5f"),
            _num(r.gtsam_lago_ms, ".3g"), _num(r.ours_ms / r.gtsam_lago_ms, ".2f"),
            _num(r.ours_gn, ".6g"), _num(r.cli, ".6g"), _num(r.cli_wall_s, ".3g"),
            _num(r.lm_input, ".6g"), str(r.lm_input_iters),
            _num(r.lm_ours, ".6g"), str(r.lm_ours_iters),
            _num(r.exact, ".6g"), str(r.exact_iters), _num(opt, ".6g"),
        ]) + " |")

    head2 = (f"| graph | start χ² tree | start χ² LAGO | passes to {TARGET}× opt: tree "
             f"| passes to {TARGET}× opt: LAGO | χ² after {passes}: tree "
             f"| χ² after {passes}: LAGO | best χ² in {passes}: tree "
             f"| best χ² in {passes}: LAGO |")
    lines += ["", f"H₂O offline (`solve_offline(graph, {passes}, init=...)`), pass 0 = the start:",
              "", *table_head(head2)]
    for r in rows:
        opt = r.optimum
        tree, lg = r.h2o.get("tree", []), r.h2o.get("lago", [])
        lines.append("| " + " | ".join([
            r.name, _num(tree[0], ".6g"), _num(lg[0], ".6g"),
            _passes_to_target(tree, opt), _passes_to_target(lg, opt),
            _num(tree[-1], ".6g"), _num(lg[-1], ".6g"),
            _num(min(tree), ".6g"), _num(min(lg), ".6g"),
        ]) + " |")

    methods = factorization_methods()
    head3 = ("| graph | Ω_x size | Ω_x nnz | "
             + " | ".join(f"Ω_x solve ms: {m}" for m in methods) + " | "
             + " | ".join(f"LAGO ms: {m}" for m in methods) + " |")
    lines += ["", "Sparse factorizations (`h2o_slam.core.lago.solve_spd`; median ms):", "",
              *table_head(head3)]
    for r in rows:
        lines.append("| " + " | ".join(
            [r.name, str(r.omega_x[0]), str(r.omega_x[1])]
            + [_num(r.factor_ms.get(m, float("nan")), ".3g") for m in methods]
            + [_num(r.lago_ms.get(m, float("nan")), ".3g") for m in methods]) + " |")

    by_answer: dict[str, list[str]] = {}
    for r in rows:
        by_answer.setdefault(r.gtsam_full_refusal, []).append(r.name)
    answers = [f"{', '.join(names)}: " + ("accepted (its matrices are diagonal, so GTSAM "
                                          "makes a diagonal noise model of them)"
                                          if answer == "accepted" else f"“{answer}”")
               for answer, names in sorted(by_answer.items())]
    lines += ["", "GTSAM's LAGO given the full information matrices — "
              + "; ".join(answers) + "."]
    notes = [f"- {r.name}: {n}" for r in rows for n in r.notes]
    if notes:
        lines += ["", "Problems:", "", *notes]
    return "\n".join(lines)


def notes(repeats: int) -> str:
    return f"""\
Notes:

- χ² is the project's evaluator `h2o_slam.core.graph.chi2` on the input graph at each
  solver's output; "opt" is the smallest χ² of any run on that graph in this table (not a
  certified global optimum).
- ours: `h2o_slam.core.lago.lago_estimate` (full 3×3 information, correlations included;
  `jacobian="estimate"`, the paper's (12)); "J at Δ̄": `lago(graph, jacobian="measurement")`,
  exactly one Gauss–Newton step from (p̂, θ̂) (Theorem 1). Time: median of {repeats} in-process
  calls after a warm-up, file reading excluded; everything from the `PoseGraph` to the
  world poses is included (regularization, both sparse solves).
- GTSAM LAGO: `gtsam.lago.initialize` on BetweenFactorPose2 with
  `noiseModel.Diagonal.Precisions` of the **diagonal** of each information matrix (it
  refuses full ones, quoted under the tables), plus a PriorFactorPose2 at the origin on
  node 0, sigma {LAGO_PRIOR_SIGMA:g} (its anchor). Time: median of {repeats} calls of
  `initialize` after a warm-up; building the factor graph excluded. Its χ² is scored with
  the full information.
- CLI: `h2o-solve IN --output OUT --solver lago --report R.json` as a subprocess; χ² of the
  written file read back; "wall s" is the report's (solve only, no start-up or I/O).
- LM: GTSAM `LevenbergMarquardtOptimizer` with the full information, at most
  {LM_MAX_ITERATIONS} iterations, tolerances {LM_TOL:g}, node 0 held by a prior of sigma
  {PRIOR_SIGMA:g}; from the graph's own estimate (its vertices, or the odometry chain) and
  from our LAGO. LM minimizes GTSAM's own error (Pose2 `Logmap`), which differs from our χ²
  where residuals are large (see the Solvers section).
- H₂O exact: `h2o_slam.core.modes.solve_exact(graph, {EXACT_ITERATIONS}, init="lago")`, damped
  Gauss–Newton on our χ² itself, from our LAGO: where LM's metric and ours disagree (large
  residuals, MIT) it finds the optimum of ours.
- H₂O offline: `h2o_slam.core.modes.solve_offline(graph, P, init=...)` in-process; pass 0 is
  the starting estimate. "passes to {TARGET}× opt" is the first pass at or below
  {TARGET} × opt.
- Factorizations: `solve_spd(Ω_x, b, method)` on the phase-3 matrix, and the whole
  `lago(graph, factorization=method)`; "cholmod" is CHOLMOD from cvxopt's wheel (the
  default), "qdldl" OSQP's LDLᵀ (columns absent when the package is not installed),
  "splu-mmd" SuperLU with MMD on Aᵀ+A in symmetric mode, "splu-colamd" SuperLU's default
  ordering, "spsolve" scipy's default.
"""


def _machine() -> str:
    versions = []
    for pkg in ("numpy", "scipy", "gtsam", "cvxopt", "qdldl"):
        try:
            versions.append(f"{pkg} {metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{pkg} not installed")
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    rev = revision(REPO)
    return (f"{cpu}, nproc {os.cpu_count()}, Python {platform.python_version()}, "
            f"{', '.join(versions)}, repo at {rev}")


def _command() -> str:
    return command(REPO)


def render_section(rows: list[Row], passes: int, repeats: int) -> str:
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return (f"{SECTION}\n\nCommand (from the repo root): `{_command()}`\n\n"
            f"Date: {when}. Machine: {_machine()}. Timings are indicative (shared machine, "
            "2 cores).\n\n"
            f"{format_tables(rows, passes)}\n\n{notes(repeats)}")


def run(data: Path | None, names: list[str] | None, passes: int, repeats: int,
        results: Path | None) -> int:
    paths = select_graphs("lago.py", data, names)
    if isinstance(paths, int):
        return paths
    planar = [p for p in paths if read_g2o(p).planar]
    if not planar:
        print(f"lago.py: no planar .g2o files in {data}; nothing to benchmark.")
        return 0
    with tempfile.TemporaryDirectory(prefix="h2o-lago-bench-") as tmp:
        rows = [bench_graph(p, Path(tmp), passes, repeats) for p in planar]
    publish(render_section(rows, passes, repeats), results, SECTION)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_graph_arguments(parser)  # 3-D graphs are skipped
    parser.add_argument("--passes", type=int, default=30,
                        help="H₂O offline passes per start (default 30)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="timed runs of each LAGO (median reported; default 5)")
    args = parser.parse_args(argv)
    if args.passes < 0 or args.repeats < 1:
        parser.error("--passes must be ≥ 0 and --repeats ≥ 1")
    return run(args.data, args.graphs, args.passes, args.repeats, results_path(args))


if __name__ == "__main__":
    sys.exit(main())
