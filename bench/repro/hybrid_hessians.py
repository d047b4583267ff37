"""Grimes, Anguelov and LeCun, *Hybrid Hessians for flexible optimization of pose graphs*
(IROS 2010): its headline comparisons against TORO, re-run on the public graphs.

The paper's measured claims: (Fig. 5) the average energy per constraint against time for
TORO and H₂O at ``D_max`` = 75, 100, 150, 200, ∞ — H₂O lowers it faster and settles an
order of magnitude below TORO; (Table I) the average and largest time per constraint of
each; (§IV) on Olson's Manhattan world H₂O converges to 1.596 per constraint, TORO to
2.062; (Table II) the graphs' nodes, edges, loop edges and longest path. Valencia and
Paris are Google's and not public: the public graphs stand in (see the section).

H₂O is :class:`h2o_slam.core.solver.H2OSolver` run as the paper's Algorithm 1
(:func:`h2o_slam.core.modes.offline_pass`: breadth-first tree, edges by root depth, τ ← 0.99 τ
per pass, rotation steps capped at π/8), each ``relax`` call timed on its own. TORO is
:func:`h2o_slam.baselines.toro.solve_toro` (a colleague's implementation of Grisetti et al. 2007).
Energy is the paper's (1)–(2), ``Σ (f − k)ᵀ S (f − k)`` = :func:`h2o_slam.core.graph.chi2`,
divided by the number of constraints.
"""

from __future__ import annotations

import datetime
import time
from dataclasses import dataclass, field

import numpy as np
from results_md import command

from h2o_slam.baselines.covariance_variants import with_variant
from h2o_slam.core.graph import EdgeKind, PoseGraph, chi2
from h2o_slam.core.modes import build_solver, offline_order, solve_exact, solve_offline
from h2o_slam.io.g2o import read_g2o
from repro.context import Context, verdict

TITLE = "Grimes, Anguelov & LeCun 2010 (hybrid Hessians): energy vs time, time per " \
    "constraint, Manhattan against TORO"

#: D_max values of Fig. 5 and Table I (None: ∞, no subsampling).
D_MAX: tuple[int | None, ...] = (75, 100, 150, 200, None)

#: Table I (Valencia): average and largest time per constraint (s).
SEED_TABLE1: dict[str, tuple[float, float]] = {
    "TORO": (1.75092e-5, 5.24759e-3), "D_max=75": (3.6635e-4, 5.3559e-2),
    "D_max=100": (4.0791e-4, 6.5095e-2), "D_max=150": (4.919e-4, 9.5015e-2),
    "D_max=200": (5.812e-4, 0.13747), "D_max=∞": (2.0823e-3, 3.583),
}
#: §IV: energy per constraint converged to on Olson's Manhattan world.
SEED_MANHATTAN = {"H₂O": 1.596, "TORO": 2.062}
#: Table II, the Manhattan row: nodes, edges, loop edges, max d, smallest D_max.
SEED_TABLE2_MANHATTAN = (3500, 5598, 2099, 184, 30)
#: Table II's Valencia row (no GPS), for the stand-in.
SEED_TABLE2_VALENCIA = (15031, 15153, 122, 1161, 40)

#: Graphs run, ``(label, file stem, covariance variant)``: the paper's Manhattan world with
#: the public file's information and with identity covariance (Olson's original has near
#: isotropic information; the public M3500's is strongly anisotropic, which TORO's diagonal
#: preconditioner handles badly), and stand-ins for Valencia (an urban drive with few loop
#: closures: kitti_00) and a large loop-rich city (city10000, full run only).
GRAPHS = (("manhattan", "manhattan", None), ("manhattan-I", "manhattan", "I"),
          ("kitti_00", "kitti_00", None), ("kitti_00-I", "kitti_00", "I"),
          ("city10000", "city10000", None))
#: Full run: the Valencia stand-in run longer, to tell a slow start from a plateau.
LONG_GRAPH, LONG_PASSES, LONG_TORO = "kitti_00", 150, 500
QUICK_GRAPHS = ("manhattan", "manhattan-I")


def _label(d_max: int | None) -> str:
    return "D_max=∞" if d_max is None else f"D_max={d_max}"


