"""``nav_msgs/Odometry`` ⇄ :class:`OdometrySample`, and the planar (3-DOF) helpers.

Pose covariance stays in ROS order ``(x, y, z, rot x, rot y, rot z)``. ROS reads an
all-zero covariance as "unknown": it is accepted here (``covariance_known`` is then
``False``) unless a ``default_covariance`` is supplied to take its place; a node must not
hand an unknown (zero) covariance to the solver.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from h2o_slam.core.geometry import PLANAR_DOF, matrix_to_yaw, yaw_to_matrix
from msg_adapters._util import (
    Array,
    covariance,
    finite_array,
    finite_float,
    new_message,
    set_float_array,
    variance,
)
from msg_adapters.errors import AdapterError
from msg_adapters.rotations import QUAT_NORM_TOL, fill_pose, pose_to_matrix
from msg_adapters.stamps import fill_header, stamp_ns

#: Variance given to z, roll and pitch by :func:`planar_covariance` unless told otherwise:
#: "not measured", as wheel-odometry drivers (diff_drive_controller) publish it.
UNOBSERVED_VARIANCE = 1e6


@dataclass(frozen=True, eq=False)
class OdometrySample:
    """One odometry message as the cores use it.

    Attributes:
        stamp_ns: header stamp, nanoseconds since the epoch.
        frame_id: frame of the pose (``odom``).
        child_frame_id: frame whose pose it is (``base_link``); the twist is in this frame.
        R: rotation ``(3, 3)`` of ``child_frame_id`` in ``frame_id``.
        t: position ``(3,)`` in metres.
        twist_linear: linear velocity ``(3,)`` in m/s, in ``child_frame_id``.
        twist_angular: angular velocity ``(3,)`` in rad/s, in ``child_frame_id``.
        covariance: pose covariance ``(6, 6)``, ROS order; zeros mean unknown.
    """

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    R: Array
    t: Array
    twist_linear: Array
    twist_angular: Array
    covariance: Array

    @property
    def covariance_known(self) -> bool:
        """``False`` for the all-zero covariance that ROS uses for "unknown"."""
        return bool(np.any(self.covariance != 0.0))

    @property
    def yaw_rad(self) -> float:
        """Heading about ``z`` (rad, in ``(-π, π]``)."""
        return float(matrix_to_yaw(self.R))

    def planar(self) -> tuple[float, float, float, Array]:
        """``(x_m, y_m, yaw_rad, covariance (3, 3))``: the 3-DOF part, covariance of
        ``(x, y, yaw)`` taken from the 6×6 one."""
        cov = self.covariance[np.ix_(PLANAR_DOF, PLANAR_DOF)]
        return float(self.t[0]), float(self.t[1]), self.yaw_rad, cov.copy()


def odometry_from_msg(
    msg: Any,
    *,
    default_covariance: Any = None,
    norm_tol: float | None = QUAT_NORM_TOL,
) -> OdometrySample:
    """Validated :class:`OdometrySample` of a ``nav_msgs/Odometry`` (rclpy or rosbags).

    Args:
        msg: the message.
        default_covariance: ``(6, 6)`` covariance to use when the message's is all zeros.
        norm_tol: accepted ``|‖q‖ − 1|`` of the orientation (``None``: any non-zero).

    Raises:
        AdapterError: bad stamp, NaN/inf anywhere in pose or twist, zero or non-unit
            quaternion, a covariance that is not symmetric positive semi-definite.
    """
    stamp = stamp_ns(msg.header, "Odometry.header.stamp")
    R, t = pose_to_matrix(msg.pose.pose, "Odometry.pose.pose", norm_tol)
    cov = covariance(msg.pose.covariance, 6, "Odometry.pose.covariance")
    if not np.any(cov != 0.0) and default_covariance is not None:
        cov = covariance(default_covariance, 6, "default_covariance")
    lin = msg.twist.twist.linear
    ang = msg.twist.twist.angular
    return OdometrySample(
        stamp_ns=stamp,
        frame_id=str(msg.header.frame_id),
        child_frame_id=str(msg.child_frame_id),
        R=R,
        t=t,
        twist_linear=finite_array((lin.x, lin.y, lin.z), "Odometry.twist.twist.linear", (3,)),
        twist_angular=finite_array((ang.x, ang.y, ang.z), "Odometry.twist.twist.angular", (3,)),
        covariance=cov,
    )


def fill_odometry(msg_or_cls: Any, sample: OdometrySample, twist_covariance: Any = None) -> Any:
    """Fill a ``nav_msgs/Odometry`` (an instance, or a new one of the class given).

    Args:
        msg_or_cls: ``Odometry`` instance (filled in place) or class (instantiated).
        sample: what to write; validated as on the way in.
        twist_covariance: ``(6, 6)`` twist covariance; zeros (unknown) when omitted.

    Returns:
        The filled message.

    Raises:
        AdapterError: NaN/inf, a non-rotation ``R``, or a covariance that is not
            symmetric positive semi-definite.
    """
    msg = new_message(msg_or_cls)
    cov = covariance(sample.covariance, 6, "OdometrySample.covariance")
    twist_cov = (
        np.zeros((6, 6))
        if twist_covariance is None
        else covariance(twist_covariance, 6, "twist_covariance")
    )
    lin = finite_array(sample.twist_linear, "OdometrySample.twist_linear", (3,))
    ang = finite_array(sample.twist_angular, "OdometrySample.twist_angular", (3,))
    fill_header(msg.header, sample.stamp_ns, sample.frame_id)
    msg.child_frame_id = str(sample.child_frame_id)
    fill_pose(msg.pose.pose, sample.R, sample.t)
    set_float_array(msg.pose, "covariance", cov)
    tw = msg.twist.twist
    tw.linear.x, tw.linear.y, tw.linear.z = (float(v) for v in lin)
    tw.angular.x, tw.angular.y, tw.angular.z = (float(v) for v in ang)
    set_float_array(msg.twist, "covariance", twist_cov)
    return msg


def planar_covariance(
    sigma_x_m: float,
    sigma_y_m: float,
    sigma_yaw_rad: float,
    *,
    cov_xy: float = 0.0,
    unobserved_variance: float = UNOBSERVED_VARIANCE,
) -> Array:
    """6×6 ROS-order covariance of a 3-DOF estimate: ``σx², σy², σyaw²`` (and the x–y
    correlation ``cov_xy`` in m²) on ``x, y, yaw``; ``unobserved_variance`` on
    ``z, roll, pitch``.

    Raises:
        AdapterError: naming the argument: a negative, NaN or infinite sigma, one whose
            square overflows (beyond about 1.3e154), or ``|cov_xy| > σx σy``.
    """
    var = [variance(value, f"planar_covariance {name}") for value, name in (
        (sigma_x_m, "sigma_x_m"), (sigma_y_m, "sigma_y_m"), (sigma_yaw_rad, "sigma_yaw_rad"))]
    xy = finite_float(cov_xy, "planar_covariance cov_xy")
    # Against the variances as stored (finite, so is their roots' product): the x-y block
    # stays positive semi-definite even when a tiny σ² underflows to 0.
    if abs(xy) > math.sqrt(var[0]) * math.sqrt(var[1]):
        raise AdapterError(f"planar_covariance cov_xy: |cov_xy| = {abs(xy):.3g} exceeds σx·σy")
    field = "planar_covariance unobserved_variance"
    unobserved = finite_float(unobserved_variance, field)
    if unobserved < 0.0:
        raise AdapterError(f"{field}: {unobserved} is not a variance")
    cov = np.diag([0.0, 0.0, unobserved, unobserved, unobserved, 0.0])
    cov[np.ix_(PLANAR_DOF, PLANAR_DOF)] = np.diag(var)
    cov[0, 1] = cov[1, 0] = xy
    return cov


def planar_odometry_sample(
    stamp_ns: int,
    frame_id: str,
    child_frame_id: str,
    x_m: float,
    y_m: float,
    yaw_rad: float,
    covariance: Any,
    *,
    v_x_mps: float = 0.0,
    yaw_rate_radps: float = 0.0,
) -> OdometrySample:
    """An :class:`OdometrySample` of a 3-DOF pose (``z = 0``, rotation about ``z``).

    Args:
        covariance: ``(6, 6)`` (e.g. from :func:`planar_covariance`) or ``(3, 3)`` over
            ``(x, y, yaw)``, which is embedded with :data:`UNOBSERVED_VARIANCE` elsewhere.
        v_x_mps, yaw_rate_radps: forward speed and yaw rate for the twist.
    """
    cov = np.asarray(covariance, dtype=float)
    if cov.shape == (3, 3):
        full = np.diag([0.0, 0.0] + [UNOBSERVED_VARIANCE] * 3 + [0.0])
        full[np.ix_(PLANAR_DOF, PLANAR_DOF)] = cov
        cov = full
    pose = finite_array((x_m, y_m, yaw_rad), "planar pose", (3,))
    return OdometrySample(
        stamp_ns=int(stamp_ns),
        frame_id=frame_id,
        child_frame_id=child_frame_id,
        R=yaw_to_matrix(pose[2]),
        t=np.array([pose[0], pose[1], 0.0]),
        twist_linear=np.array([float(v_x_mps), 0.0, 0.0]),
        twist_angular=np.array([0.0, 0.0, float(yaw_rate_radps)]),
        covariance=covariance_checked(cov),
    )


def covariance_checked(cov: Any, field: str = "covariance") -> Array:
    """A ``(6, 6)`` covariance validated as symmetric positive semi-definite."""
    return covariance(np.asarray(cov, dtype=float).ravel(), 6, field)
