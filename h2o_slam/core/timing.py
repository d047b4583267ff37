"""Time against a budget: per-callback wall time (diagnostics, benchmarks), the cost models
that predict work before it runs (:class:`CostModel`, :class:`UpdateCost` for single-edge
updates), input lateness and the share of time given to background work."""

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
        self._fit()
        self.samples += 1

    def forget(self, factor: float = 0.9) -> None:
        """Fade every sample by ``factor`` toward the prior, and the margin with them:
        called when the work was refused, since only work that runs produces the samples
        that would correct a slow one (one 20 ms copy of a 120-node tree, a preempted
        sample on a busy machine, and no snapshot ever fitted a callback again)."""
        self._A *= factor
        self._b *= factor
        self._fit()
        self.spread = max(1.1, factor * self.spread)

    def _fit(self) -> None:
        coef = np.linalg.solve(self._A + self._ridge, self._b + self._ridge @ self.prior)
        # No size makes work cheaper; a slope at zero would promise any size fits.
        self.coef = np.maximum(coef, 0.1 * self.prior)

    def fits(self, remaining_s: float, safety: float, *sizes: float) -> bool:
        """Work of these sizes, with its :meth:`margin`, fits in ``remaining_s`` seconds."""
        return self.predict(*sizes) * self.margin(safety) <= remaining_s

    def margin(self, safety: float) -> float:
        """What predictions are multiplied by: the larger of ``safety`` and the observed
        :attr:`spread`."""
        return max(safety, self.spread)


