"""``hybrid_vo_node``: the hybrid wheel/visual odometer (thesis ch. 2) as a ROS 2 node.

A thin shell over :class:`hybrid_vo.frontend.VoFrontend` and :class:`hybrid_vo.sync.StereoSync`:
parameters, subscriptions, publishing. Message layouts stay in :mod:`msg_adapters`.

Inputs (relative names, remappable): ``left/image_rect``, ``right/image_rect``
(``sensor_msgs/Image``, or ``CompressedImage`` on ``.../compressed`` with
``use_compressed``; best effort), ``left/camera_info``, ``right/camera_info`` (best effort)
and wheel ``odom`` (``nav_msgs/Odometry``, reliable), queues :data:`CAMERA_QUEUE_DEPTH` and
:data:`ODOM_QUEUE_DEPTH` deep. What became of each input's messages is counted
(:mod:`h2o_slam.ros.inputs`).

Outputs: ``odometry/hybrid`` (``nav_msgs/Odometry``, ``odom_frame`` → ``base_frame``),
``/tf`` (``odom_frame`` → ``base_frame``, with ``publish_tf``), ``~/debug_image`` (mono8
horizon band with its patches, with ``publish_debug_image``) and ``/diagnostics``.
Services: ``~/reset`` (``std_srvs/Trigger``) and ``~/pause`` (``std_srvs/SetBool``, true
pauses).

No input ends the node: every subscription callback, the timer and both services run
inside one boundary (:meth:`HybridVoNode._guarded`, :meth:`HybridVoNode._boundary`) that
turns any exception into a logged rejection counted by reason in ``/diagnostics``
(``rejected.<source>: unexpected <Type>`` for anything but the package's own errors).

For replay, every subscription callback is a public ``on_*`` method that accepts rclpy
messages and messages deserialized by rosbags alike, and every publication goes through
:meth:`HybridVoNode.emit`, which also hands it to :attr:`HybridVoNode.sink` when set.
Output stamps are message stamps, never the wall clock.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import SetBool, Trigger

import msg_adapters as ma
from h2o_slam.core.errors import InputError
from h2o_slam.ros.boundary import behind_boundary
from h2o_slam.ros.inputs import InputCounts, counted_subscription
from h2o_slam.ros.node_main import run_node
from hybrid_vo.errors import HybridVOError
from hybrid_vo.frontend import (
    BAD_IMAGE,
    NO_CALIBRATION,
    FrontendConfig,
    InputRejected,
    VoFrontend,
    VoOutput,
    reason_key,
)
from hybrid_vo.odometer import OdometerConfig
from hybrid_vo.sync import LEFT, RIGHT, SIDE_NAMES, StarvationMonitor, StereoSync, SyncConfig

NODE_NAME = "hybrid_vo_node"
#: Seconds between two log lines about the same problem.
LOG_THROTTLE_S = 5.0
NS_PER_S = 1_000_000_000
#: Queue depth of the wheel odometry (reliable): 10 s at 100 Hz, what a stall of the node
#: (a slow first frame) leaves waiting; every sample is needed for the track.
ODOM_QUEUE_DEPTH = 1000
#: Queue depth of the images and camera infos (best effort): a second of frames at 10 Hz.
#: Deeper would only add latency and memory: a frame lost costs vision for that frame, the
#: wheels carry it; every loss is counted (input.<topic>.dropped).
CAMERA_QUEUE_DEPTH = 10

Sink = Callable[[str, Any], None]


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter: name, default, description and range (``None``: no range)."""

    name: str
    default: bool | int | float | str
    description: str
    low: float | None = None
    high: float | None = None


def _frontend(name: str, description: str, low: float, high: float) -> ParamSpec:
    """A parameter of :class:`FrontendConfig`, its default taken from there."""
    return ParamSpec(name, getattr(FrontendConfig(), name), description, low, high)


def _odometer(name: str, description: str, low: float | None = None,
              high: float | None = None) -> ParamSpec:
    """``odometer.<name>`` of :class:`OdometerConfig`, its default taken from there."""
    value = getattr(OdometerConfig(), name)
    return ParamSpec(f"odometer.{name}", 0.0 if value is None else value, description, low,
                     high)


