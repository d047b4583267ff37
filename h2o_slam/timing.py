"""Per-callback wall time against a budget, for diagnostics and benchmarks."""

from __future__ import annotations

import numpy as np


class CallbackTimes:
    """The last ``window`` callback durations, and totals since the start.

    An overrun is a callback that took longer than the budget in force when it ran.
    """

    def __init__(self, window: int = 2000) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self._ms = np.zeros(window)
        self.count = 0
        self.overruns = 0
        self.max_ms = 0.0

    def add(self, elapsed_ms: float, budget_ms: float | None) -> None:
        """Record one callback."""
        self._ms[self.count % len(self._ms)] = elapsed_ms
        self.count += 1
        self.max_ms = max(self.max_ms, elapsed_ms)
        if budget_ms is not None and elapsed_ms > budget_ms:
            self.overruns += 1

    def recent(self) -> np.ndarray:
        """The durations in the window (ms), oldest first."""
        n = min(self.count, len(self._ms))
        start = self.count % len(self._ms) if self.count > len(self._ms) else 0
        return np.roll(self._ms[:n], -start) if n == len(self._ms) else self._ms[:n].copy()

    def summary(self) -> dict[str, float]:
        """Mean, p50, p99 and max of the window (ms), all-time max and counts."""
        recent = self.recent()
        if not len(recent):
            return {"callbacks": 0, "overruns": 0}
        return {
            "callbacks": self.count,
            "overruns": self.overruns,
            "mean_ms": float(recent.mean()),
            "p50_ms": float(np.percentile(recent, 50)),
            "p99_ms": float(np.percentile(recent, 99)),
            "window_max_ms": float(recent.max()),
            "max_ms": self.max_ms,
        }