@dataclass
class Run:
    """One solver on one graph: energy per constraint after each pass against cumulative
    solve seconds (index 0: the start), and per-constraint times (s)."""

    label: str
    seconds: list[float] = field(default_factory=list)
    energy: list[float] = field(default_factory=list)
    per_edge_s: np.ndarray | None = None
    per_edge_mean_s: float | None = None
    dogleg_deg: float | None = None


@dataclass
class GraphResult:
    name: str
    nodes: int
    edges: int
    loop_edges: int
    max_d: int
    mean_d: float
    optimum: float
    runs: list[Run] = field(default_factory=list)
    optimum_dogleg_deg: float | None = None


def run_h2o(graph: PoseGraph, d_max: int | None, passes: int) -> tuple[Run, list[int]]:
    """H₂O offline (Algorithm 1, no GPS edges) for ``passes`` passes, every relaxation
    timed; also returns each edge's domain size."""
    clock = time.perf_counter
    begin = clock()
    solver, start = build_solver(graph)
    order = offline_order(solver)
    spent = clock() - begin  # set-up (tree, start, regularizer), as TORO's first entry
    sizes = [len(solver.path(e).domain) for e in range(solver.num_edges)]
    m = graph.num_edges
    run = Run(_label(d_max), [spent], [chi2(start) / m])
    times = np.zeros(passes * len(order))
    k = 0
    for _ in range(passes):
        for e in order:
            begin = clock()
            solver.relax(e, d_max=d_max)
            times[k] = clock() - begin
            k += 1
        begin = clock()
        solver.end_pass()
        spent += float(np.sum(times[k - len(order):k])) + clock() - begin
        run.seconds.append(spent)
        run.energy.append(solver.chi2(graph) / m)
    run.per_edge_s = times
    run.dogleg_deg = dogleg_deg(graph, *solver.world_poses())
    return run, sizes


def run_toro(graph: PoseGraph, iterations: int) -> Run:
    from h2o_slam.baselines.toro import solve_toro

    out, history = solve_toro(graph, iterations=iterations)
    m = graph.num_edges
    run = Run("TORO", list(history.seconds), [c / m for c in history.chi2])
    run.dogleg_deg = dogleg_deg(graph, out.R, out.t)
    # One compiled pass over all edges: the mean per constraint is measurable, the largest
    # single constraint's time is not (the pass is not split per edge).
    steps = np.diff(history.seconds)
    run.per_edge_mean_s = float(np.mean(steps)) / m if len(steps) else None
    return run


#: Odometry steps shorter than this (m) have no direction of travel to compare.
DOGLEG_MIN_STEP_M = 0.2


def dogleg_deg(graph: PoseGraph, R: np.ndarray, t: np.ndarray) -> float:
    """The dog-leg of Fig. 2 / 3e as a number: RMS angle (deg) between each odometry step's
    measured direction of travel in its first pose's frame and the solved one, over steps
    ``i → i+1`` longer than :data:`DOGLEG_MIN_STEP_M`. A pose turned away from its path
    (TORO's dog-leg) shows here even when positions fit."""
    rel = (graph.kind == EdgeKind.RELATIVE) & (graph.b == graph.a + 1)
    meas = graph.meas_t[rel, :2]
    keep = np.hypot(meas[:, 0], meas[:, 1]) > DOGLEG_MIN_STEP_M
    a, b, meas = graph.a[rel][keep], graph.b[rel][keep], meas[keep]
    if not len(a):
        return float("nan")
    step = np.einsum("mji,mj->mi", R[a], t[b] - t[a])[:, :2]  # R_aᵀ (t_b − t_a)
    err = np.arctan2(step[:, 1], step[:, 0]) - np.arctan2(meas[:, 1], meas[:, 0])
    err = (err + np.pi) % (2 * np.pi) - np.pi
    return float(np.degrees(np.sqrt(np.mean(err * err))))


