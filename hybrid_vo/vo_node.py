"""``hybrid_vo_node``: the hybrid wheel/visual odometer (thesis ch. 2) as a ROS 2 node.

A thin shell over :class:`hybrid_vo.frontend.VoFrontend` and :class:`hybrid_vo.sync.StereoSync`:
parameters, subscriptions, publishing. Message layouts stay in :mod:`msg_adapters`.

Inputs (relative names, remappable): ``left/image_rect``, ``right/image_rect``
(``sensor_msgs/Image``, or ``CompressedImage`` on ``.../compressed`` with
``use_compressed``; best effort), ``left/camera_info``, ``right/camera_info`` (best effort)
and wheel ``odom`` (``nav_msgs/Odometry``, reliable), queues :data:`CAMERA_QUEUE_DEPTH` and
:data:`ODOM_QUEUE_DEPTH` deep. What became of each input's messages is counted
(:mod:`ros_node_base.inputs`).

Outputs: ``odometry/hybrid`` (``nav_msgs/Odometry``, ``odom_frame`` → ``base_frame``),
``/tf`` (``odom_frame`` → ``base_frame``, with ``publish_tf``), ``~/debug_image`` (mono8
horizon band with its patches, with ``publish_debug_image``) and ``/diagnostics``.
Services: ``~/reset`` (``std_srvs/Trigger``) and ``~/pause`` (``std_srvs/SetBool``, true
pauses).

No input ends the node: every subscription callback, the timer and both services run
behind the boundary of the shell both nodes share (:class:`ros_node_base.node.NodeBase`),
which turns any exception into a logged rejection counted by reason in ``/diagnostics``
(``rejected.<source>: unexpected <Type>`` for anything but the package's own errors).
Parameters come from one typed tree, :class:`hybrid_vo.node_config.VoNodeConfig`.

For replay, every subscription callback is a public ``on_*`` method that accepts rclpy
messages and messages deserialized by rosbags alike, and every publication goes through
:meth:`HybridVoNode.emit`, which also hands it to :attr:`HybridVoNode.sink` when set.
Output stamps are message stamps, never the wall clock.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import Odometry
from rclpy.exceptions import ParameterException
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import SetBool, Trigger

import msg_adapters as ma
from h2o_slam.core.errors import InputError
from hybrid_vo.errors import HybridVOError
from hybrid_vo.frontend import (
    BAD_IMAGE,
    NO_CALIBRATION,
    InputRejected,
    VoFrontend,
    VoOutput,
    reason_key,
)
from hybrid_vo.node_config import VoNodeConfig
from hybrid_vo.sync import LEFT, RIGHT, SIDE_NAMES, StarvationMonitor, StereoSync
from ros_node_base.main import run_node
from ros_node_base.node import NodeBase

NODE_NAME = "hybrid_vo_node"
NS_PER_S = 1_000_000_000
#: Queue depth of the wheel odometry (reliable): 10 s at 100 Hz, what a stall of the node
#: (a slow first frame) leaves waiting; every sample is needed for the track.
ODOM_QUEUE_DEPTH = 1000
#: Queue depth of the images and camera infos (best effort): a second of frames at 10 Hz.
#: Deeper would only add latency and memory: a frame lost costs vision for that frame, the
#: wheels carry it; every loss is counted (input.<topic>.dropped).
CAMERA_QUEUE_DEPTH = 10


class HybridVoNode(NodeBase[VoNodeConfig]):
    """Stereo images + camera info + wheel odometry in, corrected odometry out.

    Parameters, the boundary, the input counts and the outputs are the shell's
    (:class:`ros_node_base.node.NodeBase`); :attr:`config` is a :class:`VoNodeConfig`.

    Args:
        node_name: the node's name (``hybrid_vo_node``; tests give unique ones).
        **kwargs: passed to :class:`rclpy.node.Node` (``context``, ``namespace``,
            ``parameter_overrides``, ``cli_args``, ...).

    Attributes:
        frontend: the odometry logic (counters in ``frontend.stats``).
        sync: the stereo synchronizer.
        monitor: the starvation watchdog.
    """

    expected_errors = (InputError, HybridVOError)

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, VoNodeConfig, **kwargs)
        config = self.config
        self.frontend = VoFrontend(config.frontend)
        self.sync: StereoSync[Any] = StereoSync(config.sync)
        self.monitor = StarvationMonitor(config.starvation_timeout)
        self._models: list[ma.CameraModel | None] = [None, None]
        self._last_image_ns: list[int | None] = [None, None]
        self._newest_ns: int | None = None
        self._last_diag_ns: int | None = None
        self._inputs_since_tick = 0
        self._silent_ticks = 0
        self.tf_skipped = 0
        self._subscribe(config.use_compressed)
        self._advertise()
        self.create_service(Trigger, "~/reset", self.boundary("reset", self._on_reset))
        self.create_service(SetBool, "~/pause", self.boundary("pause", self._on_pause))
        self.create_timer(config.diagnostics_period,
                          self.boundary("diagnostics_timer", self._on_timer))
        self._diagnose = self.boundary("diagnostics", self._maybe_diagnostics)
        self._log_ready()

    # ------------------------------------------------------------------ set-up

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
        for key, msg_type, topic, callback, qos in specs:
            self.subscribe(key, msg_type, topic, callback, qos)
        partners = {"left_image": "right_image", "right_image": "left_image"}
        for key, topic in self.input_topics.items():
            partner = self.input_topics[partners[key]] if key in partners else None
            self.monitor.watch(topic, once=key.endswith("_info"), partner=partner)

    def _advertise(self) -> None:
        self.advertise("odometry", Odometry, "odometry/hybrid", 10)
        self.advertise_diagnostics()
        if self.config.publish_debug_image:
            self.advertise("debug_image", Image, "~/debug_image", qos_profile_sensor_data)
        if self.config.publish_tf:
            self.advertise_tf("odom -> base_link is not published on /tf (counted as "
                              "tf_skipped)")

    def _log_ready(self) -> None:
        """One line at start-up: the node is up, the topics it reads and writes, and the
        parameters that decide what it computes."""
        c, topics = self.config, self.input_topics
        front, odometer = c.frontend, c.frontend.odometer
        out = ", ".join(self.output_topics.values())
        self.get_logger().info(
            f"{self.get_fully_qualified_name()} ready: in {topics['left_image']}, "
            f"{topics['right_image']} ({'CompressedImage' if c.use_compressed else 'Image'}"
            f"), {topics['left_info']}, {topics['right_info']}, {topics['odom']} (wheel "
            f"odometry); out {out}; {c.odom_frame} -> {c.base_frame}, approx_sync "
            f"{str(c.sync.approx_sync).lower()} ({c.sync.approx_sync_max_interval} s), "
            f"work_width_px {odometer.work_width_px}, num_patches {odometer.num_patches}, "
            f"frame_rate_hz {odometer.frame_rate_hz}, camera_height {front.camera_height} m, "
            f"camera_pitch {front.camera_pitch} rad")

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
        """Handle one input behind the boundary (doc/nodes.md, bad input); a report is due
        after each accepted one."""
        self._inputs_since_tick += 1
        if self.guarded(source, handler, *args):
            self._diagnose()

    def rejection_reason(self, what: str, exc: Exception) -> str:
        """The frontend's reason for what it refused itself, else the field and problem."""
        return exc.reason if isinstance(exc, InputRejected) else reason_key(what, exc)

    def record_rejection(self, reason: str, exc: Exception) -> None:
        """Counted in the frontend's statistics (``rejected.<reason>`` in /diagnostics)."""
        if not isinstance(exc, InputRejected):  # the frontend counted it already
            self.frontend.count_rejection(reason, str(exc))

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
                self.log_throttled(reason, f"{self.input_topics[source]}: rejected: {exc}")
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

    def _publish(self, outputs: Sequence[VoOutput]) -> None:
        odom_frame, base_frame = self.config.odom_frame, self.config.base_frame
        for out in outputs:
            sample = ma.planar_odometry_sample(
                out.stamp_ns, odom_frame, base_frame, out.x_m, out.y_m, out.yaw_rad,
                out.covariance_6x6, yaw_rate_radps=out.yaw_rate_radps,
            )
            sample = replace(sample, twist_linear=np.array([out.v_x_mps, out.v_y_mps, 0.0]))
            self.emit("odometry", ma.fill_odometry(Odometry, sample))
            if self.config.publish_tf:
                self._publish_tf(sample)
            if self.config.publish_debug_image:
                self._publish_debug_image(out.stamp_ns)

    def _publish_tf(self, sample: ma.OdometrySample) -> None:
        if self.tf_message is None:
            self.tf_skipped += 1
            return
        self.emit_tf(ma.fill_transform(
            TransformStamped, sample.R, sample.t, stamp_ns=sample.stamp_ns,
            frame_id=sample.frame_id, child_frame_id=sample.child_frame_id,
        ))

    def _publish_debug_image(self, stamp_ns: int) -> None:
        image = self.frontend.debug_image(self.config.debug_image_scale)
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
        period_ns = int(self.config.diagnostics_period * NS_PER_S)
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
            silent_s = self._silent_ticks * self.config.diagnostics_period
            topics = ", ".join(self.input_topics.values())
            self.publish_diagnostics(stamp, extra=[f"no input for {silent_s:.0f} s on {topics}"])
        self._inputs_since_tick = 0

    def problems(self) -> list[str]:
        """Current warnings: starving inputs, unpaired stereo, no calibration, no TF."""
        found = self.monitor.starving()
        found += self._unpaired_stereo()
        if self.frontend.stats.fallbacks[NO_CALIBRATION] and not self.frontend.calibrated:
            found.append("no usable stereo calibration yet: using wheel odometry only")
        if self.config.publish_tf and self.tf_message is None:
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
            f"{self.config.sync.approx_sync_max_interval} s)"
        ]

    def publish_diagnostics(self, stamp_ns: int, extra: Sequence[str] = ()) -> None:
        """Emit one ``/diagnostics`` report stamped ``stamp_ns``; log current problems."""
        problems = [*extra, *self.problems()]
        for text in problems:
            self.log_throttled(text.split(" for ")[0], text)
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
        self.emit_report(report, stamp_ns)

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
