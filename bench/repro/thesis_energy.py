"""Thesis Fig. 3.3/3.11 and §3.4.2's Manhattan numbers: energy per constraint against time for
H₂O offline at D_max = 75, 100, 150, 200, ∞, online H₂O and TORO."""

from __future__ import annotations

import sys
import time

import numpy as np

from h2o_slam.baselines.toro import solve_toro
from h2o_slam.core.graph import PoseGraph
from h2o_slam.core.modes import solve_exact, solve_online
from h2o_slam.core.online import OnlineConfig
from h2o_slam.core.warmup import warm_up
from h2o_slam.io.g2o import read_g2o
from h2o_slam.io.synthetic import grid3d, manhattan
from repro.context import Context, verdict
from repro.thesis_common import Trace, num, offline_trace, table

TITLE = "Thesis Fig. 3.3 / 3.11 and the Manhattan figure: energy per constraint against time"

D_MAXES: list[int | None] = [75, 100, 150, 200, None]
#: The thesis' Manhattan numbers (§3.4.2): average energy per constraint at convergence.
SEED_H2O, SEED_TORO = 1.596, 2.062
#: D_max of the thesis' solved maps (Fig. 3.9: "10 iterations with D_max = 200").
THESIS_D_MAX, THESIS_PASSES = 200, 10


def _online_trace(graph: PoseGraph, passes: int) -> Trace:
    """Online H₂O (poses one by one, dynamic tree balancing, D_max = 200, no exact solves
    beside it: H₂O's updates alone, as in the thesis), then ``passes - 1`` offline passes.
    The first point is the end of the stream."""
    result = solve_online(graph, passes=passes - 1,
                          online=OnlineConfig(d_max=THESIS_D_MAX, background="off"),
                          trace_every=graph.num_nodes)
    trace = Trace("online H₂O (D_max = 200): stream, then passes")
    for spent, value in result.chi2_trace[1:]:  # [0] is pose 0's callback (no edge yet)
        trace.seconds.append(spent)
        trace.chi2.append(value)
    return trace


def _toro_trace(graph: PoseGraph, iterations: int) -> Trace:
    _, history = solve_toro(graph, iterations)
    return Trace("TORO", list(history.seconds), list(history.chi2))


def _plot(ctx: Context, name: str, m: int, traces: list[Trace], optimum: float) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.8))
    blues = plt.get_cmap("viridis")(np.linspace(0.0, 0.85, len(D_MAXES)))
    styles = {"TORO": dict(color="tab:red", marker=".", ms=3, lw=1.2),
              "online": dict(color="tab:green", marker="s", ms=4, ls="--", lw=1.4)}
    k = 0
    for tr in traces:
        y = np.array(tr.chi2) / m
        x = np.array(tr.seconds)
        if tr.label == "TORO":
            style = styles["TORO"]
        elif tr.label.startswith("online"):
            style = styles["online"]
        else:
            style = dict(color=blues[k], marker="o", ms=3, lw=1.2)
            k += 1
        ax.plot(x, y, label=tr.label, **style)
    ax.axhline(optimum / m, color="k", ls=":", lw=1, label="exact optimum")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("solver time (s), cumulative; each point one loop through all edges")
    ax.set_ylabel("energy per constraint (χ² / edges)")
    ax.set_title(f"{name}: energy per constraint against time")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    png = ctx.plots / f"thesis_energy_{name}.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return ctx.link(png)


def _at_time(tr: Trace, seconds: float) -> float:
    """χ² of ``tr`` at the last point not later than ``seconds`` (its start if none)."""
    idx = np.searchsorted(np.array(tr.seconds), seconds, side="right") - 1
    return tr.chi2[max(int(idx), 0)]


