"""launch/ and rviz/: the files `ros2 launch` and RViz read, checked without a ROS
installation (the launch packages are not on PyPI): the XML against the ROS 2 launch
format's tags and attributes, every node, parameter file, included file and substitution
they name, every remapping against the topics the nodes really open, the Python launch file's
shape, and the RViz displays against the topics the nodes really publish."""

from __future__ import annotations

import ast
import re
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from node_harness import Harness
from rclpy.parameter import Parameter

from h2o_slam.ros.h2o_node import H2ONode
from hybrid_vo.vo_node import HybridVoNode

REPO = Path(__file__).resolve().parents[2]
LAUNCH = REPO / "launch"
RVIZ = REPO / "rviz" / "h2o_slam.rviz"
XML_FILES = sorted(LAUNCH.glob("*.launch.xml"))
PACKAGE = "h2o_slam"

# The ROS 2 launch XML format (launch_xml / launch_ros frontends, Jazzy): the tags used here,
# their allowed attributes and children, and the attributes each requires.
CONDITIONS = {"if", "unless"}
FORMAT: dict[str, dict[str, Any]] = {
    "launch": {"attrs": {"version"}, "children": {"arg", "node", "include", "executable",
                                                   "group", "let", "set_env"}},
    "arg": {"attrs": {"name", "default", "description"}, "required": {"name"}},
    "node": {"attrs": {"pkg", "exec", "name", "namespace", "output", "args", "respawn",
                       "ros_args"} | CONDITIONS,
             "required": {"pkg", "exec"}, "children": {"param", "remap", "env"}},
    "param": {"attrs": {"name", "value", "from"}},
    "remap": {"attrs": {"from", "to"}, "required": {"from", "to"}},
    "include": {"attrs": {"file"} | CONDITIONS, "required": {"file"}, "children": {"arg"}},
    "include/arg": {"attrs": {"name", "value"}, "required": {"name", "value"}},
    "executable": {"attrs": {"cmd", "name", "output", "cwd", "shell"} | CONDITIONS,
                   "required": {"cmd"}},
}
SUBSTITUTION = re.compile(r"\$\(([a-z-]+)\s*([^)]*)\)")
KNOWN_SUBSTITUTIONS = {"var", "find-pkg-share", "find-pkg-prefix", "env"}


def console_scripts() -> set[str]:
    tree = ast.parse((REPO / "setup.py").read_text())
    names = {node.value.split("=")[0].strip() for node in ast.walk(tree)
             if isinstance(node, ast.Constant) and isinstance(node.value, str)
             and re.fullmatch(r"[\w-]+ = [\w.]+:\w+", node.value)}
    assert {"h2o_node", "hybrid_vo_node", "h2o-replay"} <= names
    return names


def resolve(text: str, args: dict[str, str]) -> str:
    """Substitute ``$(var …)`` with argument defaults and the package's share/prefix with
    the source tree (where setup.py installs from)."""
    def one(match: re.Match[str]) -> str:
        kind, value = match.group(1), match.group(2).strip()
        assert kind in KNOWN_SUBSTITUTIONS, match.group(0)
        if kind == "var":
            assert value in args, f"$(var {value}) names no <arg>"
            return args[value]
        if kind in ("find-pkg-share", "find-pkg-prefix"):
            assert value == PACKAGE or value == "rviz2", match.group(0)
            return str(REPO) if kind == "find-pkg-share" else "<prefix>"
        return "<env>"
    while SUBSTITUTION.search(text):  # argument defaults may hold substitutions
        text = SUBSTITUTION.sub(one, text)
    return text


def walk(element: ET.Element, parent: str = "") -> Iterator[tuple[str, ET.Element]]:
    key = f"{parent}/{element.tag}" if f"{parent}/{element.tag}" in FORMAT else element.tag
    yield key, element
    for child in element:
        yield from walk(child, element.tag)


def args_of(root: ET.Element) -> dict[str, str]:
    return {a.attrib["name"]: a.attrib.get("default", "<given>") for a in root.findall("arg")}


@pytest.mark.parametrize("path", XML_FILES, ids=lambda p: p.name)
def test_launch_xml_follows_the_ros2_launch_format(path: Path) -> None:
    root = ET.parse(path).getroot()
    assert root.tag == "launch"
    for key, element in walk(root):
        assert key in FORMAT, f"{path.name}: <{element.tag}> is not a launch tag used here"
        spec = FORMAT[key]
        assert set(element.attrib) <= spec["attrs"], (key, element.attrib)
        assert spec.get("required", set()) <= set(element.attrib), (key, element.attrib)
        for child in element:
            assert child.tag in spec.get("children", set()), (key, child.tag)
        if element.tag == "param":  # a file, or one name = value
            assert set(element.attrib) in ({"from"}, {"name", "value"}), element.attrib


