"""The shared ``main`` of the node executables: how a node stops."""

from __future__ import annotations

import pytest
import rclpy
from rclpy.node import Node
from std_msgs.msg import Empty

from h2o_slam.ros.node_main import run_node


class ShutsDownMidCallback(Node):
    """Stands in for SIGTERM arriving while a timer callback publishes: the context is
    shut down under the callback, whose publish then fails."""

    def __init__(self) -> None:
        super().__init__("shuts_down_mid_callback")
        self.pub = self.create_publisher(Empty, "~/out", 1)
        self.create_timer(0.01, self.tick)

    def tick(self) -> None:
        rclpy.shutdown()
        self.pub.publish(Empty())


class FailsInCallback(Node):
    def __init__(self) -> None:
        super().__init__("fails_in_callback")
        self.create_timer(0.01, self.tick)

    def tick(self) -> None:
        raise RuntimeError("a real bug")


def test_a_callback_cut_short_by_shutdown_is_a_normal_stop() -> None:
    assert run_node(ShutsDownMidCallback, "test", (), []) == 0
    assert not rclpy.ok()


def test_a_callback_failing_while_running_still_fails() -> None:
    with pytest.raises(RuntimeError, match="a real bug"):
        run_node(FailsInCallback, "test", (), [])
    assert not rclpy.ok()
