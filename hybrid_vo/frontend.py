"""The logic of ``hybrid_vo_node`` without ROS: calibration, wheel buffer, fallbacks, pose.

:class:`VoFrontend` takes what the node's callbacks decode — a stereo calibration
(:class:`msg_adapters.CameraModel` pair), wheel odometry poses and rectified stereo frames —
and returns one :class:`VoOutput` per frame: the corrected pose of ``base_link`` in
``odom``, its covariance and twist, and whether vision was used or why not.

* The wheel odometry is buffered as ``(stamp_ns, x_m, y_m, yaw_rad)`` samples and
  interpolated at each frame's stamp; a frame newer than the latest wheel sample waits
  (at most ``max_pending_frames``) until the wheels cover it.
* The wheel increment between consecutive frames goes to
  :meth:`hybrid_vo.odometer.HybridOdometer.process`; the corrected increment is integrated
  here, and the planar covariance grows by the yaw σ of each frame and the wheels'
  translation noise.
* Without a calibration, with an image that cannot be used, or while the odometer defers,
  the wheel increment is used and the reason is reported: the output is never missing for
  an accepted frame, and never a null pose.
* Every rejected input raises :class:`InputRejected` after being counted by reason in
  :attr:`VoFrontend.stats` (doc/nodes.md, bad input); the frontend's state is unchanged by
  it. Wheel positions beyond :data:`MAX_WHEEL_POSITION_M` are refused
  (``wheel_out_of_range``), and a frame whose pose or covariance would not be finite is
  dropped (``frame_not_finite``) without moving the track.

Stamps are integer nanoseconds; poses are ``(x_m, y_m, yaw_rad)`` of ``base_link`` in
``odom``; increments are ``T_prev⁻¹ T_new`` in the previous ``base_link`` (REP-103).
"""

from __future__ import annotations

import bisect
import math
import re
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from h2o_slam.core.errors import InputError
from h2o_slam.core.geometry import PLANAR_DOF
from h2o_slam.core.parameters import parameter
from hybrid_vo import patches as pt
from hybrid_vo.camera import CameraIntrinsics, CameraMounting
from hybrid_vo.errors import ConfigError, FrameError
from hybrid_vo.frames import StereoFrame
from hybrid_vo.odometer import FallbackReason, HybridOdometer, OdometerConfig
from msg_adapters import AdapterError, CameraModel, check_stereo_pair
from msg_adapters.odometry import UNOBSERVED_VARIANCE

FloatArray = NDArray[np.float64]
Pose = tuple[float, float, float]

#: Fallback reasons the frontend adds to the odometer's :class:`FallbackReason` values.
NO_CALIBRATION = "no_calibration"
BAD_IMAGE = "bad_image"

NS_PER_S = 1_000_000_000

#: Largest wheel odometry coordinate accepted, m (the bound msg_adapters puts on message
#: positions): no odom frame holds a robot 1e8 m from its origin, and the covariance, which
#: grows with the square of the travel, keeps ~1e250 of headroom below it.
MAX_WHEEL_POSITION_M = 1e8


class InputRejected(InputError):
    """An input the frontend refused; already counted under :attr:`reason`.

    Attributes:
        reason: short key, e.g. ``frame_time_backwards`` (the counter's name).
        detail: the full explanation.
    """

    def __init__(self, reason: str, detail: str) -> None:
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}")


def reason_key(source: str, error: Exception) -> str:
    """Counter name of a rejected input: ``"<source>: <field>: <problem>"``.

    Built from an error text such as ``"Image.encoding: unsupported 'rgb9' (...)"``: the
    field before the first colon, then the problem up to the first number, quote or
    parenthesis, so that one kind of problem always counts under one name.
    """
    field_name, _, detail = str(error).partition(": ")
    problem = re.split(r"[\d('\"]", detail, maxsplit=1)[0].strip(" ,;:")
    return f"{source}: {field_name}: {problem}" if problem else f"{source}: {field_name}"


