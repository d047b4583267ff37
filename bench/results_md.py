"""Shared plumbing of the benchmarks: each owns one ``## …`` section of ``bench/RESULTS.md``,
and those over the public pose graphs take the same ``--data/--graphs/--results`` arguments.

The public pose graphs are not in this repository: ``--data DIR`` names their folder, by
default the environment's ``H2O_POSEGRAPHS`` (``bench/README.md`` says where they come from).
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

Row = TypeVar("Row")

REPO = Path(__file__).resolve().parents[1]
DEFAULT_RESULTS = REPO / "bench" / "RESULTS.md"
#: The environment variable naming the folder of the public pose graphs (``--data``'s default).
POSEGRAPHS_ENV = "H2O_POSEGRAPHS"
#: How a recorded command shows ``--data``'s folder (``bench/RESULTS.md`` explains it).
POSEGRAPHS_SHOWN = "$POSEGRAPHS"
#: Where the graphs come from, for the line that says they were not given.
POSEGRAPHS_ORIGIN = ("the standard public pose graphs as .g2o files (intel, manhattan, CSAIL, "
                     "MIT, city10000, kitti_00, sphere2500, parking-garage, smallGrid3D, "
                     "tinyGrid3D, as the SE-Sync project's data/ folder distributes them; "
                     "see bench/README.md)")


def default_data() -> Path | None:
    """``--data``'s default: the folder ``H2O_POSEGRAPHS`` names, or None when it is unset."""
    folder = os.environ.get(POSEGRAPHS_ENV, "")
    return Path(folder) if folder else None


def no_data(prog: str) -> int:
    """Say, on one line, that no folder of graphs was given and how to give one; exit code 2."""
    print(f"{prog}: no pose graphs given: pass --data DIR (or set {POSEGRAPHS_ENV}=DIR), "
          f"DIR holding {POSEGRAPHS_ORIGIN}", file=sys.stderr)
    return 2


def command(repo: Path) -> str:
    """The command line that is running, with paths relative to ``repo`` where they can be
    and ``--data``'s folder shown as ``$POSEGRAPHS`` (it differs from machine to machine)."""
    parts = []
    for p in (Path(sys.executable), Path(sys.argv[0]).resolve()):
        try:
            parts.append(str(p.relative_to(repo)))
        except ValueError:
            parts.append(str(p))
    args: list[str] = []
    rest = iter(sys.argv[1:])
    for arg in rest:
        if arg == "--data":
            args.append(arg)
            if next(rest, None) is not None:
                args.append(POSEGRAPHS_SHOWN)
        elif arg.startswith("--data="):
            args.append(f"--data={POSEGRAPHS_SHOWN}")
        else:
            args.append(arg)
    # $POSEGRAPHS stays a variable for the reader's shell.
    return " ".join(a if POSEGRAPHS_SHOWN in a else shlex.quote(a) for a in [*parts, *args])


def revision(repo: Path) -> str:
    """The repository's short revision, flagging uncommitted changes to ``h2o_slam/``."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo,
                             capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "h2o_slam"], cwd=repo,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return rev + (" (h2o_slam/ with uncommitted changes)" if dirty else "")


def replace_section(path: Path, heading: str, section: str) -> None:
    """Replace the section that starts at the line ``heading`` (up to the next ``## `` line)
    with ``section``, or append it; every other section is kept as it was."""
    text = path.read_text() if path.exists() else "# Benchmark results\n"
    lines = text.splitlines()
    try:
        start = lines.index(heading)
    except ValueError:
        new = text.rstrip("\n") + "\n\n" + section.rstrip("\n") + "\n"
    else:
        end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")),
                   len(lines))
        before, after = "\n".join(lines[:start]), "\n".join(lines[end:])
        new = before.rstrip("\n") + "\n\n" + section.rstrip("\n") + "\n"
        if after:
            new += "\n" + after.rstrip("\n") + "\n"
    path.write_text(new.lstrip("\n"))


def add_graph_arguments(parser: argparse.ArgumentParser,
                        default_graphs: list[str] | None = None) -> None:
    """``--data`` (default: ``$H2O_POSEGRAPHS``; :func:`select_graphs` exits 2 without
    either), ``--graphs``, ``--results`` and ``--no-results``."""
    parser.add_argument("--data", type=Path, default=default_data(), metavar="DIR",
                        help=f"folder of the public pose graphs as .g2o files (default: "
                        f"${POSEGRAPHS_ENV}; see bench/README.md)")
    parser.add_argument("--graphs", nargs="+", metavar="NAME", default=default_graphs,
                        help="graphs to run, as file stems (default: "
                        f"{' '.join(default_graphs) if default_graphs else 'all'})")
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS,
                        help=f"markdown file to update (default {DEFAULT_RESULTS})")
    parser.add_argument("--no-results", action="store_true",
                        help="print the section only; do not touch the results file")


def results_path(args: argparse.Namespace) -> Path | None:
    """Where the section goes (None with ``--no-results``)."""
    return None if args.no_results else args.results


def select_graphs(prog: str, data: Path | None, names: list[str] | None) -> list[Path] | int:
    """The ``.g2o`` files of ``data`` to run (all, or ``names`` in that order), or the exit
    code after saying why there are none: 2 when no folder was given (``data`` None: neither
    ``--data`` nor ``H2O_POSEGRAPHS``), 0 when there is nothing to benchmark (the folder
    given is missing or holds no graph), 2 for a name with no file."""
    if data is None:
        return no_data(prog)
    if not data.is_dir():
        print(f"{prog}: data folder {data} is missing; nothing to benchmark (pass --data DIR).")
        return 0
    paths = sorted(data.glob("*.g2o"))
    if names:
        by_stem = {p.stem: p for p in paths}
        unknown = [n for n in names if n not in by_stem]
        if unknown:
            print(f"{prog}: no such graph in {data}: {', '.join(unknown)}", file=sys.stderr)
            return 2
        paths = [by_stem[n] for n in names]
    if not paths:
        print(f"{prog}: no .g2o files in {data}; nothing to benchmark.")
        return 0
    return paths


def publish(section: str, path: Path | None, heading: str) -> None:
    """Print the section and, unless ``path`` is None, replace it in ``path``."""
    print(section)
    if path is not None:
        replace_section(path, heading, section)
        print(f"written to {path}", file=sys.stderr)


def run_graphs(prog: str, paths: list[Path], out_dir: Path | None,
               bench_one: Callable[[Path, Path], Row]) -> tuple[list[Row], list[str]]:
    """``bench_one(graph, folder)`` for each graph, writing into ``out_dir`` (a temporary
    folder when None); a graph whose file cannot be read is skipped and listed.

    Returns:
        the rows of the graphs that ran, and ``"stem: reason"`` for each one skipped.
    """
    from h2o_slam.core.errors import H2OError

    rows: list[Row] = []
    skipped: list[str] = []
    with tempfile.TemporaryDirectory(prefix=f"h2o-{Path(prog).stem}-") as tmp:
        target = out_dir if out_dir is not None else Path(tmp)
        target.mkdir(parents=True, exist_ok=True)
        for path in paths:
            try:
                rows.append(bench_one(path, target))
            except H2OError as err:  # the input itself cannot be read: no solver can run
                print(f"{prog}: skipping {path.name}: {err}", file=sys.stderr)
                skipped.append(f"{path.stem}: {err}")
    return rows, skipped


def table_head(head: str) -> list[str]:
    """A markdown table's header line ``| a | b |`` and its ``| --- | --- |`` rule."""
    return [head, "| " + " | ".join(["---"] * (head.count("|") - 1)) + " |"]
