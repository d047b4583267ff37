"""Shared plumbing of the benchmarks: each owns one ``## …`` section of ``bench/RESULTS.md``."""

from __future__ import annotations

from pathlib import Path


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
