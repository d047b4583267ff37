"""msg_adapters.outputs: PoseArray, Path, MarkerArray, TF and diagnostics for the h2o_node."""

from __future__ import annotations

import numpy as np
import pytest
from bag_messages import TYPESTORE, random_rotation, to_rosbags
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, TransformStamped
from nav_msgs.msg import Path
from rclpy.serialization import deserialize_message, serialize_message
from visualization_msgs.msg import Marker, MarkerArray

from h2o_slam.core.geometry import compose
from msg_adapters import (
    AdapterError,
    DiagnosticReport,
    GraphMarkers,
    fill_diagnostic_array,
    fill_graph_markers,
    fill_path,
    fill_pose_array,
    fill_tf_message,
    fill_transform,
    map_to_odom,
    pose_to_matrix,
    quaternion_to_matrix,
    stamp_ns,
)
from msg_adapters.outputs import DROPPED_COLOR, residual_colors

R = np.stack([random_rotation(k) for k in range(4)])
T = np.arange(12, dtype=float).reshape(4, 3)


def test_pose_array_and_path() -> None:
    pa = fill_pose_array(PoseArray, R, T, stamp_ns=42)
    assert pa.header.frame_id == "map" and stamp_ns(pa.header) == 42
    # Through the wire and back into rosbags: the message is well formed.
    pa_bag = to_rosbags(pa)
    for k in range(4):
        Rk, tk = pose_to_matrix(pa_bag.poses[k])
        np.testing.assert_allclose(Rk, R[k], atol=1e-12)
        np.testing.assert_allclose(tk, T[k])
    path = fill_path(Path(), R, T, stamp_ns=50, stamps_ns=[1, 2, 3, 4], frame_id="world")
    assert [stamp_ns(p.header) for p in path.poses] == [1, 2, 3, 4]
    assert {p.header.frame_id for p in path.poses} == {"world"}
    np.testing.assert_allclose(pose_to_matrix(path.poses[2].pose)[1], T[2])
    assert [stamp_ns(p.header) for p in fill_path(Path, R, T, stamp_ns=9).poses] == [9] * 4
    assert (
        fill_pose_array(PoseArray, np.zeros((0, 3, 3)), np.zeros((0, 3)), stamp_ns=0).poses == []
    )


def test_pose_outputs_reject() -> None:
    with pytest.raises(AdapterError, match=r"PoseArray R: expected shape \(n, 3, 3\)"):
        fill_pose_array(PoseArray, np.eye(3), T[0], stamp_ns=0)
    with pytest.raises(AdapterError, match=r"PoseArray t: expected shape \(4, 3\)"):
        fill_pose_array(PoseArray, R, T[:3], stamp_ns=0)
    with pytest.raises(AdapterError, match="Path t: contains NaN"):
        fill_path(Path, R, np.full((4, 3), np.nan), stamp_ns=0)
    with pytest.raises(AdapterError, match="3 stamps for 4 poses"):
        fill_path(Path, R, T, stamp_ns=0, stamps_ns=[1, 2, 3])
    with pytest.raises(AdapterError, match="not a rotation matrix"):
        fill_pose_array(PoseArray, 2 * R, T, stamp_ns=0)
    with pytest.raises(AdapterError, match="needs an rclpy message class"):
        fill_pose_array(to_rosbags(PoseArray()), R, T, stamp_ns=0)


def test_tf_map_to_odom() -> None:
    R_mb, t_mb, R_ob, t_ob = R[0], T[0], R[1], T[1]
    R_mo, t_mo = map_to_odom(R_mb, t_mb, R_ob, t_ob)
    # map→odom · odom→base = map→base
    Rc, tc = compose(R_mo, t_mo, R_ob, t_ob)
    np.testing.assert_allclose(Rc, R_mb, atol=1e-12)
    np.testing.assert_allclose(tc, t_mb, atol=1e-12)
    tf = fill_transform(
        TransformStamped, R_mo, t_mo, stamp_ns=7, frame_id="map", child_frame_id="odom"
    )
    back = to_rosbags(tf)
    assert (back.header.frame_id, back.child_frame_id, stamp_ns(back.header)) == ("map", "odom", 7)
    tr, q = back.transform.translation, back.transform.rotation
    np.testing.assert_allclose([tr.x, tr.y, tr.z], t_mo, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(q), R_mo, atol=1e-12)
    with pytest.raises(AdapterError, match="odom→base R: contains NaN"):
        map_to_odom(R_mb, t_mb, np.full((3, 3), np.nan), t_ob)
    with pytest.raises(AdapterError, match="not a rotation"):
        fill_transform(
            TransformStamped, 3 * R_mo, t_mo, stamp_ns=0, frame_id="a", child_frame_id="b"
        )


