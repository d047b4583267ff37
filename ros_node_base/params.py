"""A node's parameters, read from its configuration tree: one frozen dataclass per group.

The tree is the single source of truth: a node declares one ROS parameter per documented
leaf field (name, default, range and description from the field), reads the values back as
one typed snapshot of the tree, and applies a change at run time by building the whole new
snapshot (its ``__post_init__`` checks validate it) before taking it. ``config/*.yaml`` and
the parameter tables of ``doc/nodes.md`` are written from the same tree
(:mod:`ros_node_base.documents`).

What a field says, in its ``metadata`` (plain keys, so that the cores holding the trees
need import nothing of this package; :func:`h2o_slam.core.parameters.parameter` writes the
first three):

* ``doc``: the description; a leaf field without one is internal and not a parameter.
* ``range``: ``(low, high)``, inclusive; the node refuses a value outside it.
* ``runtime``: ``True`` where a change takes effect while the node runs (the rest are
  read-only after start-up).
* ``flat``: on a field holding a group (a dataclass), ``True`` declares the group's
  parameters under their own names; otherwise they are dotted, ``<field>.<name>``.

A tuple default is a ROS array parameter (a list in YAML); the snapshot holds a tuple.

This module does not import rclpy: the trees can be read, checked and documented without it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

C = TypeVar("C")

#: The value types a parameter may have (a tuple: an array parameter).
Value = bool | int | float | str | tuple[Any, ...]


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of a tree.

    Attributes:
        name: the ROS parameter name (dotted below a group that is not flat).
        path: the attribute names leading to the field from the tree's root.
        default: the field's default.
        description: the field's ``doc``.
        low, high: the inclusive range (``None``: none).
        runtime: a change takes effect while the node runs.
    """

    name: str
    path: tuple[str, ...]
    default: Value
    description: str
    low: float | None = None
    high: float | None = None
    runtime: bool = False

    @property
    def ros_default(self) -> bool | int | float | str | list[Any]:
        """The default as rclpy declares it (an array as a list)."""
        return list(self.default) if isinstance(self.default, tuple) else self.default

    def value_of(self, config: Any) -> Value:
        """This parameter's value in a snapshot of the tree."""
        for name in self.path:
            config = getattr(config, name)
        return config


def _is_group(value: Any) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def _walk(group: Any, prefix: str, path: tuple[str, ...]) -> Iterator[ParamSpec]:
    for f in dataclasses.fields(group):
        value = getattr(group, f.name)
        meta = f.metadata
        if _is_group(value):
            inner = prefix if meta.get("flat") else f"{prefix}{f.name}."
            yield from _walk(value, inner, (*path, f.name))
        elif "doc" in meta:
            low, high = meta.get("range", (None, None))
            yield ParamSpec(f"{prefix}{f.name}", (*path, f.name), value, meta["doc"], low, high,
                            bool(meta.get("runtime", False)))


def param_specs(tree: type[Any]) -> tuple[ParamSpec, ...]:
    """Every parameter of ``tree`` (a dataclass whose fields all have defaults), in the
    order of its fields, groups in place."""
    specs = tuple(_walk(tree(), "", ()))
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"{tree.__name__}: a parameter name is used twice: {names}")
    return specs


def spec_named(tree: type[Any], name: str) -> ParamSpec:
    """The parameter ``name`` of ``tree``."""
    for spec in param_specs(tree):
        if spec.name == name:
            return spec
    raise KeyError(f"{tree.__name__} has no parameter {name!r}")


def _typed(value: Any, default: Value) -> Value:
    """A parameter value as the field's type (rclpy has checked the ROS type already)."""
    if isinstance(default, tuple):
        return tuple(float(v) if isinstance(v, int | float) else v for v in value)
    if isinstance(default, float) and not isinstance(value, bool):
        return float(value)
    return value


def _rebuild(group: C, values: Mapping[tuple[str, ...], Any], path: tuple[str, ...]) -> C:
    changes = {}
    for f in dataclasses.fields(group):  # type: ignore[arg-type]
        value = getattr(group, f.name)
        here = (*path, f.name)
        if _is_group(value):
            new = _rebuild(value, values, here)
            if new is not value:
                changes[f.name] = new
        elif here in values:
            changes[f.name] = _typed(values[here], value)
    # replace() runs the group's __post_init__: the checks of every changed group.
    return dataclasses.replace(group, **changes) if changes else group  # type: ignore[type-var]


def with_values(config: C, values: Mapping[str, Any]) -> C:
    """``config`` with the parameters ``values`` (by ROS name) changed: a new snapshot, each
    changed group validated by its own checks.

    Raises:
        KeyError: a name that is not a parameter of the tree.
        whatever the groups' checks raise for a value they refuse.
    """
    by_name = {spec.name: spec for spec in param_specs(type(config))}
    unknown = sorted(set(values) - set(by_name))
    if unknown:
        raise KeyError(f"not parameters of {type(config).__name__}: {unknown}")
    return _rebuild(config, {by_name[n].path: v for n, v in values.items()}, ())
