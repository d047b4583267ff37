"""Benchmark: H₂O's budgeted online mode (through ``h2o-solve``) against GTSAM's iSAM2, both
fed the public pose graphs one callback per arriving pose.

    .venv/bin/python bench/online.py [--data DIR] [--graphs NAME ...] [--budgets MS ...]
                                     [--timeout S] [--output-dir DIR] [--skip-isam2]
                                     [--results FILE] [--plots DIR]

For every graph: ``h2o-solve --mode online --budget-ms B --passes 10`` at each budget (a
subprocess of the real tool, with ``--report`` and ``--trace``), then GTSAM's ``ISAM2`` fed
the same arrivals (:func:`h2o_slam.modes.arrivals`: at pose ``k`` every edge whose newest
pose is ``k``) in this process, one ``update`` per pose. The reference optimum is the smallest
χ² of GTSAM Levenberg–Marquardt (in this process, the code and start of ``bench/solvers.py``),
``h2o-solve --mode exact`` and every run of this benchmark on that graph. Every χ² is the one
evaluator :func:`h2o_slam.graph.chi2`. The tables go to stdout and replace the section
``## Online (bench/online.py)`` of ``bench/RESULTS.md`` (other sections are kept); one PNG
per graph goes to ``bench/plots/online_<graph>.png``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from results_md import replace_section

from h2o_slam.errors import H2OError
from h2o_slam.g2o import read_g2o
from h2o_slam.graph import PoseGraph, chi2, edge_chi2
from h2o_slam.modes import arrivals


def _load_solvers() -> ModuleType:
    """``bench/solvers.py`` as a module (``bench/`` is not a package; the repo root is not on
    ``sys.path`` when this file runs as a script)."""
    path = Path(__file__).resolve().with_name("solvers.py")
    spec = importlib.util.spec_from_file_location("bench_solvers", path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


solvers = _load_solvers()

REPO = solvers.REPO
DEFAULT_DATA = solvers.DEFAULT_DATA
DEFAULT_RESULTS = REPO / "bench" / "RESULTS.md"
DEFAULT_PLOTS = REPO / "bench" / "plots"
SECTION = "## Online (bench/online.py)"

DEFAULT_BUDGETS_MS = (2.0, 5.0, 20.0)
#: Offline passes after the online pass.
PASSES = 10
#: Targets of issue 3: χ² after the extra passes within 5 % of the optimum; the largest
#: callback within twice the budget.
CHI2_TARGET = 1.05
MAX_TARGET = 2.0
#: About this many χ² samples of iSAM2's estimate during the online pass (for the plot).
ISAM2_CHI2_SAMPLES = 200
#: iSAM2 counts as diverged when the χ² of the edges fed so far exceeds this multiple of the
#: χ² of the same edges at the odometry-composed start, or is not finite.
DIVERGED_FACTOR = 1e3


# --- results -----------------------------------------------------------------------------------


@dataclass
class CallbackTimes:
    """Wall time of each callback in ms, one entry per pose fed (shape ``(K,)``)."""

    ms: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def mean(self) -> float:
        """Mean callback time (ms)."""
        return float(self.ms.mean()) if len(self.ms) else float("nan")

    @property
    def p99(self) -> float:
        """99th percentile (numpy's linear interpolation, as ``h2o-solve`` reports it)."""
        return float(np.percentile(self.ms, 99)) if len(self.ms) else float("nan")

    @property
    def max(self) -> float:
        """Largest callback time (ms)."""
        return float(self.ms.max()) if len(self.ms) else float("nan")

    def overruns(self, budget_ms: float) -> int:
        """Callbacks that took longer than ``budget_ms``."""
        return int(np.count_nonzero(self.ms > budget_ms))


@dataclass
class H2OOnlineRun:
    """One ``h2o-solve --mode online --budget-ms B --passes P`` run."""

    budget_ms: float
    status: str  # "ok", "timeout", or "failed (exit N): <last stderr line>"
    times: CallbackTimes = field(default_factory=CallbackTimes)
    #: the same callbacks without the spare-time revisits of old edges (``required_ms``)
    required: CallbackTimes = field(default_factory=CallbackTimes)
    chi2_online: float = float("nan")  # chi2_per_pass[0] of the report: after the online pass
    chi2_final: float = float("nan")  # our evaluator on the output file (after the passes)
    chi2_final_reported: float = float("nan")
    chi2_per_pass: list[float] = field(default_factory=list)
    #: ``(K, 2)``: cumulative solver seconds and χ², from ``--trace``.
    chi2_trace: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    passes: int = PASSES
    report_times: dict[str, float] = field(default_factory=dict)  # per_callback_ms of report
    overruns_reported: int = -1
    deferred_edges: int = -1
    d_max: Any = None
    wall_s: float = float("nan")  # wall_s of the report (solve only)
    process_s: float = float("nan")  # whole subprocess

    @property
    def label(self) -> str:
        """Row label, e.g. ``H₂O@5ms``."""
        return f"H₂O@{self.budget_ms:g}ms"


@dataclass
class ISAM2Run:
    """GTSAM iSAM2 fed one ``update`` per arriving pose."""

    status: str  # "ok", "failed at pose k: ...", "diverged at pose k ...", "timeout at pose k"
    times: CallbackTimes = field(default_factory=CallbackTimes)
    failed_at: int | None = None  # pose index where it failed, diverged or timed out
    chi2_final: float = float("nan")  # our evaluator at calculateEstimate() after the last pose
    #: ``(K, 2)``: cumulative update seconds and χ² of the edges fed so far.
    chi2_trace: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass
class Reference:
    """The optimum each χ² is divided by."""

    lm: Any  # bench/solvers.py LMRun
    exact: Any  # bench/solvers.py H2ORun (mode exact)
    optimum: float
    source: str  # which solver reached it


@dataclass
class GraphOnline:
    """Everything measured on one graph."""

    name: str
    nodes: int
    edges: int
    planar: bool
    chi2_initial: float
    h2o: list[H2OOnlineRun]
    isam2: ISAM2Run | None
    ref: Reference
    plot: Path | None = None


# --- H₂O through its command-line tool ------------------------------------------------------


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    return env


def run_h2o_online(graph: PoseGraph, path: Path, out_dir: Path, budget_ms: float,
                   passes: int, timeout_s: float) -> H2OOnlineRun:
    """``h2o-solve --mode online --budget-ms budget_ms --passes passes`` on ``path`` as a
    subprocess; its output file is rescored on ``graph``."""
    stem = f"{path.stem}.online{budget_ms:g}ms"
    out, report, trace = (out_dir / f"{stem}{ext}"
                          for ext in (".g2o", ".report.json", ".trace.json"))
    cmd = [sys.executable, "-m", "h2o_slam.cli.solve", str(path), "--output", str(out),
           "--mode", "online", "--budget-ms", f"{budget_ms:g}", "--passes", str(passes),
           "--report", str(report), "--trace", str(trace)]
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True,
                              timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        return H2OOnlineRun(budget_ms, f"timeout (> {timeout_s:g} s)")
    process_s = time.perf_counter() - start
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines() or ["(no output)"]
        return H2OOnlineRun(budget_ms, f"failed (exit {proc.returncode}): {lines[-1]}",
                            process_s=process_s)
    try:
        rep, tr = json.loads(report.read_text()), json.loads(trace.read_text())
        solved = read_g2o(out)
    except (OSError, ValueError, H2OError) as err:
        return H2OOnlineRun(budget_ms, f"failed: output unreadable: {err}", process_s=process_s)
    if not np.array_equal(solved.ids, graph.ids):
        return H2OOnlineRun(budget_ms, "failed: output node ids differ from the input's",
                            process_s=process_s)
    per_pass = [float(x) for x in rep["chi2_per_pass"]]
    return H2OOnlineRun(
        budget_ms, "ok", times=CallbackTimes(np.asarray(tr["callback_ms"], dtype=float)),
        required=CallbackTimes(np.asarray(tr["required_ms"], dtype=float)),
        chi2_online=per_pass[0] if per_pass else float("nan"),
        chi2_final=chi2(graph, solved.R, solved.t),
        chi2_final_reported=float(rep["chi2_final"]), chi2_per_pass=per_pass,
        chi2_trace=np.asarray(tr["chi2_trace"], dtype=float).reshape(-1, 2), passes=passes,
        report_times={k: float(v) for k, v in (rep.get("per_callback_ms") or {}).items()},
        overruns_reported=int(rep.get("overruns", -1)),
        deferred_edges=int(rep.get("deferred_edges", -1)), d_max=rep.get("d_max"),
        wall_s=float(rep["wall_s"]), process_s=process_s,
    )


# --- GTSAM iSAM2 -------------------------------------------------------------------------------


def _gtsam_pose(planar: bool, R: np.ndarray, t: np.ndarray) -> Any:
    import gtsam

    if planar:
        return gtsam.Pose2(t[0], t[1], float(np.arctan2(R[1, 0], R[0, 0])))
    return gtsam.Pose3(gtsam.Rot3(R), t)


def _poses_of(planar: bool, values: Any) -> tuple[np.ndarray, np.ndarray]:
    """World poses ``(R, t)`` of every key of ``values`` (keys 0..K-1), shapes ``(K, 3, 3)``
    and ``(K, 3)``."""
    import gtsam

    if planar:
        xyt = gtsam.utilities.extractPose2(values)
        c, s = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
        R = np.zeros((len(xyt), 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        return R, np.column_stack([xyt[:, :2], np.zeros(len(xyt))])
    m = gtsam.utilities.extractPose3(values)  # rows: R row-major (9), then t (3)
    return m[:, :9].reshape(-1, 3, 3), m[:, 9:].copy()


def _predict(graph: PoseGraph, edges: np.ndarray, k: int, previous: Any, start: Any) -> Any:
    """Initial value of pose ``k``: pose ``k-1``'s current estimate composed with the odometry
    edge between them (either direction), or ``start`` (the file's estimate) when none."""
    for e in edges:
        a, b = int(graph.a[e]), int(graph.b[e])
        if {a, b} == {k - 1, k}:
            meas = _gtsam_pose(graph.planar, graph.meas_R[e], graph.meas_t[e])
            return previous.compose(meas if a == k - 1 else meas.inverse())
    return start


class _PartialChi2:
    """χ² of the edges fed up to pose ``k`` (those whose newest pose is ≤ k)."""

    def __init__(self, graph: PoseGraph):
        self.graph = graph
        self.newest = np.maximum(graph.a, graph.b)

    def __call__(self, k: int, R: np.ndarray, t: np.ndarray) -> float:
        R_all, t_all = self.graph.R.copy(), self.graph.t.copy()
        R_all[: k + 1], t_all[: k + 1] = R[: k + 1], t[: k + 1]
        per_edge = edge_chi2(self.graph, R_all, t_all)
        return float(per_edge[self.newest <= k].sum())


def _odometry_start(graph: PoseGraph, arrive: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The poses iSAM2 would start from if it never moved anything: pose 0 from the file,
    every next pose predicted from the previous one by the odometry edge (the divergence
    yardstick)."""
    import gtsam

    values = gtsam.Values()
    pose = _gtsam_pose(graph.planar, graph.R[0], graph.t[0])
    values.insert(0, pose)
    for k in range(1, graph.num_nodes):
        pose = _predict(graph, arrive[k], k, pose,
                        _gtsam_pose(graph.planar, graph.R[k], graph.t[k]))
        values.insert(k, pose)
    return _poses_of(graph.planar, values)


def run_isam2(graph: PoseGraph, timeout_s: float,
              samples: int = ISAM2_CHI2_SAMPLES) -> ISAM2Run:
    """Feed ``graph`` to GTSAM ``ISAM2`` (default ``ISAM2Params``) one pose per ``update``.

    Pose 0 arrives with a prior at its file pose (sigma ``PRIOR_SIGMA`` of bench/solvers.py);
    pose ``k`` with the between factors of every edge whose newest pose is ``k`` and an initial
    value from :func:`_predict`. The time of a callback is ``update()`` plus
    ``calculateEstimate(k)`` of the new pose (which the next prediction uses); building the
    factors is not timed. Every ~N/``samples`` poses, outside the timed region, the χ² of the
    edges fed so far is evaluated at ``calculateEstimate()``.
    """
    import gtsam

    between, start = solvers._gtsam_graph(graph)  # factors in edge order; the file's poses
    arrive = arrivals(graph)
    planar, n = graph.planar, graph.num_nodes
    at = start.atPose2 if planar else start.atPose3
    partial = _PartialChi2(graph)
    R0, t0 = _odometry_start(graph, arrive)
    every = max(1, n // samples)
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    estimate_of = isam.calculateEstimatePose2 if planar else isam.calculateEstimatePose3
    times, trace, solver_s = [], [], 0.0
    began = time.perf_counter()
    latest = at(0)

    def result(status: str, k: int | None, final: float = float("nan")) -> ISAM2Run:
        return ISAM2Run(status, CallbackTimes(np.asarray(times)), k, final,
                        np.asarray(trace, dtype=float).reshape(-1, 2))

    for k in range(n):
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            noise = gtsam.noiseModel.Isotropic.Sigma(3 if planar else 6, solvers.PRIOR_SIGMA)
            prior = gtsam.PriorFactorPose2 if planar else gtsam.PriorFactorPose3
            factors.add(prior(0, at(0), noise))
            values.insert(0, at(0))
        else:
            for e in arrive[k]:
                factors.push_back(between.at(int(e)))
            values.insert(k, _predict(graph, arrive[k], k, latest, at(k)))
        try:
            tic = time.perf_counter()
            isam.update(factors, values)
            latest = estimate_of(k)
            toc = time.perf_counter()
        except Exception as err:  # IndeterminantLinearSystemException arrives as RuntimeError
            first = " ".join(str(err).strip().split("\n\n")[0].split())  # first paragraph
            return result(f"failed at pose {k}: {type(err).__name__}: {first}", k)
        times.append(1e3 * (toc - tic))
        solver_s += toc - tic
        if k % every == every - 1 or k == n - 1:
            R, t = _poses_of(planar, isam.calculateEstimate())
            value = partial(k, R, t)
            trace.append((solver_s, value))
            if not np.isfinite(value) or value > DIVERGED_FACTOR * partial(k, R0, t0):
                return result(f"diverged at pose {k} (χ² of the edges so far "
                              f"{value:.3g}, > {DIVERGED_FACTOR:g}× the odometry start)", k)
        if time.perf_counter() - began > timeout_s:
            return result(f"timeout at pose {k} (> {timeout_s:g} s)", k)
    R, t = _poses_of(planar, isam.calculateEstimate())
    return result("ok", None, chi2(graph, R, t))


# --- the optimum -------------------------------------------------------------------------------


def run_reference(graph: PoseGraph, path: Path, out_dir: Path, timeout_s: float) -> Reference:
    """GTSAM LM (in this process, as bench/solvers.py runs it) and ``h2o-solve --mode exact``;
    the optimum is filled in by :func:`_set_optimum` once the online runs are in."""
    try:
        lm = solvers.run_lm(graph)
    except Exception as err:  # reported in the table, not raised
        lm = solvers.LMRun(f"failed: {type(err).__name__}: {err}")
    exact = solvers.run_h2o(graph, path, out_dir, "exact", None, timeout_s)
    return Reference(lm, exact, float("nan"), "")


def _set_optimum(ref: Reference, h2o: list[H2OOnlineRun], isam2: ISAM2Run | None) -> None:
    cands = [("GTSAM LM", ref.lm.chi2 if ref.lm.status == "ok" else np.nan),
             ("H₂O exact", ref.exact.chi2 if ref.exact.status == "ok" else np.nan)]
    for run in h2o:
        if run.status == "ok":
            cands += [(f"{run.label} online", run.chi2_online),
                      (f"{run.label} +{run.passes}", run.chi2_final)]
    if isam2 is not None and isam2.status == "ok":
        cands.append(("iSAM2", isam2.chi2_final))
    finite = [(v, name) for name, v in cands if np.isfinite(v)]
    if finite:
        ref.optimum, ref.source = min(finite)


# --- one graph ---------------------------------------------------------------------------------


def bench_graph(path: Path, out_dir: Path, budgets_ms: list[float], timeout_s: float,
                skip_isam2: bool, plots: Path | None) -> GraphOnline:
    """Run every solver on one graph file (and plot it when ``plots`` is given)."""
    graph = read_g2o(path)

    def log(msg: str) -> None:
        print(f"[{path.stem}] {msg}", file=sys.stderr, flush=True)

    log(f"{graph.num_nodes} nodes, {graph.num_edges} edges; GTSAM LM and H₂O exact ...")
    ref = run_reference(graph, path, out_dir, timeout_s)
    log(f"LM: {ref.lm.status} (χ² {ref.lm.chi2:.6g}); exact: {ref.exact.status} "
        f"(χ² {ref.exact.chi2:.6g})")
    h2o = []
    for budget in budgets_ms:
        log(f"H₂O online at {budget:g} ms + {PASSES} passes ...")
        run = run_h2o_online(graph, path, out_dir, budget, PASSES, timeout_s)
        log(f"{run.label}: {run.status}; max {run.times.max:.3g} ms; "
            f"χ² online {run.chi2_online:.6g}, +{PASSES} passes {run.chi2_final:.6g}")
        h2o.append(run)
    isam2 = None
    if not skip_isam2:
        log("GTSAM iSAM2 ...")
        isam2 = run_isam2(graph, timeout_s)
        log(f"iSAM2: {isam2.status}; max {isam2.times.max:.3g} ms; χ² {isam2.chi2_final:.6g}")
    _set_optimum(ref, h2o, isam2)
    result = GraphOnline(path.stem, graph.num_nodes, graph.num_edges, graph.planar,
                         chi2(graph), h2o, isam2, ref)
    if plots is not None:
        result.plot = plot_graph(result, plots / f"online_{path.stem}.png")
        log(f"plot: {result.plot}")
    return result


# --- plot --------------------------------------------------------------------------------------


def plot_graph(r: GraphOnline, out: Path) -> Path:
    """Two panels: (a) callback time against pose index, budgets as horizontal lines; (b) χ²
    against cumulative solver time (online pass, then one point per offline pass)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_c) = plt.subplots(1, 2, figsize=(14, 5.2))
    colors = plt.get_cmap("tab10").colors
    for i, run in enumerate(r.h2o):
        c = colors[i]
        ax_t.axhline(run.budget_ms, color=c, lw=1.2, ls="--")
        if run.status != "ok":
            continue
        ax_t.plot(np.arange(len(run.times.ms)), run.times.ms, ".", ms=1.5, color=c, alpha=0.6,
                  label=f"{run.label}: p99 {run.times.p99:.3g}, max {run.times.max:.3g} ms")
        tr = run.chi2_trace
        online, passes = tr[: len(tr) - run.passes], tr[len(tr) - run.passes:]
        ax_c.plot(online[:, 0], online[:, 1], "-", color=c, lw=1.2, label=f"{run.label} online")
        ax_c.plot(passes[:, 0], passes[:, 1], "o-", color=c, ms=3, lw=0.8,
                  label=f"{run.label} +{run.passes} passes")
    if r.isam2 is not None and len(r.isam2.times.ms):
        t = r.isam2.times
        ax_t.plot(np.arange(len(t.ms)), t.ms, ".", ms=1.5, color="black", alpha=0.5,
                  label=f"iSAM2: p99 {t.p99:.3g}, max {t.max:.3g} ms")
        tr = r.isam2.chi2_trace
        ax_c.plot(tr[:, 0], tr[:, 1], "-", color="black", lw=1.2, label="iSAM2")
        if r.isam2.failed_at is not None:
            ax_t.axvline(r.isam2.failed_at, color="black", lw=0.8, ls=":")
            ax_t.annotate(r.isam2.status.split(":")[0].split(" (")[0],
                          (r.isam2.failed_at, 0.02), xycoords=("data", "axes fraction"),
                          rotation=90, fontsize=8, ha="right", va="bottom")
    if np.isfinite(r.ref.optimum):
        ax_c.axhline(r.ref.optimum, color="grey", lw=0.8, ls=":",
                     label=f"optimum {r.ref.optimum:.6g} ({r.ref.source})")
    ax_t.set(yscale="log", xlabel="pose index (one callback per pose)",
             ylabel="callback time (ms)",
             title=f"(a) {r.name}: time per callback; dashed: budgets")
    ax_c.set(yscale="log", xlabel="cumulative solver time (s)",
             ylabel="χ² (online: edges fed so far)",
             title=f"(b) {r.name}: χ² against solver time")
    if np.isfinite(r.ref.optimum) and r.ref.optimum > 0:
        # The first poses' χ² is ~0 (a tree fits exactly); keep the decades that matter.
        ax_c.set_ylim(bottom=1e-2 * r.ref.optimum)
    for ax, scale in ((ax_t, 4), (ax_c, 1)):
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7, markerscale=scale, loc="best")
    fig.suptitle(f"{r.name}: {r.nodes} poses, {r.edges} edges "
                 f"({'SE(2)' if r.planar else 'SE(3)'})", fontsize=11)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


# --- tables ------------------------------------------------------------------------------------


def _num(x: float, fmt: str) -> str:
    return format(x, fmt) if np.isfinite(x) else "—"


def _short(status: str) -> str:
    """A status for a table cell: everything before the first colon."""
    return status.split(":")[0]


def _yes(ok: bool | None) -> str:
    return "—" if ok is None else ("yes" if ok else "**no**")


def _overrun_cell(times: CallbackTimes, budget_ms: float) -> str:
    n = times.overruns(budget_ms)
    return f"{n} ({100.0 * n / max(1, len(times.ms)):.1f} %)"


@dataclass
class Targets:
    """The targets of one H₂O run (``None``: cannot be judged)."""

    p99: bool | None
    max: bool | None
    chi2: bool | None
    vs_isam2: bool | None
    #: the same comparison without the spare-time revisits, which fill any budget by design
    required_vs_isam2: bool | None = None


def targets(r: GraphOnline, run: H2OOnlineRun) -> Targets:
    """Judge ``run`` against the targets of issue 3."""
    if run.status != "ok":
        return Targets(False, False, False, False, False)
    b = run.budget_ms
    chi2_ok = (run.chi2_final <= CHI2_TARGET * r.ref.optimum) if np.isfinite(
        r.ref.optimum) else None
    vs = required_vs = None  # not judged when iSAM2 did not run or did not finish the graph
    if r.isam2 is not None and r.isam2.status == "ok":
        vs = run.times.max < r.isam2.times.max
        required_vs = run.required.max < r.isam2.times.max
    return Targets(run.times.p99 <= b, run.times.max <= MAX_TARGET * b, chi2_ok, vs,
                   required_vs)


def _h2o_row(r: GraphOnline, run: H2OOnlineRun) -> list[str]:
    opt = r.ref.optimum
    if run.status != "ok":
        return [r.name, run.label] + [_short(run.status)] * 7 + [_yes(False)] * 5
    t = targets(r, run)
    return [r.name, run.label, _num(run.times.mean, ".3g"), _num(run.times.p99, ".3g"),
            _num(run.times.max, ".3g"), _num(run.required.max, ".3g"),
            _overrun_cell(run.times, run.budget_ms),
            _num(run.chi2_online / opt, ".4g"), _num(run.chi2_final / opt, ".4f"),
            _yes(t.p99), _yes(t.max), _yes(t.chi2), _vs_cell(r, t.vs_isam2),
            _vs_cell(r, t.required_vs_isam2)]


def _vs_cell(r: GraphOnline, ok: bool | None) -> str:
    if ok is None and r.isam2 is not None:
        return f"iSAM2 {_short(r.isam2.status).split(' (')[0]}"
    return _yes(ok)


def _isam2_row(r: GraphOnline, budgets_ms: list[float]) -> list[str]:
    s = r.isam2
    assert s is not None
    over = "; ".join(f"{b:g} ms: {_overrun_cell(s.times, b)}" for b in budgets_ms)
    chi2_cell = (_num(s.chi2_final / r.ref.optimum, ".4g") if s.status == "ok"
                 else _short(s.status))
    return [r.name, "iSAM2", _num(s.times.mean, ".3g"), _num(s.times.p99, ".3g"),
            _num(s.times.max, ".3g"), "—", over or "—", chi2_cell, "—", "—", "—", "—", "—",
            "—"]


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    return (["| " + " | ".join(head) + " |", "| " + " | ".join(["---"] * len(head)) + " |"]
            + ["| " + " | ".join(row) + " |" for row in rows])


def format_tables(results: list[GraphOnline], budgets_ms: list[float]) -> str:
    """The reference table, the main table, the targets summary, checks and failures."""
    ref_rows = []
    for r in results:
        lm, ex = r.ref.lm, r.ref.exact
        ref_rows.append([
            r.name, "SE(2)" if r.planar else "SE(3)", str(r.nodes), str(r.edges),
            _num(r.chi2_initial, ".6g"),
            _num(lm.chi2, ".6g") if lm.status == "ok" else _short(lm.status),
            _num(ex.chi2, ".6g") if ex.status == "ok" else _short(ex.status),
            _num(r.ref.optimum, ".6g"), r.ref.source or "—"])
    lines = ["Reference optimum per graph:", ""]
    lines += _table(["graph", "kind", "nodes", "edges", "χ² initial", "LM χ²", "H₂O exact χ²",
                     "optimum χ²", "reached by"], ref_rows)

    rows = []
    for r in results:
        rows += [_h2o_row(r, run) for run in r.h2o]
        if r.isam2 is not None:
            rows.append(_isam2_row(r, budgets_ms))
    lines += ["", "Per graph and solver (times per callback in ms; χ² as a ratio to the "
              "optimum above):", ""]
    lines += _table(["graph", "solver", "mean", "p99", "max", "max without revisits",
                     "overruns of the budget", "χ² online / opt", f"χ² +{PASSES} passes / opt",
                     "p99 ≤ budget", f"max ≤ {MAX_TARGET:g}×budget",
                     f"χ² +{PASSES} ≤ {CHI2_TARGET:g}×opt", "max < iSAM2 max",
                     "max without revisits < iSAM2 max"], rows)
    lines += ["", _summary(results)]

    check_rows = []
    for r in results:
        for run in r.h2o:
            if run.status != "ok":
                continue
            rt = run.report_times
            check_rows.append([
                r.name, run.label, str(run.d_max), str(run.deferred_edges),
                f"{run.overruns_reported} / {run.times.overruns(run.budget_ms)}",
                "/".join(_num(rt.get(k, np.nan), ".3g") for k in ("mean", "p99", "max")),
                _num(run.chi2_final_reported / run.chi2_final, ".10f"),
                _num(run.wall_s, ".3g"), _num(run.process_s, ".3g"),
                str(len(run.times.ms)), str(len(run.chi2_trace))])
    if check_rows:
        lines += ["", "Checks (H₂O runs):", ""]
        lines += _table(["graph", "run", "d_max (report)", "deferred edges",
                         "overruns: report / trace", "report mean/p99/max ms",
                         "report χ² final / ours", "wall s", "process s", "callbacks traced",
                         "χ² samples"], check_rows)

    failures = [f"- {r.name}, {run.label}: {run.status}" for r in results for run in r.h2o
                if run.status != "ok"]
    failures += [f"- {r.name}, iSAM2: {r.isam2.status}" for r in results
                 if r.isam2 is not None and r.isam2.status != "ok"]
    failures += [f"- {r.name}, reference {who}: {run.status}" for r in results
                 for who, run in (("GTSAM LM", r.ref.lm), ("H₂O exact", r.ref.exact))
                 if run.status != "ok"]
    if failures:
        lines += ["", "Failures, divergences and timeouts:", "", *failures]
    return "\n".join(lines)


def _summary(results: list[GraphOnline]) -> str:
    """How many H₂O runs meet each target."""
    judged = [targets(r, run) for r in results for run in r.h2o]
    parts = []
    for name, attr in (("p99 ≤ budget", "p99"), (f"max ≤ {MAX_TARGET:g}×budget", "max"),
                       (f"χ² after {PASSES} passes ≤ {CHI2_TARGET:g}×optimum", "chi2"),
                       ("max < iSAM2's max", "vs_isam2"),
                       ("max without revisits < iSAM2's max", "required_vs_isam2")):
        vals = [getattr(t, attr) for t in judged if getattr(t, attr) is not None]
        parts.append(f"{name}: {sum(vals)}/{len(vals)}")
    return "Targets met by the H₂O runs — " + "; ".join(parts) + "."


NOTES = f"""\
Notes:

- Feed: for pose k, every edge whose newest pose is k (`h2o_slam.modes.arrivals`, the order
  `h2o-solve --mode online` uses), one callback per pose, poses in index order.
- H₂O: `h2o-solve IN --output OUT --mode online --budget-ms B --passes {PASSES} --report R
  --trace T`, default d_max, as a subprocess. Callback times are the `callback_ms` of the
  trace (the tool's own timing of each callback); mean/p99/max/overruns are computed here
  from them (p99: numpy's linear interpolation) and cross-checked against the report in the
  checks table. "χ² online" is `chi2_per_pass[0]` of the report (after the online pass);
  "χ² +{PASSES} passes" is our evaluator on the output file. An overrun is a callback longer
  than the budget. "max without revisits" is the largest `required_ms` of the trace: the
  callback less the time spent revisiting old edges, which H₂O does with whatever budget is
  left (3.3.13), so it is the work the callback could not have skipped.
- GTSAM iSAM2 (same process as this script): `ISAM2(ISAM2Params())` with GTSAM's defaults
  (Gauss–Newton, relinearizeThreshold 0.1, relinearizeSkip 10, wildfire 0.001, Cholesky);
  BetweenFactorPose2/Pose3 built by bench/solvers.py from `h2o_slam.g2o.read_g2o` (same
  information matrices, Pose3 information permuted to GTSAM's rotation-first order); a prior
  of sigma {solvers.PRIOR_SIGMA:g} on pose 0 at its file pose. The initial value of pose k is
  pose k−1's current iSAM2 estimate composed with the k−1→k odometry measurement. One
  `update(new_factors, new_values)` per pose; the time of a callback is `update` plus
  `calculateEstimatePose2/3(k)` of the new pose (perf_counter around both); building the
  factor objects is not timed. Its overruns are counted against each H₂O budget. Failures
  are caught and the pose index recorded; "diverged" means the χ² of the edges fed so far
  (sampled about every N/{ISAM2_CHI2_SAMPLES} poses, outside the timed region) went
  non-finite or above {DIVERGED_FACTOR:g}× the χ² of the same edges at the odometry-composed
  start. "χ² online" for iSAM2 is our evaluator at `calculateEstimate()` after the last pose.
- Optimum: the smallest χ² on that graph among GTSAM LM (in this process, `run_lm` of
  bench/solvers.py: from the file's estimate, prior on node 0, max 100 iterations),
  `h2o-solve --mode exact` (default 20 iterations) and every H₂O and iSAM2 result of this
  benchmark; "reached by" names which. It is not a certified global optimum. Every χ² is
  `h2o_slam.graph.chi2` on the input graph.
- Targets (issue 3): p99 ≤ budget; max ≤ {MAX_TARGET:g}× budget; χ² after {PASSES} offline
  passes ≤ {CHI2_TARGET:g}× optimum; H₂O's max callback below iSAM2's max callback on the
  same graph (only judged where iSAM2 finished the graph; where it failed the cell says so).
  A failed H₂O run fails every target.
- The machine has 2 cores shared with other work: single runs, timings indicative; the tails
  (p99, max) are the most sensitive to other load.
- Plots: `bench/plots/online_<graph>.png`. (a) callback time against pose index, budgets
  dashed; (b) χ² against cumulative solver time — during the online pass the χ² of the edges
  fed so far (so it grows with the graph), then one point per offline pass; the y axis
  starts at 1 % of the optimum.
"""


def render_section(results: list[GraphOnline], budgets_ms: list[float],
                   skipped: list[str]) -> str:
    """The ``## Online`` section of RESULTS.md."""
    skip = "".join(f"- skipped {s}\n" for s in skipped)
    skip = f"Graphs that could not be read:\n\n{skip}\n" if skip else ""
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return (f"{SECTION}\n\nCommand (from the repo root): `{solvers._command()}`\n\n"
            f"Date: {when}. Machine: {solvers._machine()}; 2 cores shared with other work, "
            "timings indicative.\n\n"
            f"{format_tables(results, budgets_ms)}\n\n{skip}{NOTES}")


def write_section(path: Path, section: str) -> None:
    """Replace (or append) this benchmark's section of ``path``, keeping the others."""
    replace_section(path, SECTION, section)


# --- entry point -------------------------------------------------------------------------------


def _select(data: Path, names: list[str] | None) -> list[Path] | str:
    """The graph files to run, or a message saying why there are none."""
    paths = sorted(data.glob("*.g2o"))
    if names:
        by_stem = {p.stem: p for p in paths}
        unknown = [n for n in names if n not in by_stem]
        if unknown:
            return f"no such graph in {data}: {', '.join(unknown)}"
        paths = [by_stem[n] for n in names]
    return paths


def run(data: Path, names: list[str] | None, budgets_ms: list[float], timeout_s: float,
        out_dir: Path | None, skip_isam2: bool, results_path: Path, plots: Path) -> int:
    """Benchmark the graphs of ``data`` (all, or ``names``); return an exit code."""
    if not data.is_dir():
        print(f"online.py: data folder {data} is missing; nothing to benchmark "
              "(pass --data DIR).")
        return 0
    paths = _select(data, names)
    if isinstance(paths, str):
        print(f"online.py: {paths}", file=sys.stderr)
        return 2
    if not paths:
        print(f"online.py: no .g2o files in {data}; nothing to benchmark.")
        return 0
    with tempfile.TemporaryDirectory(prefix="h2o-online-") as tmp:
        target = out_dir if out_dir is not None else Path(tmp)
        target.mkdir(parents=True, exist_ok=True)
        results, skipped = [], []
        for p in paths:
            try:
                results.append(bench_graph(p, target, budgets_ms, timeout_s, skip_isam2,
                                           plots))
            except H2OError as err:  # the input itself cannot be read: no solver can run
                print(f"online.py: skipping {p.name}: {err}", file=sys.stderr)
                skipped.append(f"{p.stem}: {err}")
    section = render_section(results, budgets_ms, skipped)
    print(section)
    write_section(results_path, section)
    print(f"written to {results_path}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA,
                        help=f"folder of .g2o graphs (default {DEFAULT_DATA})")
    parser.add_argument("--graphs", nargs="+", metavar="NAME",
                        help="run only these graphs (file stems, e.g. intel MIT)")
    parser.add_argument("--budgets", nargs="+", type=float, metavar="MS",
                        default=list(DEFAULT_BUDGETS_MS),
                        help="H₂O per-callback budgets in ms (default 2 5 20)")
    parser.add_argument("--timeout", type=float, default=1800.0, metavar="S",
                        help="limit per solver run in seconds (default 1800)")
    parser.add_argument("--output-dir", type=Path, default=None,
                        help="keep solved files, reports and traces here (default: a temp dir)")
    parser.add_argument("--skip-isam2", action="store_true", help="do not run GTSAM iSAM2")
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS,
                        help=f"markdown file to update (default {DEFAULT_RESULTS})")
    parser.add_argument("--plots", type=Path, default=DEFAULT_PLOTS,
                        help=f"folder for the PNGs (default {DEFAULT_PLOTS})")
    args = parser.parse_args(argv)
    if any(b <= 0 for b in args.budgets):
        parser.error("--budgets must be positive")
    return run(args.data, args.graphs, args.budgets, args.timeout, args.output_dir,
               args.skip_isam2, args.results, args.plots)


if __name__ == "__main__":
    sys.exit(main())
