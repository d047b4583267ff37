"""Shared plumbing of the benchmarks: each owns one ``## …`` section of ``bench/RESULTS.md``,
and those over the public pose graphs take the same ``--data/--graphs/--results`` arguments."""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

Row = TypeVar("Row")

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "posegraphs"
DEFAULT_RESULTS = REPO / "bench" / "RESULTS.md"


def command(repo: Path) -> str:
    """The command line that is running, with paths relative to ``repo`` where they can be."""
    parts = []
    for p in (Path(sys.executable), Path(sys.argv[0]).resolve()):
        try:
            parts.append(str(p.relative_to(repo)))
        except ValueError:
            parts.append(str(p))
    return shlex.join([*parts, *sys.argv[1:]])


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
    """``--data``, ``--graphs``, ``--results`` and ``--no-results``."""
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA,
                        help=f"folder of .g2o graphs (default {DEFAULT_DATA})")
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


def select_graphs(prog: str, data: Path, names: list[str] | None) -> list[Path] | int:
    """The ``.g2o`` files of ``data`` to run (all, or ``names`` in that order), or the exit
    code after saying why there are none: 0 when there is nothing to benchmark (a missing
    folder: the data are optional), 2 for a name with no file."""
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
