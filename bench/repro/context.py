"""What ``bench/reproduce.py`` hands every experiment module."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: Verdicts an experiment may give, worded as ``bench/REPRODUCTION.md`` uses them.
VERDICTS = ("reproduced", "reproduced in shape", "not reproduced")


@dataclass(frozen=True)
class Context:
    """``quick``: a few-minute subset; ``data``: the folder of the public pose graphs (None
    when not given; a graph may be missing); ``plots``: where PNGs go (linked from the
    markdown as ``repro_plots/<name>.png``); ``kitti``: a KITTI stereo sequence (or None)."""

    quick: bool
    data: Path | None
    plots: Path
    repo: Path
    kitti: Path | None = None

    def graph(self, stem: str) -> Path | None:
        """``data/<stem>.g2o`` when it exists (experiments skip a missing graph and say so)."""
        if self.data is None:
            return None
        path = self.data / f"{stem}.g2o"
        return path if path.exists() else None

    def link(self, png: Path) -> str:
        """A markdown image link to ``png`` relative to ``bench/``."""
        return f"![{png.stem}]({png.relative_to(self.repo / 'bench').as_posix()})"


def verdict(word: str, why: str) -> str:
    """The one-line verdict that ends each section."""
    if word not in VERDICTS:
        raise ValueError(f"verdict {word!r} is not one of {VERDICTS}")
    return f"**Verdict: {word}** — {why}"