#: Every parameter of the node, in the order of ``config/hybrid_vo.yaml``. Defaults come from
#: the cores' config dataclasses.
PARAMETERS: tuple[ParamSpec, ...] = (
    ParamSpec("odom_frame", "odom", "frame of the published pose (REP-105 odom)"),
    ParamSpec("base_frame", "base_link", "frame whose pose is published (child frame)"),
    ParamSpec("publish_tf", True, "publish odom_frame -> base_frame on /tf"),
    ParamSpec("use_compressed", False,
              "subscribe to sensor_msgs/CompressedImage on <image topic>/compressed"),
    ParamSpec("publish_debug_image", False,
              "publish ~/debug_image: the horizon band (mono8) with the sampled patches"),
    ParamSpec("debug_image_scale", 4, "enlargement of the debug image", 1, 16),
    ParamSpec("diagnostics_period", 1.0,
              "seconds of message time between /diagnostics reports", 0.1, 60.0),
    ParamSpec("starvation_timeout", 2.0,
              "seconds of silence on an input (while others arrive) before a warning",
              0.1, 60.0),
    ParamSpec("approx_sync", True,
              "pair left/right images by nearest stamp (false: equal stamps only)"),
    ParamSpec("approx_sync_max_interval", SyncConfig().approx_sync_max_interval,
              "largest left/right stamp difference of a pair, s (keep below half the "
              "frame period)", 0.0, 1.0),
    ParamSpec("sync_queue_size", SyncConfig().sync_queue_size,
              "unpaired images kept per side", 1, 100),
    _frontend("camera_yaw", "left camera yaw on base_link, rad (positive: turned left)",
              -math.pi, math.pi),
    _frontend("camera_pitch", "left camera pitch, rad (REP-103: positive tilts down)",
              -1.5, 1.5),
    _frontend("camera_roll", "left camera roll about its forward axis, rad", -1.5, 1.5),
    _frontend("camera_height", "height of the left optical centre above the ground, m",
              0.01, 100.0),
    _frontend("camera_forward", "left optical centre ahead of base_link, m", -100.0, 100.0),
    _frontend("camera_left", "left optical centre left of base_link, m", -100.0, 100.0),
    _frontend("wheel_buffer", "seconds of wheel odometry kept for interpolation at frame "
              "stamps", 0.1, 600.0),
    _frontend("max_pending_frames", "stereo frames that may wait for wheel odometry to reach "
              "their stamp", 1, 1000),
    _frontend("wheel_sigma_per_m", "wheel translation noise, 1 sigma per metre travelled",
              1e-6, 1.0),
    _frontend("initial_sigma", "1 sigma of the first pose (m, rad)", 1e-9, 10.0),
    _odometer("work_width_px", "images are downsampled to this width (height keeps the "
              "aspect ratio); thesis: 160", 32, 4096),
    _odometer("num_patches", "patches tracked per frame (thesis: 6)", 1, 64),
    _odometer("patch_width_px", "patch width in spherical pixels, odd (thesis: 13)", 3, 63),
    _odometer("patch_height_px", "patch height in spherical pixels, odd (thesis: 3)", 3, 63),
    _odometer("min_patches", "fewer usable patches -> the frame uses wheel odometry", 1, 64),
    _odometer("band_half_height_rad", "the horizon band covers this pitch above and below "
              "the horizon, rad", 0.01, 0.8),
    _odometer("theta_max_rad", "half-width of the patch sampling region, rad; 0: from the "
              "mounting", 0.0, 1.5),
    _odometer("max_speed_m_s", "largest robot speed, m/s (with frame_rate_hz: the r_min "
              "range test)", 0.01, 50.0),
    _odometer("frame_rate_hz", "camera frame rate, Hz", 0.1, 200.0),
    _odometer("min_ncc", "a patch match below this normalized cross-correlation is "
              "discarded", -0.99, 0.99),
    _odometer("fallback_yaw_sigma_rad", "yaw sigma of a frame that uses wheel odometry, rad",
              1e-6, 1.0),
    _odometer("sigma_merge", "how patch yaw sigmas combine: thesis or inverse_variance"),
    _odometer("parallax_correction", "remove from each patch the parallax predicted from "
              "the wheel travel and its stereo range (beyond the thesis)"),
    _odometer("balance_sides", "take patches from both sides of the direction of travel, "
              "equally weighted (beyond the thesis)"),
    _odometer("parallax_min_disparity_px", "patches with less disparity are taken as "
              "infinitely far, px", 0.0, 100.0),
    _odometer("symmetric_subpixel", "average the forward match with a match back from the "
              "current frame (beyond the thesis)"),
    _odometer("stereo_at_input_resolution", "range patches on the stereo pair as it "
              "arrives, not the downsampled one"),
    _odometer("match_blur_px", "Gaussian blur (sigma, spherical px) before corners and "
              "NCC; 0 disables", 0.0, 10.0),
)


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    desc = ParameterDescriptor(description=spec.description, read_only=True)
    if spec.low is None or spec.high is None:
        return desc
    if isinstance(spec.default, int) and not isinstance(spec.default, bool):
        desc.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high),
                                           step=1)]
    else:
        desc.floating_point_range = [FloatingPointRange(from_value=float(spec.low),
                                                        to_value=float(spec.high), step=0.0)]
    return desc


