"""A configuration field that is also a node parameter.

The nodes declare their ROS parameters from their configuration trees
(:mod:`ros_node_base.params`): a field is a parameter when its ``metadata`` has a ``doc``,
with an inclusive ``range`` and a ``runtime`` flag beside it. :func:`parameter` writes that
metadata, so that the keys are spelt in one place (a misspelt key would be silently ignored)
and every core that holds part of a tree can use it without importing the node base.
"""

from __future__ import annotations

from dataclasses import field
from typing import Any


def parameter(default: Any, doc: str, bounds: tuple[float, float] | None = None,
              runtime: bool = False) -> Any:
    """A dataclass field with ``default`` that the node declares as a parameter described
    by ``doc``, refused outside the inclusive ``bounds``, and changeable while the node runs
    when ``runtime``."""
    metadata: dict[str, Any] = {"doc": doc, "runtime": runtime}
    if bounds is not None:
        metadata["range"] = bounds
    return field(default=default, metadata=metadata)