def bench_graph(name: str, graph: PoseGraph, passes: int, toro_iterations: int) -> GraphResult:
    exact = solve_exact(graph)
    optimum = exact.chi2_final
    runs, sizes = [], None
    for d_max in D_MAX:
        run, sizes = run_h2o(graph, d_max, passes)
        runs.append(run)
    assert sizes is not None
    d = np.array(sizes)
    result = GraphResult(name, graph.num_nodes, graph.num_edges, int(np.sum(d > 1)),
                         int(d.max()), float(d.mean()), optimum / graph.num_edges, runs,
                         dogleg_deg(graph, exact.R, exact.t))
    try:
        result.runs.append(run_toro(graph, toro_iterations))
    except ModuleNotFoundError:
        pass
    return result


def long_run_text(graph: PoseGraph, name: str) -> tuple[str, float]:
    """H₂O (D_max=200) for :data:`LONG_PASSES` passes and TORO for :data:`LONG_TORO`
    iterations: energy per constraint at checkpoints, and H₂O's final / TORO's final."""
    h2o, _ = run_h2o(graph, 200, LONG_PASSES)
    toro = run_toro(graph, LONG_TORO)
    optimum = solve_exact(graph).chi2_final / graph.num_edges
    hk = [k for k in (5, 20, 50, 100, LONG_PASSES) if k < len(h2o.energy)]
    tk = [k for k in (10, 100, 300, LONG_TORO) if k < len(toro.energy)]
    h = ", ".join(f"{k}: {_g(h2o.energy[k])} ({h2o.seconds[k]:.1f} s)" for k in hk)
    t = ", ".join(f"{k}: {_g(toro.energy[k])} ({toro.seconds[k]:.1f} s)" for k in tk)
    text = (f"**Longer run on {name}** (energy per constraint after n passes / iterations; "
            f"optimum {_g(optimum)}): H₂O D_max=200 — {h}; TORO — {t}.")
    return text, h2o.energy[-1] / toro.energy[-1]


@dataclass
class GpsResult:
    """H₂O on a Manhattan world with a GPS fix every ``every`` poses (Fig. 3d's setting)."""

    nodes: int
    edges: int
    gps: int
    every: int
    optimum: float
    optimum_dogleg_deg: float
    h2o: float
    h2o_dogleg_deg: float
    h2o_s: float
    passes: int
    toro: str


GPS_EVERY = 100


def gps_experiment(passes: int, poses: int) -> GpsResult:
    """The paper's GPS claim on a synthetic Manhattan world (no public graph has GPS):
    H₂O offline at D_max=200 with GPS edges in batches of 30, against the exact optimum;
    TORO is offered the same graph."""
    from h2o_slam.baselines.toro import solve_toro
    from h2o_slam.core.errors import InputError
    from h2o_slam.io.synthetic import manhattan

    graph = manhattan(poses, seed=7, gps_every=GPS_EVERY).graph
    m = graph.num_edges
    exact = solve_exact(graph)
    begin = time.perf_counter()
    res = solve_offline(graph, passes=passes, d_max=200)
    sec = time.perf_counter() - begin
    try:
        solve_toro(graph, iterations=1)
        toro = "ran"
    except InputError as err:
        toro = f"refused: “{err}”"
    gps = int(np.sum(graph.kind == EdgeKind.POSITION))
    return GpsResult(graph.num_nodes, m, gps, GPS_EVERY, exact.chi2_final / m,
                     dogleg_deg(graph, exact.R, exact.t), res.chi2_final / m,
                     dogleg_deg(graph, res.R, res.t), sec, passes, toro)


def gps_text(g: GpsResult) -> str:
    return (f"**GPS** (Fig. 3d, the abstract's claim): a synthetic Manhattan world "
            f"(`h2o_slam.io.synthetic.manhattan`, {g.nodes} poses, {g.edges} edges of which "
            f"{g.gps} GPS fixes, one every {g.every} poses, σ 1 m). H₂O offline, D_max=200, "
            f"GPS in batches of 30, {g.passes} passes in {g.h2o_s:.1f} s: energy per "
            f"constraint {_g(g.h2o)} against the optimum's {_g(g.optimum)} "
            f"({g.h2o / g.optimum:.3f}×); dog-leg RMS {_g(g.h2o_dogleg_deg)}° against the "
            f"optimum's {_g(g.optimum_dogleg_deg)}°. TORO: {g.toro}.")


# --- report -----------------------------------------------------------------------------------


