"""Helpers shared by the thesis experiments (``thesis_energy``, ``thesis_dmax``,
``thesis_noise``): timed offline H₂O passes, tree statistics, markdown tables, plots."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from h2o_slam.core.graph import EdgeKind, PoseGraph
from h2o_slam.core.modes import build_solver, offline_order, offline_pass
from h2o_slam.core.solver import SolverConfig


@dataclass
class Trace:
    """χ² against cumulative solver time (s): index 0 is the start (after set-up)."""

    label: str
    seconds: list[float] = field(default_factory=list)
    chi2: list[float] = field(default_factory=list)
    R: np.ndarray | None = None  # final world poses, when kept
    t: np.ndarray | None = None

    @property
    def final(self) -> float:
        """χ² at the end."""
        return self.chi2[-1]


def offline_trace(graph: PoseGraph, d_max: int | None, passes: int,
                  config: SolverConfig | None = None, label: str = "") -> Trace:
    """H₂O offline (thesis Algorithm 1) from the tree initialization for ``passes`` passes at
    ``d_max``; set-up (tree, start, regularizer) is timed, χ² evaluation is not. A pass whose
    χ² is not finite ends the run (the trace keeps it as ``inf``)."""
    begin = time.perf_counter()
    solver, start = build_solver(graph, config)
    order = offline_order(solver)
    spent = time.perf_counter() - begin
    trace = Trace(label or dmax_label(d_max), [spent], [solver.chi2(graph)])
    for _ in range(passes):
        begin = time.perf_counter()
        with np.errstate(all="ignore"):
            offline_pass(solver, order, d_max)
        spent += time.perf_counter() - begin
        value = solver.chi2(graph)
        trace.seconds.append(spent)
        trace.chi2.append(value if np.isfinite(value) else np.inf)
        if not np.isfinite(value):
            break
    trace.R, trace.t = solver.world_poses()
    return trace


def dmax_label(d_max: int | None) -> str:
    """``D_max = 75`` or ``D_max = ∞``."""
    return "D_max = ∞" if d_max is None else f"D_max = {d_max}"


@dataclass(frozen=True)
class TreeStats:
    """Table 3.1's columns: nodes, edges, loop edges (more than two nodes in their tree
    path, i.e. a domain of two or more), and the largest domain ``max d``."""

    nodes: int
    edges: int
    loop_edges: int
    max_d: int


def tree_stats(graph: PoseGraph) -> TreeStats:
    """Statistics of ``graph`` on H₂O's breadth-first tree (the one offline mode uses)."""
    solver, _ = build_solver(graph, regularizer=False)
    rel = np.flatnonzero(graph.kind == EdgeKind.RELATIVE)
    domains = np.array([len(solver.path(int(e)).domain) for e in rel])
    return TreeStats(graph.num_nodes, graph.num_edges, int(np.sum(domains > 1)),
                     int(domains.max()))


def table(head: list[str], rows: list[list[str]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def num(x: float, fmt: str = ".4g") -> str:
    """A number for a table (``—`` when not finite)."""
    return format(x, fmt) if np.isfinite(x) else "—"