def test_tf_message_rosbags() -> None:
    tf_cls = TYPESTORE.types["tf2_msgs/msg/TFMessage"]
    tf = to_rosbags(
        fill_transform(
            TransformStamped, R[0], T[0], stamp_ns=7, frame_id="map", child_frame_id="odom"
        )
    )
    msg = fill_tf_message(tf_cls(transforms=[]), [tf])
    raw = TYPESTORE.serialize_cdr(msg, "tf2_msgs/msg/TFMessage")
    back = TYPESTORE.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage")
    assert back.transforms[0].child_frame_id == "odom"


def test_tf_message_rclpy() -> None:
    tf2_msgs = pytest.importorskip("tf2_msgs.msg", reason="tf2_msgs is not installed")
    tf = fill_transform(
        TransformStamped, R[0], T[0], stamp_ns=7, frame_id="map", child_frame_id="odom"
    )
    msg = fill_tf_message(tf2_msgs.TFMessage, [tf])
    back = deserialize_message(serialize_message(msg), tf2_msgs.TFMessage)
    assert back.transforms[0].child_frame_id == "odom"


def test_graph_markers() -> None:
    graph = GraphMarkers(
        positions=T,
        edges=np.array([[0, 1], [1, 2], [2, 3], [3, 0]]),
        edge_residuals=np.array([0.0, 1.0, 10.0, 1e6]),
        gps_nodes=np.array([1, 3]),
        gps_positions=T[[1, 3]] + 0.5,
        gps_residuals=np.array([0.0, 100.0]),
    )
    msg = fill_graph_markers(MarkerArray, graph, stamp_ns=3, clear=True)
    deserialize_message(serialize_message(msg), MarkerArray)  # well formed on the wire
    wipe, nodes, edges, gps, dropped = msg.markers
    assert (dropped.ns, len(dropped.points)) == ("dropped", 0)
    assert wipe.action == Marker.DELETEALL
    assert (nodes.ns, nodes.type, len(nodes.points)) == ("nodes", Marker.SPHERE_LIST, 4)
    assert (edges.ns, edges.type, len(edges.points), len(edges.colors)) == (
        "edges",
        Marker.LINE_LIST,
        8,
        8,
    )
    assert (gps.ns, len(gps.points)) == ("gps", 4)
    assert gps.points[1].x == T[1, 0] + 0.5
    # Edges: green at zero residual, red at large; GPS: a different (cyan → magenta) scale.
    assert (edges.colors[0].r, edges.colors[0].g) == (0.0, 1.0)
    assert edges.colors[6].r == 1.0 and edges.colors[6].g < 0.01
    assert edges.colors[2].r == edges.colors[2].g == 1.0  # residual = scale: yellow
    assert (gps.colors[0].r, gps.colors[0].g, gps.colors[0].b) == (0.0, 1.0, 1.0)
    assert gps.colors[2].b == 1.0 and gps.colors[2].r > 0.9
    # Without GPS or edges the namespaces stay, empty.
    only_nodes = fill_graph_markers(MarkerArray(), GraphMarkers(positions=T), stamp_ns=3)
    assert [len(m.points) for m in only_nodes.markers] == [4, 0, 0, 0]


