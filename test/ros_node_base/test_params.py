"""Parameters from a configuration tree: names, defaults and ranges from the fields, a
snapshot from values, and a change validated whole."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from ros_node_base.documents import parameters_yaml, yaml_value
from ros_node_base.params import param_specs, spec_named, with_values


@dataclass(frozen=True)
class Limits:
    low: float = field(default=0.0, metadata={"doc": "Lower end.", "range": (-10.0, 10.0),
                                              "runtime": True})
    high: float = field(default=1.0, metadata={"doc": "Upper end.", "runtime": True})
    internal: int = 3

    def __post_init__(self) -> None:
        if self.low > self.high:
            raise ValueError(f"low {self.low} > high {self.high}")


@dataclass(frozen=True)
class Tree:
    name: str = field(default="x", metadata={"doc": "A name."})
    offset: tuple[float, ...] = field(default=(0.0, 0.0), metadata={"doc": "An offset."})
    limits: Limits = field(default_factory=Limits)
    flat: Limits = field(default_factory=lambda: Limits(2.0, 3.0), metadata={"flat": True})


@dataclass(frozen=True)
class Twice:
    low: float = field(default=0.0, metadata={"doc": "Clashes with the flat group's."})
    flat: Limits = field(default_factory=Limits, metadata={"flat": True})


def test_the_specs_are_the_documented_fields_in_order() -> None:
    specs = param_specs(Tree)
    assert [s.name for s in specs] == ["name", "offset", "limits.low", "limits.high", "low",
                                       "high"]
    low = spec_named(Tree, "limits.low")
    assert (low.path, low.low, low.high, low.runtime) == (("limits", "low"), -10.0, 10.0, True)
    assert spec_named(Tree, "low").default == 2.0  # the group's own default
    assert spec_named(Tree, "offset").ros_default == [0.0, 0.0]
    with pytest.raises(KeyError, match="internal"):
        spec_named(Tree, "limits.internal")
    with pytest.raises(ValueError, match="used twice"):
        param_specs(Twice)


def test_a_snapshot_takes_values_by_name_and_types_them() -> None:
    config = with_values(Tree(), {"offset": [1, 2.5], "limits.high": 4, "low": -1.0})
    assert config.offset == (1.0, 2.5) and isinstance(config.offset[0], float)
    assert config.limits == Limits(0.0, 4.0) and isinstance(config.limits.high, float)
    assert config.flat == Limits(-1.0, 3.0)
    assert with_values(config, {}) is config


def test_a_change_is_validated_whole_and_leaves_the_old_snapshot() -> None:
    old = Tree()
    with pytest.raises(ValueError, match="low 5.0 > high 1.0"):
        with_values(old, {"limits.low": 5.0})
    assert old.limits == Limits()
    new = with_values(old, {"limits.low": 5.0, "limits.high": 6.0})  # together they fit
    assert new.limits == Limits(5.0, 6.0) and new.flat is old.flat
    with pytest.raises(KeyError, match="limits.internal"):
        with_values(old, {"limits.internal": 4})


def test_the_yaml_nests_dotted_names_and_keeps_float_points() -> None:
    text = parameters_yaml("n", Tree, "head")
    assert text.startswith("# head\nn:\n  ros__parameters:\n")
    assert "    limits:\n      # Lower end. [-10, 10] Run-time changeable.\n      low: 0.0\n" \
        in text
    assert "    # Lower end. [-10, 10] Run-time changeable.\n    low: 2.0\n" in text
    assert [yaml_value(v) for v in (1e-6, 2.0, 3, True, "a b", (0.0, 1.5))] == [
        "1.0e-06", "2.0", "3", "true", '"a b"', "[0.0, 1.5]"]