class InputHealth:
    """Messages of one periodic input that never arrived, or arrived late, judged from
    their stamps alone (the node cannot see a best-effort queue overflow or a lost packet).

    * **Dropped**: the period is learned as the mean of the last ``history`` intervals
      between consecutive stamps (a mean, since jitter cancels in it; a gap enters it as one
      period); a gap of ``k`` periods (rounded) counts ``k - 1`` messages dropped.
      Out-of-order or repeated stamps count nothing (the mapper refuses them).
    * **Late**: a message's *lag* is the time it is handled (any monotonic clock, ns) minus
      its stamp, less the smallest such difference seen so far: clocks need not agree (a
      bag's stamps, simulated time), only tick at one rate. A message is late when its lag
      exceeds ``late_ms``.
    """

    def __init__(self, late_ms: float, history: int = 32, min_intervals: int = 8) -> None:
        if not late_ms > 0.0:
            raise ValueError(f"late_ms must be > 0, got {late_ms!r}")
        self.late_ms = late_ms
        self._intervals = np.zeros(history, dtype=np.int64)
        self._seen = 0  # intervals recorded
        self._min_intervals = min_intervals
        self._last_stamp_ns: int | None = None
        self._offset_ns: int | None = None  # smallest (handled - stamp)
        self.received = 0
        self.dropped = 0
        self.late = 0
        self.lag_ms = 0.0  # of the newest message
        self.max_lag_ms = 0.0

    @property
    def period_ns(self) -> int | None:
        """The learned period (ns), once ``min_intervals`` intervals are known."""
        if self._seen < self._min_intervals:
            return None
        n = min(self._seen, len(self._intervals))
        return int(np.mean(self._intervals[:n]))

    def restart(self) -> None:
        """Judge no gap before the next message: the node ignored those in between on
        purpose (while paused) and counted them itself."""
        self._last_stamp_ns = None

    def observe(self, stamp_ns: int, handled_ns: int) -> None:
        """One message with stamp ``stamp_ns``, handled at ``handled_ns``."""
        self.received += 1
        last, self._last_stamp_ns = self._last_stamp_ns, (
            stamp_ns if self._last_stamp_ns is None else max(self._last_stamp_ns, stamp_ns))
        if last is not None and stamp_ns > last:
            gap = stamp_ns - last
            period = self.period_ns
            if period is not None and period > 0:
                # Rounded: jitter of up to half a period is not a drop.
                missing = int((gap + period // 2) // period) - 1
                self.dropped += max(missing, 0)
                if missing > 0:
                    gap = period  # a gap is not a sample of the period
            self._intervals[self._seen % len(self._intervals)] = gap
            self._seen += 1
        offset = handled_ns - stamp_ns
        if self._offset_ns is None or offset < self._offset_ns:
            self._offset_ns = offset
        self.lag_ms = 1e-6 * (offset - self._offset_ns)
        self.max_lag_ms = max(self.max_lag_ms, self.lag_ms)
        if self.lag_ms > self.late_ms:
            self.late += 1


class CostShare:
    """Rate limit for periodic work whose cost grows (graph publication, χ² over every
    edge): the next run is due after the longer of ``period_s`` and ``cost / share``, so the
    work takes at most ``share`` of the thread's time however large the graph grows.

    Times are seconds of one monotonic clock, passed in.
    """

    def __init__(self, period_s: float, share: float) -> None:
        if not (period_s >= 0.0 and 0.0 < share <= 1.0):
            raise ValueError(f"period_s must be >= 0 and share in (0, 1], got {period_s!r}, "
                             f"{share!r}")
        self.period_s = period_s
        self.share = share
        self._next_s = -np.inf
        self.runs = 0
        self.last_cost_s = 0.0

    def due(self, now_s: float) -> bool:
        """Whether the work may run at ``now_s``."""
        return now_s >= self._next_s

    def ran(self, start_s: float, cost_s: float) -> None:
        """The work ran from ``start_s`` for ``cost_s`` seconds."""
        self.runs += 1
        self.last_cost_s = cost_s
        self._next_s = start_s + max(self.period_s, cost_s / self.share)


class UpdateCost:
    """Seconds of a single-edge update with domain size ``d`` solving ``s`` of its nodes.

    Full updates (``s = d``) and interpolated ones (``s < d``, 3.3.6) are modelled apart:
    both are linear in ``d`` (the path is linearized and moved whole either way), but the
    solve is linear in ``s`` only for interpolated ones, which add the merge's and the
    distribution's own per-node costs (``bench/cost.py``, kitti_00's d = 1427 edge: full
    0.92 ms, interpolated at ``d_max`` = 75 0.55 ms). One model of ``(1, d, s)`` for both
    cannot tell ``d`` from ``s`` in full updates and learnt a zero domain slope, predicting
    1 ms for 11 ms updates.
    """

    def __init__(self) -> None:
        self.full = CostModel((2e-4, 3e-6), (50.0,))
        # The prior's slope in d is what a graph's first long loops are priced at, and only
        # updates that fit teach the model: 5 µs a node priced kitti_00's closure 4,455 → 5
        # (d = 1,372) at 7.5 ms, so it waited for a later callback (r 1,899 after its own),
        # where an interpolated update of it takes 0.86 ms (0.54 µs a node learnt).
        self.interpolated = CostModel((6e-4, 6e-7, 2e-6), (200.0, 10.0))

    def _model(self, d: int, s: int) -> tuple[CostModel, tuple[float, ...]]:
        if s >= d:
            return self.full, (d,)
        return self.interpolated, (d, s)

    def predict(self, d: int, s: int) -> float:
        """Predicted seconds for domain size ``d`` solving ``s`` nodes."""
        model, sizes = self._model(d, s)
        return model.predict(*sizes)

    def predict_with_margin(self, d: int, s: int, safety: float) -> float:
        """:meth:`predict` times the margin its model needs."""
        model, sizes = self._model(d, s)
        return model.predict(*sizes) * model.margin(safety)

    def update(self, d: int, s: int, seconds: float) -> None:
        """Fold in one measured update."""
        model, sizes = self._model(d, s)
        model.update(seconds, *sizes)

    def relax_margins(self) -> None:
        """Shrink the learnt margins: called when nothing fitted, since only updates that
        run produce the samples that would shrink them."""
        for model in (self.full, self.interpolated):
            model.spread = max(1.1, 0.9 * model.spread)

    def largest_fitting(self, d: int, cap: int, remaining_s: float, safety: float) -> int:
        """The most nodes (≤ ``cap``) to solve whose predicted cost, with margin, fits
        ``remaining_s`` (0: none)."""
        if cap >= d and self.predict_with_margin(d, d, safety) <= remaining_s:
            return d
        c0, c1, c2 = self.interpolated.coef
        room = remaining_s / self.interpolated.margin(safety) - c0 - c1 * d
        if room < 0.0:
            return 0
        return int(min(cap, d - 1, room / c2))
