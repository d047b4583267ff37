"""Per-callback timing statistics used by h2o_node's diagnostics."""

from __future__ import annotations

import numpy as np
import pytest

from h2o_slam.timing import CallbackTimes


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
