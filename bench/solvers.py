"""Benchmark: H₂O (exact and offline modes, through ``h2o-solve``) against GTSAM's
Levenberg–Marquardt on the public pose graphs.

    .venv/bin/python bench/solvers.py [--data DIR] [--graphs NAME ...] [--timeout S]
                                      [--output-dir DIR] [--results FILE]

Every solver starts from the same estimate — the graph as :func:`h2o_slam.io.g2o.read_g2o`
returns it: the file's vertices, or the odometry chain when the file has none — and every
solution is scored by the one evaluator :func:`h2o_slam.core.graph.chi2` on the input graph,
not by the solver's own report. The table goes to stdout and replaces the section
``## Solvers (bench/solvers.py)`` of ``bench/RESULTS.md`` (other sections are kept).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import multiprocessing as mp
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
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
    run_graphs,
    select_graphs,
    table_head,
)

from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import EdgeKind, PoseGraph, chi2
from h2o_slam.io.g2o import read_g2o

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Solvers (bench/solvers.py)"

#: LM settings (everything else is GTSAM's default, including the lambda schedule).
LM_MAX_ITERATIONS = 100
LM_RELATIVE_TOL = 1e-10
LM_ABSOLUTE_TOL = 1e-10
#: Standard deviation of the prior that fixes node 0 at its start pose (gauge), all axes.
PRIOR_SIGMA = 1e-6
#: Our 6-D error order is (x, y, z, rot x, rot y, rot z); GTSAM's Pose3 tangent is
#: (rot x, rot y, rot z, x, y, z). GTSAM coordinate k is our coordinate POSE3_PERM[k].
POSE3_PERM = np.array([3, 4, 5, 0, 1, 2])


@dataclass
class H2ORun:
    """One ``h2o-solve`` run: its own report and our rescoring of the file it wrote."""

    mode: str
    status: str  # "ok", "timeout", or "failed: <message>"
    chi2: float = float("nan")  # input graph scored at the output estimate
    chi2_reported: float = float("nan")  # chi2_final of the report JSON
    chi2_gtsam: float = float("nan")  # 2 × GTSAM's error() at the output estimate
    wall_s: float = float("nan")  # wall_s of the report JSON (solve only, no I/O)
    process_s: float = float("nan")  # whole subprocess, including start-up and file I/O


@dataclass
class LMRun:
    """One GTSAM Levenberg–Marquardt run."""

    status: str  # "ok", "timeout", or "failed: <message>"
    chi2: float = float("nan")  # our evaluator at LM's estimate
    chi2_gtsam: float = float("nan")  # 2 × GTSAM's error() of the between factors
    build_s: float = float("nan")  # building factors and initial values (not in optimize_s)
    optimize_s: float = float("nan")  # optimize() only
    iterations: int = 0
    max_iterations: int = LM_MAX_ITERATIONS


@dataclass
class GraphResult:
    """Everything measured on one graph."""

    name: str
    nodes: int
    edges: int
    planar: bool
    chi2_initial: float
    exact: H2ORun
    offline: H2ORun
    lm: LMRun

    @property
    def optimum(self) -> float:
        """Smallest χ² any solver reached on this graph in this run."""
        values = [r.chi2 for r in (self.exact, self.offline, self.lm) if r.status == "ok"]
        finite = [v for v in values if np.isfinite(v)]
        return min(finite) if finite else float("nan")


# --- H₂O through its command-line tool ------------------------------------------------------


def run_h2o(
    graph: PoseGraph, path: Path, out_dir: Path, mode: str, passes: int | None, timeout_s: float
) -> H2ORun:
    """Run ``h2o-solve`` on ``path`` as a subprocess and rescore its output on ``graph``."""
    stem = f"{path.stem}.{mode}"
    out, report = out_dir / f"{stem}.g2o", out_dir / f"{stem}.report.json"
    cmd = [sys.executable, "-m", "h2o_slam.app.cli.solve", str(path), "--output", str(out),
           "--mode", mode, "--report", str(report)]
    if passes is not None:
        cmd += ["--passes", str(passes)]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True,
                              timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return H2ORun(mode, "timeout")
    process_s = time.perf_counter() - start
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines() or ["(no output)"]
        return H2ORun(mode, f"failed (exit {proc.returncode}): {lines[-1]}",
                      process_s=process_s)
    rep = json.loads(report.read_text())
    solved = read_g2o(out)
    if not np.array_equal(solved.ids, graph.ids):
        return H2ORun(mode, "failed: output node ids differ from the input's",
                      process_s=process_s)
    return H2ORun(mode, "ok", chi2=chi2(graph, solved.R, solved.t),
                  chi2_reported=float(rep["chi2_final"]),
                  chi2_gtsam=gtsam_chi2(graph, solved.R, solved.t),
                  wall_s=float(rep["wall_s"]), process_s=process_s)


# --- GTSAM Levenberg–Marquardt -----------------------------------------------------------------


def _gtsam_graph(graph: PoseGraph) -> tuple[Any, Any]:
    """Between factors of ``graph`` and its estimate as GTSAM ``Values`` (keys = node index)."""
    import gtsam

    if np.any(graph.kind != EdgeKind.RELATIVE):
        raise ValueError("only relative-pose edges are supported by this benchmark")
    factors = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    if graph.planar:
        dof = geo.PLANAR_DOF  # (x, y, yaw): GTSAM's Pose2 tangent order as well
        yaw, meas_yaw = geo.matrix_to_yaw(graph.R), geo.matrix_to_yaw(graph.meas_R)
        for i in range(graph.num_nodes):
            values.insert(i, gtsam.Pose2(graph.t[i, 0], graph.t[i, 1], yaw[i]))
        for k in range(graph.num_edges):
            noise = gtsam.noiseModel.Gaussian.Information(graph.info[k][np.ix_(dof, dof)])
            meas = gtsam.Pose2(graph.meas_t[k, 0], graph.meas_t[k, 1], meas_yaw[k])
            factors.add(gtsam.BetweenFactorPose2(int(graph.a[k]), int(graph.b[k]), meas, noise))
    else:
        for i in range(graph.num_nodes):
            values.insert(i, gtsam.Pose3(gtsam.Rot3(graph.R[i]), graph.t[i]))
        for k in range(graph.num_edges):
            info = graph.info[k][np.ix_(POSE3_PERM, POSE3_PERM)]
            noise = gtsam.noiseModel.Gaussian.Information(info)
            meas = gtsam.Pose3(gtsam.Rot3(graph.meas_R[k]), graph.meas_t[k])
            factors.add(gtsam.BetweenFactorPose3(int(graph.a[k]), int(graph.b[k]), meas, noise))
    return factors, values


def gtsam_chi2(graph: PoseGraph, R: np.ndarray, t: np.ndarray) -> float:
    """2 × GTSAM's ``error()`` of the between factors of ``graph`` at ``(R, t)``: the
    objective LM minimizes (without the gauge prior), for comparison with :func:`chi2`."""
    factors, values = _gtsam_graph(graph.with_estimate(R, t))
    return 2.0 * factors.error(values)


def _poses(graph: PoseGraph, values: Any) -> tuple[np.ndarray, np.ndarray]:
    """World poses ``(R, t)`` of all nodes from GTSAM ``Values``."""
    n = graph.num_nodes
    if graph.planar:
        p2 = [values.atPose2(i) for i in range(n)]
        t = np.array([[p.x(), p.y(), 0.0] for p in p2])
        return geo.yaw_to_matrix(np.array([p.theta() for p in p2])), t
    p3 = [values.atPose3(i) for i in range(n)]
    R = np.array([p.rotation().matrix() for p in p3])
    return R, np.array([p.translation() for p in p3])


def run_lm(graph: PoseGraph) -> LMRun:
    """GTSAM LM from the graph's own estimate, node 0 held by a tight prior at its start."""
    import gtsam

    start = time.perf_counter()
    between, initial = _gtsam_graph(graph)
    # Gauge: a prior on node 0 at its start pose, as GTSAM's Pose2/Pose3SLAMExample_g2o do
    # (they use sigmas ~1e-3..1e-4; tighter here so node 0 does not move measurably).
    factors = gtsam.NonlinearFactorGraph(between)
    if graph.planar:
        prior = gtsam.PriorFactorPose2(0, initial.atPose2(0),
                                       gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA))
    else:
        prior = gtsam.PriorFactorPose3(0, initial.atPose3(0),
                                       gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA))
    factors.add(prior)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(LM_MAX_ITERATIONS)
    params.setRelativeErrorTol(LM_RELATIVE_TOL)
    params.setAbsoluteErrorTol(LM_ABSOLUTE_TOL)
    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, initial, params)
    build_s = time.perf_counter() - start
    start = time.perf_counter()
    result = optimizer.optimize()
    optimize_s = time.perf_counter() - start
    R, t = _poses(graph, result)
    return LMRun("ok", chi2=chi2(graph, R, t), chi2_gtsam=2.0 * between.error(result),
                 build_s=build_s, optimize_s=optimize_s, iterations=optimizer.iterations())