def _graph_section(ctx: Context, name: str, graph: PoseGraph, passes: int,
                   toro_iterations: int) -> tuple[str, dict[str, float]]:
    m = graph.num_edges
    print(f"thesis_energy: {name}", file=sys.stderr)
    traces = [offline_trace(graph, d, passes) for d in D_MAXES]
    traces.append(_online_trace(graph, passes))
    traces.append(_toro_trace(graph, toro_iterations))
    begin = time.perf_counter()
    exact = solve_exact(graph)
    exact_s = time.perf_counter() - begin
    optimum = exact.chi2_final
    link = _plot(ctx, name, m, traces, optimum)
    h2o_end = max(tr.seconds[-1] for tr in traces[:-1])
    toro = traces[-1]
    rows = []
    for tr in traces:
        rows.append([tr.label, str(len(tr.chi2) - 1), num(tr.seconds[-1], ".3g"),
                     num(tr.chi2[0] / m), num(tr.final / m), num(tr.final / optimum, ".3g"),
                     num(_at_time(tr, h2o_end) / m) if tr is toro else "—"])
    rows.append(["exact (Gauss–Newton, this package)", str(len(exact.chi2_per_pass)),
                 num(exact_s, ".3g"), num(exact.chi2_initial / m), num(optimum / m), "1",
                 "—"])
    body = (f"**{name}** ({graph.num_nodes} nodes, {m} edges); passes = loops through all "
            f"edges (TORO: iterations).\n\n"
            + table(["solver", "passes", "time (s)", "start χ²/edge", "final χ²/edge",
                     "final / optimum", f"TORO at {h2o_end:.2g} s (H₂O's longest run)"], rows)
            + f"\n{link}\n")
    by = {tr.label: tr for tr in traces}
    h2o_thesis = by["D_max = 200"]
    toro_100 = toro.chi2[min(100, len(toro.chi2) - 1)]
    numbers = {"m": m, "optimum": optimum,
               "h2o_10": h2o_thesis.chi2[min(THESIS_PASSES, len(h2o_thesis.chi2) - 1)],
               "h2o_final": h2o_thesis.final, "toro_100": toro_100, "toro_final": toro.final,
               "toro_at_h2o": _at_time(toro, h2o_thesis.seconds[-1]),
               "h2o_inf_final": by["D_max = ∞"].final,
               "online_final": traces[-2].final, "online_first": traces[-2].chi2[0],
               "offline200_first": h2o_thesis.chi2[1]}
    return body, numbers


#: Carlone et al. 2014, Table 1, variant I (identity information): (graph, Carlone's name,
#: Gauss–Newton objective, released TORO's objective).
CARLONE_I = [("CSAIL", "CSAIL", 0.107, 0.118), ("intel", "INTEL", 0.789, 1.17),
             ("manhattan", "M3500", 3.02, 5.42)]


def _carlone_check(ctx: Context) -> str:
    """TORO (100 iterations, the released code's default) and the exact optimum on the
    graphs of Carlone's Table 1 with identity information, beside the released TORO's
    numbers there."""
    rows = []
    for stem, theirs, gn, toro in CARLONE_I:
        path = ctx.graph(stem)
        if path is None:
            continue
        graph = read_g2o(path)
        graph.info[:] = 0.0
        graph.info[:, [0, 1, 5], [0, 1, 5]] = 1.0
        _, history = solve_toro(graph, 100)
        best = solve_exact(graph).chi2_final
        rows.append([f"{stem} ({theirs})", f"{gn:.3g}", f"{toro:.3g}", f"{toro / gn:.3g}",
                     num(best), num(history.chi2[-1]), num(history.chi2[-1] / best, ".3g")])
    return ("TORO check on the graphs of Carlone et al. 2014, Table 1, variant I (every "
            "information matrix the identity; objective Σ eᵀe; TORO 100 iterations, the "
            "released code's default):\n\n"
            + table(["graph", "GN (Carlone)", "released TORO (Carlone)", "TORO / GN (Carlone)",
                     "exact (ours)", "TORO (ours)", "TORO / exact (ours)"], rows))


def run(ctx: Context) -> str:
    """Energy per constraint against time on manhattan (the thesis' graph), intel and
    city10000 (quick: manhattan and intel)."""
    warm_up()
    # Compile (or load) both TORO variants' kernels before any clock runs.
    solve_toro(manhattan(30, seed=0).graph, 2)
    solve_toro(grid3d(30, seed=0).graph, 2)
    passes, toro_iterations = (10, 100) if ctx.quick else (30, 1000)
    names = ["manhattan", "intel"] if ctx.quick else ["manhattan", "intel", "city10000",
                                                       "sphere2500"]
    parts, numbers, missing = [], {}, []
    for name in names:
        path = ctx.graph(name)
        if path is None:
            missing.append(name)
            continue
        graph = read_g2o(path)
        # TORO's 3-D iterations cost ~10× its planar ones; 300 still outlast H₂O's passes.
        iterations = toro_iterations if graph.planar or ctx.quick else 300
        body, nums = _graph_section(ctx, name, graph, passes, iterations)
        parts.append(body)
        numbers[name] = nums
    return _report(ctx, passes, toro_iterations, parts, numbers, missing,
                   _carlone_check(ctx))


