"""The nodes' parameter files and the tables of doc/nodes.md are what the configuration trees
say: a default, range, name or description changed in one place only fails here."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from rclpy.parameter import Parameter, parameter_dict_from_yaml_file

from h2o_slam.app.parameter_files import NODES, PAGE, stale, written
from ros_node_base.params import param_specs

ROOT = Path(__file__).resolve().parents[1]
FIX = "run `python -m h2o_slam.app.parameter_files` and commit what it writes"


def test_the_yaml_files_and_doc_tables_are_what_the_trees_write() -> None:
    assert stale(ROOT) == [], f"differ from the configuration trees: {FIX}"


@pytest.mark.parametrize("node", NODES, ids=lambda n: n.node)
def test_ros_reads_every_default_back_with_its_type(node) -> None:
    """What ROS loads from the file (``--params-file``) is each declared default, of the
    declared type (a float keeps its point, an array stays a list)."""
    loaded = parameter_dict_from_yaml_file(str(ROOT / node.yaml))
    specs = param_specs(node.tree)
    assert list(loaded) == [spec.name for spec in specs]
    for spec in specs:
        value = Parameter.from_parameter_msg(loaded[spec.name]).value
        got = list(value) if isinstance(value, list | tuple) or hasattr(value, "tolist") \
            else value
        assert got == spec.ros_default and type(got) is type(spec.ros_default), spec.name


def _copy(tmp_path: Path) -> Path:
    for path in written(ROOT):
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / path, tmp_path / path)
    return tmp_path


@pytest.mark.parametrize(
    ("path", "old", "new"),
    [
        (Path("config/h2o.yaml"), "    budget_ms: 5.0\n", "    budget_ms: 4.0\n"),
        (Path("config/h2o.yaml"), "    keyframe_distance: 0.5\n", "    keyframe_dist: 0.5\n"),
        (Path("config/hybrid_vo.yaml"), "      num_patches: 6\n", "      num_patches: 7\n"),
        (PAGE, "| `budget_ms` | 5.0 | 0–1000 |", "| `budget_ms` | 5.0 | 0–100 |"),
        (PAGE, "| `camera_pitch` | 0.0 |", "| `camera_tilt` | 0.0 |"),
    ],
)
def test_a_drifted_default_name_or_range_is_found(tmp_path: Path, path: Path, old: str,
                                                  new: str) -> None:
    root = _copy(tmp_path)
    text = (root / path).read_text()
    assert text.count(old) == 1, old
    (root / path).write_text(text.replace(old, new))
    assert stale(root) == [path]