@pytest.mark.parametrize("path", XML_FILES, ids=lambda p: p.name)
def test_everything_a_launch_file_names_exists(path: Path) -> None:
    root = ET.parse(path).getroot()
    args = args_of(root)
    scripts = console_scripts()
    for element in root.iter():
        for value in element.attrib.values():
            resolve(value, args)  # every substitution is known and every var declared
    for node in root.iter("node"):
        if node.attrib["pkg"] == PACKAGE:
            assert node.attrib["exec"] in scripts
        else:
            assert (node.attrib["pkg"], node.attrib["exec"]) == ("rviz2", "rviz2")
            rviz = resolve(node.attrib["args"], args).split("-d ", 1)[1]
            assert Path(rviz) == RVIZ
        for param in node.iter("param"):
            if "from" in param.attrib:
                assert Path(resolve(param.attrib["from"], args)).is_file(), param.attrib
    for include in root.iter("include"):
        included = Path(resolve(include.attrib["file"], args))
        assert included.parent == LAUNCH and included.is_file()
        declared = args_of(ET.parse(included).getroot())
        assert {a.attrib["name"] for a in include.iter("arg")} <= set(declared)
    for exe in root.iter("executable"):
        cmd = resolve(exe.attrib["cmd"], args).split()
        assert cmd[0] == "<prefix>/lib/h2o_slam/h2o-replay" and "--realtime" in cmd
        assert Path(cmd[cmd.index("--topics") + 1]).is_file()


def test_the_replay_launch_needs_a_bag_and_the_robot_launch_needs_nothing() -> None:
    robot = ET.parse(LAUNCH / "h2o_slam.launch.xml").getroot()
    assert all("default" in a.attrib for a in robot.findall("arg"))
    replay = ET.parse(LAUNCH / "h2o_slam_replay.launch.xml").getroot()
    assert [a.attrib["name"] for a in replay.findall("arg") if "default" not in a.attrib] \
        == ["bag"]


def test_python_launch_file_includes_the_xml_and_imports_launch_only_when_run() -> None:
    path = LAUNCH / "h2o_slam.launch.py"
    tree = ast.parse(path.read_text())
    top_imports = {alias.name.split(".")[0] for node in tree.body
                   if isinstance(node, ast.Import | ast.ImportFrom)
                   for alias in (node.names if isinstance(node, ast.Import)
                                 else [ast.alias(node.module or "")])}
    assert not top_imports & {"launch", "launch_ros"}
    functions = {node.name for node in tree.body if isinstance(node, ast.FunctionDef)}
    assert "generate_launch_description" in functions
    assert '"h2o_slam.launch.xml"' in path.read_text()


@pytest.fixture(scope="module")
def node_topics() -> Iterator[dict[str, dict[str, set[str]]]]:
    """Names (relative to the harness namespace) of what each node subscribes and publishes,
    with raw and with compressed images."""
    h = Harness()
    try:
        out: dict[str, dict[str, set[str]]] = {}
        for key, make, overrides in (
                ("h2o_node", H2ONode, []),
                ("hybrid_vo_node", HybridVoNode, []),
                ("hybrid_vo_node/compressed", HybridVoNode,
                 [Parameter("use_compressed", value=True), Parameter("publish_debug_image",
                                                                     value=True)])):
            node = h.add(make, parameter_overrides=overrides)
            strip = len(h.namespace) + 1
            out[key] = {
                "in": {s.topic_name[strip:] for s in node.subscriptions
                       if s.topic_name.startswith(h.namespace)},
                "out": {p.topic_name if not p.topic_name.startswith(h.namespace + "/")
                        else p.topic_name[strip:] for p in node.publishers},
            }
            h.remove(node)
        yield out
    finally:
        h.close()


def test_remappings_name_the_topics_the_nodes_open(node_topics) -> None:
    root = ET.parse(LAUNCH / "h2o_slam.launch.xml").getroot()
    for node in root.iter("node"):
        name = node.attrib.get("name")
        if node.attrib["pkg"] != PACKAGE:
            continue
        inputs = node_topics[name]["in"] | node_topics.get(f"{name}/compressed", {}).get(
            "in", set())
        remapped = {r.attrib["from"] for r in node.iter("remap")}
        assert remapped <= inputs, remapped - inputs
        # Every input the node opens is remappable from the command line.
        assert inputs - {"parameter_events"} <= remapped, inputs - remapped
    # The VO's output feeds h2o_node by default.
    default = args_of(root)["odometry"]
    assert default.lstrip("/") in node_topics["hybrid_vo_node"]["out"]


def test_parameter_files_set_the_launched_node_names() -> None:
    root = ET.parse(LAUNCH / "h2o_slam.launch.xml").getroot()
    args = args_of(root)
    for node in root.iter("node"):
        for param in node.iter("param"):
            if "from" in param.attrib:
                data = yaml.safe_load(Path(resolve(param.attrib["from"], args)).read_text())
                assert node.attrib["name"] in data, (node.attrib["name"], list(data))


def test_rviz_shows_the_graph_path_markers_and_tf_the_nodes_publish(node_topics) -> None:
    config = yaml.safe_load(RVIZ.read_text())
    manager = config["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == "map"
    displays = {d["Class"].split("/")[-1]: d for d in manager["Displays"]}
    assert {"TF", "Path", "PoseArray", "MarkerArray", "Pose", "Odometry"} <= set(displays)
    published = {"/" + t.lstrip("/") for key in ("h2o_node", "hybrid_vo_node/compressed")
                 for t in node_topics[key]["out"]}
    for display in manager["Displays"]:
        if "Topic" in display:
            assert display["Topic"]["Value"] in published, display["Name"]
    # The graph topics are latched: RViz must ask for transient-local to get them.
    for kind in ("Path", "PoseArray", "MarkerArray"):
        assert displays[kind]["Topic"]["Durability Policy"] == "Transient Local"
    assert {p["Class"] for p in config["Panels"]} >= {"rviz_common/Displays"}
