"""What the h2o_node publishes: PoseArray, Path, MarkerArray, TF and DiagnosticArray.

Each ``fill_*`` takes a message instance (filled in place) or a message class (a new
instance is made) and returns the message, so this module never imports rclpy or a
message package itself. Messages that hold sequences of other messages (``poses``,
``markers``, ``transforms``, ``status``, ``values``, ``points``) must be rclpy message
classes: the element classes are found from the generated type description.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from h2o_slam.core.geometry import compose, inverse, matrix_to_quat
from msg_adapters._util import Array, as_rotations, element_class, finite_array, new_message
from msg_adapters.errors import AdapterError
from msg_adapters.rotations import fill_transform_fields
from msg_adapters.stamps import fill_header


def _set_poses(poses: list[Any], R: Array, t: Array, what: str) -> None:
    """Write ``(R[k], t[k])`` into ``poses[k]`` (``geometry_msgs/Pose``), the quaternions
    computed in one batch: per-pose conversion costs ~80 µs, too much for a 5 ms budget."""
    if len(R):
        err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(1, 2))
        bad = np.flatnonzero((err > 1e-6) | (np.linalg.det(R) < 0.0))
        if bad.size:
            raise AdapterError(f"{what} R[{bad[0]}]: not a rotation matrix")
    q = matrix_to_quat(R).tolist() if len(R) else []
    for pose, qk, tk in zip(poses, q, t.tolist(), strict=True):
        pos, ori = pose.position, pose.orientation
        pos.x, pos.y, pos.z = tk
        ori.x, ori.y, ori.z, ori.w = qk


def fill_pose_array(
    msg_or_cls: Any, R: Any, t: Any, *, stamp_ns: int, frame_id: str = "map"
) -> Any:
    """``geometry_msgs/PoseArray`` of world poses ``R (n, 3, 3)``, ``t (n, 3)``;
    pose ``i`` is graph node ``i``."""
    msg = new_message(msg_or_cls)
    R_arr, t_arr = as_rotations(R, t, "PoseArray")
    pose_cls = element_class(msg, "poses")
    fill_header(msg.header, stamp_ns, frame_id)
    poses = [pose_cls() for _ in range(len(R_arr))]
    _set_poses(poses, R_arr, t_arr, "PoseArray")
    msg.poses = poses
    return msg


def fill_path(
    msg_or_cls: Any,
    R: Any,
    t: Any,
    *,
    stamp_ns: int,
    frame_id: str = "map",
    stamps_ns: Sequence[int] | None = None,
) -> Any:
    """``nav_msgs/Path`` of world poses ``R (n, 3, 3)``, ``t (n, 3)``.

    Args:
        stamps_ns: each pose's own stamp (the keyframe's); ``stamp_ns`` for all if omitted.
    """
    msg = new_message(msg_or_cls)
    R_arr, t_arr = as_rotations(R, t, "Path")
    if stamps_ns is not None and len(stamps_ns) != len(R_arr):
        raise AdapterError(f"Path: {len(stamps_ns)} stamps for {len(R_arr)} poses")
    stamps = [stamp_ns] * len(R_arr) if stamps_ns is None else list(stamps_ns)
    pose_cls = element_class(msg, "poses")
    fill_header(msg.header, stamp_ns, frame_id)
    poses = []
    for si in stamps:
        ps = pose_cls()
        fill_header(ps.header, si, frame_id)
        poses.append(ps)
    _set_poses([ps.pose for ps in poses], R_arr, t_arr, "Path")
    msg.poses = poses
    return msg


def fill_transform(
    msg_or_cls: Any, R: Any, t: Any, *, stamp_ns: int, frame_id: str, child_frame_id: str
) -> Any:
    """``geometry_msgs/TransformStamped``: pose ``(R, t)`` of ``child_frame_id`` in
    ``frame_id``."""
    msg = new_message(msg_or_cls)
    fill_header(msg.header, stamp_ns, frame_id)
    msg.child_frame_id = str(child_frame_id)
    fill_transform_fields(msg.transform, R, t)
    return msg


def fill_tf_message(msg_or_cls: Any, transforms: Iterable[Any]) -> Any:
    """``tf2_msgs/TFMessage`` holding the given ``TransformStamped`` messages."""
    msg = new_message(msg_or_cls)
    msg.transforms = list(transforms)
    return msg


def map_to_odom(
    R_map_base: Any, t_map_base: Any, R_odom_base: Any, t_odom_base: Any
) -> tuple[Array, Array]:
    """The ``map → odom`` transform ``T_map_base · T_odom_base⁻¹`` that makes the
    optimized pose of ``base`` in ``map`` agree with the odometry's pose in ``odom``."""
    Ri, ti = inverse(
        finite_array(R_odom_base, "odom→base R", (3, 3)),
        finite_array(t_odom_base, "odom→base t", (3,)),
    )
    return compose(
        finite_array(R_map_base, "map→base R", (3, 3)),
        finite_array(t_map_base, "map→base t", (3,)),
        Ri,
        ti,
    )


# ---------------------------------------------------------------------------- markers

