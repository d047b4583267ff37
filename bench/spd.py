"""Benchmark: sparse SPD factorizations on the systems LAGO and exact mode solve.

    .venv/bin/python bench/spd.py [--data DIR] [--graphs NAME ...] [--repeats R]
                                  [--results FILE | --no-results]

For every ``*.g2o`` in ``--data`` (default ``$H2O_POSEGRAPHS``; neither: exit 2; a missing
folder is reported and the script exits 0), two matrices:

- LAGO's phase-3 matrix ``Ω_x`` (planar graphs; ``lago(graph).information``), solved once:
  what LAGO pays (ordering, symbolic analysis and numeric factorization, then the solve);
- exact mode's ``H = JᵀJ`` at the tree initialization
  (``h2o_slam.core.exact.ExactSystem.normal_equations``),
  refactorized with the kept symbolic analysis: what each Gauss–Newton iteration pays.

Every backend of :mod:`h2o_slam.core.spd` that is installed is timed, fresh and (for exact
mode) refactorized, median of ``--repeats`` after a warm-up. The table goes to stdout and
replaces the section ``## Sparse factorizations (bench/spd.py)`` of ``bench/RESULTS.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from results_md import add_graph_arguments, command, publish, results_path, revision, select_graphs

from h2o_slam.core import spd
from h2o_slam.core.exact import ExactSystem
from h2o_slam.core.lago import lago
from h2o_slam.core.modes import build_solver
from h2o_slam.io.g2o import read_g2o

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Sparse factorizations (bench/spd.py)"


def median_ms(fn: Callable[[], Any], repeats: int) -> float:
    """Median wall time of ``fn()`` in ms over ``repeats`` runs after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def time_matrix(H: Any, repeats: int) -> dict[str, tuple[float, float]]:
    """Per backend: (fresh factorization + solve ms, refactorization + solve ms)."""
    U = spd.upper(H)
    g = np.random.default_rng(0).standard_normal(U.shape[0])
    out = {}
    for method in spd.METHODS[1:]:
        if not spd.available(method):
            continue
        fresh = median_ms(
            lambda m=method: spd.SPDFactor(U.indptr, U.indices, m).solve(U.data, g), repeats)
        kept = spd.SPDFactor(U.indptr, U.indices, method)
        again = median_ms(lambda k=kept: k.solve(U.data, g), repeats)
        out[method] = (fresh, again)
    return out


def bench_graph(path: Path, repeats: int) -> list[tuple[str, str, int, int, dict]]:
    """Rows ``(graph, matrix, size, nnz, times)`` of one graph."""
    graph = read_g2o(path)
    rows = []
    if graph.planar:
        omega = sp.csc_matrix(lago(graph).information)
        rows.append((path.stem, "LAGO Ω_x", omega.shape[0], omega.nnz,
                     time_matrix(omega, repeats)))
    solver, _ = build_solver(graph)
    H, _, _ = ExactSystem(solver).normal_equations()
    rows.append((path.stem, "exact JᵀJ", H.shape[0], H.nnz, time_matrix(H, repeats)))
    print(f"spd.py: {path.stem} done", file=sys.stderr, flush=True)
    return rows


def render(rows: list[tuple[str, str, int, int, dict]], repeats: int) -> str:
    methods = [m for m in spd.METHODS[1:] if spd.available(m)]
    head = ("| graph | matrix | size | nnz | "
            + " | ".join(f"{m} fresh ms" for m in methods) + " | "
            + " | ".join(f"{m} refactor ms" for m in methods) + " |")
    lines = [head, "| " + " | ".join(["---"] * (4 + 2 * len(methods))) + " |"]
    for name, matrix, size, nnz, times in rows:
        fresh = [f"{times[m][0]:.3g}" for m in methods]
        again = [f"{times[m][1]:.3g}" if m != "splu" else "—" for m in methods]
        lines.append(f"| {name} | {matrix} | {size} | {nnz} | " + " | ".join(fresh + again)
                     + " |")
    versions = []
    for pkg in ("numpy", "scipy", "cvxopt", "qdldl"):
        try:
            versions.append(f"{pkg} {metadata.version(pkg)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{pkg} not installed")
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return "\n".join([
        SECTION, "", f"Command (from the repo root): `{command(REPO)}`", "",
        f"Date: {when}. Machine: {platform.machine()}, nproc {os.cpu_count()}, Python "
        f"{platform.python_version()}, {', '.join(versions)}, repo at {revision(REPO)}. "
        "Timings are indicative (shared machine, 2 cores).", "", *lines, "",
        "Notes:", "",
        f"- Median of {repeats} runs after a warm-up, each a factorization and one solve of a "
        "random right-hand side. \"fresh\": ordering, symbolic analysis and numeric "
        "factorization (what LAGO pays once per matrix); \"refactor\": a numeric "
        "factorization with the symbolic analysis kept (`h2o_slam.core.spd.SPDFactor`), what "
        "each exact-mode iteration and damping retry pays. SuperLU keeps nothing.",
        "- `cholmod` is CHOLMOD from cvxopt's wheel (supernodal, AMD, OpenBLAS), `qdldl` "
        "OSQP's LDLᵀ (AMD), `splu` SuperLU in symmetric mode with MMD on Aᵀ+A.",
        "- Exact mode's matrix is taken at the tree initialization of `h2o-solve --mode "
        "exact`; its pattern is the one every iteration uses.",
    ]) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_graph_arguments(parser)
    parser.add_argument("--repeats", type=int, default=7,
                        help="timed runs per backend (median; default 7)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be ≥ 1")
    paths = select_graphs("spd.py", args.data, args.graphs)
    if isinstance(paths, int):
        return paths
    rows = [row for p in paths for row in bench_graph(p, args.repeats)]
    publish(render(rows, args.repeats), results_path(args), SECTION)
    return 0


if __name__ == "__main__":
    sys.exit(main())