def frontend_config(values: dict[str, Any]) -> FrontendConfig:
    """The :class:`FrontendConfig` of parameter values by name (odometer ones dotted).

    Raises:
        ConfigError: values the cores refuse.
    """
    odometer = {
        f.name: values[f"odometer.{f.name}"]
        for f in fields(OdometerConfig)
        if f"odometer.{f.name}" in values
    }
    if odometer.get("theta_max_rad") == 0.0:
        odometer["theta_max_rad"] = None  # 0 asks for the thesis' choice from the mounting
    front = {f.name: values[f.name] for f in fields(FrontendConfig) if f.name in values}
    return FrontendConfig(**front, odometer=OdometerConfig(**odometer))


def _tf_message_class() -> Any:
    """``tf2_msgs/TFMessage``, or None when tf2_msgs is not installed."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return TFMessage


class HybridVoNode(Node):
    """Stereo images + camera info + wheel odometry in, corrected odometry out.

    Args:
        node_name: the node's name (``hybrid_vo_node``; tests give unique ones).
        **kwargs: passed to :class:`rclpy.node.Node` (``context``, ``namespace``,
            ``parameter_overrides``, ``cli_args``, ...).

    Attributes:
        sink: callable ``(topic, msg)`` that also receives every published message, or None.
        frontend: the odometry logic (counters in ``frontend.stats``).
        sync: the stereo synchronizer.
        monitor: the starvation watchdog.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.sink: Sink | None = None
        p = self._declare_parameters()
        self._p = p
        self.frontend = VoFrontend(frontend_config(p))
        self.sync: StereoSync[Any] = StereoSync(
            SyncConfig(p["approx_sync"], p["approx_sync_max_interval"], p["sync_queue_size"])
        )
        self.monitor = StarvationMonitor(p["starvation_timeout"])
        self._models: list[ma.CameraModel | None] = [None, None]
        self._last_image_ns: list[int | None] = [None, None]
        self._newest_ns: int | None = None
        self._last_diag_ns: int | None = None
        self._inputs_since_tick = 0
        self._silent_ticks = 0
        self._warned: dict[str, float] = {}
        self.tf_skipped = 0
        #: What became of each input's messages (h2o_slam.ros.inputs), by source key.
        self.inputs: dict[str, InputCounts] = {}
        self._subscribe(bool(p["use_compressed"]))
        self._advertise()
        self.create_service(Trigger, "~/reset", self._boundary("reset", self._on_reset))
        self.create_service(SetBool, "~/pause", self._boundary("pause", self._on_pause))
        self.create_timer(float(p["diagnostics_period"]),
                          self._boundary("diagnostics_timer", self._on_timer))
        self._diagnose = self._boundary("diagnostics", self._maybe_diagnostics)
        self._log_ready()

    # ------------------------------------------------------------------ set-up

    def _declare_parameters(self) -> dict[str, Any]:
        values = {}
        for spec in PARAMETERS:
            param = self.declare_parameter(spec.name, spec.default, _descriptor(spec))
            values[spec.name] = param.value
        return values

    def _subscribe(self, compressed: bool) -> None:
        image_type, suffix = (CompressedImage, "/compressed") if compressed else (Image, "")
        sensor = QoSProfile(depth=CAMERA_QUEUE_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT)
        # The executor serves ready subscriptions in creation order: wheel odometry and
        # camera info first, so that a frame finds what it needs when all arrive at once.
        specs = (
            # Wheel odometry drivers publish reliably; one lost sample would leave a gap.
            ("odom", Odometry, "odom", self.on_wheel_odom, QoSProfile(depth=ODOM_QUEUE_DEPTH)),
            ("left_info", CameraInfo, "left/camera_info", self.on_left_info, sensor),
            ("right_info", CameraInfo, "right/camera_info", self.on_right_info, sensor),
            ("left_image", image_type, f"left/image_rect{suffix}", self.on_left_image, sensor),
            ("right_image", image_type, f"right/image_rect{suffix}", self.on_right_image, sensor),
        )
        self.input_topics: dict[str, str] = {}
        for key, msg_type, topic, callback, qos in specs:
            self.inputs[key] = InputCounts()
            sub = counted_subscription(self, self.inputs[key], msg_type, topic, callback, qos)
            self.input_topics[key] = sub.topic_name
        partners = {"left_image": "right_image", "right_image": "left_image"}
        for key, topic in self.input_topics.items():
            partner = self.input_topics[partners[key]] if key in partners else None
            self.monitor.watch(topic, once=key.endswith("_info"), partner=partner)

    def _advertise(self) -> None:
        p = self._p
        self._publishers_by_key: dict[str, Any] = {
            "odometry": self.create_publisher(Odometry, "odometry/hybrid", 10),
            "diagnostics": self.create_publisher(DiagnosticArray, "/diagnostics", 10),
        }
        if p["publish_debug_image"]:
            self._publishers_by_key["debug_image"] = self.create_publisher(
                Image, "~/debug_image", qos_profile_sensor_data
            )
        self._tf_class = _tf_message_class() if p["publish_tf"] else None
        if self._tf_class is not None:
            self._publishers_by_key["tf"] = self.create_publisher(
                self._tf_class, "/tf", QoSProfile(depth=100)
            )
        elif p["publish_tf"]:
            self.get_logger().warning(
                "publish_tf is true but tf2_msgs is not installed (ros-jazzy-tf2-msgs); "
                "odom -> base_link is not published on /tf (counted as tf_skipped)"
            )

    def _log_ready(self) -> None:
        """One line at start-up: the node is up, the topics it reads and writes, and the
        parameters that decide what it computes."""
        p, topics = self._p, self.input_topics
        out = ", ".join(self.output_topics.values())
        self.get_logger().info(
            f"{self.get_fully_qualified_name()} ready: in {topics['left_image']}, "
            f"{topics['right_image']} ({'CompressedImage' if p['use_compressed'] else 'Image'}"
            f"), {topics['left_info']}, {topics['right_info']}, {topics['odom']} (wheel "
            f"odometry); out {out}; {p['odom_frame']} -> {p['base_frame']}, approx_sync "
            f"{str(p['approx_sync']).lower()} ({p['approx_sync_max_interval']} s), work_width_px "
            f"{p['odometer.work_width_px']}, num_patches {p['odometer.num_patches']}, "
            f"frame_rate_hz {p['odometer.frame_rate_hz']}, camera_height "
            f"{p['camera_height']} m, camera_pitch {p['camera_pitch']} rad")

    @property
    def output_topics(self) -> dict[str, str]:
        """Resolved topic of each output, by key (``odometry``, ``tf``, ...)."""
        return {key: pub.topic_name for key, pub in self._publishers_by_key.items()}

    # ------------------------------------------------------------------ callbacks

    def on_left_image(self, msg: Any) -> None:
        """Left rectified image (``Image`` or ``CompressedImage``)."""
        self._guarded("left_image", self._image, LEFT, msg)

    def on_right_image(self, msg: Any) -> None:
        """Right rectified image (``Image`` or ``CompressedImage``)."""
        self._guarded("right_image", self._image, RIGHT, msg)

    def on_left_info(self, msg: Any) -> None:
        """Left ``CameraInfo``; the latest one is used."""
        self._guarded("left_info", self._info, LEFT, msg)

    def on_right_info(self, msg: Any) -> None:
        """Right ``CameraInfo`` (its ``P`` gives the baseline); the latest one is used."""
        self._guarded("right_info", self._info, RIGHT, msg)

    def on_wheel_odom(self, msg: Any) -> None:
        """Wheel ``nav_msgs/Odometry``: pose of the robot in the wheels' odometry frame."""
        self._guarded("odom", self._wheel_odom, msg)

    def _guarded(self, source: str, handler: Callable[..., None], *args: Any) -> None:
        """Run a callback's work: the boundary of every input callback. A bad input is
        logged, counted and skipped (doc/nodes.md, bad input); so is any other exception,
        counted as ``<source>: unexpected <Type>`` (a bug, logged as an error)."""
        self._inputs_since_tick += 1
        try:
            handler(*args)
        except Exception as exc:  # the boundary: no message ends the node (issue 13)
            self.inputs[source].rejected += 1
            self._count_rejection(source, exc)
            return
        self.inputs[source].accepted += 1
        self._diagnose()

    def _count_rejection(self, source: str, exc: Exception) -> None:
        """Log and count a refused input (or a failed timer or service) by reason."""
        where = self.input_topics.get(source, source)
        if isinstance(exc, InputRejected):  # counted by the frontend already
            self._warn(exc.reason, f"{where}: {exc}")
        elif isinstance(exc, InputError | HybridVOError):
            reason = reason_key(source, exc)
            self.frontend.count_rejection(reason, str(exc))
            self._warn(reason, f"{where}: rejected: {exc}")
        else:
            reason = f"{source}: unexpected {type(exc).__name__}"
            self.frontend.count_rejection(reason, str(exc))
            now = time.monotonic()
            if now - self._warned.get(reason, -math.inf) >= LOG_THROTTLE_S:
                self._warned[reason] = now
                self.get_logger().error(f"{where}: unexpected {type(exc).__name__}: {exc}")

    def _boundary(self, what: str, work: Callable[..., Any]) -> Callable[..., Any]:
        """``work`` (the timer or a service) behind the node's boundary: an exception is
        logged and counted, never raised into the executor; a service then answers
        ``success=False`` with the reason."""
        return behind_boundary(what, work, self._count_rejection)

    def _note(self, source: str, stamp_ns: int) -> None:
        self.monitor.note(self.input_topics[source], stamp_ns)
        if self._newest_ns is None or stamp_ns > self._newest_ns:
            self._newest_ns = stamp_ns

    def _image(self, side: int, msg: Any) -> None:
        kind = "CompressedImage" if hasattr(msg, "format") else "Image"
        stamp = ma.stamp_ns(msg.header, f"{kind}.header.stamp")
        ma.check_stamp_order(self._last_image_ns[side], stamp, field=f"{kind}.header.stamp",
                             strict=True)
        self._last_image_ns[side] = stamp
        self._note(f"{SIDE_NAMES[side]}_image", stamp)
        unpaired = list(self.sync.stats.dropped)
        pair = self.sync.add(side, stamp, msg)
        self._discard_unpaired(unpaired)
        if pair is not None:
            self._stereo(pair.stamp_ns, pair.left, pair.right)

    def _discard_unpaired(self, before: list[int]) -> None:
        """Images the synchronizer dropped unpaired since its counts were ``before``: taken
        in earlier (accepted), dropped now."""
        for s in (LEFT, RIGHT):
            count = self.sync.stats.dropped[s] - before[s]
            if count:
                self.inputs[f"{SIDE_NAMES[s]}_image"].move("discarded", count)

    def _stereo(self, stamp_ns: int, left_msg: Any, right_msg: Any) -> None:
        odometer = self.frontend.odometer
        if odometer is None:
            self._publish(self.frontend.add_frame(stamp_ns, None, None, NO_CALIBRATION))
            return
        intr = odometer.input_intrinsics
        size = (intr.width_px, intr.height_px)
        images = []
        for source, msg in (("left_image", left_msg), ("right_image", right_msg)):
            try:
                images.append(ma.image_msg_to_gray8(msg, expected_size=size))
            except ma.AdapterError as exc:
                reason = reason_key(source, exc)
                self.frontend.count_rejection(reason, str(exc))
                self.inputs[source].move("rejected")  # taken in when it arrived
                self._warn(reason, f"{self.input_topics[source]}: rejected: {exc}")
                self._publish(self.frontend.add_frame(stamp_ns, None, None, BAD_IMAGE))
                return
        self._publish(self.frontend.add_frame(stamp_ns, images[0], images[1]))

    def _info(self, side: int, msg: Any) -> None:
        model = ma.camera_info_from_msg(msg)
        self._models[side] = model
        self._note(f"{SIDE_NAMES[side]}_info", model.stamp_ns)
        left, right = self._models
        if left is not None and right is not None and self.frontend.set_calibration(left, right):
            odometer = self.frontend.odometer
            assert odometer is not None
            self.get_logger().info(
                f"stereo calibration {left.width}x{left.height}, baseline "
                f"{odometer.mounting.baseline_m:.4f} m: odometer ready (r_min "
                f"{odometer.r_min_m:.2f} m)"
            )

    def _wheel_odom(self, msg: Any) -> None:
        sample = ma.odometry_from_msg(msg)
        x, y, yaw, _ = sample.planar()
        self._note("odom", sample.stamp_ns)
        self._publish(self.frontend.add_wheel(sample.stamp_ns, x, y, yaw))

    # ------------------------------------------------------------------ outputs

    def emit(self, key: str, msg: Any) -> None:
        """Publish ``msg`` on output ``key`` and hand it to :attr:`sink` (if set)."""
        pub = self._publishers_by_key[key]
        pub.publish(msg)
        if self.sink is not None:
            self.sink(pub.topic_name, msg)

    def _publish(self, outputs: Sequence[VoOutput]) -> None:
        odom_frame, base_frame = self._p["odom_frame"], self._p["base_frame"]
        for out in outputs:
            sample = ma.planar_odometry_sample(
                out.stamp_ns, odom_frame, base_frame, out.x_m, out.y_m, out.yaw_rad,
                out.covariance_6x6, yaw_rate_radps=out.yaw_rate_radps,
            )
            sample = replace(sample, twist_linear=np.array([out.v_x_mps, out.v_y_mps, 0.0]))
            self.emit("odometry", ma.fill_odometry(Odometry, sample))
            if self._p["publish_tf"]:
                self._publish_tf(sample)
            if self._p["publish_debug_image"]:
                self._publish_debug_image(out.stamp_ns)

    def _publish_tf(self, sample: ma.OdometrySample) -> None:
        if self._tf_class is None:
            self.tf_skipped += 1
            return
        transform = ma.fill_transform(
            TransformStamped, sample.R, sample.t, stamp_ns=sample.stamp_ns,
            frame_id=sample.frame_id, child_frame_id=sample.child_frame_id,
        )
        self.emit("tf", ma.fill_tf_message(self._tf_class, [transform]))

    def _publish_debug_image(self, stamp_ns: int) -> None:
        image = self.frontend.debug_image(int(self._p["debug_image_scale"]))
        if image is None:
            return
        left = self._models[LEFT]
        frame_id = left.frame_id if left is not None else ""
        self.emit("debug_image", ma.fill_image(Image, image, stamp_ns=stamp_ns,
                                               frame_id=frame_id))

    # ------------------------------------------------------------------ diagnostics

    def _maybe_diagnostics(self) -> None:
        """Report every ``diagnostics_period`` of message time (deterministic on replay)."""
        newest = self._newest_ns
        if newest is None:
            return
        period_ns = int(self._p["diagnostics_period"] * NS_PER_S)
        if self._last_diag_ns is None or newest - self._last_diag_ns >= period_ns:
            self._last_diag_ns = newest
            self.publish_diagnostics(newest)

    def _on_timer(self) -> None:
        # Message time stands still when no input arrives; report that on the node clock.
        if self._inputs_since_tick:
            self._silent_ticks = 0
        else:
            self._silent_ticks += 1
            stamp = self._newest_ns
            if stamp is None:
                stamp = self.get_clock().now().nanoseconds
            silent_s = self._silent_ticks * self._p["diagnostics_period"]
            topics = ", ".join(self.input_topics.values())
            self.publish_diagnostics(stamp, extra=[f"no input for {silent_s:.0f} s on {topics}"])
        self._inputs_since_tick = 0

    def problems(self) -> list[str]:
        """Current warnings: starving inputs, unpaired stereo, no calibration, no TF."""
        found = self.monitor.starving()
        found += self._unpaired_stereo()
        if self.frontend.stats.fallbacks[NO_CALIBRATION] and not self.frontend.calibrated:
            found.append("no usable stereo calibration yet: using wheel odometry only")
        if self._p["publish_tf"] and self._tf_class is None:
            found.append("tf2_msgs not installed: /tf not published")
        return found

    def _unpaired_stereo(self) -> list[str]:
        left_ns, right_ns = self._last_image_ns
        if left_ns is None or right_ns is None or self._newest_ns is None:
            return []
        since = self.sync.stats.last_pair_ns
        quiet_ns = self._newest_ns - (since if since is not None else min(left_ns, right_ns))
        if quiet_ns <= self.monitor.timeout_ns:
            return []
        gap_s = (left_ns - right_ns) / NS_PER_S
        return [
            f"{self.input_topics['left_image']} and {self.input_topics['right_image']} "
            f"arrive but no pair for {quiet_ns / NS_PER_S:.1f} s (latest stamps differ by "
            f"{gap_s:+.3f} s; approx_sync_max_interval "
            f"{self._p['approx_sync_max_interval']} s)"
        ]

    def publish_diagnostics(self, stamp_ns: int, extra: Sequence[str] = ()) -> None:
        """Emit one ``/diagnostics`` report stamped ``stamp_ns``; log current problems."""
        problems = [*extra, *self.problems()]
        for text in problems:
            self._warn(text.split(" for ")[0], text)
        st = self.frontend.stats
        values: dict[str, object] = {
            "frames": st.frames,
            "vision_frames": st.vision_frames,
            "fallback_fraction": st.fallback_fraction,
            "frame_time_ms_last": 1e3 * st.frame_time_last_s,
            "frame_time_ms_mean": 1e3 * st.frame_time_mean_s,
            "frame_time_ms_max": 1e3 * st.frame_time_max_s,
            "rejected_total": sum(st.rejected.values()),
            "last_rejection": st.last_rejection,
            "pending_frames": self.frontend.pending_frames,
            "stereo_pairs": self.sync.stats.pairs,
            "unpaired_left": self.sync.stats.dropped[LEFT],
            "unpaired_right": self.sync.stats.dropped[RIGHT],
            "calibrated": self.frontend.calibrated,
            "paused": self.frontend.paused,
            "dropped_paused": st.dropped_paused,
            "tf_skipped": self.tf_skipped,
        }
        for key, counts in self.inputs.items():
            values.update(counts.values(f"input.{key}."))
        values.update({f"fallback.{k}": v for k, v in sorted(st.fallbacks.items())})
        values.update({f"rejected.{k}": v for k, v in sorted(st.rejected.items())})
        message = "; ".join(problems) if problems else (
            "paused" if self.frontend.paused else
            f"{st.frames} frames, {100 * st.fallback_fraction:.0f}% wheel only"
        )
        report = ma.DiagnosticReport(
            name=f"{self.get_name()}: hybrid visual odometry",
            level="WARN" if problems else "OK",
            message=message,
            values=values,
        )
        self.emit("diagnostics", ma.fill_diagnostic_array(DiagnosticArray, [report],
                                                          stamp_ns=stamp_ns))

    def _warn(self, key: str, text: str) -> None:
        """Log ``text`` unless the same problem was logged less than LOG_THROTTLE_S ago."""
        now = time.monotonic()
        if now - self._warned.get(key, -math.inf) >= LOG_THROTTLE_S:
            self._warned[key] = now
            self.get_logger().warning(text)

    # ------------------------------------------------------------------ services

    def reset(self) -> None:
        """Restart odometry at the origin of ``odom``; calibration and counters are kept."""
        self.frontend.reset()
        for side in (LEFT, RIGHT):  # images waiting for a partner are dropped
            self.inputs[f"{SIDE_NAMES[side]}_image"].move("discarded", self.sync.queued(side))
        self.sync.clear()
        self.monitor.reset()
        self._last_image_ns = [None, None]
        self._newest_ns = self._last_diag_ns = None
        self.get_logger().info("reset: odometry restarts at the origin of odom")

    def set_paused(self, paused: bool) -> None:
        """Pause (frames ignored) or resume (wheel motion while paused is added)."""
        if paused:
            self.frontend.pause()
        else:
            self.frontend.resume()

    def _on_reset(self, request: Any, response: Any) -> Any:
        self.reset()
        response.success = True
        response.message = "odometry reset to the origin"
        return response

    def _on_pause(self, request: Any, response: Any) -> Any:
        self.set_paused(bool(request.data))
        response.success = True
        response.message = "paused" if request.data else "resumed"
        return response


def main(args: list[str] | None = None) -> int:
    """Run the node until shutdown; a bad parameter ends it with one line and exit code 1."""
    return run_node(HybridVoNode, NODE_NAME, (HybridVOError, InputError, ParameterException),
                    args)


if __name__ == "__main__":
    sys.exit(main())
