"""``sensor_msgs/CameraInfo`` → :class:`CameraModel`, validated; the stereo baseline."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters._util import Array, finite_array, new_message, set_float_array
from msg_adapters.errors import AdapterError
from msg_adapters.images import MAX_IMAGE_PIXELS
from msg_adapters.stamps import fill_header, stamp_ns

#: Number of distortion coefficients of each model this package knows.
DISTORTION_MODELS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
#: Largest accepted magnitude of an entry of K, R, P or D. Focal lengths and principal
#: points are pixels of an image of at most MAX_IMAGE_PIXELS (a 0.01° field of view on
#: 16k pixels is f = 9e7 px); P[0, 3] = −f·baseline adds at most a few metres' factor.
MAX_CALIBRATION_ENTRY = 1e9


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Calibration of one camera (pixels; the optical frame is x right, y down, z forward).

    Attributes:
        stamp_ns: header stamp, nanoseconds.
        frame_id: optical frame.
        width, height: image size in pixels.
        K: intrinsic matrix ``(3, 3)`` of the raw image.
        D: distortion coefficients ``(n,)`` (may be empty for rectified images).
        R: rectification rotation ``(3, 3)`` (identity for a monocular camera).
        P: projection matrix ``(3, 4)`` of the rectified image; for the right camera of a
            stereo pair ``P[0, 3] = −fx · baseline``.
        distortion_model: ``plumb_bob``, ``rational_polynomial``, ``equidistant`` or ``""``.
    """

    stamp_ns: int
    frame_id: str
    width: int
    height: int
    K: Array
    D: Array
    R: Array
    P: Array
    distortion_model: str

    @property
    def fx(self) -> float:
        """Focal length in x of the rectified image (``P[0, 0]``), pixels."""
        return float(self.P[0, 0])

    @property
    def fy(self) -> float:
        """Focal length in y of the rectified image (``P[1, 1]``), pixels."""
        return float(self.P[1, 1])

    @property
    def cx(self) -> float:
        """Principal point x of the rectified image (``P[0, 2]``), pixels."""
        return float(self.P[0, 2])

    @property
    def cy(self) -> float:
        """Principal point y of the rectified image (``P[1, 2]``), pixels."""
        return float(self.P[1, 2])


def camera_info_from_msg(msg: Any) -> CameraModel:
    """Validated :class:`CameraModel` of a ``sensor_msgs/CameraInfo`` (rclpy or rosbags).

    An all-zero ``R`` (left so by some drivers of monocular cameras) is read as the
    identity. Binning and region of interest are not applied: images are expected at the
    calibrated resolution.

    Raises:
        AdapterError: zero size or more than ``MAX_IMAGE_PIXELS``; NaN/inf or entries
            beyond :data:`MAX_CALIBRATION_ENTRY`; an uncalibrated (zero) ``K`` or ``P``;
            non-positive focal lengths; a last row of ``K`` other than ``[0, 0, 1]``;
            ``R`` not a rotation; an unknown distortion model or a wrong number of
            coefficients for it.
    """
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise AdapterError(f"CameraInfo: empty image size {width}x{height}")
    if width * height > MAX_IMAGE_PIXELS:
        raise AdapterError(
            f"CameraInfo: image size {width}x{height} exceeds {MAX_IMAGE_PIXELS} pixels"
        )
    flat: dict[str, Array] = {}
    for name, size in (("k", 9), ("r", 9), ("p", 12), ("d", -1)):
        arr = finite_array(
            getattr(msg, name), f"CameraInfo.{name}", max_abs=MAX_CALIBRATION_ENTRY
        ).ravel()
        if size >= 0 and arr.size != size:
            raise AdapterError(f"CameraInfo.{name}: {arr.size} values, expected {size}")
        flat[name] = arr
    K: Array = flat["k"].reshape(3, 3)
    R: Array = flat["r"].reshape(3, 3)
    P: Array = flat["p"].reshape(3, 4)
    D = flat["d"]
    if not np.any(K):
        raise AdapterError("CameraInfo.k: all zero (camera not calibrated)")
    if not np.any(P):
        raise AdapterError("CameraInfo.p: all zero (camera not calibrated)")
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise AdapterError(f"CameraInfo.k: focal lengths {K[0, 0]}, {K[1, 1]} must be > 0")
    if P[0, 0] <= 0.0 or P[1, 1] <= 0.0:
        raise AdapterError(f"CameraInfo.p: focal lengths {P[0, 0]}, {P[1, 1]} must be > 0")
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9):
        raise AdapterError(f"CameraInfo.k: last row {K[2].tolist()} is not [0, 0, 1]")
    if not np.allclose(P[2, :3], [0.0, 0.0, 1.0], atol=1e-9):
        raise AdapterError(f"CameraInfo.p: last row {P[2].tolist()} is not [0, 0, 1, *]")
    if not np.any(R):
        R = np.eye(3)
    elif np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) < 0.0:
        raise AdapterError("CameraInfo.r: not a rotation matrix")
    model = str(msg.distortion_model)
    if D.size and model not in DISTORTION_MODELS:
        raise AdapterError(f"CameraInfo.distortion_model: unknown {model!r}")
    if D.size and D.size != DISTORTION_MODELS[model]:
        raise AdapterError(
            f"CameraInfo.d: {D.size} coefficients, {model} has {DISTORTION_MODELS[model]}"
        )
    return CameraModel(
        stamp_ns=stamp_ns(msg.header, "CameraInfo.header.stamp"),
        frame_id=str(msg.header.frame_id),
        width=width,
        height=height,
        K=K,
        D=D,
        R=R,
        P=P,
        distortion_model=model,
    )