def _lm_child(path: str, conn: Any) -> None:
    try:
        conn.send(run_lm(read_g2o(path)))
    except Exception as err:  # reported in the table, not raised
        conn.send(LMRun(f"failed: {type(err).__name__}: {err}"))
    finally:
        conn.close()


def run_lm_with_timeout(path: Path, timeout_s: float) -> LMRun:
    """:func:`run_lm` in a fresh process (spawned, so no threads inherited), killed at
    ``timeout_s``."""
    ctx = mp.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_lm_child, args=(str(path), send), daemon=True)
    proc.start()
    send.close()
    try:
        if not recv.poll(timeout_s):
            return LMRun("timeout")
        return recv.recv()
    except EOFError:
        proc.join(5.0)
        return LMRun(f"failed: LM process died (exit code {proc.exitcode})")
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join()


# --- one graph, tables, RESULTS.md ------------------------------------------------------------


def bench_graph(path: Path, out_dir: Path, timeout_s: float) -> GraphResult:
    """Run every solver on one graph file."""
    graph = read_g2o(path)

    def log(msg: str) -> None:
        print(f"[{path.stem}] {msg}", file=sys.stderr, flush=True)

    log(f"{graph.num_nodes} nodes, {graph.num_edges} edges; H₂O exact ...")
    exact = run_h2o(graph, path, out_dir, "exact", None, timeout_s)
    log(f"exact: {exact.status}; H₂O offline (10 passes) ...")
    offline = run_h2o(graph, path, out_dir, "offline", 10, timeout_s)
    log(f"offline: {offline.status}; GTSAM LM ...")
    lm = run_lm_with_timeout(path, timeout_s)
    log(f"LM: {lm.status}")
    return GraphResult(path.stem, graph.num_nodes, graph.num_edges, graph.planar,
                       chi2(graph), exact, offline, lm)


