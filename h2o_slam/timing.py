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


class CostModel:
    """Predicted seconds ``c · (1, x₁, x₂, …)`` of work described by a few sizes.

    Fitted by least squares over exponentially fading samples, pulled toward a prior by a
    fixed ridge term: the sizes of most samples barely vary (nearly every update has a tiny
    domain), and plain recursive least squares then winds up and predicts nonsense (after
    which nothing fits and no new sample arrives to correct it).
    """

    def __init__(self, prior: tuple[float, ...], typical: tuple[float, ...],
                 fading: float = 0.99, prior_weight: float = 4.0) -> None:
        self.prior = np.array(prior, dtype=float)
        self.coef = self.prior.copy()
        self._fading = fading
        # Ridge in units where each prior coefficient counts like `prior_weight` samples of
        # work of the typical sizes.
        scale = np.array([1.0, *typical])
        self._ridge = prior_weight * np.diag(scale**2)
        self._A = np.zeros((len(prior), len(prior)))
        self._b = np.zeros(len(prior))
        self.samples = 0
        #: A fading maximum of measured / predicted time: the margin predictions need.
        self.spread = 1.2

    def predict(self, *sizes: float) -> float:
        """Predicted seconds for work of these sizes."""
        return float(self.coef[0] + self.coef[1:] @ np.asarray(sizes, dtype=float))

    def update(self, seconds: float, *sizes: float) -> None:
        """Fold in one measured piece of work."""
        x = np.array([1.0, *sizes])
        ratio = seconds / max(self.predict(*sizes), 1e-9)
        self.spread = max(1.1, min(ratio, 2.0), 0.995 * self.spread)
        self._A = self._fading * self._A + np.outer(x, x)
        self._b = self._fading * self._b + x * seconds
        coef = np.linalg.solve(self._A + self._ridge, self._b + self._ridge @ self.prior)
        # No size makes work cheaper; a slope at zero would promise any size fits.
        self.coef = np.maximum(coef, 0.1 * self.prior)
        self.samples += 1

    def margin(self, safety: float) -> float:
        """What predictions are multiplied by: the larger of ``safety`` and the observed
        :attr:`spread`."""
        return max(safety, self.spread)
