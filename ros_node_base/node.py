"""The node both executables build on: parameters from a configuration tree, inputs and
outputs by key, and one boundary around every callback.

What it gives a node (``h2o_node``, ``hybrid_vo_node``):

* **Parameters**: declared from the node's configuration tree (:mod:`ros_node_base.params`)
  with descriptors (range, description, read-only unless ``runtime``), read as one typed
  snapshot, :attr:`NodeBase.config`. A change at run time is built into a whole new snapshot
  and validated before rclpy takes it; a refused change leaves the old snapshot (and the
  parameters) as they were, and a taken one reaches :meth:`NodeBase.on_config_change`.
* **Inputs**: :meth:`NodeBase.subscribe` opens a subscription whose messages are accounted
  for (:class:`ros_node_base.inputs.InputCounts`); :meth:`NodeBase.guarded` runs an input's
  handling behind the boundary.
* **The boundary**: no exception reaches the executor. The node's own errors
  (:attr:`NodeBase.expected_errors`) are bad input, logged as a warning and counted under
  :meth:`NodeBase.rejection_reason`; anything else is a bug, logged as an error and counted
  as ``<input>: unexpected <Type>``. Logs are throttled per reason.
* **Outputs**: :meth:`NodeBase.emit` publishes by key and hands every message to
  :attr:`NodeBase.sink` (replay records through it); ``/tf`` where tf2_msgs is installed;
  ``/diagnostics`` from one :class:`msg_adapters.DiagnosticReport`.
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile

import msg_adapters as ma
from ros_node_base.boundary import behind_boundary
from ros_node_base.inputs import InputCounts, counted_subscription
from ros_node_base.params import ParamSpec, param_specs, with_values

C = TypeVar("C")

#: Seconds between two log lines about the same problem.
LOG_THROTTLE_S = 5.0

Sink = Callable[[str, Any], None]


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """The ROS descriptor of a parameter: description, range, read-only unless run-time."""
    desc = ParameterDescriptor(description=spec.description, read_only=not spec.runtime)
    if spec.low is None or spec.high is None or isinstance(spec.default, bool):
        return desc
    if isinstance(spec.default, int):
        desc.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high),
                                           step=1)]
    else:
        desc.floating_point_range = [FloatingPointRange(from_value=float(spec.low),
                                                        to_value=float(spec.high), step=0.0)]
    return desc


def tf_message_class() -> Any:
    """``tf2_msgs/TFMessage``, or ``None`` where tf2_msgs is not installed."""
    try:
        return importlib.import_module("tf2_msgs.msg").TFMessage
    except ImportError:
        return None


class NodeBase(Node, Generic[C]):
    """A node configured by the tree ``config_type`` (module docstring).

    Args:
        node_name: the node's name.
        config_type: the configuration tree (a dataclass whose fields all have defaults).
        **kwargs: passed to :class:`rclpy.node.Node` (``context``, ``namespace``,
            ``parameter_overrides``, ``cli_args``, ...).

    Attributes:
        config: the parameters as one typed snapshot of the tree.
        sink: callable ``(topic, msg)`` that also receives every published message, or None.
        inputs: what became of each input's messages, by key.
        input_topics: the resolved topic of each input, by key.
        publishers_by_key: the outputs, by key.
        tf_message: ``tf2_msgs/TFMessage``, or None where it is not installed.
    """

    #: The errors that are bad input, not bugs (subclasses name their package's own).
    expected_errors: tuple[type[Exception], ...] = ()

    def __init__(self, node_name: str, config_type: type[C], **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.sink: Sink | None = None
        self.inputs: dict[str, InputCounts] = {}
        self.input_topics: dict[str, str] = {}
        self.publishers_by_key: dict[str, Any] = {}
        self.tf_message = tf_message_class()
        self._logged_s: dict[str, float] = {}
        values = {spec.name: self.declare_parameter(spec.name, spec.ros_default,
                                                    descriptor(spec)).value
                  for spec in param_specs(config_type)}
        self.config: C = with_values(config_type(), values)
        # Registered after declaring: rclpy calls them for later changes only.
        self.add_on_set_parameters_callback(self._check_change)
        self.add_post_set_parameters_callback(self.boundary("parameters", self._take_change))

    # -- parameters ---------------------------------------------------------------------------

    def _changed(self, params: list[Parameter]) -> C:
        return with_values(self.config, {p.name: p.value for p in params})

    def _check_change(self, params: list[Parameter]) -> SetParametersResult:
        refused: tuple[type[Exception], ...] = (ValueError, TypeError, KeyError,
                                                *self.expected_errors)
        try:
            self._changed(params)
        except refused as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _take_change(self, params: list[Parameter]) -> None:
        old, self.config = self.config, self._changed(params)
        self.get_logger().info(
            "parameters changed: " + ", ".join(f"{p.name}={p.value}" for p in params))
        self.on_config_change(old)

    def on_config_change(self, old: C) -> None:
        """A change at run time was taken: :attr:`config` is new, ``old`` the snapshot
        before. Nodes whose parts keep their own copy hand them the new one here."""

    # -- the boundary -------------------------------------------------------------------------

    def boundary(self, what: str, work: Callable[..., Any]) -> Callable[..., Any]:
        """``work`` (a timer, service or parameter callback) behind the boundary: an
        exception is logged and counted (:meth:`count_rejection`), never raised into the
        executor; a service then answers ``success=False`` with the reason."""
        return behind_boundary(what, work, self.count_rejection)

    def guarded(self, what: str, handler: Callable[..., None], *args: Any) -> bool:
        """Handle one message of the input ``what``: ``handler(*args)``, counted accepted,
        or, when it raises, counted rejected with its reason. Returns whether it was
        accepted."""
        counts = self.inputs[what]
        try:
            handler(*args)
        except Exception as exc:  # the boundary: no message ends the node
            counts.rejected += 1
            self.count_rejection(what, exc)
            return False
        counts.accepted += 1
        return True

    def count_rejection(self, what: str, exc: Exception) -> None:
        """Log and count a refused input (or a failed timer or service) by reason."""
        where = self.input_topics.get(what, what)
        if isinstance(exc, self.expected_errors):
            reason = self.rejection_reason(what, exc)
            self.log_throttled(reason, f"{where}: rejected: {exc}")
        else:  # a bug, not bad input: say so loudly, and keep running
            reason = f"{what}: unexpected {type(exc).__name__}"
            self.log_throttled(reason, f"{where}: unexpected {type(exc).__name__}: {exc}",
                               error=True)
        self.record_rejection(reason, exc)

    def rejection_reason(self, what: str, exc: Exception) -> str:
        """The counter name of bad input ``exc`` on ``what`` (one kind of problem, one name)."""
        return f"{what}: {exc}"

    def record_rejection(self, reason: str, exc: Exception) -> None:
        """Count a rejection under ``reason`` (nodes keep their counts where they report
        them)."""
        raise NotImplementedError

    def log_throttled(self, key: str, text: str, error: bool = False) -> None:
        """Log ``text`` unless the same ``key`` was logged less than LOG_THROTTLE_S ago."""
        now = time.monotonic()
        if now - self._logged_s.get(key, -math.inf) < LOG_THROTTLE_S:
            return
        self._logged_s[key] = now
        # Two call sites: rclpy refuses one site logging at two severities.
        if error:
            self.get_logger().error(text)
        else:
            self.get_logger().warning(text)

    # -- inputs and outputs -------------------------------------------------------------------

    def subscribe(self, key: str, msg_type: Any, topic: str, callback: Callable[[Any], None],
                  qos: QoSProfile) -> None:
        """The input ``key``: a subscription whose messages are accounted for."""
        self.inputs[key] = InputCounts()
        subscription = counted_subscription(self, self.inputs[key], msg_type, topic, callback,
                                            qos)
        self.input_topics[key] = subscription.topic_name

    def advertise(self, key: str, msg_type: Any, topic: str, qos: QoSProfile | int) -> None:
        """The output ``key``."""
        self.publishers_by_key[key] = self.create_publisher(msg_type, topic, qos)

    def advertise_tf(self, without: str) -> None:
        """The output ``tf`` on ``/tf`` where tf2_msgs is installed; where not, a warning
        saying what the node does ``without`` it."""
        if self.tf_message is None:
            self.get_logger().warning(f"tf2_msgs is not installed: {without}")
            return
        self.advertise("tf", self.tf_message, "/tf", QoSProfile(depth=100))

    def advertise_diagnostics(self) -> None:
        """The output ``diagnostics`` on ``/diagnostics``."""
        self.advertise("diagnostics", DiagnosticArray, "/diagnostics", 10)

    @property
    def output_topics(self) -> dict[str, str]:
        """Resolved topic of each output, by key."""
        return {key: pub.topic_name for key, pub in self.publishers_by_key.items()}

    def emit(self, key: str, msg: Any) -> None:
        """Publish on the output ``key`` and hand the message to the sink, if any."""
        publisher = self.publishers_by_key[key]
        publisher.publish(msg)
        if self.sink is not None:
            self.sink(publisher.topic_name, msg)

    def emit_tf(self, transform: Any) -> None:
        """One ``TransformStamped`` on ``/tf`` (the caller checks :attr:`tf_message`)."""
        self.emit("tf", ma.fill_tf_message(self.tf_message, [transform]))

    def emit_report(self, report: ma.DiagnosticReport, stamp_ns: int) -> None:
        """One ``/diagnostics`` message holding ``report``, stamped ``stamp_ns``."""
        self.emit("diagnostics", ma.fill_diagnostic_array(DiagnosticArray, [report],
                                                          stamp_ns=stamp_ns))
