"""A configuration tree written out for people: the ``--params-file`` YAML of a node and the
parameter table of its documentation page.

Both are written from the tree (:mod:`ros_node_base.params`), so a name, default, range or
description cannot drift from what the node declares; a test compares the files in the
repository with what these functions write. No rclpy here.
"""

from __future__ import annotations

import json
import textwrap
from typing import Any

from ros_node_base.params import ParamSpec, Value, param_specs

#: The YAML line length (the repository's).
WIDTH = 99

#: The head of a parameter table.
TABLE_HEAD = "| parameter | default | range | meaning |\n| --- | --- | --- | --- |\n"
#: What a parameter table adds to the meaning of a parameter that changes at run time.
RUN_TIME = "**Run time.**"


def yaml_value(value: Value) -> str:
    """A default as YAML that ROS reads back with the same type (a float keeps its point)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, float):
        text = repr(value)
        mantissa, e, exponent = text.partition("e")
        return text if "." in mantissa or not e else f"{mantissa}.0e{exponent}"
    if isinstance(value, str):
        return json.dumps(value)
    return str(value)


def range_text(spec: ParamSpec) -> str:
    """``[low, high]`` or nothing."""
    return "" if spec.low is None or spec.high is None else f"[{spec.low:g}, {spec.high:g}]"


def _comment(spec: ParamSpec, indent: str) -> list[str]:
    words = " ".join(t for t in (spec.description, range_text(spec),
                                 "Run-time changeable." if spec.runtime else "") if t)
    return textwrap.wrap(words, WIDTH - len(indent) - 2, initial_indent=f"{indent}# ",
                         subsequent_indent=f"{indent}# ", break_on_hyphens=False)


def parameters_yaml(node_name: str, tree: type[Any], header: str) -> str:
    """The ``--params-file`` YAML of ``node_name``: ``header`` (comment lines), then every
    parameter of ``tree`` with its description, range and run-time note as a comment; dotted
    names nest."""
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    lines += [f"{node_name}:", "  ros__parameters:"]
    opened: list[str] = []
    for spec in param_specs(tree):
        *groups, leaf = spec.name.split(".")
        keep = 0
        while keep < min(len(groups), len(opened)) and groups[keep] == opened[keep]:
            keep += 1
        for depth in range(keep, len(groups)):
            lines.append(f"{'  ' * (depth + 2)}{groups[depth]}:")
        opened = groups
        indent = "  " * (len(groups) + 2)
        lines += _comment(spec, indent)
        lines.append(f"{indent}{leaf}: {yaml_value(spec.default)}")
    return "\n".join(lines) + "\n"


def table_default(value: Value) -> str:
    """A default as a parameter table writes it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return f"`{list(value)}`"
    if isinstance(value, str):
        return f"`{value}`"
    return str(value)


def parameter_table(tree: type[Any]) -> str:
    """The Markdown table of every parameter of ``tree``: name, default, range, meaning
    (``**Run time.**`` where a change takes effect while the node runs)."""
    rows = []
    for spec in param_specs(tree):
        limits = "" if spec.low is None or spec.high is None else f"{spec.low:g}–{spec.high:g}"
        meaning = spec.description.replace("|", "\\|") + (f" {RUN_TIME}" if spec.runtime
                                                           else "")
        rows.append(f"| `{spec.name}` | {table_default(spec.default)} | {limits} | {meaning} |")
    return TABLE_HEAD + "\n".join(rows) + "\n"