@dataclass(frozen=True)
class FrontendConfig:
    """Settings of :class:`VoFrontend`; the node declares each documented field as a
    parameter (``metadata``: :mod:`ros_node_base.params`), the odometer's as ``odometer.*``.

    Attributes:
        camera_yaw, camera_pitch, camera_roll: left camera mounting on ``base_link`` (rad;
            REP-103: positive pitch tilts the camera down, positive yaw turns it left).
        camera_height: optical centre above the ground (m).
        camera_forward, camera_left: optical centre in ``base_link`` (m).
        wheel_buffer: seconds of wheel odometry kept for interpolation.
        max_pending_frames: frames that may wait for wheel odometry to cover their stamp;
            beyond that the oldest is dropped (counted as ``frame_wheel_timeout``).
        wheel_sigma_per_m: translation noise of the wheels per metre travelled (1σ, along
            and across the motion); grows the x/y covariance.
        initial_sigma: 1σ of the first pose (m and rad); keeps the covariance invertible.
        odometer: the hybrid odometer's own settings.
    """

    camera_yaw: float = parameter(
        0.0, "Left camera yaw on base_link, rad (positive: turned left).",
        bounds=(-math.pi, math.pi))
    camera_pitch: float = parameter(
        0.0, "Left camera pitch, rad (REP-103: positive tilts down).", bounds=(-1.5, 1.5))
    camera_roll: float = parameter(
        0.0, "Left camera roll about its forward axis, rad (positive rolls it right).",
        bounds=(-1.5, 1.5))
    camera_height: float = parameter(
        1.0, "Height of the left optical centre above the ground, m.", bounds=(0.01, 100.0))
    camera_forward: float = parameter(
        0.0, "Left optical centre ahead of base_link, m.", bounds=(-100.0, 100.0))
    camera_left: float = parameter(
        0.0, "Left optical centre left of base_link, m.", bounds=(-100.0, 100.0))
    wheel_buffer: float = parameter(
        5.0, "Seconds of wheel odometry kept to interpolate the wheel pose at frame stamps.",
        bounds=(0.1, 600.0))
    max_pending_frames: int = parameter(
        10, "Stereo frames that may wait for wheel odometry to reach their stamp; beyond "
        "that the oldest is dropped and counted (rejected.frame_wheel_timeout).", bounds=(1, 1000))
    wheel_sigma_per_m: float = parameter(
        0.02, "Wheel translation noise, 1 sigma per metre travelled (along and across); the "
        "published x/y covariance grows with it.", bounds=(1e-6, 1.0))
    initial_sigma: float = parameter(
        1e-3, "1 sigma of the first pose (m, rad); keeps the covariance invertible.",
        bounds=(1e-9, 10.0))
    odometer: OdometerConfig = field(default_factory=OdometerConfig)

    def __post_init__(self) -> None:
        for name in ("wheel_buffer", "wheel_sigma_per_m", "initial_sigma"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"{name} must be finite and > 0, got {value!r}")
        if self.max_pending_frames < 1:
            raise ConfigError(f"max_pending_frames must be >= 1, got {self.max_pending_frames}")
        self.mounting(0.12)  # validates the mounting now, not at the first calibration

    def mounting(self, baseline_m: float) -> CameraMounting:
        """The :class:`CameraMounting` of these settings with a stereo baseline."""
        return CameraMounting(
            yaw_rad=self.camera_yaw,
            pitch_rad=self.camera_pitch,
            roll_rad=self.camera_roll,
            height_m=self.camera_height,
            baseline_m=baseline_m,
            forward_m=self.camera_forward,
            left_m=self.camera_left,
        )


