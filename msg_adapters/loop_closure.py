"""The loop-closure message convention (a standard message; no custom .msg).

A loop closure is a ``nav_msgs/Odometry`` on the h2o_node's loop-closure topic:

* ``header.frame_id`` names the earlier pose *from*, ``child_frame_id`` the pose *to*.
  Each is either ``node/<id>`` — a graph node id, a decimal integer 0 … 2⁶³ − 1 without
  sign or leading zeros, as in the node's saved g2o file and the index in its PoseArray
  output — or ``stamp/<sec>.<nanosec>`` — the pose at that time, ``nanosec`` written with
  exactly nine digits (``stamp/1700000000.000000042``); the node resolves a stamp to the
  keyframe closest in time (within its tolerance) and rejects it otherwise.
  The two may mix, but must not name the same pose.
* ``pose.pose`` is the relative pose of *to* in the frame of *from*,
  ``T_from⁻¹ · T_to`` (metres, unit quaternion ``x, y, z, w``).
* ``pose.covariance`` (6×6, row-major, ROS order x, y, z, rot x, rot y, rot z) is the
  covariance of the error ``[t_E; Log(R_E)]`` of ``K⁻¹ (T_from⁻¹ T_to)`` with ``K`` the
  measurement: a perturbation applied on the right, in the frame of *to* — the
  convention of the solver (``h2o_slam.core.geometry``) and the inverse of a g2o
  ``EDGE_SE3:QUAT`` information matrix. It must be positive definite; all zeros
  ("unknown") takes the node's default covariance, if it has one.
* ``header.stamp`` is when the closure was found (informational); ``twist`` is ignored.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters._util import (
    MAX_POSITION_M,
    Array,
    covariance,
    finite_array,
    inverse_spd,
    new_message,
    set_float_array,
)
from msg_adapters.errors import AdapterError
from msg_adapters.rotations import QUAT_NORM_TOL, fill_pose, pose_to_matrix
from msg_adapters.stamps import NS_PER_S, fill_header, stamp_ns, to_stamp


@dataclass(frozen=True)
class NodeRef:
    """A pose addressed by graph node id."""

    node_id: int

    def __str__(self) -> str:
        return f"node/{self.node_id}"


@dataclass(frozen=True)
class StampRef:
    """A pose addressed by its time stamp (nanoseconds since the epoch)."""

    stamp_ns: int

    def __str__(self) -> str:
        sec, nanosec = divmod(self.stamp_ns, NS_PER_S)
        return f"stamp/{sec}.{nanosec:09d}"


PoseRef = NodeRef | StampRef

_NODE = re.compile(r"node/(0|[1-9][0-9]*)")
_STAMP = re.compile(r"stamp/(0|[1-9][0-9]*)\.([0-9]{9})")

#: Largest graph node id: the solver indexes nodes with int64.
MAX_NODE_ID = 2**63 - 1
#: Largest ``sec`` of a stamp reference (``builtin_interfaces/Time`` has int32 seconds).
MAX_STAMP_SEC = 2**31 - 1


def _bounded_int(digits: str, limit: int, field: str, what: str) -> int:
    """The decimal ``digits`` as an int within ``0 … limit``; the length is checked before
    converting, since Python refuses to convert more than 4300 digits (a ValueError that
    would name nothing)."""
    if len(digits) > len(str(limit)) or int(digits) > limit:
        shown = digits if len(digits) <= 24 else f"{digits[:12]}…({len(digits)} digits)"
        raise AdapterError(f"{field}: {what} {shown} is out of range (0 … {limit})")
    return int(digits)


def parse_pose_ref(text: str, field: str = "frame_id") -> PoseRef:
    """``node/<id>`` → :class:`NodeRef`, ``stamp/<sec>.<nanosec>`` → :class:`StampRef`.

    Raises:
        AdapterError: anything else (including surrounding blanks), and a node id or
            ``sec`` out of range (beyond :data:`MAX_NODE_ID`, :data:`MAX_STAMP_SEC`), however
            many digits it has.
    """
    match = _NODE.fullmatch(text)
    if match is not None:
        return NodeRef(_bounded_int(match.group(1), MAX_NODE_ID, field, "node id"))
    match = _STAMP.fullmatch(text)
    if match is not None:
        sec = _bounded_int(match.group(1), MAX_STAMP_SEC, field, "stamp sec")
        return StampRef(sec * NS_PER_S + int(match.group(2)))
    shown = repr(text) if len(text) <= 80 else f"{text[:40]!r}…({len(text)} characters)"
    raise AdapterError(
        f"{field}: {shown} is not a pose reference (node/<id> or stamp/<sec>.<9-digit nanosec>)"
    )


def format_pose_ref(ref: PoseRef) -> str:
    """The text form of a reference (inverse of :func:`parse_pose_ref`)."""
    if isinstance(ref, NodeRef) and ref.node_id < 0:
        raise AdapterError(f"loop closure: negative node id {ref.node_id}")
    if isinstance(ref, NodeRef) and ref.node_id > MAX_NODE_ID:
        raise AdapterError(f"loop closure: node id beyond {MAX_NODE_ID}")
    if isinstance(ref, StampRef):
        to_stamp(ref.stamp_ns)
    return str(ref)


@dataclass(frozen=True, eq=False)
class LoopClosure:
    """A relative-pose measurement between two earlier poses.

    Attributes:
        from_ref, to_ref: the two poses.
        R, t: measured ``T_from⁻¹ T_to``: rotation ``(3, 3)``, translation ``(3,)`` m.
        covariance: ``(6, 6)`` ROS order, of the right-perturbation error (module doc).
        information: its inverse, the edge's stiffness ``S = Σ⁻¹``.
        stamp_ns: when the closure was found.
    """

    from_ref: PoseRef
    to_ref: PoseRef
    R: Array
    t: Array
    covariance: Array
    information: Array
    stamp_ns: int = 0


def make_loop_closure(
    from_ref: PoseRef, to_ref: PoseRef, R: Any, t: Any, cov: Any, stamp_ns: int = 0
) -> LoopClosure:
    """A validated :class:`LoopClosure` (information computed from the covariance; the
    translation finite and within :data:`~msg_adapters._util.MAX_POSITION_M`)."""
    if from_ref == to_ref:
        raise AdapterError(f"loop closure: from and to are the same pose ({from_ref})")
    full = covariance(cov, 6, "loop closure covariance", definite=True)
    return LoopClosure(
        from_ref=from_ref,
        to_ref=to_ref,
        R=finite_array(R, "loop closure R", (3, 3)),
        t=finite_array(t, "loop closure t", (3,), max_abs=MAX_POSITION_M),
        covariance=full,
        information=inverse_spd(full, "loop closure covariance"),
        stamp_ns=int(stamp_ns),
    )


def loop_closure_from_msg(
    msg: Any, *, default_covariance: Any = None, norm_tol: float | None = QUAT_NORM_TOL
) -> LoopClosure:
    """Validated :class:`LoopClosure` of a ``nav_msgs/Odometry`` (rclpy or rosbags).

    Args:
        default_covariance: ``(6, 6)`` used when the message's covariance is all zeros.

    Raises:
        AdapterError: malformed references, the same pose twice, NaN/inf, zero or
            non-unit quaternion, a covariance that is not symmetric positive definite,
            or an all-zero covariance without ``default_covariance``.
    """
    from_ref = parse_pose_ref(str(msg.header.frame_id), "loop closure header.frame_id")
    to_ref = parse_pose_ref(str(msg.child_frame_id), "loop closure child_frame_id")
    R, t = pose_to_matrix(msg.pose.pose, "loop closure pose.pose", norm_tol)
    cov = covariance(msg.pose.covariance, 6, "loop closure pose.covariance")
    if not np.any(cov != 0.0):
        if default_covariance is None:
            raise AdapterError("loop closure pose.covariance: all zero (unknown), no default")
        cov = np.asarray(default_covariance, dtype=float)
    return make_loop_closure(
        from_ref, to_ref, R, t, cov, stamp_ns(msg.header, "loop closure header.stamp")
    )


def fill_loop_closure(msg_or_cls: Any, closure: LoopClosure) -> Any:
    """Fill a ``nav_msgs/Odometry`` (instance or class) with a loop closure."""
    msg = new_message(msg_or_cls)
    fill_header(msg.header, closure.stamp_ns, format_pose_ref(closure.from_ref))
    msg.child_frame_id = format_pose_ref(closure.to_ref)
    fill_pose(msg.pose.pose, closure.R, closure.t)
    cov = covariance(closure.covariance, 6, "LoopClosure.covariance", definite=True)
    set_float_array(msg.pose, "covariance", cov)
    return msg