def _report(ctx: Context, passes: int, toro_iterations: int, parts: list[str],
            numbers: dict[str, dict[str, float]], missing: list[str], check: str) -> str:
    out = [
        "Seed: Grimes 2012, Fig. 3.3/3.11 (Valencia, 15 031 poses: H₂O at D_max = 75 … ∞ "
        "reaches a log-energy per constraint an order of magnitude below TORO's, sooner; "
        "online H₂O's curve is offline's shifted right by the tree balancing) and §3.4.2: on "
        f"Olson's Manhattan world H₂O converges to **{SEED_H2O}** per constraint, TORO to "
        f"**{SEED_TORO}** (ratio {SEED_TORO / SEED_H2O:.2f}).\n",
        "Protocol here: every solver starts from the tree initialization (tree edges' "
        "measurements composed down the breadth-first tree, thesis §3.4.2 — TORO's own "
        f"start too); H₂O offline runs {passes} passes at τ₀ = 1 (×0.99 a pass), edges by "
        "root depth; online H₂O feeds the poses one by one (dynamic balancing, D_max = 200, "
        f"no background exact solves), then {passes - 1} offline passes; TORO "
        f"(`h2o_slam/baselines/toro.py`) runs {toro_iterations} iterations (3-D: see below). "
        "Energy = χ² = Σ eᵀΩe (`h2o_slam.core.graph.chi2`) over the number of edges; time = "
        "solver time only (set-up included, χ² evaluation excluded); each point is one loop "
        "through all edges. The exact optimum (this package's Gauss–Newton) is the dotted "
        "line.\n",
        "Differences: Valencia and Paris are not public, so the Valencia figure is re-run on "
        "manhattan, intel, city10000 (Olson's M10000-class graph) and, in full runs, "
        "sphere2500 (3-D). Our manhattan.g2o has "
        "5 453 edges and the information of the g2o distribution (Carlone's P_s-like "
        "variant: its optimum χ² 3 549 matches Carlone's Table 1 Gauss–Newton 3.55E+03), "
        "where the thesis' copy has 5 598 edges and its own weights, so per-constraint "
        "values are not comparable across copies in absolute terms — only the ordering and "
        "ratios are. TORO is our re-implementation (`h2o_slam/baselines/toro.py`: the RSS 2007 "
        "method on planar graphs, its IROS 2007 3-D extension on sphere2500, 300 iterations "
        "there), checked against Carlone's Table 1 below.\n",
    ]
    if missing:
        out.append(f"Missing graphs (skipped): {', '.join(missing)}.\n")
    out += parts
    man = numbers.get("manhattan")
    if man is None:
        out.append(verdict("not reproduced", "manhattan.g2o is missing; nothing to compare."))
        return "\n".join(out)
    m = man["m"]
    rows = [
        ["H₂O (thesis: converged; ours: D_max = 200, 10 passes)", f"{SEED_H2O}",
         num(man["h2o_10"] / m)],
        *([[f"H₂O D_max = 200 after {passes} passes", "—", num(man["h2o_final"] / m)]]
          if passes != THESIS_PASSES else []),
        ["TORO (thesis: converged; ours: 100 iterations, TORO's default)", f"{SEED_TORO}",
         num(man["toro_100"] / m)],
        *([[f"TORO after {toro_iterations} iterations", "—", num(man["toro_final"] / m)]]
          if toro_iterations != 100 else []),
        ["TORO / H₂O", f"{SEED_TORO / SEED_H2O:.2f}",
         num(man["toro_100"] / man["h2o_10"], ".3g") + " (100 it. / 10 passes); "
         + num(man["toro_final"] / man["h2o_final"], ".3g") + " (both at the end)"],
        ["exact optimum", "—", num(man["optimum"] / m)],
    ]
    out.append("**Manhattan, seed and ours** (energy per constraint):\n\n"
               + table(["", "thesis", "ours"], rows))
    intel = numbers.get("intel")
    out.append(
        "TORO check against its published behaviour: Carlone et al. 2014, Table 1, ran the "
        "released TORO (default settings, 100 iterations) on M3500 P_s: 2.18E+06 against "
        "Gauss–Newton's 3.55E+03 (615×). Ours after 100 iterations on the same-information "
        f"manhattan: {num(man['toro_100'], '.3g')} against {num(man['optimum'], '.3g')} "
        f"({num(man['toro_100'] / man['optimum'], '.3g')}×): the same order of magnitude."
        + (f" On intel (the Intel Research Lab graph) it ends at "
           f"{num(intel['toro_final'] / intel['optimum'], '.3g')}× the optimum." if intel
           else "") + "\n")
    out.append(check)
    ratio_ours = man["toro_100"] / man["h2o_10"]
    out.append(
        f"Reading: on manhattan H₂O at D_max = 200 reaches {num(man['h2o_10'] / m)} per "
        f"constraint in 10 passes and {num(man['h2o_final'] / m)} after {passes}; TORO "
        f"{num(man['toro_100'] / m)} after 100 iterations and "
        f"{num(man['toro_final'] / m)} after {toro_iterations}; at H₂O's end time TORO "
        f"stands at {num(man['toro_at_h2o'] / m)}. TORO / H₂O: {num(ratio_ours, '.3g')} at "
        f"TORO's default 100 iterations against H₂O's 10 passes, "
        f"{num(man['toro_at_h2o'] / man['h2o_final'], '.3g')} at equal time (H₂O's end), "
        f"{num(man['toro_final'] / man['h2o_final'], '.3g')} with TORO run "
        f"{toro_iterations} iterations "
        f"(thesis: {SEED_TORO / SEED_H2O:.2f}). Neither reaches the thesis' absolute level: "
        f"the optimum of this copy is {num(man['optimum'] / m)} per constraint and H₂O's "
        f"D_max = 200 run stops {num(man['h2o_final'] / man['optimum'], '.3g')}× above it "
        "(H₂O's stochastic fixed point under the 0.99 temperature schedule, thesis §3.5; "
        "this package's exact mode reaches the optimum in a fraction of the time). Online "
        f"H₂O's first point (end of the stream, {num(man['online_first'] / m)}) comes "
        f"later than offline's first pass ({num(man['offline200_first'] / m)}), the "
        "right-shift of Fig. 3.11.\n")
    lines = []
    for name, nums in numbers.items():
        below = nums["h2o_final"] < nums["toro_at_h2o"]
        per = nums["m"]
        lines.append(f"- {name}: H₂O D_max = 200 ends at {num(nums['h2o_final'] / per)}"
                     f" per constraint, TORO at the same time {num(nums['toro_at_h2o'] / per)}"
                     f" and after all its iterations {num(nums['toro_final'] / per)}: "
                     + ("H₂O lower" if below else "**TORO lower**")
                     + f" ({num(nums['toro_at_h2o'] / nums['h2o_final'], '.3g')}× at equal "
                     "time).")
    out.append("Per graph, at equal solver time:\n\n" + "\n".join(lines) + "\n")
    wins = [n for n, v in numbers.items() if v["h2o_final"] < v["toro_at_h2o"]]
    losses = [n for n in numbers if n not in wins]
    shifted = man["online_first"] > man["offline200_first"]
    equal = man["toro_at_h2o"] / man["h2o_final"]
    if man["h2o_final"] < man["toro_final"] and equal > SEED_TORO / SEED_H2O:
        why = (f"on manhattan H₂O descends faster than TORO and ends {num(equal, '.3g')}× "
               f"below it at equal time ({num(man['toro_final'] / man['h2o_final'], '.3g')}× "
               f"after TORO's {toro_iterations} iterations; the thesis: "
               f"{SEED_TORO / SEED_H2O:.2f}×)"
               + (", and online is offline shifted right, as in Fig. 3.11" if shifted else "")
               + "; the absolute 1.596 / 2.062 are not reproduced (a different copy of the "
               "graph, and both stochastic solvers stop far above this copy's optimum)")
        if losses:
            why += (f"; on {', '.join(losses)} TORO ends lower than H₂O's stochastic passes, "
                    "which the thesis does not show")
        out.append(verdict("reproduced in shape", why + "."))
    else:
        out.append(verdict("not reproduced",
                           "on manhattan H₂O does not end below TORO by the thesis' margin."))
    return "\n".join(out)