#: Marker namespaces of :func:`fill_graph_markers`.
NS_NODES, NS_EDGES, NS_GPS, NS_DROPPED = "nodes", "edges", "gps", "dropped"
_ADD, _DELETEALL = 0, 3
_SPHERE_LIST, _LINE_LIST = 7, 5


def residual_colors(residuals: Any, scale: float, gps: bool = False) -> Array:
    """RGBA ``(n, 4)`` for residuals (χ² per edge): ``r / (r + scale)`` maps 0 → green,
    ``scale`` → yellow, ∞ → red; GPS edges go from cyan (0) to magenta (∞) instead."""
    r = np.maximum(finite_array(residuals, "residuals").ravel(), 0.0)
    if not scale > 0.0:
        raise AdapterError(f"residual colour scale {scale} must be > 0")
    u = r / (r + scale)
    out = np.ones((len(r), 4))
    if gps:
        out[:, 0], out[:, 1], out[:, 2] = u, 1.0 - u, 1.0
    else:
        out[:, 0] = np.minimum(1.0, 2.0 * u)
        out[:, 1] = np.minimum(1.0, 2.0 * (1.0 - u))
        out[:, 2] = 0.0
    return out


@dataclass
class GraphMarkers:
    """Geometry for :func:`fill_graph_markers` (all in the ``map`` frame, metres).

    Attributes:
        positions: node positions ``(n, 3)``.
        edges: node index pairs ``(m, 2)`` of relative-pose edges.
        edge_residuals: χ² of each edge ``(m,)``.
        gps_nodes: node index of each GPS edge ``(k,)``.
        gps_positions: measured ENU position of each GPS edge ``(k, 3)``.
        gps_residuals: χ² of each GPS edge ``(k,)``.
        edge_dropped, gps_dropped: which edges the robust back end holds out as outliers
            (bool ``(m,)`` and ``(k,)``; default none): drawn in their own namespace
            ``dropped`` and colour instead of by χ².
    """

    positions: Any
    edges: Any = field(default_factory=lambda: np.zeros((0, 2), dtype=int))
    edge_residuals: Any = field(default_factory=lambda: np.zeros(0))
    gps_nodes: Any = field(default_factory=lambda: np.zeros(0, dtype=int))
    gps_positions: Any = field(default_factory=lambda: np.zeros((0, 3)))
    gps_residuals: Any = field(default_factory=lambda: np.zeros(0))
    edge_dropped: Any = None
    gps_dropped: Any = None


#: Colour (r, g, b, a) of edges held out as outliers: orange, half transparent.
DROPPED_COLOR = (1.0, 0.55, 0.0, 0.6)


def _dropped(values: Any, count: int, what: str) -> Any:
    """A bool mask of ``count`` entries (``None``: none dropped)."""
    if values is None:
        return np.zeros(count, dtype=bool)
    mask = np.asarray(values)
    if mask.shape != (count,) or mask.dtype != bool:
        raise AdapterError(f"{what}: expected {count} booleans, got {mask.dtype} {mask.shape}")
    return mask


def _indices(values: Any, n: int, pairs: bool, what: str) -> Any:
    """Node indices ``(m, 2)`` (``pairs``) or ``(k,)``, checked against ``n`` nodes."""
    idx = np.asarray(values)
    if idx.size == 0:
        return np.zeros((0, 2) if pairs else (0,), dtype=int)
    if (idx.ndim, idx.shape[-1]) != ((2, 2) if pairs else (1, idx.shape[-1])):
        raise AdapterError(f"{what}: bad shape {idx.shape}")
    if not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= n:
        raise AdapterError(f"{what}: node indices must be integers in [0, {n})")
    return idx