def test_dropped_edges_and_fixes_are_drawn_apart() -> None:
    """Closures and fixes the robust back end holds out leave the χ²-coloured lists for
    their own namespace and colour."""
    graph = GraphMarkers(
        positions=T, edges=np.array([[0, 1], [1, 2], [2, 3], [3, 0]]),
        edge_residuals=np.array([0.0, 1.0, 10.0, 1e6]), gps_nodes=np.array([1, 3]),
        gps_positions=T[[1, 3]] + 0.5, gps_residuals=np.array([0.0, 100.0]),
        edge_dropped=np.array([False, False, False, True]),
        gps_dropped=np.array([False, True]))
    _, edges, gps, dropped = fill_graph_markers(MarkerArray, graph, stamp_ns=3).markers
    assert (len(edges.points), len(gps.points), len(dropped.points)) == (6, 2, 4)
    assert dropped.ns == "dropped" and dropped.type == Marker.LINE_LIST
    assert (dropped.color.r, dropped.color.g, dropped.color.b) == pytest.approx(
        DROPPED_COLOR[:3])
    assert (dropped.points[0].x, dropped.points[1].x) == (T[3, 0], T[0, 0])
    assert dropped.points[3].x == T[3, 0] + 0.5  # the fix's measured position
    with pytest.raises(AdapterError, match="edges dropped: expected 4 booleans"):
        fill_graph_markers(MarkerArray, GraphMarkers(
            positions=T, edges=graph.edges, edge_residuals=graph.edge_residuals,
            edge_dropped=np.array([1, 0, 0, 0])), stamp_ns=3)


@pytest.mark.parametrize(
    ("graph", "match"),
    [
        (GraphMarkers(positions=np.zeros((2, 2))), r"expected shape \(n, 3\)"),
        (GraphMarkers(positions=T, edges=[[0, 4]], edge_residuals=[1.0]), r"in \[0, 4\)"),
        (GraphMarkers(positions=T, edges=[[0, 1]], edge_residuals=[]), "0 for 1 edges"),
        (GraphMarkers(positions=T, edges=[0, 1], edge_residuals=[1.0]), "bad shape"),
        (GraphMarkers(positions=T, edges=[[0.5, 1]], edge_residuals=[1.0]), "integers"),
        (GraphMarkers(positions=T, gps_nodes=[0], gps_positions=[[0, 0, 0]]), "0 residuals"),
        (GraphMarkers(positions=[[np.nan] * 3]), "graph positions: contains NaN"),
    ],
)
def test_graph_markers_reject(graph: GraphMarkers, match: str) -> None:
    with pytest.raises(AdapterError, match=match):
        fill_graph_markers(MarkerArray, graph, stamp_ns=0)


def test_residual_colors_reject() -> None:
    with pytest.raises(AdapterError, match="scale 0 must be > 0"):
        residual_colors([1.0], 0)


def test_diagnostics() -> None:
    reports = [
        DiagnosticReport(
            "h2o_node: solver",
            "WARN",
            "over budget",
            {"callback_ms_p99": 5.123456789, "overruns": 3, "paused": False},
            "h2o",
        ),
        DiagnosticReport("h2o_node: gps", 0),
    ]
    msg = fill_diagnostic_array(DiagnosticArray, reports, stamp_ns=11)
    back = deserialize_message(serialize_message(msg), DiagnosticArray)
    first = back.status[0]
    assert first.level == DiagnosticStatus.WARN
    assert (first.name, first.message, first.hardware_id) == (
        "h2o_node: solver",
        "over budget",
        "h2o",
    )
    assert {kv.key: kv.value for kv in first.values} == {
        "callback_ms_p99": "5.12346",
        "overruns": "3",
        "paused": "false",
    }
    assert back.status[1].level == DiagnosticStatus.OK
    assert to_rosbags(msg).status[0].level == 1
    with pytest.raises(AdapterError, match="unknown 'FINE'"):
        fill_diagnostic_array(DiagnosticArray, [DiagnosticReport("x", "FINE")], stamp_ns=0)
    with pytest.raises(AdapterError, match="level: 7 outside 0..3"):
        fill_diagnostic_array(DiagnosticArray, [DiagnosticReport("x", 7)], stamp_ns=0)