@dataclass(frozen=True)
class VoOutput:
    """One frame's result: what the node publishes as ``nav_msgs/Odometry``.

    Attributes:
        stamp_ns: the frame's stamp.
        x_m, y_m, yaw_rad: pose of ``base_link`` in ``odom``.
        covariance: ``(3, 3)`` covariance of ``(x, y, yaw)`` (m², rad²).
        v_x_mps, v_y_mps, yaw_rate_radps: twist in ``base_link`` over the last increment.
        yaw_sigma_rad: 1σ of this frame's yaw increment.
        fallback: ``"none"`` when vision corrected the yaw, else why the wheels were used
            (a :class:`FallbackReason` value, ``no_calibration`` or ``bad_image``).
        wheel_delta, delta: wheel and corrected increments ``(dx_m, dy_m, dyaw_rad)``.
        frame_time_s: wall time spent on this frame.
    """

    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    covariance: FloatArray
    v_x_mps: float
    v_y_mps: float
    yaw_rate_radps: float
    yaw_sigma_rad: float
    fallback: str
    wheel_delta: Pose
    delta: Pose
    frame_time_s: float

    @property
    def used_vision(self) -> bool:
        """True when the yaw increment came from the visual tracker."""
        return self.fallback == FallbackReason.NONE.value

    @property
    def pose(self) -> Pose:
        """``(x_m, y_m, yaw_rad)``."""
        return (self.x_m, self.y_m, self.yaw_rad)

    @property
    def covariance_6x6(self) -> FloatArray:
        """ROS-order ``(6, 6)`` covariance; z, roll and pitch are marked unobserved."""
        full = np.diag([0.0, 0.0] + [UNOBSERVED_VARIANCE] * 3 + [0.0])
        full[np.ix_(PLANAR_DOF, PLANAR_DOF)] = self.covariance
        return full


@dataclass
class FrontendStats:
    """Counters over the frontend's lifetime (a reset keeps them).

    Attributes:
        frames: outputs produced.
        vision_frames: outputs whose yaw came from vision.
        fallbacks: outputs that used the wheels alone, by reason.
        rejected: inputs refused, by reason.
        dropped_paused: frames ignored while paused.
        calibrations: odometers built (one per distinct calibration).
        frame_time_last_s, frame_time_max_s, frame_time_total_s: wall time per frame.
        last_rejection: text of the latest rejection.
    """

    frames: int = 0
    vision_frames: int = 0
    fallbacks: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)
    dropped_paused: int = 0
    calibrations: int = 0
    frame_time_last_s: float = 0.0
    frame_time_max_s: float = 0.0
    frame_time_total_s: float = 0.0
    last_rejection: str = ""

    @property
    def fallback_fraction(self) -> float:
        """Fraction of outputs that used the wheels alone."""
        return 1.0 - self.vision_frames / self.frames if self.frames else 0.0

    @property
    def frame_time_mean_s(self) -> float:
        """Mean wall time per frame."""
        return self.frame_time_total_s / self.frames if self.frames else 0.0


@dataclass(frozen=True)
class _Frame:
    stamp_ns: int
    left: NDArray[np.uint8] | None
    right: NDArray[np.uint8] | None
    unusable: str | None  # why vision cannot be used on this frame, if known already


@dataclass(frozen=True)
class _Track:
    """State after the latest output."""

    stamp_ns: int
    wheel: Pose  # interpolated wheel pose at stamp_ns
    pose: Pose
    covariance: FloatArray


def wrap(angle_rad: float) -> float:
    """``angle_rad`` wrapped into ``[-π, π)``."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def between(a: Pose, b: Pose) -> Pose:
    """``a⁻¹ b``: planar pose ``b`` in the frame of ``a``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2]))


