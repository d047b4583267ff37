"""The shared ``main`` of the node executables: how a node stops."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
import rclpy
from rclpy.node import Node
from std_msgs.msg import Empty

from ros_node_base.main import run_node


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


@pytest.mark.parametrize("delay_s", [0.0, 0.3, 0.8, 2.0])
def test_ctrl_c_at_any_instant_of_the_start_is_a_quiet_stop(delay_s: float) -> None:
    """SIGINT to the process group, as a terminal sends it, while the node still imports
    or builds itself: exit 0, no traceback (it used to print the import it interrupted).
    The clock starts when the entry point is called (the interpreter's own start-up, before
    any of the package's code runs, is Python's)."""
    code = ("import sys; from h2o_slam.app.cli import nodes; print('entered', flush=True); "
            "sys.exit(nodes.h2o_node())")
    proc = subprocess.Popen([sys.executable, "-c", code, "--ros-args", "-r",
                             f"__ns:=/sigint{os.getpid()}"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "entered"
    time.sleep(delay_s)
    os.killpg(proc.pid, signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err
    assert "Traceback" not in err, err


def test_a_signal_while_the_node_is_built_is_a_normal_stop() -> None:
    """rclpy's handler shuts the context down on SIGINT/SIGTERM; a node still being built
    then fails with "the given context is not valid" (seen on a busy machine): exit 0."""

    def built_after_the_signal() -> Node:
        rclpy.shutdown()  # what the signal handler does
        return Node("built_after_the_signal")

    assert run_node(built_after_the_signal, "test", (), []) == 0


def test_only_the_half_built_rclpy_logger_is_silenced_at_a_stop() -> None:
    """What a Ctrl-C inside ``RcutilsLogger.__init__`` leaves (a logger without the
    attribute its ``__del__`` reads) is dropped; any other unraisable error still reaches
    the hook that was there before."""
    from rclpy.impl.rcutils_logger import RcutilsLogger

    from ros_node_base.main import _quiet_half_built_logger

    seen: list[sys.UnraisableHookArgs] = []
    before = sys.unraisablehook
    sys.unraisablehook = _quiet_half_built_logger(seen.append)
    try:
        half_built = RcutilsLogger.__new__(RcutilsLogger)
        del half_built

        class Other:
            def __del__(self) -> None:
                raise AttributeError("another bug")

        other = Other()
        del other
    finally:
        sys.unraisablehook = before
    assert [str(u.exc_value) for u in seen] == ["another bug"]
