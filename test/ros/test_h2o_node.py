"""h2o_node in-process: the synthetic world's streams go through real publishers into the
node, one SingleThreadedExecutor spins both, and the tests assert on what it publishes."""

from __future__ import annotations

import gc
import math
import os
import subprocess
import sys
import time
import weakref
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
from node_harness import LATCHED, Harness
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from sensor_msgs.msg import NavSatFix
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

import msg_adapters as ma
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import edge_chi2
from h2o_slam.ros import realtime
from h2o_slam.ros.h2o_node import H2ONode
from hybrid_vo.sim import world
from hybrid_vo.sim.messages import DEFAULT_START_NS, StreamMessage, drive_messages

ROLES = {"/wheel/odom": ("odom", Odometry), "/gps/fix": ("gps/fix", NavSatFix),
         "/loop_closure": ("loop_closure", Odometry)}
DATUM = list(world.GPS_DATUM)  # where the simulated world puts its ENU origin


@pytest.fixture(scope="module")
def slip_drive() -> world.Drive:
    """Heavy wheel slip (hallucinated turns): what GPS must correct."""
    return world.make_drive(world.scenario("slip", seed=2))


@pytest.fixture(scope="module")
def loop_drive() -> world.Drive:
    """Two laps with ordinary wheel noise, and loop closures where the laps meet. (Under
    the slip drive's hallucinated turns the gate rightly refuses closures: they are 0.7 rad
    off what the odometry noise model allows.)"""
    return world.make_drive(world.scenario("loop", seed=2))


def stream(drive: world.Drive, gps: bool, loops: bool) -> list[StreamMessage]:
    keep = {"/wheel/odom"} | ({"/gps/fix"} if gps else set()) | (
        {"/loop_closure"} if loops else set())
    return [m for m in drive_messages(drive, with_images=False) if m.topic in keep]


def start(h: Harness, **params: Any) -> tuple[H2ONode, dict[str, list[Any]]]:
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    node = h.add(H2ONode, parameter_overrides=overrides)
    outputs = {
        "pose": h.subscribe(PoseStamped, "h2o_node/pose"),
        "poses": h.subscribe(PoseArray, "h2o_node/graph/poses", LATCHED),
        "diag": h.subscribe(DiagnosticArray, "/diagnostics"),
        "m2o": h.subscribe(TransformStamped, "h2o_node/map_to_odom"),
    }
    for role, msg_type in ROLES.values():
        h.wait_for_subscribers(msg_type, role)
    return node, outputs


def taken_in(h: Harness, node: H2ONode, before: int, count: int, what: str) -> None:
    """Spin until the node has handled ``count`` more inputs than ``before`` (its callback
    count), whatever it decided: a fixed wait passes only on an idle machine."""
    h.spin_until(lambda: node.times.count >= before + count, 10.0, what)


def play(h: Harness, messages: list[StreamMessage], node: H2ONode | None = None) -> None:
    """Publish in order; with ``node``, wait until it has taken each message, so that
    the test does not depend on how DDS interleaves topics under load."""
    for m in messages:
        role, msg_type = ROLES[m.topic]
        count = node.times.count if node is not None else 0
        h.publish(msg_type, role, m.msg, spins=0)
        if node is not None:
            taken_in(h, node, count, 1, f"{role} taken")
    h.spin_for(0.3)


def final_error(outputs: dict[str, list[Any]], drive: world.Drive) -> float:
    last = outputs["pose"][-1]
    p = last.pose.position
    return float(math.hypot(p.x - drive.truth[-1, 0], p.y - drive.truth[-1, 1]))


def wheel_error(drive: world.Drive) -> float:
    return float(np.hypot(*(drive.wheel_poses()[-1, :2] - drive.truth[-1, :2])))


