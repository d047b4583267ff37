"""A one-line progress bar for the commands, drawn only on a terminal."""

from __future__ import annotations

import math
import sys
import time
from typing import TextIO


class Progress:
    """A one-line progress bar on stderr, drawn only when stderr is a terminal.

    Args:
        total: the amount that means done (e.g. the bag's duration in s).
        label: text before the bar.
        stream: where to draw; ``sys.stderr`` by default.
        unit: unit of ``total`` shown after the numbers.
        min_interval_s: least wall time between two redraws (drawing is not free).
    """

    WIDTH = 30

    def __init__(
        self,
        total: float,
        label: str = "",
        stream: TextIO | None = None,
        unit: str = "s",
        min_interval_s: float = 0.1,
    ) -> None:
        self.total = max(float(total), 0.0)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.unit = unit
        self.min_interval_s = min_interval_s
        self.enabled = _is_tty(self.stream)
        self._start = time.monotonic()
        self._last_draw = -math.inf
        self._done = 0.0

    def update(self, done: float, note: str = "") -> None:
        """Set how much is done (same unit as ``total``); redraws when due."""
        self._done = float(done)
        now = time.monotonic()
        if self.enabled and now - self._last_draw >= self.min_interval_s:
            self._last_draw = now
            self.stream.write("\r" + self.line(now - self._start, note))
            self.stream.flush()

    def line(self, elapsed_s: float, note: str = "") -> str:
        """The text of the bar after ``elapsed_s`` of wall time."""
        frac = min(self._done / self.total, 1.0) if self.total > 0 else 0.0
        filled = int(round(frac * self.WIDTH))
        bar = "#" * filled + "-" * (self.WIDTH - filled)
        rate = ""
        if elapsed_s > 0:
            speed = self._done / elapsed_s
            # Bag seconds per wall second is the replay's speed as a multiple of real time.
            unit = "x real time" if self.unit == "s" else f"{self.unit}/s"
            rate = f" {speed:.1f} {unit}"
        text = f"{self.label} [{bar}] {frac:4.0%} {self._done:.1f}/{self.total:.1f} {self.unit}"
        return f"{text}{rate} {note}".rstrip()

    def close(self) -> None:
        """Draw the final state and end the line (only if anything was drawn)."""
        if self.enabled:
            self.stream.write("\r" + self.line(time.monotonic() - self._start) + "\n")
            self.stream.flush()


def _is_tty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or replaced streams (pytest capture)
        return False
