"""Thesis Table 3.1: the smallest D_max that does not diverge on each graph, at τ₀ = 1, with
the graph's nodes, edges, loop edges and largest domain (max d)."""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from h2o_slam.core.graph import PoseGraph
from h2o_slam.core.warmup import warm_up
from h2o_slam.io.g2o import read_g2o
from repro.context import Context, verdict
from repro.thesis_common import Trace, TreeStats, num, offline_trace, table, tree_stats

TITLE = "Thesis Table 3.1: smallest D_max that does not diverge"

#: The thesis' Table 3.1 (dataset, nodes, edges, loop edges, max d, D_max).
SEED_ROWS = [
    ("“Manhattan world”", 3500, 5598, 2099, 184, 30),
    ("Valencia w/o GPS", 15031, 15153, 122, 1161, 40),
    ("Valencia w/GPS", 15031, 15440, 409, 1834, 90),
    ("Paris1 w/o GPS", 27093, 27716, 590, 3599, 190),
    ("Paris1 w/GPS", 27093, 28943, 1817, 3605, 200),
    ("Paris2 w/o GPS", 41957, 55392, 13384, 701, 150),
    ("Paris2 w/GPS", 41957, 56109, 13878, 802, 200),
]
#: D_max values tried, from the largest below the graph's max d downwards.
LADDER = [2, 3, 5, 10, 15, 20, 30, 40, 50, 75, 100, 150, 200, 300, 500, 1000]
PASSES = 10
#: A run diverges when χ² rises from one pass to the next by more than this fraction after
#: the first pass (oscillation instead of descent), is not finite, or ends above
#: ``WORSE_THAN_INF`` times the D_max = ∞ run's final χ².
RISE = 0.01
WORSE_THAN_INF = 2.0
GRAPHS = ["manhattan", "intel", "CSAIL", "MIT", "city10000", "kitti_00", "tinyGrid3D",
          "smallGrid3D", "sphere2500", "parking-garage"]
QUICK_GRAPHS = ["manhattan", "intel", "smallGrid3D"]


@dataclass
class Search:
    """One graph's ladder: the runs made (D_max → trace) and the answer."""

    name: str
    stats: TreeStats
    reference: Trace
    runs: dict[int, Trace]
    reasons: dict[int, str]
    smallest: int | None  # None: even the largest ladder value below max d diverged


def diverges(trace: Trace, reference: float) -> str:
    """Why ``trace`` diverged (empty: it did not)."""
    c = np.array(trace.chi2)
    if not np.all(np.isfinite(c)):
        return "χ² not finite"
    rises = np.flatnonzero(c[2:] > (1.0 + RISE) * c[1:-1])
    if len(rises):
        k = int(rises[0]) + 2
        return f"χ² rose at pass {k} ({c[k - 1]:.3g} → {c[k]:.3g})"
    if c[-1] > WORSE_THAN_INF * reference:
        return f"ends at {c[-1] / reference:.3g}× the D_max = ∞ run"
    return ""


def search(name: str, graph: PoseGraph) -> Search:
    """Run D_max = ∞, then the ladder downwards from below max d until a run diverges."""
    stats = tree_stats(graph)
    print(f"thesis_dmax: {name} (max d {stats.max_d})", file=sys.stderr)
    reference = offline_trace(graph, None, PASSES)
    runs, reasons = {}, {}
    smallest: int | None = None
    for d in sorted((d for d in LADDER if d < stats.max_d), reverse=True):
        runs[d] = offline_trace(graph, d, PASSES)
        reasons[d] = diverges(runs[d], reference.final)
        if reasons[d]:
            break
        smallest = d
    if smallest is None and not runs:
        smallest = stats.max_d  # no ladder value below max d: every update is whole
    return Search(name, stats, reference, runs, reasons, smallest)


def run(ctx: Context) -> str:
    """Table 3.1 on the public graphs (quick: manhattan, intel, smallGrid3D)."""
    warm_up()
    results, missing = [], []
    for name in QUICK_GRAPHS if ctx.quick else GRAPHS:
        path = ctx.graph(name)
        if path is None:
            missing.append(name)
            continue
        results.append(search(name, read_g2o(path)))
    return _report(ctx, results, missing)


