"""h2o_node's inputs in-process: the start-up line, and every message of each input
accounted for in /diagnostics (received = accepted + rejected + dropped), bursts included."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from node_harness import Harness, info_lines
from rclpy.parameter import Parameter
from std_srvs.srv import SetBool

import msg_adapters as ma
from h2o_slam.ros.h2o_node import H2ONode

T0 = 1_700_000_000 * 10**9
COUNTS = ("received", "accepted", "rejected", "dropped")


def _odometry(stamp_ns: int, x: float) -> Odometry:
    sample = ma.planar_odometry_sample(stamp_ns, "odom", "base_link", x, 0.0, 0.0,
                                       ma.planar_covariance(0.01, 0.01, 0.01))
    return ma.fill_odometry(Odometry, sample)


def _closure(a: int, b: int, poses: np.ndarray) -> Odometry:
    """A loop closure from node ``a`` to node ``b`` that agrees with the map (a straight
    drive along x: no rotation)."""
    closure = ma.make_loop_closure(
        ma.NodeRef(a), ma.NodeRef(b), np.eye(3), [poses[b, 0] - poses[a, 0], 0.0, 0.0],
        ma.planar_covariance(0.05, 0.05, 0.01, unobserved_variance=1.0), stamp_ns=T0)
    return ma.fill_loop_closure(Odometry, closure)


def _start(h: Harness, **params: Any) -> H2ONode:
    node = h.add(H2ONode, parameter_overrides=[Parameter(k, value=v)
                                               for k, v in params.items()])
    h.wait_for_subscribers(Odometry, "odom")
    h.wait_for_subscribers(Odometry, "loop_closure")
    return node


def _drive(h: Harness, node: H2ONode, samples: int = 40) -> np.ndarray:
    """Odometry along x through the topic, 0.6 m apart: one keyframe per sample."""
    for i in range(samples):
        h.publish(Odometry, "odom", _odometry(T0 + i * 10**8, 0.6 * i), spins=0)
    h.spin_until(lambda: node.inputs["odometry"].received == samples, 20.0, "odometry")
    assert node.mapper.num_nodes == samples
    return node.mapper.poses()


def _burst(h: Harness, node: H2ONode, poses: np.ndarray, count: int) -> None:
    """``count`` valid closures published at once, each between two existing poses."""
    rng = np.random.default_rng(5)
    publisher = h.publisher(Odometry, "loop_closure")
    for _ in range(count):
        a, b = sorted(rng.choice(len(poses), size=2, replace=False))
        publisher.publish(_closure(int(a), int(b), poses))


def _counts(node: H2ONode) -> dict[str, dict[str, int]]:
    """The input counts as the node's next /diagnostics carries them (taken from the sink:
    other tests' nodes of the same name publish on the global topic too)."""
    sent: list[Any] = []
    node.sink = lambda topic, msg: sent.append(msg) if topic == "/diagnostics" else None
    node.publish_diagnostics()
    node.sink = None
    values = {kv.key: kv.value for kv in sent[-1].status[0].values}
    return {what: {c: int(values[f"input {what} {c}"]) for c in COUNTS}
            for what in ("odometry", "loop_closure", "gps")}


def _balanced(counts: dict[str, int]) -> bool:
    return counts["received"] == counts["accepted"] + counts["rejected"] + counts["dropped"]


def test_a_burst_of_a_thousand_loop_closures_is_accepted_whole(harness: Harness) -> None:
    # A detector catching up after a revisit: 1000 closures within a second. The default
    # queue (200 deep before) overwrote 680 of them without a trace.
    node = _start(harness, budget_ms=1.0)
    poses = _drive(harness, node)
    _burst(harness, node, poses, 1000)
    closures = node.inputs["loop_closure"]
    harness.spin_until(lambda: closures.received >= 1000, 120.0, "1000 closures taken")
    counts = _counts(node)
    assert counts["loop_closure"] == {"received": 1000, "accepted": 1000, "rejected": 0,
                                      "dropped": 0}
    assert counts["odometry"] == {"received": 40, "accepted": 40, "rejected": 0, "dropped": 0}
    assert node.mapper.h2o.solver.num_edges == 39 + 1000


