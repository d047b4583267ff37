"""The pure pieces of bench/robust.py (no solver run): which rows meet issue 23's targets and
how the summary counts them."""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import EdgeKind, PoseGraph

_BENCH = Path(__file__).resolve().parent.parent / "bench"
if str(_BENCH) not in sys.path:
    sys.path.insert(0, str(_BENCH))
robust = importlib.import_module("robust")


def _row(solver: str, status: str = "ok", **scores: float) -> object:
    fields = dict(ate_m=0.0, chi2_ratio=1.0, p99_ms=4.0, max_ms=9.0) | scores
    return robust.Row("g", "random", 10, solver, status, **fields)


def test_a_row_meets_the_target_on_its_map_and_a_node_row_on_its_callbacks_too():
    assert robust.target(_row("h2o", max_ms=50.0)) == "met"
    assert robust.target(_row("node")) == "met"
    assert robust.target(_row("node", max_ms=10.5, over=1)).startswith("missed: callbacks")
    assert robust.target(_row("h2o", ate_m=0.06)) == "missed: ATE 0.06 m"
    assert robust.target(_row("h2o", "timeout (300 s)")) == "missed (timeout (300 s))"
    assert robust.target(_row("gnc", ate_m=9.0)) == ""


def test_the_summary_leaves_out_rows_skipped_by_design():
    rows = [_row("h2o"), _row("node", "skipped: 3-D (the node is planar)"), _row("lm")]
    assert robust.target(rows[1]) == ""
    assert robust.target_summary(rows).endswith("met on 1 of 1 rows.")


def test_a_default_model_node_row_is_held_to_the_node_rows_targets():
    assert robust.target(_row(robust.NODE_DEFAULTS, max_ms=10.5, over=1)).startswith(
        "missed: callbacks")


def test_only_callbacks_the_host_took_time_from_may_exceed_twice_the_budget():
    row = _row("node", max_ms=30.0, over=3, over_host=3)
    assert robust.target(row) == "met"
    assert robust.target(_row("node", max_ms=30.0, over=3, over_host=2)) == (
        "missed: callbacks p99 4.00 ms, 1 over 10 ms")
    assert robust.target(_row("node", p99_ms=5.5, over=0)).startswith("missed: callbacks p99")


def test_a_callback_is_stolen_from_when_the_counter_moves_by_30_ms_after_its_end():
    mapper_stream = importlib.import_module("mapper_stream")
    start = np.array([0.0, 0.005, 0.010, 0.050])
    end = start + 0.002
    steal = np.array([7, 7, 7, 8])
    # The counter moved between the readings at 0.010 and 0.050. The first three windows
    # (to 30 ms after each end) close before 0.050, whose reading is the first one after
    # them; the last one's closing reading is the final one.
    stolen = mapper_stream.stolen_during(start, end, steal, final=8)
    assert stolen.tolist() == [True, True, True, False]
    assert mapper_stream.stolen_during(start, end, steal, final=9).tolist() == [
        True, True, True, True]
    assert not mapper_stream.stolen_during(start, end, np.full(4, 7), final=7).any()


def test_a_stream_reports_each_callbacks_wall_and_cpu_time_and_the_hosts_steal():
    mapper_stream = importlib.import_module("mapper_stream")
    n = 30
    graph = PoseGraph(True, np.arange(n), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)),
                      np.full(n - 1, EdgeKind.RELATIVE, np.int8), np.arange(n - 1),
                      np.arange(1, n), np.tile(np.eye(3), (n - 1, 1, 1)),
                      np.tile([1.0, 0.0, 0.0], (n - 1, 1)), np.tile(np.eye(6), (n - 1, 1, 1)))
    out = mapper_stream.stream_graph(graph, 5.0, idle_s=0.0, background="inline")
    assert (out.callback_ms.shape == out.callback_cpu_ms.shape == out.callback_stolen.shape
            == out.callback_off_ms.shape)
    assert len(out.callback_ms) == n
    assert out.callback_stolen.dtype == bool
    # CPU time is the thread's own: never (beyond the clocks' granularity) above wall time.
    assert np.all(out.callback_cpu_ms <= out.callback_ms + 0.5)
    assert np.all(out.callback_cpu_ms >= 0.0)
    assert np.all((out.callback_off_ms >= 0.0) & (out.callback_off_ms <= out.callback_ms))
    assert mapper_stream.host_steal_ticks() >= 0


def test_thread_clocks_count_the_threads_cpu_time_and_its_blocking():
    mapper_stream = importlib.import_module("mapper_stream")
    run, wait, switches = mapper_stream.thread_clocks()
    if run == 0.0:
        pytest.skip("this kernel keeps no /proc/thread-self/schedstat")
    spin_until = time.thread_time() + 0.02
    while time.thread_time() < spin_until:
        pass
    run_spun, wait_spun, _ = mapper_stream.thread_clocks()
    assert run_spun - run >= 0.015 and wait_spun >= wait
    time.sleep(0.01)
    assert mapper_stream.thread_clocks()[2] > switches  # sleeping blocks the thread


def test_the_fitted_odometry_model_is_the_one_a_graph_was_written_with():
    """Odometry written from the mapper's own noise model (σ 0.12 m per metre, heading σ
    0.01 rad per metre and 0.03 per radian turned) gives those numbers back."""
    mapper_stream = importlib.import_module("mapper_stream")
    rng = np.random.default_rng(3)
    n = 200
    dist = rng.uniform(0.5, 2.0, n)
    turn = np.where(rng.uniform(size=n) < 0.5, 0.0, rng.uniform(0.2, 1.5, n))
    info = np.zeros((n, 6, 6))
    info[:, 0, 0] = info[:, 1, 1] = 1.0 / (0.12 * dist) ** 2
    info[:, 5, 5] = 1.0 / (0.03 * turn + 0.01 * dist) ** 2
    info[:, 2, 2] = info[:, 3, 3] = info[:, 4, 4] = 1.0
    meas_t = np.column_stack([dist, np.zeros(n), np.zeros(n)])
    graph = PoseGraph(True, np.arange(n + 1), np.tile(np.eye(3), (n + 1, 1, 1)),
                      np.zeros((n + 1, 3)), np.full(n, EdgeKind.RELATIVE, np.int8),
                      np.arange(n), np.arange(1, n + 1), geo.yaw_to_matrix(turn), meas_t, info)
    fitted = mapper_stream.fitted_odometry(graph)
    assert fitted["odom_sigma_per_m"] == pytest.approx(0.12)
    assert fitted["odom_yaw_sigma_per_m"] == pytest.approx(0.01)
    assert fitted["odom_yaw_sigma_per_rad"] == pytest.approx(0.03)


def test_a_kernel_beats_a_row_only_when_better_on_both_counts_beyond_noise():
    ours = _row("h2o", ate_m=0.002, chi2_ratio=1.005)
    both = _row("dcs", ate_m=0.0002, chi2_ratio=1.00001)
    one = _row("cauchy", ate_m=0.0001, chi2_ratio=1.2)
    noise = _row("gnc", ate_m=0.0015, chi2_ratio=1.00495)
    assert robust.beaten_by(ours, [ours, both, one, noise]) == ["dcs"]
    assert robust.beaten_by(ours, [ours, one, noise]) == []
    lines = robust.kernel_summary([ours, both, one])
    assert lines[0].endswith(": 1 of 1.") and "beaten by dcs" in lines[1]