def _num(x: float, fmt: str) -> str:
    return format(x, fmt) if np.isfinite(x) else "—"


def _cell(run: H2ORun | LMRun, value: float, fmt: str) -> str:
    return _num(value, fmt) if run.status == "ok" else run.status.split(":")[0]


def _time_ratio(a: H2ORun, lm: LMRun, with_build: bool = False) -> str:
    lm_s = lm.optimize_s + (lm.build_s if with_build else 0.0)
    if a.status != "ok" or lm.status != "ok" or lm_s <= 0.0:
        return "—"
    return f"{a.wall_s / lm_s:.3g}"


def _lm_iters(lm: LMRun) -> str:
    if lm.status != "ok":
        return lm.status.split(":")[0]
    hit = " (limit)" if lm.iterations >= lm.max_iterations else ""
    return f"{lm.iterations}{hit}"


def format_tables(results: list[GraphResult]) -> str:
    """The main table, the sanity-check table and the failures, as markdown."""
    head = ("| graph | nodes | edges | χ² initial "
            "| exact χ² | exact χ²/opt | exact s "
            "| offline χ² | offline χ²/opt | offline s "
            "| LM χ² | LM χ²/opt | LM s | LM iters "
            "| exact / LM time | exact / LM time with LM's set-up | offline / LM time |")
    lines = table_head(head)
    for r in results:
        opt = r.optimum
        row = [r.name, str(r.nodes), str(r.edges), _num(r.chi2_initial, ".6g")]
        for run in (r.exact, r.offline):
            row += [_cell(run, run.chi2, ".6g"), _cell(run, run.chi2 / opt, ".6f"),
                    _cell(run, run.wall_s, ".3g")]
        lm = r.lm
        row += [_cell(lm, lm.chi2, ".6g"), _cell(lm, lm.chi2 / opt, ".6f"),
                _cell(lm, lm.optimize_s, ".3g"), _lm_iters(lm),
                _time_ratio(r.exact, lm), _time_ratio(r.exact, lm, with_build=True),
                _time_ratio(r.offline, lm)]
        lines.append("| " + " | ".join(row) + " |")

    check_head = ("| graph | kind | LM: our χ² | LM: 2·GTSAM error | ours / GTSAM "
                  "| exact: 2·GTSAM error | offline: 2·GTSAM error | LM build s "
                  "| exact: report χ² / ours | offline: report χ² / ours "
                  "| exact process s | offline process s |")
    lines += ["", "Checks:", "", *table_head(check_head)]
    for r in results:
        lm = r.lm
        row = [r.name, "SE(2)" if r.planar else "SE(3)", _cell(lm, lm.chi2, ".10g"),
               _cell(lm, lm.chi2_gtsam, ".10g"), _cell(lm, lm.chi2 / lm.chi2_gtsam, ".6g")]
        row += [_cell(run, run.chi2_gtsam, ".10g") for run in (r.exact, r.offline)]
        row += [_cell(lm, lm.build_s, ".3g")]
        row += [_cell(run, run.chi2_reported / run.chi2, ".10f") for run in (r.exact, r.offline)]
        row += [_cell(run, run.process_s, ".3g") for run in (r.exact, r.offline)]
        lines.append("| " + " | ".join(row) + " |")

    failures = [(r.name, run) for r in results for run in (r.exact, r.offline, r.lm)
                if run.status not in ("ok", "timeout")]
    if failures:
        lines += ["", "Failures:", ""]
        for name, run in failures:
            who = f"H₂O {run.mode}" if isinstance(run, H2ORun) else "GTSAM LM"
            lines.append(f"- {name}, {who}: {run.status}")
    return "\n".join(lines)