def test_closures_a_full_queue_overwrote_are_counted_as_dropped(harness: Harness) -> None:
    node = _start(harness, budget_ms=1.0, loop_closure_queue_depth=50)
    poses = _drive(harness, node)
    closures = node.inputs["loop_closure"]
    _burst(harness, node, poses, 1)  # the first message a gap is judged from
    harness.spin_until(lambda: closures.received == 1, 10.0, "the first closure")
    _burst(harness, node, poses, 999)
    harness.spin_until(lambda: closures.received >= 1000, 120.0, "1000 closures accounted")
    counts = _counts(node)["loop_closure"]
    assert counts["received"] == 1000 and _balanced(counts), counts
    # Every one overwritten is counted (gaps in the publisher's sequence numbers): the
    # middleware reports no loss for a KEEP_LAST queue that overwrites.
    assert counts["rejected"] == 0 and counts["dropped"] > 0, counts
    assert counts["accepted"] == node.mapper.h2o.solver.num_edges - 39


def test_inputs_ignored_while_paused_or_refused_are_accounted_for(harness: Harness) -> None:
    node = _start(harness)
    poses = _drive(harness, node, samples=20)
    harness.call(SetBool, "h2o_node/pause", SetBool.Request(data=True))
    for i in range(20, 30):  # ignored, and not counted again as a gap in the stamps
        harness.publish(Odometry, "odom", _odometry(T0 + i * 10**8, 0.6 * i), spins=0)
    harness.publish(Odometry, "loop_closure", _closure(0, 5, poses), spins=0)
    harness.spin_until(lambda: node.inputs["odometry"].discarded == 10
                       and node.inputs["loop_closure"].discarded == 1, 10.0, "paused inputs")
    harness.call(SetBool, "h2o_node/pause", SetBool.Request(data=False))
    for i in range(30, 40):
        harness.publish(Odometry, "odom", _odometry(T0 + i * 10**8, 0.6 * i), spins=0)
    bad = _closure(0, 5, poses)
    bad.child_frame_id = "node/" + "9" * 4301
    harness.publish(Odometry, "loop_closure", bad, spins=0)
    harness.publish(Odometry, "loop_closure", _closure(1, 9, poses), spins=0)
    harness.spin_until(lambda: node.inputs["odometry"].received == 40
                       and node.inputs["loop_closure"].received == 3, 10.0, "inputs")
    counts = _counts(node)
    assert counts["odometry"] == {"received": 40, "accepted": 30, "rejected": 0, "dropped": 10}
    assert counts["loop_closure"] == {"received": 3, "accepted": 1, "rejected": 1,
                                      "dropped": 1}


def test_a_held_closure_refused_when_odometry_reaches_it_counts_as_rejected(
        harness: Harness) -> None:
    node = _start(harness)
    _drive(harness, node, samples=20)  # odometry up to 1.9 s
    # Stamped after the newest odometry: held; once odometry reaches it, both ends land
    # on one keyframe and it is refused.
    later = ma.make_loop_closure(
        ma.StampRef(T0 + 25 * 10**8), ma.StampRef(T0 + 25 * 10**8 + 1), np.eye(3),
        [0.0, 0.0, 0.0], ma.planar_covariance(0.05, 0.05, 0.01, unobserved_variance=1.0))
    harness.publish(Odometry, "loop_closure", ma.fill_loop_closure(Odometry, later), spins=0)
    harness.spin_until(lambda: node.inputs["loop_closure"].accepted == 1, 10.0, "held")
    for i in range(20, 30):
        harness.publish(Odometry, "odom", _odometry(T0 + i * 10**8, 0.6 * i), spins=0)
    harness.spin_until(lambda: node.inputs["odometry"].received == 30, 10.0, "odometry")
    assert _counts(node)["loop_closure"] == {"received": 1, "accepted": 0, "rejected": 1,
                                             "dropped": 0}
    assert node.mapper.rejected["loop_same_node"] == 1


def test_start_up_says_the_node_is_ready_with_its_topics_and_budget(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    lines = info_lines(monkeypatch)
    node = harness.add(H2ONode, parameter_overrides=[Parameter("budget_ms", value=3.0)])
    ready = [line for line in lines if "ready" in line]
    assert len(ready) == 1, lines
    ns = harness.namespace
    for topic in (f"{ns}/odom", f"{ns}/loop_closure", f"{ns}/gps/fix",
                  f"{ns}/h2o_node/graph/poses", f"{ns}/h2o_node/pose",
                  f"{ns}/h2o_node/map_to_odom"):
        assert topic in ready[0], (topic, ready[0])
    assert ready[0].startswith(f"{ns}/h2o_node ready")
    assert "budget_ms 3 " in ready[0] and "loop closures" in ready[0]
    assert node.input_topics["odometry"] == f"{ns}/odom"