def _answer(s: Search) -> str:
    if s.smallest is None:
        below = min(s.runs)
        return f"> {below} (all ladder values below max d diverged)"
    tried = [d for d in s.runs if s.reasons[d]]
    if not tried:
        return f"≤ {s.smallest} (none of the ladder diverged)"
    return str(s.smallest)


def _report(ctx: Context, results: list[Search], missing: list[str]) -> str:
    seed = table(["dataset", "nodes", "edges", "loop edges", "max d", "D_max"],
                 [[str(c) for c in row] for row in SEED_ROWS])
    rows, detail = [], []
    for s in results:
        st = s.stats
        diverged = [d for d in s.runs if s.reasons[d]]
        first = (f"{diverged[0]}: {s.reasons[diverged[0]]}" if diverged else "—")
        rows.append([s.name, str(st.nodes), str(st.edges), str(st.loop_edges), str(st.max_d),
                     _answer(s), first, num(s.reference.final / st.edges),
                     num(s.runs[s.smallest].final / st.edges)
                     if s.smallest in s.runs else "—"])
        detail.append(f"{s.name}: " + ", ".join(
            f"{d}→{num(s.runs[d].final / st.edges, '.3g')}{'✗' if s.reasons[d] else ''}"
            for d in s.runs))
    ours = table(["graph", "nodes", "edges", "loop edges", "max d", "smallest D_max",
                  "first divergence (D_max: why)", f"χ²/edge, D_max = ∞, {PASSES} passes",
                  "χ²/edge at the smallest D_max"], rows)
    out = [
        "Seed: Grimes 2012, Table 3.1 (at τ₀ = 1; \"not hard minimums, as divergence may "
        "also be avoided by lowering the initial temperature\"):\n",
        seed,
        "Protocol here: H₂O offline from the tree initialization, τ₀ = 1 (×0.99 a pass), "
        f"{PASSES} passes (the thesis' solved maps use 10), D_max from the ladder "
        f"{', '.join(map(str, LADDER))} tried downwards from the largest value below the "
        "graph's max d, stopping at the first that diverges. *Diverges* (the thesis gives "
        "no criterion; ours): χ² rises by more than "
        f"{RISE:.0%} from one pass to the next after the first pass, is not finite, or ends "
        f"above {WORSE_THAN_INF:g}× the D_max = ∞ run's χ² after the same passes. Loop "
        "edges: edges with more than two nodes in their tree path (domain ≥ 2); max d: the "
        "largest domain, on H₂O's breadth-first tree. The answer is the smallest ladder "
        "value above the first divergence (a ladder, not a bisection: between two rungs "
        "the true threshold is unknown).\n",
        ours,
        "Each run's final χ²/edge by D_max (✗: diverged):\n\n"
        + "\n".join(f"- {line}" for line in detail) + "\n",
    ]
    if missing:
        out.append(f"Missing graphs (skipped): {', '.join(missing)}.\n")
    out.append(
        "Differences: Valencia and Paris are not public; Manhattan is the only graph in both "
        "tables. Ours is the g2o distribution's copy (5 453 edges, where the thesis lists "
        "5 598).\n")
    man = next((s for s in results if s.name == "manhattan"), None)
    if man is None:
        out.append(verdict("not reproduced", "manhattan.g2o is missing."))
        return "\n".join(out)
    st = man.stats
    same_d = st.max_d == 184
    answer = man.smallest
    out.append(
        f"Manhattan: ours {st.nodes} nodes, {st.edges} edges, {st.loop_edges} loop edges, "
        f"max d {st.max_d} (thesis 3500 / 5598 / 2099 / 184"
        + (": the same tree depth" if same_d else "") + f"); smallest D_max {_answer(man)} "
        "(thesis 30).\n")
    if answer is not None and 20 <= answer <= 40:  # within a rung of the thesis' 30
        word, why = ("reproduced", f"on manhattan the smallest non-diverging D_max is "
                     f"{answer} against the thesis' 30 (ladder rungs around it), with the "
                     "same max d; too small a D_max makes χ² oscillate instead of descend")
    elif answer is not None:
        word, why = ("reproduced in shape", f"too small a D_max does make H₂O oscillate, but "
                     f"on manhattan the threshold is {answer}, not the thesis' 30 (another "
                     "copy of the graph, and our divergence criterion is our own)")
    else:
        word, why = ("not reproduced", "every D_max below max d diverged on manhattan")
    out.append(verdict(word, why + "."))
    return "\n".join(out)