def fill_graph_markers(
    msg_or_cls: Any,
    graph: GraphMarkers,
    *,
    stamp_ns: int,
    frame_id: str = "map",
    residual_scale: float = 1.0,
    node_scale_m: float = 0.1,
    line_width_m: float = 0.03,
    clear: bool = False,
) -> Any:
    """``visualization_msgs/MarkerArray`` of the graph: namespace ``nodes`` (one sphere
    list), ``edges`` (a line list coloured by χ², green → red), ``gps`` (lines from
    each node to its GPS measurement, cyan → magenta) and ``dropped`` (loop closures and
    fixes held out as outliers, :data:`DROPPED_COLOR`). With ``clear``, a ``DELETEALL``
    marker comes first (after a reset)."""
    msg = new_message(msg_or_cls)
    pos = finite_array(graph.positions, "graph positions")
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise AdapterError(f"graph positions: expected shape (n, 3), got {pos.shape}")
    n = len(pos)
    edges = _indices(graph.edges, n, True, "graph edges")
    edge_res = finite_array(graph.edge_residuals, "edge residuals").ravel()
    if len(edge_res) != len(edges):
        raise AdapterError(f"edge residuals: {len(edge_res)} for {len(edges)} edges")
    gps_nodes = _indices(graph.gps_nodes, n, False, "gps nodes")
    gps_pos = finite_array(graph.gps_positions, "gps positions").reshape(-1, 3)
    gps_res = finite_array(graph.gps_residuals, "gps residuals").ravel()
    if not len(gps_nodes) == len(gps_pos) == len(gps_res):
        raise AdapterError(
            f"gps markers: {len(gps_nodes)} nodes, {len(gps_pos)} positions, "
            f"{len(gps_res)} residuals"
        )
    edge_out = _dropped(graph.edge_dropped, len(edges), "edges dropped")
    gps_out = _dropped(graph.gps_dropped, len(gps_nodes), "gps dropped")
    marker_cls = element_class(msg, "markers")
    proto = marker_cls()
    point_cls = element_class(proto, "points")
    color_cls = element_class(proto, "colors")

    def marker(ns: str, kind: int, scale: float) -> Any:
        m = marker_cls()
        fill_header(m.header, stamp_ns, frame_id)
        m.ns, m.id, m.type, m.action = ns, 0, kind, _ADD
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = float(scale)
        m.color.r, m.color.g, m.color.b, m.color.a = 1.0, 1.0, 1.0, 1.0
        return m

    def point(p: Array) -> Any:
        out = point_cls()
        out.x, out.y, out.z = float(p[0]), float(p[1]), float(p[2])
        return out

    def color(c: Array) -> Any:
        out = color_cls()
        out.r, out.g, out.b, out.a = (float(v) for v in c)
        return out

    markers = []
    if clear:
        wipe = marker_cls()
        fill_header(wipe.header, stamp_ns, frame_id)
        wipe.action = _DELETEALL
        markers.append(wipe)
    nodes = marker(NS_NODES, _SPHERE_LIST, node_scale_m)
    nodes.color.r, nodes.color.g, nodes.color.b = 0.2, 0.4, 1.0
    nodes.points = [point(p) for p in pos]
    markers.append(nodes)
    for ns, starts, ends, res, gps in (
        (NS_EDGES, pos[edges[~edge_out, 0]], pos[edges[~edge_out, 1]], edge_res[~edge_out],
         False),
        (NS_GPS, pos[gps_nodes[~gps_out]], gps_pos[~gps_out], gps_res[~gps_out], True),
    ):
        lines = marker(ns, _LINE_LIST, line_width_m)
        cols = residual_colors(res, residual_scale, gps=gps)
        lines.points = [point(p) for pair in zip(starts, ends, strict=True) for p in pair]
        lines.colors = [color(c) for c in cols for _ in range(2)]
        markers.append(lines)
    dropped = marker(NS_DROPPED, _LINE_LIST, line_width_m)
    dropped.color.r, dropped.color.g, dropped.color.b, dropped.color.a = DROPPED_COLOR
    starts = np.concatenate([pos[edges[edge_out, 0]], pos[gps_nodes[gps_out]]])
    ends = np.concatenate([pos[edges[edge_out, 1]], gps_pos[gps_out]])
    dropped.points = [point(p) for pair in zip(starts, ends, strict=True) for p in pair]
    markers.append(dropped)
    msg.markers = markers
    return msg


# ----------------------------------------------------------------------- diagnostics

#: ``diagnostic_msgs/DiagnosticStatus`` levels by name.
LEVELS = {"OK": 0, "WARN": 1, "ERROR": 2, "STALE": 3}


@dataclass
class DiagnosticReport:
    """One ``DiagnosticStatus``: ``level`` is 0..3 or ``"OK"``, ``"WARN"``, ``"ERROR"``,
    ``"STALE"``; ``values`` become key/value strings (floats with 6 significant digits,
    booleans as ``true``/``false``)."""

    name: str
    level: int | str
    message: str = ""
    values: Mapping[str, object] = field(default_factory=dict)
    hardware_id: str = ""


def format_value(value: object) -> str:
    """A diagnostics value as text."""
    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    if isinstance(value, float | np.floating):
        return f"{float(value):.6g}"
    return str(value)


def _level(level: int | str) -> int:
    if isinstance(level, str):
        if level.upper() not in LEVELS:
            raise AdapterError(f"diagnostic level: unknown {level!r} (OK, WARN, ERROR, STALE)")
        return LEVELS[level.upper()]
    if int(level) not in LEVELS.values():
        raise AdapterError(f"diagnostic level: {level} outside 0..3")
    return int(level)


def fill_diagnostic_array(
    msg_or_cls: Any, reports: Iterable[DiagnosticReport], *, stamp_ns: int
) -> Any:
    """``diagnostic_msgs/DiagnosticArray`` of the given reports."""
    msg = new_message(msg_or_cls)
    status_cls = element_class(msg, "status")
    kv_cls = None
    fill_header(msg.header, stamp_ns, "")
    statuses = []
    for report in reports:
        st = status_cls()
        kv_cls = kv_cls or element_class(st, "values")
        level = _level(report.level)
        # `byte` is bytes of length 1 in rclpy (an int in rosbags).
        st.level = bytes([level]) if isinstance(st.level, bytes) else level
        st.name, st.message, st.hardware_id = report.name, report.message, report.hardware_id
        values = []
        for key, value in report.values.items():
            kv = kv_cls()
            kv.key, kv.value = str(key), format_value(value)
            values.append(kv)
        st.values = values
        statuses.append(st)
    msg.status = statuses
    return msg
