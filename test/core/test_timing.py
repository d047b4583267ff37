"""Per-callback timing statistics used by h2o_node's diagnostics."""

from __future__ import annotations

import numpy as np
import pytest

from h2o_slam.core.timing import CallbackTimes, CostModel, CostShare, InputHealth


def test_summary_counts_overruns_against_the_budget_in_force() -> None:
    times = CallbackTimes(window=100)
    for ms in (1.0, 2.0, 6.0, 3.0):
        times.add(ms, 5.0)
    times.add(6.0, 10.0)  # under a larger budget: not an overrun
    times.add(50.0, None)  # no budget (paused or unlimited): never an overrun
    s = times.summary()
    assert s["callbacks"] == 6 and s["overruns"] == 1
    assert s["max_ms"] == 50.0 and s["mean_ms"] == pytest.approx(68.0 / 6)


def test_window_keeps_the_newest_in_arrival_order() -> None:
    times = CallbackTimes(window=4)
    for ms in range(10):
        times.add(float(ms), None)
    np.testing.assert_array_equal(times.recent(), [6.0, 7.0, 8.0, 9.0])
    assert times.summary()["max_ms"] == 9.0 and times.summary()["p50_ms"] == 7.5
    partial = CallbackTimes(window=4)
    partial.add(3.0, None)
    np.testing.assert_array_equal(partial.recent(), [3.0])


def test_empty_and_invalid() -> None:
    assert CallbackTimes().summary() == {"callbacks": 0, "overruns": 0}
    with pytest.raises(ValueError, match="window"):
        CallbackTimes(window=0)


def test_input_health_counts_gaps_in_the_stamps_as_drops() -> None:
    health = InputHealth(late_ms=50.0)
    period = 10_000_000  # 100 Hz
    stamps = [k * period for k in range(20)] + [25 * period, 26 * period, 30 * period]
    jitter = [0, 3_000_000, -4_000_000]  # under half a period: not drops
    for i, s in enumerate(stamps):
        health.observe(s + jitter[i % 3] * (i < 20), s + 1_000_000)
    assert health.period_ns == pytest.approx(period, rel=0.1)
    assert health.dropped == 5 + 3  # 20..24 and 27..29 missing
    assert health.received == len(stamps) and health.late == 0
    health.observe(29 * period, 29 * period)  # out of order: no drop, no period sample
    assert health.dropped == 8


def test_input_health_lateness_is_relative_to_the_smallest_delay() -> None:
    health = InputHealth(late_ms=20.0)
    clock_offset = 5_000_000_000_000  # the sender's clock is far from ours
    for k, delay_ms in enumerate([3.0, 1.0, 10.0, 21.5, 40.0, 1.0]):
        stamp = k * 10_000_000
        health.observe(stamp, stamp + clock_offset + int(delay_ms * 1e6))
    assert health.late == 2  # 21.5 - 1 and 40 - 1 exceed 20 ms; 10 - 1 does not
    assert health.lag_ms == pytest.approx(0.0) and health.max_lag_ms == pytest.approx(39.0)
    assert health.dropped == 0
    with pytest.raises(ValueError, match="late_ms"):
        InputHealth(late_ms=0.0)


def test_cost_share_stretches_the_period_of_costly_work() -> None:
    share = CostShare(period_s=1.0, share=0.05)
    assert share.due(0.0)
    share.ran(0.0, 0.01)  # cheap: the configured period
    assert not share.due(0.99) and share.due(1.0)
    share.ran(1.0, 0.5)  # 0.5 s of work at most 5 % of the time: every 10 s
    assert not share.due(10.9) and share.due(11.0)
    assert share.runs == 2 and share.last_cost_s == 0.5
    with pytest.raises(ValueError, match="share"):
        CostShare(period_s=1.0, share=0.0)


def test_work_fits_when_its_prediction_with_margin_does() -> None:
    model = CostModel((1e-3, 1e-6), (1000.0,))
    need = model.predict(500.0) * model.margin(1.5)  # 1.5 ms × 1.5
    assert model.fits(need, 1.5, 500.0)
    assert not model.fits(0.99 * need, 1.5, 500.0)


def test_refused_work_fades_a_slow_sample_until_the_work_fits_again() -> None:
    """Only work that runs produces samples: one preempted sample must not keep it from
    fitting for good."""
    model = CostModel((5e-5, 2e-8), (1000.0,))
    model.update(5e-5 + 2e-8 * 120, 120.0)
    fits_before = model.fits(1e-3, 1.5, 120.0)
    model.update(0.02, 120.0)  # preempted for 20 ms
    assert fits_before and not model.fits(1e-3, 1.5, 120.0)
    refusals = 0
    while not model.fits(1e-3, 1.5, 120.0):
        model.forget()
        refusals += 1
    assert 10 < refusals < 100
    for _ in range(100):
        model.forget()
    assert model.predict(120.0) == pytest.approx(5e-5 + 2e-8 * 120, rel=0.05)
    assert model.spread == pytest.approx(1.1)
