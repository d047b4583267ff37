"""Shared plumbing of the benchmarks: each owns one ``## …`` section of ``bench/RESULTS.md``."""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path


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
