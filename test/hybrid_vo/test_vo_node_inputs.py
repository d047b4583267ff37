"""hybrid_vo_node's inputs: the start-up line, and every message of each input accounted
for in /diagnostics (received = accepted + rejected + dropped), bursts included."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from node_harness import Harness, info_lines
from sensor_msgs.msg import Image

import msg_adapters as ma
from hybrid_vo.vo_node import HybridVoNode

T0 = 1_700_000_000 * 10**9
KEYS = ("odom", "left_info", "right_info", "left_image", "right_image")
COUNTS = ("received", "accepted", "rejected", "dropped")


def _counts(node: HybridVoNode) -> dict[str, dict[str, int]]:
    """The input counts as the node's next /diagnostics carries them (from the sink: other
    tests' nodes of the same name publish on the global topic too)."""
    sent: list[Any] = []
    node.sink = lambda topic, msg: sent.append(msg) if topic == "/diagnostics" else None
    node.publish_diagnostics(T0)
    node.sink = None
    values = {kv.key: kv.value for kv in sent[-1].status[0].values}
    return {key: {c: int(values[f"input.{key}.{c}"]) for c in COUNTS} for key in KEYS}


def _wheel(stamp_ns: int, x: float) -> Odometry:
    sample = ma.planar_odometry_sample(stamp_ns, "odom", "base_link", x, 0.0, 0.0,
                                       ma.planar_covariance(0.01, 0.01, 0.01))
    return ma.fill_odometry(Odometry, sample)


def _image(stamp_ns: int) -> Image:
    return ma.fill_image(Image, np.zeros((48, 64), np.uint8), stamp_ns=stamp_ns,
                         frame_id="left")


def test_a_burst_of_wheel_odometry_is_taken_whole(harness: Harness) -> None:
    # 10 s of 100 Hz wheel odometry waiting at once (a stalled node): the queue (100 deep
    # before) overwrote 90 % of it without a trace.
    node = harness.add(HybridVoNode)
    harness.wait_for_subscribers(Odometry, "odom")
    publisher = harness.publisher(Odometry, "odom")
    for i in range(1000):
        publisher.publish(_wheel(T0 + i * 10**7, 0.01 * i))
    odom = node.inputs["odom"]
    harness.spin_until(lambda: odom.received >= 1000, 60.0, "1000 wheel samples taken")
    assert _counts(node)["odom"] == {"received": 1000, "accepted": 1000, "rejected": 0,
                                     "dropped": 0}


def test_images_unpaired_refused_or_reset_away_are_accounted_for(harness: Harness) -> None:
    node = harness.add(HybridVoNode)  # sync_queue_size 10
    for i in range(12):  # no partner: the two oldest overflow the synchronizer's queue
        node.on_left_image(_image(T0 + i * 10**8))
    node.on_left_image(_image(T0))  # time going backwards: refused
    node.on_right_image(_image(T0 + 11 * 10**8))  # pairs the newest; the 9 before it drop
    node.on_right_image(_image(T0 + 12 * 10**8))  # waits for a partner...
    node.reset()  # ...and is dropped with the queue
    counts = _counts(node)
    assert counts["left_image"] == {"received": 13, "accepted": 1, "rejected": 1,
                                    "dropped": 11}
    assert counts["right_image"] == {"received": 2, "accepted": 1, "rejected": 0,
                                     "dropped": 1}
    assert node.sync.stats.dropped[0] == 11


def test_start_up_says_the_node_is_ready_with_its_topics(
        harness: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    lines = info_lines(monkeypatch)
    harness.add(HybridVoNode)
    ready = [line for line in lines if "ready" in line]
    assert len(ready) == 1, lines
    ns = harness.namespace
    assert ready[0].startswith(f"{ns}/hybrid_vo_node ready")
    for topic in ("left/image_rect", "right/image_rect", "left/camera_info",
                  "right/camera_info", "odom", "odometry/hybrid"):
        assert f"{ns}/{topic}" in ready[0], (topic, ready[0])
    assert "work_width_px 160" in ready[0] and "odom -> base_link" in ready[0]
