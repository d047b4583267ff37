"""Both nodes fuzzed through every callback, timer and service (issue 13).

Hypothesis draws sequences of messages (odometry, loop closures, NavSatFix, camera info,
raw and compressed images), timer ticks and service calls (``test/node_fuzz.py``), mostly
those of a robot driving about and a tenth hostile; the driver calls the callbacks the
nodes registered, as the executor would. Every example must end with no exception out of
a callback, nothing non-finite published or held, and no rejection counted as unexpected
(the boundary catches bugs; these tests say there are none left to catch). The example
counts are bounded for CI (~15 s per node here); ``bench/fuzz.py --examples N`` runs long
campaigns of the same strategies.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from nav_msgs.msg import Odometry
from node_fuzz import (
    DATUM,
    H2O_OPS,
    VO_OPS,
    NodeDriver,
    camera_info_msg,
    make_h2o_node,
    make_vo_node,
    run_h2o,
    run_vo,
)
from rclpy.context import Context
from sensor_msgs.msg import NavSatFix

from h2o_slam.core.errors import InputError

# Bounded for CI: about 15 s per node here (a graph solved in full per input is the cost).
FUZZ = dict(deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


def assert_clean(driver: NodeDriver) -> None:
    out = driver.outcome
    assert not out.escaped, out.escaped
    assert not out.non_finite, out.non_finite
    assert not out.unexpected, dict(out.unexpected)


@pytest.mark.slow
@settings(max_examples=30, **FUZZ)
@given(ops=H2O_OPS)
def test_h2o_node_survives_any_input(context: Context, tmp_path_factory: Any,
                                     ops: list[tuple[Any, ...]]) -> None:
    node = make_h2o_node(context, tmp_path_factory.getbasetemp())
    try:
        driver = NodeDriver(node)
        run_h2o(driver, ops)
        assert_clean(driver)
    finally:
        node.destroy_node()


@pytest.mark.slow
@settings(max_examples=100, **FUZZ)
@given(ops=VO_OPS)
def test_vo_node_survives_any_input(context: Context, ops: list[tuple[Any, ...]]) -> None:
    node = make_vo_node(context)
    try:
        driver = NodeDriver(node)
        run_vo(driver, ops)
        assert_clean(driver)
    finally:
        node.destroy_node()


# -- the inputs issue 13 found, one by one ----------------------------------------------


def odom(stamp_s: float, x: float, cov: list[float] | None = None) -> Odometry:
    msg = Odometry()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(1.7e18 + stamp_s * 1e9), 10**9)
    msg.header.frame_id, msg.child_frame_id = "odom", "base_link"
    msg.pose.pose.position.x = x
    msg.pose.pose.orientation.w = 1.0
    if cov is not None:
        msg.pose.covariance = cov
    return msg


def test_issue_inputs_leave_no_trace_in_h2o_node(context: Context, tmp_path: Any) -> None:
    node = make_h2o_node(context, tmp_path)
    try:
        driver = NodeDriver(node)
        for i in range(8):
            driver.deliver("odom", odom(i * 0.5, 0.6 * i))
        track, edges = node.mapper.track.size, node.mapper.h2o.solver.num_edges
        # x = 1e200 (was: OverflowError in increment_covariance, the sample kept).
        driver.deliver("odom", odom(4.0, 1e200))
        key = "odometry: Odometry.pose.pose.position: magnitude # beyond the bound #"
        assert node.rejected[key] == 1
        # The same through the mapper directly (an adapter that let it pass).
        with pytest.raises(InputError, match="beyond 1e\\+08 m"):
            node.mapper.add_odometry(int(1.7e18 + 4e9), np.array([1e200, 0.0, 0.0]))
        assert node.mapper.rejected["odometry_out_of_range"] == 1
        assert (node.mapper.track.size, node.mapper.h2o.solver.num_edges) == (track, edges)
        # A later good fix (it once raised again on the kept sample).
        fix = NavSatFix(latitude=DATUM[0], longitude=DATUM[1], altitude=DATUM[2])
        fix.header.stamp = odom(3.5, 0.0).header.stamp
        fix.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
        fix.position_covariance = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        driver.deliver("gps/fix", fix)
        assert node.mapper.accepted["gps"] == 1
        # A loop closure 1.79e308 m long (was: chi2 NaN passed the gate, the graph timer
        # then raised on inf residuals), in the message and straight into the mapper.
        lie = odom(4.0, -1.79e308)
        lie.header.frame_id, lie.child_frame_id = "node/0", "node/5"
        driver.deliver("loop_closure", lie)
        with pytest.raises(InputError, match="is beyond 1e\\+08 m"):
            node.mapper.add_loop_closure(0, 5, np.array([-1.79e308, 0.0, 0.0]), np.eye(3))
        with pytest.raises(InputError, match="sigma below"):
            node.mapper.add_loop_closure(0, 5, np.array([1.0, 0.0, 0.0]), np.eye(3) * 1e-300)
        assert node.mapper.accepted["loop_closure"] == 0
        for timer in driver.timers:
            driver.call("timer", timer.callback)
        assert_clean(driver)
        assert np.all(np.isfinite(node.mapper.poses()))
    finally:
        node.destroy_node()


def test_issue_inputs_do_not_end_hybrid_vo_node(context: Context) -> None:
    node = make_vo_node(context)
    try:
        driver = NodeDriver(node)
        for side in ("left", "right"):
            driver.deliver(f"{side}/camera_info",
                           camera_info_msg(driver.clock, ("info", side, ("dt", 0), None)))
        huge = [1.7e308 if i in (0, 1, 6, 7) else (1.0 if i % 7 == 0 else 0.0)
                for i in range(36)]
        pair = ("pair", ("abs", 1_700_000_000, 0), 1, "raw", "raw")
        driver.deliver("odom", odom(-0.1, 0.0))
        # A 1.7e308 covariance block (was: LinAlgError in eigvalsh).
        driver.deliver("odom", odom(-0.05, 0.0, huge))
        # x = 1e200 (was: OverflowError at the next stereo frame).
        driver.deliver("odom", odom(0.0, 1e200))
        assert node.frontend.stats.rejected[
            "odom: Odometry.pose.pose.position: magnitude"] == 1
        run_vo(driver, [pair, ("wheel", ("dt", 100), (0.1, 0.0, 0.0, ("yaw", 0.0)), ("zero",))])
        with pytest.raises(InputError, match="wheel_out_of_range"):
            node.frontend.add_wheel(2_000_000_000 * 10**9, 1e200, 0.0, 0.0)
        assert node.frontend.stats.frames >= 4  # the warm-up's and the pair's
        assert_clean(driver)
    finally:
        node.destroy_node()
