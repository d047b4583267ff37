"""The node base: parameters declared from a tree, read as one snapshot, changed whole."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest
from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter

from ros_node_base.inputs import InputCounts
from ros_node_base.node import NodeBase


@dataclass(frozen=True)
class Window:
    low: float = field(default=0.0, metadata={"doc": "Lower end.", "range": (-10.0, 10.0),
                                              "runtime": True})
    high: float = field(default=1.0, metadata={"doc": "Upper end.", "runtime": True})
    depth: int = field(default=5, metadata={"doc": "Fixed at start-up.", "range": (1, 9)})

    def __post_init__(self) -> None:
        if self.low > self.high:
            raise ValueError(f"low {self.low} > high {self.high}")


class WindowNode(NodeBase[Window]):
    expected_errors = (ValueError,)

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("window", Window, **kwargs)
        self.changes: list[tuple[Window, Window]] = []
        self.rejected: list[str] = []

    def on_config_change(self, old: Window) -> None:
        self.changes.append((old, self.config))

    def record_rejection(self, reason: str, exc: Exception) -> None:
        self.rejected.append(reason)


def _set(node: WindowNode, **values: Any) -> SetParametersResult:
    return node.set_parameters_atomically([Parameter(k, value=v) for k, v in values.items()])


def test_parameters_are_declared_from_the_tree_and_read_as_one_snapshot(harness) -> None:
    node = harness.add(WindowNode, parameter_overrides=[Parameter("depth", value=7)])
    assert node.config == Window(depth=7)
    assert node.describe_parameter("low").floating_point_range[0].from_value == -10.0
    assert node.describe_parameter("depth").integer_range[0].to_value == 9
    assert node.describe_parameter("depth").read_only
    assert not node.describe_parameter("high").read_only
    with pytest.raises(InvalidParameterValueException):
        harness.add(WindowNode, parameter_overrides=[Parameter("depth", value=10)])


def test_a_change_is_taken_whole_or_not_at_all(harness) -> None:
    node = harness.add(WindowNode)
    refused = _set(node, low=5.0)  # above high: the whole snapshot is checked
    assert not refused.successful and "low 5.0 > high 1.0" in refused.reason
    assert node.config == Window() and node.get_parameter("low").value == 0.0
    assert node.changes == []
    assert _set(node, low=5.0, high=6.0).successful
    assert node.config == Window(low=5.0, high=6.0)
    assert node.changes == [(Window(), Window(low=5.0, high=6.0))]
    assert not _set(node, depth=3).successful  # read-only after start-up
    assert node.config.depth == 5


def test_the_boundary_counts_what_it_catches(harness) -> None:
    node = harness.add(WindowNode)
    node.inputs["in"] = InputCounts()

    def bad() -> None:
        raise ValueError("in.value: 3 is not allowed")

    def bug() -> None:
        raise KeyError("oops")

    assert not node.guarded("in", bad) and not node.guarded("in", bug)
    assert node.guarded("in", lambda: None)
    assert node.rejected == ["in: in.value: 3 is not allowed", "in: unexpected KeyError"]
    assert (node.inputs["in"].accepted, node.inputs["in"].rejected) == (1, 2)
    timer = node.boundary("timer", bug)
    assert timer() is None and node.rejected[-1] == "timer: unexpected KeyError"