def compose(a: Pose, d: Pose) -> Pose:
    """``a ⊕ d``: increment ``d`` (in ``a``'s frame) applied to planar pose ``a``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * d[0] - s * d[1], a[1] + s * d[0] + c * d[1], wrap(a[2] + d[2]))


def propagate_covariance(
    cov: FloatArray, pose: Pose, delta: Pose, yaw_sigma_rad: float, sigma_per_m: float
) -> FloatArray:
    """Covariance ``(3, 3)`` of ``pose ⊕ delta`` given that of ``pose``.

    First-order: ``F P Fᵀ + G Q Gᵀ`` with ``Q = diag(σt², σt², σyaw²)``, where the
    translation noise ``σt = sigma_per_m · |travel|`` is the wheels' and ``σyaw`` the frame's.
    """
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx, dy = delta[0], delta[1]
    F = np.array([[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]])
    G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    sigma_t = sigma_per_m * math.hypot(dx, dy)
    # Products, not ``**``: a float power that overflows raises instead of giving inf, which
    # the caller checks for.
    Q = np.diag([sigma_t * sigma_t, sigma_t * sigma_t, yaw_sigma_rad * yaw_sigma_rad])
    with np.errstate(over="ignore", invalid="ignore"):
        out: FloatArray = F @ cov @ F.T + G @ Q @ G.T
        return 0.5 * (out + out.T)


class WheelBuffer:
    """Wheel odometry poses by stamp, interpolated at frame stamps.

    Args:
        keep_s: seconds of history kept behind the newest sample.
    """

    def __init__(self, keep_s: float) -> None:
        self.keep_ns = int(keep_s * NS_PER_S)
        self.stamps: list[int] = []
        self.poses: list[Pose] = []

    def __len__(self) -> int:
        return len(self.stamps)

    def add(self, stamp_ns: int, pose: Pose) -> None:
        """Append a sample (the caller checks that time moves forward)."""
        self.stamps.append(stamp_ns)
        self.poses.append(pose)

    def covers(self, stamp_ns: int) -> bool:
        """True when a sample at or after ``stamp_ns`` has arrived."""
        return bool(self.stamps) and self.stamps[-1] >= stamp_ns

    def at(self, stamp_ns: int) -> Pose | None:
        """Pose at ``stamp_ns`` (linear in x, y and the shortest yaw arc); ``None`` when the
        samples do not bracket it."""
        i = bisect.bisect_left(self.stamps, stamp_ns)
        if i == len(self.stamps) or (i == 0 and self.stamps[0] != stamp_ns):
            return None
        if self.stamps[i] == stamp_ns:
            return self.poses[i]
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        a, b = self.poses[i - 1], self.poses[i]
        u = (stamp_ns - t0) / (t1 - t0)
        return (
            a[0] + u * (b[0] - a[0]),
            a[1] + u * (b[1] - a[1]),
            wrap(a[2] + u * wrap(b[2] - a[2])),
        )

    def trim(self) -> None:
        """Drop samples older than ``keep_s`` behind the newest, keeping the last one before
        that horizon so that stamps inside it can still be interpolated."""
        if not self.stamps:
            return
        i = bisect.bisect_right(self.stamps, self.stamps[-1] - self.keep_ns) - 1
        if i > 0:
            del self.stamps[:i]
            del self.poses[:i]

    def clear(self) -> None:
        """Forget every sample."""
        self.stamps.clear()
        self.poses.clear()


class VoFrontend:
    """Stereo frames + wheel odometry → corrected planar odometry (see the module docstring).

    Args:
        config: settings; defaults when omitted.
    """

    def __init__(self, config: FrontendConfig | None = None) -> None:
        self.config = config if config is not None else FrontendConfig()
        self.stats = FrontendStats()
        self.odometer: HybridOdometer | None = None
        self._calibration_key: tuple[Any, ...] | None = None
        self._wheel = WheelBuffer(self.config.wheel_buffer)
        self._pending: deque[_Frame] = deque()
        self._last_frame_ns: int | None = None
        self._track: _Track | None = None
        self._start_pose: Pose = (0.0, 0.0, 0.0)
        self._paused = False
        self._last_left: NDArray[np.uint8] | None = None

    # ------------------------------------------------------------------ inputs

    def set_calibration(self, left: CameraModel, right: CameraModel) -> bool:
        """Use a rectified stereo calibration; builds the odometer when it changed.

        Returns:
            True when a new odometer was built (the next frame starts tracking afresh).

        Raises:
            InputRejected: ``calibration``: not a rectified stereo pair, or the mounting
                and camera do not let the odometer see the horizon. The previous
                calibration, if any, stays in use.
        """
        key = (left.width, left.height, left.P.tobytes(), right.P.tobytes())
        if key == self._calibration_key:
            return False
        try:
            baseline = check_stereo_pair(left, right)
            intrinsics = CameraIntrinsics(
                int(left.width), int(left.height), left.fx, left.fy, left.cx, left.cy
            )
            odometer = HybridOdometer(
                intrinsics, self.config.mounting(baseline), self.config.odometer
            )
        except (AdapterError, ConfigError) as exc:
            raise self._reject("calibration", str(exc)) from None
        self.odometer = odometer
        self._calibration_key = key
        self.stats.calibrations += 1
        return True

    @property
    def calibrated(self) -> bool:
        """True once a usable stereo calibration has been set."""
        return self.odometer is not None

    def add_wheel(self, stamp_ns: int, x_m: float, y_m: float, yaw_rad: float) -> list[VoOutput]:
        """Buffer a wheel odometry pose; returns outputs of frames it lets through.

        Raises:
            InputRejected: ``wheel_not_finite``, ``wheel_out_of_range`` (a coordinate beyond
                :data:`MAX_WHEEL_POSITION_M`), or ``wheel_time_backwards`` when the stamp
                is not after the previous sample's.
        """
        if not all(math.isfinite(v) for v in (x_m, y_m, yaw_rad)):
            raise self._reject("wheel_not_finite", f"pose ({x_m}, {y_m}, {yaw_rad})")
        if max(abs(x_m), abs(y_m)) > MAX_WHEEL_POSITION_M:
            raise self._reject(
                "wheel_out_of_range",
                f"position ({x_m:.3g}, {y_m:.3g}) m beyond {MAX_WHEEL_POSITION_M:.0e} m",
            )
        if self._wheel.stamps and stamp_ns <= self._wheel.stamps[-1]:
            raise self._reject(
                "wheel_time_backwards",
                f"stamp {stamp_ns} ns is not after the previous {self._wheel.stamps[-1]} ns",
            )
        self._wheel.add(int(stamp_ns), (float(x_m), float(y_m), wrap(float(yaw_rad))))
        outputs = self._flush()
        self._wheel.trim()
        return outputs

    def add_frame(
        self,
        stamp_ns: int,
        left: NDArray[np.uint8] | None,
        right: NDArray[np.uint8] | None,
        unusable: str | None = None,
    ) -> list[VoOutput]:
        """Take a synchronized rectified stereo pair; returns the outputs now possible.

        Args:
            stamp_ns: the pair's stamp.
            left, right: uint8 grayscale ``(H, W)`` images at the calibration's size, or
                ``None`` when they could not be decoded.
            unusable: why vision cannot be used on this frame (e.g. ``bad_image``); the
                frame then advances the pose by the wheel increment alone.

        Raises:
            InputRejected: ``frame_time_backwards`` when the stamp is not after the
                previous frame's.
        """
        if self._paused:
            self.stats.dropped_paused += 1
            return []
        if self._last_frame_ns is not None and stamp_ns <= self._last_frame_ns:
            raise self._reject(
                "frame_time_backwards",
                f"stamp {stamp_ns} ns is not after the previous frame's {self._last_frame_ns} ns",
            )
        if unusable is None and (left is None or right is None):
            unusable = BAD_IMAGE
        self._last_frame_ns = int(stamp_ns)
        self._pending.append(_Frame(int(stamp_ns), left, right, unusable))
        while len(self._pending) > self.config.max_pending_frames:
            old = self._pending.popleft()
            self._count("frame_wheel_timeout", f"frame {old.stamp_ns} ns: no wheel odometry")
        return self._flush()

    def count_rejection(self, reason: str, detail: str = "") -> None:
        """Count an input rejected elsewhere (e.g. a message the node could not decode)."""
        self._count(reason, detail or reason)

    # ------------------------------------------------------------------ control

    def reset(self, pose: Pose = (0.0, 0.0, 0.0)) -> None:
        """Restart at ``pose``: the next frame is output there with the initial covariance.

        Buffered wheel samples, waiting frames and the stamp history are dropped (so a
        replay may start again from its beginning); calibration and counters are kept.
        """
        self._start_pose = (float(pose[0]), float(pose[1]), wrap(float(pose[2])))
        self._track = None
        self._wheel.clear()
        self._pending.clear()
        self._last_frame_ns = None
        if self.odometer is not None:
            self.odometer.reset()

    def pause(self) -> None:
        """Ignore frames (counted in ``dropped_paused``) until :meth:`resume`."""
        self._paused = True

    def resume(self) -> None:
        """Process frames again. The first frame after it adds the wheel motion made while
        paused (so ``odom`` stays continuous) and restarts visual tracking."""
        if self._paused and self.odometer is not None:
            self.odometer.reset()
        self._paused = False

    @property
    def paused(self) -> bool:
        """True while paused."""
        return self._paused

    @property
    def pending_frames(self) -> int:
        """Frames waiting for wheel odometry to reach their stamp."""
        return len(self._pending)

    # ------------------------------------------------------------------ work

    def _flush(self) -> list[VoOutput]:
        outputs = []
        while self._pending and self._wheel.covers(self._pending[0].stamp_ns):
            frame = self._pending.popleft()
            wheel = self._wheel.at(frame.stamp_ns)
            if wheel is None:
                self._count(
                    "frame_not_covered_by_wheel",
                    f"frame {frame.stamp_ns} ns is older than the buffered wheel odometry "
                    f"(from {self._wheel.stamps[0]} ns)",
                )
                continue
            output = self._process(frame, wheel)
            if output is not None:
                outputs.append(output)
        return outputs

    def _process(self, frame: _Frame, wheel: Pose) -> VoOutput | None:
        """The frame's output, or ``None`` (counted as ``frame_not_finite``, the track
        unchanged) when its pose, covariance or twist would not be finite."""
        t0 = time.perf_counter()
        track = self._track
        wheel_delta = (0.0, 0.0, 0.0) if track is None else between(track.wheel, wheel)
        delta, yaw_sigma, fallback = self._increment(frame, wheel_delta)
        if track is None:
            pose = self._start_pose
            cov = np.eye(3) * self.config.initial_sigma**2
            dt_s = 0.0
            if fallback == FallbackReason.NONE.value:  # cannot happen with a fresh odometer
                fallback = FallbackReason.FIRST_FRAME.value
        else:
            pose = compose(track.pose, delta)
            cov = propagate_covariance(
                track.covariance, track.pose, delta, yaw_sigma, self.config.wheel_sigma_per_m
            )
            dt_s = (frame.stamp_ns - track.stamp_ns) / NS_PER_S
        rate = 1.0 / dt_s if dt_s > 0.0 else 0.0
        twist = (delta[0] * rate, delta[1] * rate, delta[2] * rate)
        if not (all(math.isfinite(v) for v in (*pose, *twist, yaw_sigma))
                and np.all(np.isfinite(cov))):
            self._count("frame_not_finite", f"frame {frame.stamp_ns} ns: pose {pose}, "
                        f"increment {delta}: not finite")
            return None
        self._track = _Track(frame.stamp_ns, wheel, pose, cov)
        elapsed = time.perf_counter() - t0
        self._tally(fallback, elapsed)
        return VoOutput(
            stamp_ns=frame.stamp_ns,
            x_m=pose[0],
            y_m=pose[1],
            yaw_rad=pose[2],
            covariance=cov,
            v_x_mps=twist[0],
            v_y_mps=twist[1],
            yaw_rate_radps=twist[2],
            yaw_sigma_rad=yaw_sigma,
            fallback=fallback,
            wheel_delta=wheel_delta,
            delta=delta,
            frame_time_s=elapsed,
        )

    def _increment(self, frame: _Frame, wheel_delta: Pose) -> tuple[Pose, float, str]:
        """Corrected increment, its yaw σ and the fallback reason (``"none"``)."""
        odometer = self.odometer
        reason = NO_CALIBRATION if odometer is None else frame.unusable
        if odometer is not None and reason is None:
            assert frame.left is not None and frame.right is not None
            try:
                upd = odometer.process(
                    StereoFrame(frame.left, frame.right, frame.stamp_ns), np.array(wheel_delta)
                )
            except FrameError as exc:
                self._count(BAD_IMAGE, str(exc))
                reason = BAD_IMAGE
            else:
                self._last_left = frame.left
                return (upd.dx_m, upd.dy_m, upd.dyaw_rad), upd.yaw_sigma_rad, upd.fallback.value
        if odometer is not None:
            odometer.reset()  # the next usable frame must not be compared across this one
        sigma = self.config.odometer.fallback_yaw_sigma_rad
        return wheel_delta, sigma, reason or BAD_IMAGE

    def _tally(self, fallback: str, elapsed_s: float) -> None:
        st = self.stats
        st.frames += 1
        if fallback == FallbackReason.NONE.value:
            st.vision_frames += 1
        else:
            st.fallbacks[fallback] += 1
        st.frame_time_last_s = elapsed_s
        st.frame_time_max_s = max(st.frame_time_max_s, elapsed_s)
        st.frame_time_total_s += elapsed_s

    def _count(self, reason: str, detail: str) -> None:
        self.stats.rejected[reason] += 1
        self.stats.last_rejection = f"{reason}: {detail}"

    def _reject(self, reason: str, detail: str) -> InputRejected:
        self._count(reason, detail)
        return InputRejected(reason, detail)

    # ------------------------------------------------------------------ debug

    def debug_image(self, scale: int = 4) -> NDArray[np.uint8] | None:
        """The latest tracked frame's horizon band (mono8) with the sampling region and the
        patches the odometer would sample in it; ``None`` before the first tracked frame."""
        if self.odometer is None or self._last_left is None:
            return None
        return draw_band(self.odometer, self._last_left, scale)


def draw_band(odometer: HybridOdometer, left: NDArray[np.uint8], scale: int) -> NDArray[np.uint8]:
    """Spherical horizon band of ``left`` (input resolution) enlarged ``scale`` times, with
    the sampling region's edges (dark lines), the frontal direction (a bright line) and the
    patches sampled at Harris corners (bright boxes), as :mod:`hybrid_vo.odometer` does."""
    work = odometer.work_intrinsics
    small = cv2.resize(left, (work.width_px, work.height_px), interpolation=cv2.INTER_AREA)
    band = odometer.spherical.remap(small)
    cfg = odometer.config
    half = odometer.theta_max_rad / odometer.spherical.a_rad_per_px
    lo = int(math.ceil(odometer.frontal_col - half))
    hi = int(math.floor(odometer.frontal_col + half)) + 1
    picks = pt.sample_patches(
        band, lo, hi, cfg.num_patches, cfg.patch_width_px, cfg.patch_height_px,
        cfg.harris_min_response,
    )
    band_u8 = np.clip(band, 0, 255).astype(np.uint8)
    img = np.ascontiguousarray(
        cv2.resize(band_u8, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST),
        dtype=np.uint8,
    )
    rows = img.shape[0]
    for col, level in ((lo, 0), (hi, 0), (odometer.frontal_col, 255)):
        x = int(round(col * scale))
        cv2.line(img, (x, 0), (x, rows - 1), level, 1)
    hw, hh = cfg.patch_width_px // 2, cfg.patch_height_px // 2
    for r, c in picks:
        top_left = ((c - hw) * scale, (r - hh) * scale)
        bottom_right = ((c + hw + 1) * scale - 1, (r + hh + 1) * scale - 1)
        cv2.rectangle(img, top_left, bottom_right, 255, 1)
    return img