def late_errors(outputs: dict[str, list[Any]], drive: world.Drive) -> tuple[float, float]:
    """Mean position error of the poses published over the second half of the drive, and
    of the wheel odometry at the same stamps."""
    stamps = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                       for m in outputs["pose"]]) - DEFAULT_START_NS
    xy = np.array([[m.pose.position.x, m.pose.position.y] for m in outputs["pose"]])
    late = stamps >= drive.stamps_ns[len(drive.stamps_ns) // 2]
    index = np.searchsorted(drive.stamps_ns, stamps[late])
    truth = drive.truth[index, :2]
    published = np.mean(np.hypot(*(xy[late] - truth).T))
    wheel = np.mean(np.hypot(*(drive.wheel_poses()[index, :2] - truth).T))
    return float(published), float(wheel)


def latest_diagnostics(h: Harness, outputs: dict[str, list[Any]], node: H2ONode) -> dict[str, str]:
    count = len(outputs["diag"])
    node.publish_diagnostics()
    h.spin_until(lambda: len(outputs["diag"]) > count, 10.0, "diagnostics")
    for msg in reversed(outputs["diag"]):
        for status in msg.status:
            if status.hardware_id == "h2o_slam" and node.get_name() in status.name:
                return {kv.key: kv.value for kv in status.values}
    raise AssertionError("no h2o_node diagnostics")


def test_loop_closures_pull_the_graph_together(harness: Harness,
                                               loop_drive: world.Drive) -> None:
    node, out = start(harness, budget_ms=20.0)
    messages = stream(loop_drive, gps=False, loops=True)
    assert any(m.topic == "/loop_closure" for m in messages)
    play(harness, messages, node)
    diag = latest_diagnostics(harness, out, node)
    assert int(diag["accepted loop_closure"]) >= 3
    # The map's own newest pose, with the correction composed now: the last published
    # ~/pose reuses the map->odom of the last refresh and may predate the last merge.
    latest = node.mapper.latest_pose()
    assert latest is not None
    pose = latest[1]
    error = float(np.hypot(pose[0] - loop_drive.truth[-1, 0], pose[1] - loop_drive.truth[-1, 1]))
    assert error < 0.5 * wheel_error(loop_drive)
    # The graph went out too, reliable and transient-local.
    node.publish_graph()
    harness.spin_until(
        lambda: bool(out["poses"]) and len(out["poses"][-1].poses) == node.mapper.num_nodes,
        5.0, "graph poses of every keyframe")


def test_pose_after_a_merge_carries_its_correction(
        harness: Harness, loop_drive: world.Drive) -> None:
    # The transform timer refreshes map->odom every 10 s only: what keeps ~/pose right
    # after the map moves as a whole is the refresh on the map's revision.
    node, out = start(harness, budget_ms=20.0, transform_publish_period=10.0)
    messages = stream(loop_drive, gps=False, loops=True)
    closures = [m for m in messages if m.topic == "/loop_closure"]
    play(harness, [m for m in messages if m.topic != "/loop_closure"], node)
    before = node._correction().copy()
    merges = node.mapper.h2o.converger.state.merges
    play(harness, closures, node)
    # The exact solver's answer is merged in the node's own steps, as on a robot.
    harness.spin_until(lambda: node.mapper.h2o.converger.state.merges > merges, 10.0,
                       "an exact solution merged")
    count = len(out["pose"])
    latest = node.mapper.latest_pose()  # fresh, with nothing spinning in between
    node.publish_pose()
    harness.spin_until(lambda: len(out["pose"]) > count, 5.0, "a pose after the merge")
    assert latest is not None
    p = out["pose"][-1].pose.position
    assert (p.x, p.y) == pytest.approx((latest[1][0], latest[1][1]), abs=1e-9)
    # The closures moved the map by a wheel drift's worth: a stale correction would show.
    moved = node.mapper.map_to_odom() - before
    assert float(np.hypot(moved[0], moved[1])) > 0.2 * wheel_error(loop_drive)


def test_gps_anchors_the_graph_in_enu(harness: Harness, slip_drive: world.Drive) -> None:
    node, out = start(harness, datum=DATUM, budget_ms=20.0)
    play(harness, stream(slip_drive, gps=True, loops=False), node)
    diag = latest_diagnostics(harness, out, node)
    assert int(diag["accepted gps"]) > 40
    # Dropouts (NO_FIX) are refused and counted, with the reason.
    assert any("NO_FIX" in key for key in diag), diag
    published, wheel = late_errors(out, slip_drive)
    # Over the poses published, not the last one alone: that one follows the latest fixes
    # (σ 1.5 m) and lands 0.9–4.7 m off between runs, against 2.4 m for the exact optimum.
    # Over the second half: 1.5–1.9 m against 10 m.
    assert published < 0.3 * wheel
    poses = node.mapper.poses()
    stamps = np.asarray(node.mapper.keyframes.stamps) - DEFAULT_START_NS
    truth = slip_drive.truth[np.searchsorted(slip_drive.stamps_ns, stamps)]
    graph_error = np.median(np.hypot(*(poses[:, :2] - truth[:, :2]).T))
    wheel_xy = slip_drive.wheel_poses()[:, :2]
    wheel_median = np.median(np.hypot(*(wheel_xy - slip_drive.truth[:, :2]).T))
    # The exact optimum's median is 1.14 m; where the budgeted steps leave the graph varies
    # with timing (1.1–2.5 m seen), against 8.6 m for wheel odometry.
    assert graph_error < 0.35 * wheel_median


def test_false_loop_closure_is_held_counted_and_the_map_survives(
        harness: Harness, loop_drive: world.Drive) -> None:
    node, out = start(harness, budget_ms=20.0)
    markers = harness.subscribe(MarkerArray, "h2o_node/graph/markers", LATCHED)
    messages = stream(loop_drive, gps=False, loops=True)
    play(harness, messages, node)
    # At the optimum first (as ~/exact_solve does): merges of exact solves still under way
    # would move the map during the check below whatever happens to the false closure.
    node.mapper.exact_solve()
    before = node.mapper.poses().copy()
    closures_before = node.mapper.accepted["loop_closure"]
    # Node 0 and the newest node 10 m apart and facing apart, claimed coincident.
    newest = node.mapper.num_nodes - 1
    lie = ma.make_loop_closure(ma.NodeRef(0), ma.NodeRef(newest), np.eye(3),
                               np.array([25.0, -5.0, 0.0]),
                               ma.planar_covariance(0.05, 0.05, 0.01, unobserved_variance=1.0))
    before_lie = node.times.count
    harness.publish(Odometry, "loop_closure", ma.fill_loop_closure(Odometry, lie))
    # (A CI run saw it not yet handled after a fixed 0.3 s.)
    taken_in(harness, node, before_lie, 1, "the false closure")
    node.mapper.exact_solve()  # the robust optimum: the lie stays out
    diag = latest_diagnostics(harness, out, node)
    # Held by the gate, kept out by the robust solve, counted; nothing refused.
    assert int(diag["accepted loop_closure_held"]) == 1
    assert int(diag["robust loop_closures out"]) == 1
    assert int(diag["robust loop_closures in"]) == closures_before
    assert "rejected loop_gated" not in diag
    assert node.mapper.accepted["loop_closure"] == closures_before
    np.testing.assert_allclose(node.mapper.poses(), before, atol=0.05)
    # Drawn in its own namespace on ~/graph/markers (the exact solve above ran outside any
    # callback, so the graph is marked as changed by hand, as the service does).
    count = len(markers)
    node._graph_dirty = True
    node.publish_graph()
    harness.spin_until(lambda: len(markers) > count, 5.0, "graph markers after the lie")
    dropped = next(m for m in markers[-1].markers if m.ns == "dropped")
    assert len(dropped.points) == 2


def test_save_restart_restore_continues_without_loss(harness: Harness, tmp_path: Any,
                                                     loop_drive: world.Drive) -> None:
    path = str(tmp_path / "graph.g2o")
    messages = stream(loop_drive, gps=False, loops=True)
    half = len(messages) // 2
    node, out = start(harness, map_file=path, budget_ms=20.0)
    play(harness, messages[:half], node)
    answer = harness.call(Trigger, "h2o_node/save_map", Trigger.Request())
    assert answer.success, answer.message
    saved = node.mapper.num_nodes
    saved_edges = node.mapper.graph().num_edges
    harness.remove(node)

    node, out = start(harness, map_file=path, load_map_on_start=True, budget_ms=20.0)
    assert node.mapper.num_nodes == saved
    play(harness, messages[half:], node)
    graph = node.mapper.graph()
    assert node.mapper.num_nodes > saved
    assert graph.num_edges > saved_edges
    # The first new keyframe hangs off the last saved one: one connected chain.
    assert {int(a) for a, b in zip(graph.a, graph.b, strict=True) if b == saved} == {saved - 1}
    # Judged once the exact solves have caught up (idle steps merge them), on a pose
    # published then (0.13x the wheel error); mid-merge it depends on timing (0.3-0.67x seen).
    converger = node.mapper.h2o.converger
    harness.spin_until(lambda: not converger.busy and converger.outside() == 0, 20.0,
                       "the exact solution of every edge merged")
    count = len(out["pose"])
    node.publish_pose()
    harness.spin_until(lambda: len(out["pose"]) > count, 5.0, "a pose at the optimum")
    assert final_error(out, loop_drive) < 0.3 * wheel_error(loop_drive)


def test_budget_changes_at_run_time(harness: Harness, slip_drive: world.Drive) -> None:
    # Idle steps off: they take their own budget, and run while exact solves are merged.
    node, out = start(harness, budget_ms=5.0, idle_budget_ms=0.0)
    budgets: list[float | None] = []
    step = node.mapper.step

    def spy(budget_s: float | None) -> Any:
        budgets.append(budget_s)
        return step(budget_s)

    node.mapper.step = spy  # type: ignore[method-assign]
    messages = stream(slip_drive, gps=False, loops=False)
    play(harness, messages[:50], node)
    request = SetParameters.Request()
    request.parameters = [Parameter("budget_ms", value=0.5).to_parameter_msg(),
                          Parameter("keyframe_distance", value=2.0).to_parameter_msg()]
    result = harness.call(SetParameters, "h2o_node/set_parameters", request)
    assert all(r.successful for r in result.results)
    first = len(budgets)
    play(harness, messages[50:100], node)
    assert max(b for b in budgets[:first] if b is not None) > 0.002
    assert max(b for b in budgets[first:] if b is not None) <= 0.0005
    assert node.mapper.config.keyframe_distance == 2.0
    assert latest_diagnostics(harness, out, node)["budget_ms"] == "0.5"
    # Start-up-only parameters are refused while running, with the reason.
    request.parameters = [Parameter("map_frame", value="world").to_parameter_msg()]
    result = harness.call(SetParameters, "h2o_node/set_parameters", request)
    assert not result.results[0].successful
    assert "read-only" in result.results[0].reason


def test_a_destroyed_node_is_freed_although_its_solver_froze_the_collector(
        harness: Harness, slip_drive: world.Drive) -> None:
    """Steps call ``gc.freeze``; a node unloaded at run time (a restart, a component
    container) must not stay in memory, with its DDS endpoints, for the rest of the process."""
    node, _ = start(harness, budget_ms=5.0)
    play(harness, stream(slip_drive, gps=False, loops=False)[:40], node)
    assert node.mapper.num_nodes > 1 and gc.get_freeze_count() > 0
    ref = weakref.ref(node)
    harness.remove(node)
    del node
    # The executor's pending wait holds the nodes it was spinning until it next spins.
    for _ in range(20):
        harness.spin_for(0.05)
        gc.collect()
        if ref() is None:
            break
    if ref() is not None:
        holders = [type(r).__name__ for r in gc.get_referrers(ref())]
        raise AssertionError(f"node still referenced by {holders}")


def _odometry(stamp_ns: int, x: float) -> Odometry:
    sample = ma.planar_odometry_sample(stamp_ns, "odom", "base_link", x, 0.0, 0.0,
                                       ma.planar_covariance(0.01, 0.01, 0.01))
    return ma.fill_odometry(Odometry, sample)


def _fix(stamp_ns: int, lat: float, status: int = 0) -> NavSatFix:
    return ma.fill_navsat_fix(NavSatFix, stamp_ns=stamp_ns, frame_id="gps", lat_deg=lat,
                              lon_deg=DATUM[1], alt_m=30.0, covariance_enu=np.eye(3),
                              status=status)


def test_bad_inputs_are_rejected_counted_and_survived(harness: Harness) -> None:
    node, out = start(harness, datum=DATUM)
    t0 = 1_700_000_000 * 10**9
    before = node.times.count
    for i in range(20):
        harness.publish(Odometry, "odom", _odometry(t0 + i * 10**8, 0.1 * i))
    taken_in(harness, node, before, 20, "the good odometry")
    nodes, poses = node.mapper.num_nodes, node.mapper.poses().copy()
    bad: list[tuple[str, Any, Any]] = []
    nan_odom = _odometry(t0 + 30 * 10**8, 0.0)
    nan_odom.pose.pose.position.x = math.nan
    bad.append(("odom", Odometry, nan_odom))
    zero_q = _odometry(t0 + 31 * 10**8, 0.0)
    zero_q.pose.pose.orientation.w = 0.0
    bad.append(("odom", Odometry, zero_q))
    bad.append(("odom", Odometry, _odometry(t0, 5.0)))  # time going backwards
    indefinite = ma.fill_loop_closure(Odometry, ma.make_loop_closure(
        ma.NodeRef(0), ma.NodeRef(1), np.eye(3), np.zeros(3), np.eye(6)))
    indefinite.pose.covariance[0] = -1.0
    bad.append(("loop_closure", Odometry, indefinite))
    bad.append(("loop_closure", Odometry, ma.fill_loop_closure(Odometry, ma.make_loop_closure(
        ma.NodeRef(0), ma.NodeRef(999), np.eye(3), np.zeros(3), np.eye(6)))))
    bad.append(("gps/fix", NavSatFix, _fix(t0 + 10**9, math.nan, status=-1)))
    nan_fix = _fix(t0 + 10**9, DATUM[0])
    nan_fix.latitude = math.nan
    bad.append(("gps/fix", NavSatFix, nan_fix))
    bad.append(("gps/fix", NavSatFix, _fix(t0 + 10**9, 91.0)))
    before = node.times.count
    for role, msg_type, msg in bad:
        harness.publish(msg_type, role, msg)
    taken_in(harness, node, before, len(bad), "the bad inputs")
    diag = latest_diagnostics(harness, out, node)
    assert int(diag["rejected total"]) == len(bad), diag
    assert node.mapper.num_nodes == nodes
    np.testing.assert_array_equal(node.mapper.poses(), poses)
    # Still running: a good message after all that is taken.
    for i in range(40, 60):
        harness.publish(Odometry, "odom", _odometry(t0 + i * 10**8, 0.1 * i))
    harness.spin_until(lambda: node.mapper.num_nodes > nodes, 10.0, "a good message after")


def test_pause_reset_and_exact_solve_services(harness: Harness,
                                              loop_drive: world.Drive) -> None:
    node, out = start(harness)
    messages = stream(loop_drive, gps=False, loops=True)
    play(harness, messages[:200], node)
    answer = harness.call(SetBool, "h2o_node/pause", SetBool.Request(data=True))
    assert answer.success and node.paused
    nodes = node.mapper.num_nodes
    play(harness, messages[200:300])
    assert node.mapper.num_nodes == nodes
    harness.call(SetBool, "h2o_node/pause", SetBool.Request(data=False))
    answer = harness.call(Trigger, "h2o_node/exact_solve", Trigger.Request())
    assert answer.success and "chi2" in answer.message
    values = node.diagnostics().values
    assert values["edges"] > 0
    assert values["deferred_edges"] == 0 and values["edges_outside_converged"] == 0
    assert values["optimality_ratio"] == pytest.approx(1.0, rel=1e-9)
    answer = harness.call(Trigger, "h2o_node/reset", Trigger.Request())
    assert answer.success and node.mapper.num_nodes == 0
    harness.spin_until(lambda: bool(out["m2o"]), 10.0, "map->odom on its timer")


def test_bad_parameters_end_the_node_with_one_line(harness: Harness) -> None:
    with pytest.raises(InputError, match="datum"):
        harness.add(H2ONode, parameter_overrides=[Parameter("datum", value=[1.0, 2.0])])


def test_idle_steps_drain_edges_the_callbacks_could_not_fit(
        harness: Harness, loop_drive: world.Drive) -> None:
    # A budget so small that loop closures cannot be relaxed inside the input callbacks.
    node = harness.add(H2ONode, parameter_overrides=[
        Parameter("budget_ms", value=0.1), Parameter("idle_budget_ms", value=0.0)])
    for m in stream(loop_drive, gps=False, loops=True):
        (node.on_odom if m.topic == "/wheel/odom" else node.on_loop_closure)(m.msg)
    assert node.mapper.h2o.pending, "nothing was deferred: the test proves nothing"
    before = float(np.sum(edge_chi2(node.mapper.graph())))
    node.idle_step()
    assert node.idle_times.count == 0  # disabled by its parameter
    node.set_parameters([Parameter("idle_budget_ms", value=50.0)])
    for _ in range(200):
        node.idle_step()
        if not node.mapper.h2o.pending:
            break
    assert not node.mapper.h2o.pending
    assert node.idle_times.count > 0
    # The deferred loop closures were relaxed: the graph's energy fell.
    assert float(np.sum(edge_chi2(node.mapper.graph()))) < 0.9 * before


def test_dropped_and_late_odometry_are_counted_and_waiting_inputs_come_first(
        harness: Harness) -> None:
    node = harness.add(H2ONode, parameter_overrides=[Parameter("input_late_ms", value=100.0)])
    t0 = 1_700_000_000 * 10**9
    period = 10**7  # 100 Hz
    ticks = [*range(40), *range(45, 60)]  # 40..44 never arrive
    for k in ticks:  # handled faster than they were sent: never late
        node.on_odom(_odometry(t0 + k * period, 0.01 * k))
    assert not node.behind()
    time.sleep(0.15)  # the next sample waited 150 ms, 140 ms more than its period
    node.on_odom(_odometry(t0 + 60 * period, 0.6))
    assert node.behind()
    idle_steps = node.idle_times.count
    node._idle_timer()
    assert node.idle_yielded == 1 and node.idle_times.count == idle_steps
    values = node.diagnostics().values
    assert values["dropped odometry"] == 5 and values["late odometry"] == 1
    assert values["lag_max_ms odometry"] == pytest.approx(140.0, abs=60.0)
    assert values["idle_yielded"] == 1 and values["rss_mb"] > 10.0
    assert values["chi2_age_s"] == 0.0
    # χ² is kept between refreshes (its age reported), then computed anew.
    node.on_odom(_odometry(t0 + 61 * period, 0.7))
    stale = node.diagnostics(refresh_chi2=False).values
    assert stale["chi2"] == values["chi2"] and stale["chi2_age_s"] > 0.0
    assert node.diagnostics().values["chi2_age_s"] == 0.0


def test_graph_timer_publishes_only_what_someone_listens_to(harness: Harness) -> None:
    node = harness.add(H2ONode)
    t0 = 1_700_000_000 * 10**9
    for k in range(30):
        node.on_odom(_odometry(t0 + k * 10**8, 0.2 * k))
    node._graph_timer()  # no subscriber: nothing is built, the graph stays due
    assert node.shares["graph"].runs == 0 and node._graph_dirty
    poses = harness.subscribe(PoseArray, "h2o_node/graph/poses", LATCHED)
    harness.spin_until(lambda: node.publishers_by_key["poses"].get_subscription_count() > 0,
                       10.0, "graph subscriber")
    node._graph_timer()
    harness.spin_until(lambda: bool(poses), 10.0, "graph poses")
    assert node.shares["graph"].runs == 1 and len(poses[-1].poses) == node.mapper.num_nodes


def test_inputs_while_the_kernels_load_are_held_and_then_all_handled(
        harness: Harness, loop_drive: world.Drive, monkeypatch: pytest.MonkeyPatch) -> None:
    """A first start compiles the kernels beside the executor: the node answers at once,
    says it is warming up, holds every input in order, and handles them all when ready, as
    if they had come after (same graph as a node that was warm from the start)."""
    from h2o_slam.core import warmup

    messages = stream(loop_drive, gps=False, loops=True)[:150]
    other = Harness()  # its own namespace: the two nodes must not hear each other
    try:
        warm, _ = start(other)
        play(other, messages, warm)
        expected = (warm.mapper.num_nodes, dict(warm.mapper.accepted))
    finally:
        other.close()
    ready = {"now": False}
    monkeypatch.setattr(warmup, "is_ready", lambda: ready["now"])
    node, out = start(harness)
    for m in messages:
        role, msg_type = ROLES[m.topic]
        harness.publish(msg_type, role, m.msg, spins=0)
    harness.spin_until(lambda: node.held_while_warming == len(messages), 10.0, "all held")
    assert node.mapper.num_nodes == 0
    diag = latest_diagnostics(harness, out, node)
    assert diag["warming_up"] == "true" and int(diag["held_inputs"]) == len(messages)
    answer = harness.call(Trigger, "h2o_node/exact_solve", Trigger.Request())
    assert not answer.success and "warming up" in answer.message
    ready["now"] = True
    harness.spin_until(lambda: not node._held, 10.0, "held inputs handled")
    assert (node.mapper.num_nodes, dict(node.mapper.accepted)) == expected
    assert expected[0] > 10
    diag = latest_diagnostics(harness, out, node)
    assert diag["warming_up"] == "false"
    assert int(diag["held_while_warming"]) == len(messages)


def test_realtime_priority_runs_the_callbacks_under_fifo_until_the_node_ends(
        harness: Harness) -> None:
    """``realtime_priority`` 3: the thread that builds and spins the node is under
    SCHED_FIFO 3 (said in /diagnostics), a process it starts (the exact solver's worker) is
    not, and destroying the node gives the thread its policy back."""
    probe = realtime.fifo_callbacks(1)
    realtime.restore(probe)
    if not probe.applied:
        pytest.skip(probe.words)
    try:
        node, out = start(harness, realtime_priority=3)
        assert os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
        assert os.sched_getparam(0).sched_priority == 3
        child = subprocess.run(
            [sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
            capture_output=True, text=True, timeout=60, check=True)
        assert int(child.stdout) == os.SCHED_OTHER
        assert latest_diagnostics(harness, out, node)["scheduling"] == "SCHED_FIFO 3"
        harness.executor.remove_node(node)
        node.destroy_node()
        assert os.sched_getscheduler(0) == os.SCHED_OTHER
    finally:  # the rest of the session at the default policy, whatever failed above
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def test_a_refused_realtime_priority_leaves_the_default_policy_and_says_why(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    node, out = start(harness, realtime_priority=3)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    said = latest_diagnostics(harness, out, node)["scheduling"]
    assert said.startswith("SCHED_FIFO 3 refused (Operation not permitted")
    assert not node.realtime.applied and node.realtime.saved is None


def test_the_pose_after_a_merge_carries_the_new_correction(harness: Harness,
                                                           loop_drive: world.Drive) -> None:
    """A callback whose step merges an exact solution (the map moves as a whole) ends with
    the pose in the merged map: the one sent before the step carried the old map->odom
    (a run's final pose was 0.36 m off its map's)."""
    node, _ = start(harness)  # budgeted: solutions come from the worker, merged by a step
    poses: list[Any] = []
    node.sink = lambda topic, msg: poses.append(msg) if topic.endswith("/pose") else None
    merges_seen = 0
    handlers = {"/wheel/odom": node.on_odom, "/loop_closure": node.on_loop_closure}
    for m in stream(loop_drive, gps=False, loops=True):
        revision = node.mapper.map_revision()
        handlers[m.topic](m.msg)
        time.sleep(0.005)  # the worker's solve runs meanwhile
        if m.topic != "/wheel/odom" or node.mapper.map_revision() == revision:
            continue
        merges_seen += 1
        _, pose = node.mapper.latest_pose(node.mapper.map_to_odom())
        last = poses[-1].pose.position
        assert (last.x, last.y) == pytest.approx((pose[0], pose[1]), abs=1e-9)
    assert merges_seen > 0
