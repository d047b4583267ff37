"""In-process rclpy harness for node tests: a fresh context, one SingleThreadedExecutor,
a test node with real publishers and subscribers, and waiting with a timeout.

Each harness puts everything under a unique namespace so that tests running at the same
time on this machine (same DDS domain, loopback profile) never see each other's topics.
"""

from __future__ import annotations

import gc
import time
import uuid
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Harness:
    """Owns the context; nodes under test are added with :meth:`add`."""

    def __init__(self) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.namespace = "/t" + uuid.uuid4().hex[:10]
        self.executor = SingleThreadedExecutor(context=self.context)
        self.tester = Node("tester", namespace=self.namespace, context=self.context)
        self.executor.add_node(self.tester)
        self.received: dict[str, list[Any]] = defaultdict(list)
        self._publishers: dict[str, Any] = {}

    def add(self, make: Callable[..., Node], **kwargs: Any) -> Any:
        """Create a node under test in this harness's namespace and context."""
        node = make(namespace=self.namespace, context=self.context, **kwargs)
        self.executor.add_node(node)
        return node

    def remove(self, node: Node) -> None:
        """Stop spinning a node and destroy it (a "restart" is remove + add)."""
        self.executor.remove_node(node)
        node.destroy_node()

    def topic(self, name: str) -> str:
        """Absolute name of a relative topic in the harness namespace."""
        return name if name.startswith("/") else f"{self.namespace}/{name}"

    def publisher(self, msg_type: Any, name: str, qos: QoSProfile = RELIABLE) -> Any:
        """A (cached) publisher on ``name``."""
        key = self.topic(name)
        if key not in self._publishers:
            self._publishers[key] = self.tester.create_publisher(msg_type, key, qos)
        return self._publishers[key]

    def subscribe(self, msg_type: Any, name: str, qos: QoSProfile = RELIABLE) -> list[Any]:
        """Collect every message on ``name``; returns the (live) list."""
        key = self.topic(name)
        self.tester.create_subscription(msg_type, key, self.received[key].append, qos)
        return self.received[key]

    def publish(self, msg_type: Any, name: str, msg: Any, spins: int = 3) -> None:
        """Publish and let the executor deliver it."""
        self.publisher(msg_type, name).publish(msg)
        for _ in range(spins):
            self.executor.spin_once(timeout_sec=0.0)

    def wait_for_subscribers(self, msg_type: Any, name: str, count: int = 1,
                             timeout_s: float = 10.0) -> None:
        """Block until ``count`` subscribers have matched a publisher (discovery)."""
        pub = self.publisher(msg_type, name)
        self.spin_until(lambda: pub.get_subscription_count() >= count, timeout_s,
                        f"no subscriber on {self.topic(name)}")

    def spin_until(self, done: Callable[[], bool], timeout_s: float = 10.0,
                   what: str = "condition") -> None:
        """Spin until ``done()`` or fail after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        """Spin for a while (timers fire)."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def call(self, srv_type: Any, name: str, request: Any, timeout_s: float = 30.0) -> Any:
        """Call a service and wait for the answer."""
        client = self.tester.create_client(srv_type, self.topic(name))
        self.spin_until(lambda: client.service_is_ready(), timeout_s, f"service {name}")
        future = client.call_async(request)
        self.spin_until(future.done, timeout_s, f"answer of {name}")
        self.tester.destroy_client(client)
        return future.result()

    def close(self) -> None:
        """Destroy everything, shut the context down and free its DDS participant."""
        self.executor.shutdown()
        for node in list(self.executor.get_nodes()) + [self.tester]:
            node.destroy_node()
        rclpy.shutdown(context=self.context)
        # The participant goes with the context object, which nodes' reference cycles keep
        # alive until a collection (and the solver freezes the collector): collect now, or
        # every test leaves one behind.
        del self.executor, self.tester, self.context, self._publishers
        gc.unfreeze()
        gc.collect()


def info_lines(monkeypatch: Any) -> list[str]:
    """Every rclpy logger info line from now on, as the node's code wrote it (the logger
    still prints them); ``monkeypatch`` is pytest's, which undoes the spy."""
    from rclpy.impl.rcutils_logger import RcutilsLogger

    lines: list[str] = []
    info = RcutilsLogger.info

    def spy(self: RcutilsLogger, message: str, **kwargs: Any) -> Any:
        lines.append(message)
        return info(self, message, **kwargs)

    monkeypatch.setattr(RcutilsLogger, "info", spy)
    return lines