NOTES = f"""\
Notes:

- Every solver starts from the graph as `h2o_slam.io.g2o.read_g2o` returns it (the file's
  vertices, or the odometry chain when the file has none). Every χ² is the project's
  evaluator `h2o_slam.core.graph.chi2` on the *input* graph at the solver's output estimate (for
  H₂O: the `--output` g2o file read back), not the solver's own report.
- χ²/opt divides by the smallest χ² any of the three solvers reached on that graph in this
  run (not a certified global optimum).
- H₂O: `h2o-solve IN --output OUT --mode exact --report R.json` (up to 100 iterations, until
  the relative χ² decrease falls to 1e-10) and
  `--mode offline --passes 10`, run as subprocesses. Its time is `wall_s` of the report:
  the solve only, without interpreter start-up, the compiled kernels' loading and file I/O
  (the whole process time is in the checks table).
- GTSAM LM: `LevenbergMarquardtOptimizer`, max {LM_MAX_ITERATIONS} iterations, relative
  and absolute error tolerance {LM_RELATIVE_TOL:g} / {LM_ABSOLUTE_TOL:g}, default lambda
  schedule; BetweenFactorPose2/Pose3 with `noiseModel.Gaussian.Information` of the same
  (eigen-clamped) information matrices; gauge fixed by a PriorFactor on node 0 at its start
  pose, isotropic sigma {PRIOR_SIGMA:g}. "LM s" is `optimize()` only; building factors and
  values is excluded (listed as "LM build s"). "(limit)" marks a run that used all
  iterations. Time ratios: H₂O `wall_s` / LM `optimize()` time. H₂O's `wall_s` includes
  building its solver from the graph (pose tree, edge table, whitening: on tinyGrid3D about
  a quarter of it), the counterpart of LM's build, so "with LM's set-up" divides by LM's
  build + `optimize()`.
- "ours / GTSAM": our χ² over 2 × GTSAM's `error()` of the between factors (prior
  excluded) at LM's estimate. The objectives differ: in this gtsam wheel the between
  factors' local coordinates are the group logarithm of T_meas⁻¹·(A⁻¹B) — `Pose2.Logmap`
  and `Pose3.Logmap`, whose translation part is V(θ)⁻¹·t — while ours are [t; Log R]
  (doc/design.md, Conventions). The two agree to first order, so the ratio is ≈ 1 when the
  residuals are small and departs from 1 when they are not; each solver can only be optimal
  in its own metric. "exact/offline: 2·GTSAM error" score the H₂O outputs in GTSAM's metric, so a
  worse LM χ² can be told apart from a metric difference (LM stuck in a worse minimum
  vs. LM at the minimum of its own objective).
- "report χ² / ours": `chi2_final` of the H₂O report over our rescoring of its output file.
"""