def stereo_baseline_m(right: CameraModel) -> float:
    """Baseline in metres of a rectified stereo pair from the right camera's ``P``:
    ``−P[0, 3] / P[0, 0]``.

    Raises:
        AdapterError: a baseline that is not positive (e.g. the left camera's info) or not
            finite.
    """
    baseline = -float(right.P[0, 3]) / float(right.P[0, 0]) + 0.0  # no "-0" in messages
    if not 0.0 < baseline < math.inf:  # inf: a legal P[0, 3] over a subnormal fx
        raise AdapterError(
            f"CameraInfo.p: right camera baseline {baseline:.6g} m is not positive and finite "
            "(P[0, 3] must be −fx·baseline; is this the left camera?)"
        )
    return baseline


def check_stereo_pair(left: CameraModel, right: CameraModel) -> float:
    """Check that two models form a rectified stereo pair; returns the baseline in metres.

    Raises:
        AdapterError: different image sizes, a left ``P[0, 3]`` that is not zero,
            different rectified intrinsics, or a non-positive baseline.
    """
    if (left.width, left.height) != (right.width, right.height):
        raise AdapterError(
            f"stereo CameraInfo: sizes differ ({left.width}x{left.height} left, "
            f"{right.width}x{right.height} right)"
        )
    if abs(left.P[0, 3]) > 1e-9 * max(1.0, left.fx):
        raise AdapterError(f"left CameraInfo.p: P[0, 3] = {left.P[0, 3]:.6g}, expected 0")
    if not np.allclose(left.P[:, :3], right.P[:, :3], rtol=1e-6, atol=1e-9):
        raise AdapterError("stereo CameraInfo.p: left and right rectified intrinsics differ")
    return stereo_baseline_m(right)


def fill_camera_info(msg_or_cls: Any, model: CameraModel) -> Any:
    """Fill a ``sensor_msgs/CameraInfo`` (an instance, or a new one of the class given).

    Raises:
        AdapterError: what :func:`camera_info_from_msg` would reject in the result.
    """
    msg = new_message(msg_or_cls)
    fill_header(msg.header, model.stamp_ns, model.frame_id)
    msg.width, msg.height = int(model.width), int(model.height)
    msg.distortion_model = str(model.distortion_model)
    msg.d = [float(v) for v in finite_array(model.D, "CameraModel.D").ravel()]
    for name, value, shape in (("k", model.K, (3, 3)), ("r", model.R, (3, 3)),
                               ("p", model.P, (3, 4))):
        set_float_array(msg, name, finite_array(value, f"CameraModel.{name.upper()}", shape))
    camera_info_from_msg(msg)
    return msg