def _g(x: float | None) -> str:
    return "—" if x is None else f"{x:.4g}" if 1e-3 <= abs(x) < 1e5 else f"{x:.3e}"


def table1(results: list[GraphResult]) -> str:
    head = ["solver", "seed: avg (s)", "seed: max (s)"]
    for r in results:
        head += [f"{r.name}: avg (s)", f"{r.name}: max (s)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    labels = [_label(d) for d in D_MAX] + ["TORO"]
    for label in ["TORO", *labels[:-1]]:
        seed = SEED_TABLE1[label]
        row = [label, _g(seed[0]), _g(seed[1])]
        for r in results:
            run = next((x for x in r.runs if x.label == label), None)
            if run is None:
                row += ["—", "—"]
            elif run.per_edge_s is not None:
                row += [_g(float(np.mean(run.per_edge_s))), _g(float(np.max(run.per_edge_s)))]
            else:
                row += [_g(run.per_edge_mean_s), "not split per edge"]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def energy_table(results: list[GraphResult]) -> str:
    head = ["graph", "optimum (exact mode)", *[x.label for x in results[0].runs]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        row = [r.name, _g(r.optimum)]
        for run in r.runs:
            row.append(f"{_g(run.energy[-1])} ({len(run.energy) - 1} passes, "
                       f"{run.seconds[-1]:.1f} s)")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def dogleg_table(results: list[GraphResult]) -> str:
    labels = [x.label for x in results[0].runs]
    head = ["graph", "optimum (exact mode)", *labels]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        row = [r.name, _g(r.optimum_dogleg_deg)]
        row += [_g(next((x.dogleg_deg for x in r.runs if x.label == lab), None))
                for lab in labels]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def table2(results: list[GraphResult]) -> str:
    lines = ["| graph | nodes | edges | loop edges | max d | mean d |",
             "|---|---|---|---|---|---|"]
    n, m, loops, d, _ = SEED_TABLE2_MANHATTAN
    lines.append(f"| seed: Manhattan world (Olson) | {n} | {m} | {loops} | {d} | — |")
    n, m, loops, d, _ = SEED_TABLE2_VALENCIA
    lines.append(f"| seed: Valencia w/o GPS | {n} | {m} | {loops} | {d} | 1.53 |")
    for r in results:
        lines.append(f"| {r.name} | {r.nodes} | {r.edges} | {r.loop_edges} | {r.max_d} | "
                     f"{r.mean_d:.2f} |")
    return "\n".join(lines)


def plot_energy(r: GraphResult, ctx: Context) -> str:
    """Fig. 5 re-drawn on one graph: energy per constraint (log) against seconds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for run in r.runs:
        style = {"color": "k", "lw": 2.0} if run.label == "TORO" else {"lw": 1.3}
        ax.plot(run.seconds, run.energy, marker=".", ms=3, label=run.label, **style)
    ax.axhline(r.optimum, color="gray", ls="--", lw=0.8, label="optimum (exact mode)")
    ax.set_yscale("log")
    ax.set_xlabel("solver time (s), energy measured after each pass")
    ax.set_ylabel("energy per constraint")
    ax.set_title(f"Fig. 5 re-drawn on {r.name} ({r.nodes} poses, {r.edges} constraints)",
                 fontsize=10)
    ax.grid(which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out = ctx.plots / f"hessians_energy_{r.name}.png"
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return ctx.link(out)


def _final(r: GraphResult, label: str) -> float | None:
    run = next((x for x in r.runs if x.label == label), None)
    return None if run is None else run.energy[-1]


def _reach(run: Run, target: float) -> float | None:
    """Seconds at which ``run`` first gets within ``target`` (None: never)."""
    for s, e in zip(run.seconds, run.energy, strict=True):
        if e <= target:
            return s
    return None


def checks(results: list[GraphResult]) -> list[str]:
    out = []
    for r in results:
        toro = _final(r, "TORO")
        if toro is None:
            continue
        best_h2o = min(_final(r, _label(d)) or np.inf for d in D_MAX)
        d200 = _final(r, "D_max=200")
        toro_run = next(x for x in r.runs if x.label == "TORO")
        h_run = next(x for x in r.runs if x.label == "D_max=200")
        t_h = _reach(h_run, toro)
        out.append(
            f"{r.name}: final energy per constraint H₂O D_max=200 {_g(d200)}, best D_max "
            f"{_g(best_h2o)}, TORO {_g(toro)} (after {toro_run.seconds[-1]:.1f} s), optimum "
            f"{_g(r.optimum)}: TORO / H₂O = {toro / best_h2o:.2f} (the paper: ≈10 on Valencia, "
            f"2.062 / 1.596 = 1.29 on Manhattan); H₂O D_max=200 reaches TORO's final energy "
            + (f"after {t_h:.2f} s" if t_h is not None else "never in its passes") + ".")
        out.append(f"{r.name}: dog-leg RMS TORO {_g(toro_run.dogleg_deg)}°, H₂O D_max=200 "
                   f"{_g(h_run.dogleg_deg)}°, optimum {_g(r.optimum_dogleg_deg)}° (the paper "
                   "shows TORO's poses turned off their path on Paris, Fig. 3e, and H₂O's "
                   "not, 3f).")
        times = {x.label: x for x in r.runs if x.per_edge_s is not None}
        ratio = (float(np.mean(times["D_max=200"].per_edge_s))  # type: ignore[arg-type]
                 / toro_run.per_edge_mean_s) if toro_run.per_edge_mean_s else None
        if ratio is not None:
            out.append(f"{r.name}: H₂O D_max=200 costs {ratio:.0f}× TORO per constraint (the "
                       "paper: 33×); its largest single relaxation "
                       f"{float(np.max(times['D_max=200'].per_edge_s)) * 1e3:.1f} ms, D_max=∞ "
                       f"{float(np.max(times['D_max=∞'].per_edge_s)) * 1e3:.1f} ms "
                       "(the paper: 137 ms and 3.58 s on Valencia's 1161-node paths).")
    return out


PROTOCOL = """\
Protocol and its differences from the paper's:

- **Graphs.** Valencia and Paris are Google Street View graphs and not public. The
  paper's Manhattan world is Olson's (5598 edges); ours is the public M3500 file of the same
  3500-pose world (5453 edges, Carlone's version, with its own information matrices), so
  its energies are on another scale than the paper's 1.596 / 2.062. kitti_00 stands in for
  Valencia (an urban drive with few loop closures and long paths){city}.
- **Solvers.** H₂O: the paper's Algorithm 1 from the tree initialization, {passes} passes,
  τ₀ = 1 decaying 0.99 per pass, no GPS edges (as Fig. 5). TORO: `h2o_slam/baselines/toro.py` (a
  colleague's Python/numba implementation of Grisetti et al. 2007, not Google's C++ TORO the
  paper ran), {toro} iterations from the same tree initialization.
- **Times.** Wall seconds of the solver alone (χ² evaluation excluded), one process, this
  2-core machine; the paper's are C++ on its own machine. H₂O's per-constraint times are
  each `relax` call timed on its own over all passes; TORO's are one compiled pass over all
  edges divided by the edge count (its largest single constraint is not measurable that
  way). Each H₂O relaxation is a Python call into compiled kernels (20–30 µs each here, per
  the table), TORO's pass one compiled loop over all edges: that favours TORO in Table I.
- **Not re-run here:** Table II's smallest non-diverging D_max and the noisified graphs of
  Fig. 8 are the thesis' Table 3.1 and Fig. 3.12 (their own sections of this file). Fig. 3's
  GPS runs need Google's graphs with GPS, which are not public: a synthetic Manhattan world
  with GPS stands in."""


def run_line(ctx: Context) -> str:
    """When and how this section was made (the file's header may be older)."""
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return f"Made {now} by `{command(ctx.repo)}`" + (", quick subset." if ctx.quick else ".")

def run(ctx: Context) -> str:
    quick = ctx.quick
    passes = 5 if quick else 20
    toro_iterations = 30 if quick else 100
    results, missing = [], []
    for name, stem, variant in GRAPHS:
        if quick and name not in QUICK_GRAPHS:
            continue
        path = ctx.graph(stem)
        if path is None:
            missing.append(name)
            continue
        graph = read_g2o(path)
        if variant is not None:
            graph = with_variant(graph, variant)
        results.append(bench_graph(name, graph, passes, toro_iterations))
    if not results:
        return "No graph found in the data folder; nothing was run.\n"
    city = "" if quick else "; city10000 is a larger loop-rich city"
    parts = [run_line(ctx), "", PROTOCOL.format(passes=passes, toro=toro_iterations, city=city),
             ""]
    if missing:
        parts.append("Missing here: " + ", ".join(missing) + ".\n")
    if quick:
        parts.append("Quick subset: manhattan (both variants) only, 5 passes, 30 TORO "
                     "iterations.\n")
    parts += ["**Table I** (time per constraint; seed: Valencia):", "", table1(results), "",
              "**Energy per constraint at the end** (seed, Manhattan: H₂O 1.596, TORO 2.062; "
              "Fig. 5, Valencia: H₂O about ten times below TORO):", "", energy_table(results),
              "", "**Dog-leg** (Fig. 2 / 3e): RMS angle (deg) between each odometry step's "
              f"measured and solved direction of travel (steps over {DOGLEG_MIN_STEP_M} m):",
              "", dogleg_table(results), "",
              "**Table II's columns** for the graphs run:", "", table2(results), "",
              "Measured against the paper's claims:", ""]
    parts += [f"- {line}" for line in checks(results)]
    parts += ["", gps_text(gps_experiment(passes, 1000 if quick else 3500)), ""]
    long_path = None if quick else ctx.graph(LONG_GRAPH)
    long_ratio = None
    if long_path is not None:
        text, long_ratio = long_run_text(read_g2o(long_path), LONG_GRAPH)
        parts += [text, ""]
    for r in results:
        parts += [plot_energy(r, ctx), ""]
    parts.append(summary_verdict(results, long_ratio))
    return "\n".join(parts) + "\n"


def summary_verdict(results: list[GraphResult], long_ratio: float | None = None) -> str:
    """From the measurements: does H₂O end below TORO, and by how much."""
    pairs = [(r.name, min(_final(r, _label(d)) or np.inf for d in D_MAX), _final(r, "TORO"))
             for r in results]
    pairs = [(n, h, t) for n, h, t in pairs if t is not None]
    if not pairs:
        return verdict("not reproduced", "no TORO baseline was available to compare with")
    below = [n for n, h, t in pairs if h < t]
    ratios = ", ".join(f"{n} {t / h:.2f}×" for n, h, t in pairs)
    legs = [(r.name, next(x for x in r.runs if x.label == "D_max=200").dogleg_deg,
             next(x for x in r.runs if x.label == "TORO").dogleg_deg)
            for r in results if _final(r, "TORO") is not None]
    straighter = [n for n, h, t in legs if h is not None and t is not None and h < t]
    dog = (f"; H₂O's dog-leg is smaller than TORO's on {len(straighter)} of {len(legs)} "
           f"graphs ({', '.join(straighter) or 'none'})")
    if len(below) == len(pairs):
        word = "reproduced in shape"
        why = (f"H₂O ends below TORO on every graph (TORO / H₂O energy: {ratios}; the paper: "
               "1.29× on Manhattan, ≈10× on Valencia) and per constraint costs more than "
               "TORO but stays in real-time bounds with D_max, as Table I" + dog
               + "; absolute numbers are not comparable (other graphs, Python against C++)")
    else:
        word = "not reproduced"
        above = [n for n, h, t in pairs if h >= t]
        why = (f"H₂O ends below TORO on {len(below)} of {len(pairs)} graphs (TORO / H₂O "
               f"energy: {ratios}; the paper: 1.29× on Manhattan, ≈10× on Valencia): on "
               f"{', '.join(above)} TORO ends lower, so the Valencia-like claim of Fig. 5 "
               "does not carry over to our stand-in"
               + (f" (after {LONG_PASSES} passes H₂O is still {long_ratio:.2f}× TORO's "
                  f"{LONG_TORO}-iteration energy on {LONG_GRAPH}: H₂O plateaus above TORO, "
                  "it does not merely start slower)" if long_ratio is not None else "")
               + dog)
    return verdict(word, why)
