"""The nodes' parameter files and tables, written from their configuration trees.

``config/h2o.yaml``, ``config/hybrid_vo.yaml`` and the two parameter tables of
``doc/nodes.md`` are what :class:`h2o_slam.ros.node_config.H2ONodeConfig` and
:class:`hybrid_vo.node_config.VoNodeConfig` say, written by :mod:`ros_node_base.documents`.
After changing a tree, ``python -m h2o_slam.app.parameter_files`` writes them again;
``test/test_parameter_files.py`` fails while they differ. (Here in ``app``, the one place
that joins both nodes' packages.)
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from h2o_slam.ros.node_config import H2ONodeConfig
from hybrid_vo.node_config import VoNodeConfig
from ros_node_base.documents import TABLE_HEAD, parameter_table, parameters_yaml

ROOT = Path(__file__).resolve().parents[2]
#: The page holding both nodes' parameter tables.
PAGE = Path("doc/nodes.md")


@dataclass(frozen=True)
class NodeParameters:
    """Where one node's parameters are written.

    Attributes:
        node: the node's name (the YAML's top key).
        tree: its configuration tree.
        yaml: the parameter file, relative to the repository.
        header: the parameter file's opening comment.
        heading: the heading of the node's section in :data:`PAGE`, which holds its table.
    """

    node: str
    tree: type[Any]
    yaml: Path
    header: str
    heading: str


_WRITTEN = ("Written from {tree}\nby `python -m h2o_slam.app.parameter_files`: change the "
            "tree, not this file\n(test/test_parameter_files.py compares the two).")

NODES = (
    NodeParameters(
        "h2o_node", H2ONodeConfig, Path("config/h2o.yaml"),
        "h2o_node parameters (ros2 run h2o_slam h2o_node --ros-args --params-file "
        "config/h2o.yaml).\nEach entry: meaning, [range], and whether it can change while "
        "the node runs.\n" + _WRITTEN.format(tree="h2o_slam.ros.node_config.H2ONodeConfig"),
        "## `h2o_node`"),
    NodeParameters(
        "hybrid_vo_node", VoNodeConfig, Path("config/hybrid_vo.yaml"),
        "hybrid_vo_node parameters (ros2 run h2o_slam hybrid_vo_node --ros-args --params-file\n"
        "config/hybrid_vo.yaml). Every parameter is listed with its default; ranges are "
        "enforced\nwhen the node starts (a value outside them stops it with one line naming "
        "the parameter).\nAll parameters are read at start-up only. Write floating-point "
        "values with a decimal\npoint (1.0, not 1): ROS 2 refuses an integer for a double "
        "parameter.\n" + _WRITTEN.format(tree="hybrid_vo.node_config.VoNodeConfig"),
        "## `hybrid_vo_node`"),
)


def with_table(page: str, heading: str, table: str) -> str:
    """``page`` with the parameter table of the section under ``heading`` replaced."""
    section = page.index(heading + "\n")
    start = page.index(TABLE_HEAD, section)
    end = re.compile(r"^(?!\|)", flags=re.M).search(page, start + len(TABLE_HEAD))
    stop = end.start() if end else len(page)
    return page[:start] + table + page[stop:]


def written(root: Path = ROOT) -> dict[Path, str]:
    """Every file the trees write, by path relative to ``root``, as they should read."""
    files = {node.yaml: parameters_yaml(node.node, node.tree, node.header) for node in NODES}
    page = (root / PAGE).read_text(encoding="utf-8")
    for node in NODES:
        page = with_table(page, node.heading, parameter_table(node.tree))
    files[PAGE] = page
    return files


def stale(root: Path = ROOT) -> list[Path]:
    """The files under ``root`` that differ from what the trees write."""
    return [path for path, text in written(root).items()
            if (root / path).read_text(encoding="utf-8") != text]


def main() -> int:
    """Write every stale file again; prints the ones written. Run in a source checkout
    (an installed copy has no ``doc/``): exit code 1 elsewhere."""
    if not (ROOT / PAGE).is_file():
        print(f"parameter_files: no {PAGE} under {ROOT}: run it in a source checkout",
              file=sys.stderr)
        return 1
    for path, text in written().items():
        target = ROOT / path
        if target.read_text(encoding="utf-8") != text:
            target.write_text(text, encoding="utf-8")
            print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