def _machine() -> str:
    try:
        gtsam_version = metadata.version("gtsam")
    except metadata.PackageNotFoundError:
        gtsam_version = "not installed"
    rev = revision(REPO)
    return (f"{platform.machine()}, nproc {os.cpu_count()}, Python "
            f"{platform.python_version()}, numpy {np.__version__}, gtsam {gtsam_version}, "
            f"repo at {rev}")


def _command() -> str:
    return command(REPO)


def render_section(results: list[GraphResult], skipped: list[str]) -> str:
    """The ``## Solvers`` section of RESULTS.md."""
    skip = "".join(f"- skipped {s}\n" for s in skipped)
    skip = f"Graphs that could not be read:\n\n{skip}\n" if skip else ""
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return (f"{SECTION}\n\nCommand (from the repo root): `{_command()}`\n\n"
            f"Date: {when}. Machine: {_machine()}. Timings are indicative (shared machine).\n\n"
            f"{format_tables(results)}\n\n{skip}{NOTES}")


def run(data: Path | None, names: list[str] | None, timeout_s: float, out_dir: Path | None,
        results: Path | None) -> int:
    """Benchmark the graphs of ``data`` (all, or ``names``); return an exit code."""
    paths = select_graphs("solvers.py", data, names)
    if isinstance(paths, int):
        return paths
    rows, skipped = run_graphs("solvers.py", paths, out_dir,
                               lambda p, folder: bench_graph(p, folder, timeout_s))
    publish(render_section(rows, skipped), results, SECTION)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_graph_arguments(parser)
    parser.add_argument("--timeout", type=float, default=900.0, metavar="S",
                        help="limit per solver run in seconds (default 900)")
    parser.add_argument("--output-dir", type=Path, default=None,
                        help="keep the solved files and reports here (default: a temp dir)")
    args = parser.parse_args(argv)
    return run(args.data, args.graphs, args.timeout, args.output_dir, results_path(args))


if __name__ == "__main__":
    sys.exit(main())
