"""Benchmark: time per constraint over one offline pass, the thesis' Table 3.2 experiment.

    .venv/bin/python bench/cost.py [--data DIR] [--graphs NAME ...] [--results FILE]

For each graph (default city10000, kitti_00, manhattan) one offline pass — edges by
increasing root depth from the tree initialization, as :func:`h2o_slam.core.modes.offline_pass`
orders them — is run once per solver: a TORO-style update and H₂O's single-edge update
(:meth:`H2OSolver.relax`) with ``d_max`` = 75, 100, 150, 200 and ∞. Every update is timed
on its own; the table gives the average and maximum time per constraint, the average time of
the tree-edge updates (d = 1), the longest domain, and χ² after the pass. The table goes to
stdout and replaces the section ``## Cost per constraint (bench/cost.py)`` of
``bench/RESULTS.md`` (other sections are kept).
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from results_md import add_graph_arguments, command, publish, results_path, revision, select_graphs  # noqa: E402

from h2o_slam.core import geometry as geo  # noqa: E402
from h2o_slam.core import interpolate  # noqa: E402
from h2o_slam.core.errors import H2OError  # noqa: E402
from h2o_slam.core.graph import EdgeKind, PoseGraph  # noqa: E402
from h2o_slam.core.modes import build_solver, offline_order  # noqa: E402
from h2o_slam.core.solver import H2OSolver  # noqa: E402
from h2o_slam.core.warmup import warm_up  # noqa: E402
from h2o_slam.io.g2o import read_g2o  # noqa: E402

SECTION = "## Cost per constraint (bench/cost.py)"
DEFAULT_GRAPHS = ["city10000", "kitti_00", "manhattan"]
#: ``None`` is D_max = ∞; "toro" the TORO-style update.
SOLVERS: list[int | str | None] = ["toro", 75, 100, 150, 200, None]


def toro_update(solver: H2OSolver, edge: int) -> None:
    """A TORO-style update of one relative edge: no linearization and no solve.

    The endpoint that has a chain below the root is moved (by the temperature's share) to
    where the measurement puts it relative to the other endpoint, and the move is spread over
    its chain with :func:`h2o_slam.core.interpolate.distribute_into`, weighted by the compliance
    ``1 / diag(B)`` as TORO weights by its preconditioner: O(d) compositions.
    """
    if solver.kind[edge] != EdgeKind.RELATIVE:
        return
    path = solver.path(edge)
    meas_R, meas_t = solver.meas_R[edge], solver.meas_t[edge]
    fixed, moved = path.a_chain, path.b_chain
    if len(moved) == 0:  # b is the root: move a to b · K⁻¹ instead
        fixed, moved = moved, fixed
        meas_R, meas_t = geo.inverse(meas_R, meas_t)
    tree = solver.tree
    R_f, t_f = _chain_end(tree.R, tree.t, fixed)
    R_p, t_p = _chain_end(tree.R, tree.t, moved[:-1])
    target_R, target_t = geo.compose(R_f, t_f, meas_R, meas_t)
    local_R, local_t = geo.between(R_p, t_p, target_R, target_t)
    end = moved[-1]
    step = np.concatenate([local_t - tree.t[end],
                           geo.so3_log(tree.R[end].T @ local_R)])[None] * solver.temperature
    compliance = interpolate.compliance(np.ascontiguousarray(solver.B[moved]))
    interpolate.distribute_into(tree.R, tree.t, moved, np.array([len(moved) - 1]),
                                np.array([0]), step, compliance)


def _chain_end(R: np.ndarray, t: np.ndarray, chain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(chain) == 0:
        return np.eye(3), np.zeros(3)
    return geo.chain_product(R[chain], t[chain])


@dataclass
class PassCost:
    """Per-constraint times (s) of one offline pass with one solver."""

    solver: str
    times_s: np.ndarray
    domains: np.ndarray
    chi2_after: float

    @property
    def tree_edges_s(self) -> float:
        """Average time of the updates of edges with a domain of one node."""
        ones = self.times_s[self.domains == 1]
        return float(ones.mean()) if len(ones) else float("nan")


@dataclass
class GraphCost:
    """All solvers' passes over one graph."""

    name: str
    nodes: int
    edges: int
    max_domain: int
    mean_domain: float
    passes: list[PassCost]


def _label(d_max: int | str | None) -> str:
    if d_max == "toro":
        return "TORO-style"
    return "D_max = ∞" if d_max is None else f"D_max = {d_max}"


def time_pass(graph: PoseGraph, d_max: int | str | None, repeat: int = 3) -> PassCost:
    """One offline pass from the tree initialization, every update timed on its own; the
    pass is run ``repeat`` times from scratch (the same updates each time) and each update
    keeps its fastest time, so that a time slice lost to another process on the shared
    machine, or a garbage collection, does not pose as the cost of a constraint."""
    runs = [_one_pass(graph, d_max) for _ in range(repeat)]
    times = np.min([r.times_s for r in runs], axis=0)
    return PassCost(runs[0].solver, times, runs[0].domains, runs[0].chi2_after)


def _one_pass(graph: PoseGraph, d_max: int | str | None) -> PassCost:
    solver, _ = build_solver(graph)
    order = offline_order(solver)
    domains = np.array([len(solver.path(e).domain) for e in order])
    times = np.empty(len(order))
    gc.collect()
    gc.disable()
    try:
        _timed_updates(solver, order, d_max, times)
    finally:
        gc.enable()
    solver.end_pass()
    return PassCost(_label(d_max), times, domains, solver.chi2(graph))


def _timed_updates(solver: H2OSolver, order: list[int], d_max: int | str | None,
                   times: np.ndarray) -> None:
    clock = time.perf_counter
    for k, e in enumerate(order):
        if d_max == "toro":
            start = clock()
            toro_update(solver, e)
        elif solver.kind[e] == EdgeKind.POSITION:
            start = clock()
            solver.relax_batch([e])
        else:
            limit = d_max if isinstance(d_max, int) else None
            start = clock()
            solver.relax(e, d_max=limit)
        times[k] = clock() - start


def bench_graph(path: Path, repeat: int = 3) -> GraphCost:
    """Every solver's pass over one graph."""
    graph = read_g2o(path)
    passes = []
    for d_max in SOLVERS:
        print(f"cost.py: {path.stem} {_label(d_max)}", file=sys.stderr)
        passes.append(time_pass(graph, d_max, repeat))
    dom = passes[0].domains
    return GraphCost(path.stem, graph.num_nodes, graph.num_edges, int(dom.max()),
                     float(dom.mean()), passes)


def format_table(results: list[GraphCost]) -> str:
    """The markdown table: one row per graph and solver."""
    head = ("| graph | nodes | edges | mean d | max d | solver | avg µs / constraint | "
            "max ms / constraint | avg µs, tree edges (d = 1) | max ∞ / max this | "
            "χ² after the pass |\n" + "| --- " * 11 + "|\n")
    rows = []
    for g in results:
        worst_inf = max(p.times_s.max() for p in g.passes if p.solver == "D_max = ∞")
        for p in g.passes:
            rows.append(
                f"| {g.name} | {g.nodes} | {g.edges} | {g.mean_domain:.2f} | {g.max_domain} | "
                f"{p.solver} | {1e6 * p.times_s.mean():.1f} | {1e3 * p.times_s.max():.3f} | "
                f"{1e6 * p.tree_edges_s:.1f} | {worst_inf / p.times_s.max():.1f} | "
                f"{p.chi2_after:.6g} |")
    return head + "\n".join(rows)


def targets(results: list[GraphCost]) -> str:
    """The two targets of issue 12, judged on these results."""
    longest = max(results, key=lambda g: g.max_domain)
    by = {p.solver: p for p in longest.passes}
    ratio = by["D_max = ∞"].times_s.max() / by["D_max = 75"].times_s.max()
    tree = np.concatenate([p.times_s[p.domains == 1] for g in results for p in g.passes
                           if p.solver != "TORO-style"])
    tree_us = 1e6 * float(tree.mean())
    return (f"- Longest loop: {longest.name} (d = {longest.max_domain}). Max per constraint "
            f"D_max = ∞ / D_max = 75: {ratio:.1f}× (target ≥ 20×): "
            f"{'met' if ratio >= 20 else 'missed'}.\n"
            f"- Tree-edge update (d = 1), all graphs and H₂O passes: {tree_us:.1f} µs on "
            f"average over {len(tree)} updates (target ≤ 30 µs): "
            f"{'met' if tree_us <= 30 else 'missed'}.\n")


NOTES = """Notes:

- One offline pass per row, from the tree initialization (`build_solver(graph)`), edges by
  increasing root depth (`offline_order`), each update timed alone with `perf_counter`,
  garbage collection off, compiled kernels warmed up before the first pass. The pass is run
  `--repeat` times from scratch (the same updates each time) and each update keeps its
  fastest time: on the shared two-core machine a lost time slice would otherwise pose as a
  constraint's maximum. "max ∞ / max this" divides the D_max = ∞ row's maximum by this
  row's.
- ais2klinik (15 115 poses) is not among the public graphs benchmarked here: city10000, the
  largest of them, stands in for its size, and kitti_00, the longest loop (its longest domain),
  for its long loops.
- TORO-style: no linearization and no solve; one endpoint is moved to where the measurement
  puts it and the move is spread over its chain by the compliance `1 / diag(B)`
  (`bench/cost.py: toro_update`). It is a cost reference, not a solver to compare χ² with.
- Our D_max = ∞ update is O(d) (`h2o_slam.core.hybrid`), not the thesis' O(d²) Givens QR, so the
  ratio of maxima is a ratio of per-node constants, not of d² to d·D_max. On kitti_00's
  d = 1427 edge (planar) both updates share the linearization, `B_c` and the contribution
  store (≈0.05 µs per node); the full update adds the solve (≈0.43 µs per node) and
  applying the step (≈0.12 µs per node), the interpolated one the tree-edge constraints,
  their merge (eq. 3.36–3.38) and the TORO-style distribution (≈0.15 µs per node), plus
  the solve for the D_max kept nodes (≈45 µs at 75).
"""


def render_section(results: list[GraphCost]) -> str:
    """The ``## Cost per constraint`` section of RESULTS.md."""
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    machine = (f"{platform.machine()}, nproc {os.cpu_count()}, Python "
               f"{platform.python_version()}, numpy {np.__version__}, repo at {revision(REPO)}")
    return (f"{SECTION}\n\nCommand (from the repo root): `{command(REPO)}`\n\n"
            f"Date: {when}. Machine: {machine}. Timings are indicative (shared machine).\n\n"
            f"{format_table(results)}\n\nTargets (issue 12):\n\n{targets(results)}\n{NOTES}")


def run(data: Path | None, names: list[str], results: Path | None, repeat: int = 3) -> int:
    """Benchmark ``names`` from ``data``; return an exit code."""
    paths = select_graphs("cost.py", data, names)
    if isinstance(paths, int):
        return paths
    warm_up()
    rows = []
    for path in paths:
        try:
            rows.append(bench_graph(path, repeat))
        except H2OError as err:
            print(f"cost.py: skipping {path.stem}: {err}", file=sys.stderr)
    if not rows:
        return 1
    publish(render_section(rows), results, SECTION)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_graph_arguments(parser, DEFAULT_GRAPHS)
    parser.add_argument("--repeat", type=int, default=3, metavar="N",
                        help="passes per solver; each update keeps its fastest (default 3)")
    args = parser.parse_args(argv)
    return run(args.data, args.graphs, results_path(args), max(1, args.repeat))


if __name__ == "__main__":
    sys.exit(main())
