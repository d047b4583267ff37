"""Quaternions of ROS messages (``x, y, z, w``) ⇄ the cores' rotation matrices.

The cores use rotation matrices (:mod:`h2o_slam.core.geometry`); quaternions meet them only
here. A quaternion must be finite, non-zero and of unit norm within ``norm_tol`` (it is
then normalized); anything else is a malformed message, not something to repair.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from msg_adapters._util import MAX_POSITION_M, Array, finite_array
from msg_adapters.errors import AdapterError

#: Default tolerance on ``|‖q‖ − 1|`` for an incoming quaternion.
QUAT_NORM_TOL = 1e-3


def quaternion_array(q: Any, field: str = "orientation") -> Array:
    """``(x, y, z, w)`` of a quaternion message (``.x .y .z .w``) or a sequence of four."""
    if all(hasattr(q, name) for name in ("x", "y", "z", "w")):
        q = (q.x, q.y, q.z, q.w)
        if all(isinstance(v, float) and math.isfinite(v) for v in q):
            return np.array(q)  # the common case, without numpy's checks
    return finite_array(q, field, (4,))


def quaternion_to_matrix(
    q: Any, field: str = "orientation", norm_tol: float | None = QUAT_NORM_TOL
) -> Array:
    """Rotation matrix ``(3, 3)`` of a quaternion message or ``(x, y, z, w)`` sequence.

    Args:
        q: ``geometry_msgs/Quaternion`` (rclpy or rosbags) or four numbers.
        field: the field name used in error messages.
        norm_tol: accepted ``|‖q‖ − 1|``; ``None`` accepts any non-zero norm.

    Raises:
        AdapterError: NaN/inf, zero quaternion, or norm off by more than ``norm_tol``.
    """
    x, y, z, w = (float(v) for v in quaternion_array(q, field))
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm < 1e-9:
        raise AdapterError(f"{field}: zero quaternion")
    if norm_tol is not None and abs(norm - 1.0) > norm_tol:
        raise AdapterError(f"{field}: quaternion norm {norm:.6g} is not 1 (tolerance {norm_tol})")
    # One quaternion per message: plain floats are ~10x faster than the batched numpy path
    # (h2o_slam.core.geometry.quat_to_matrix), which 50 Hz odometry notices.
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return np.array([
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ])


def matrix_to_quaternion(R: Any) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` with ``w ≥ 0`` of a rotation matrix ``(3, 3)``.

    Raises:
        AdapterError: NaN/inf or not a rotation (``RᵀR`` off the identity by > 1e-6,
            or a reflection).
    """
    R_arr = finite_array(R, "rotation", (3, 3))
    err = float(np.max(np.abs(R_arr.T @ R_arr - np.eye(3))))
    (a, b, c), (d, e, f), (g, h, i) = R_arr.tolist()
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if err > 1e-6 or det < 0.0:
        raise AdapterError(f"rotation: not a rotation matrix (|RᵀR − I| = {err:.3g})")
    # Shepperd: divide by the largest of the four candidates, in plain floats (one matrix
    # per message; the batched h2o_slam.core.geometry.matrix_to_quat costs ~10x more).
    trace = a + e + i
    if trace >= max(a, e, i):
        r = math.sqrt(1.0 + trace)
        q = ((h - f) / (2 * r), (c - g) / (2 * r), (d - b) / (2 * r), 0.5 * r)
    elif a >= e and a >= i:
        r = math.sqrt(1.0 + a - e - i)
        q = (0.5 * r, (b + d) / (2 * r), (c + g) / (2 * r), (h - f) / (2 * r))
    elif e >= i:
        r = math.sqrt(1.0 - a + e - i)
        q = ((b + d) / (2 * r), 0.5 * r, (f + h) / (2 * r), (c - g) / (2 * r))
    else:
        r = math.sqrt(1.0 - a - e + i)
        q = ((c + g) / (2 * r), (f + h) / (2 * r), 0.5 * r, (d - b) / (2 * r))
    norm = math.sqrt(sum(v * v for v in q))
    sign = -1.0 if q[3] < 0.0 else 1.0
    x, y, z, w = (sign * v / norm for v in q)
    return x, y, z, w


def fill_quaternion(msg: Any, R: Any) -> Any:
    """Set ``x, y, z, w`` of a ``geometry_msgs/Quaternion`` from a rotation matrix."""
    msg.x, msg.y, msg.z, msg.w = matrix_to_quaternion(R)
    return msg


def fill_pose(msg: Any, R: Any, t: Any) -> Any:
    """Set a ``geometry_msgs/Pose`` (``position``, ``orientation``) from ``R``, ``t``."""
    t_arr = finite_array(t, "position", (3,))
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in t_arr)
    fill_quaternion(msg.orientation, R)
    return msg


def fill_transform_fields(msg: Any, R: Any, t: Any) -> Any:
    """Set a ``geometry_msgs/Transform`` (``translation``, ``rotation``) from ``R``, ``t``."""
    t_arr = finite_array(t, "translation", (3,))
    msg.translation.x, msg.translation.y, msg.translation.z = (float(v) for v in t_arr)
    fill_quaternion(msg.rotation, R)
    return msg


def pose_to_matrix(
    msg: Any, field: str = "pose", norm_tol: float | None = QUAT_NORM_TOL
) -> tuple[Array, Array]:
    """``(R (3, 3), t (3,))`` of a ``geometry_msgs/Pose``, validated: finite, every
    coordinate within :data:`~msg_adapters._util.MAX_POSITION_M`, a unit quaternion."""
    p = msg.position
    t = finite_array((p.x, p.y, p.z), f"{field}.position", (3,), max_abs=MAX_POSITION_M)
    R = quaternion_to_matrix(msg.orientation, f"{field}.orientation", norm_tol)
    return R, t
