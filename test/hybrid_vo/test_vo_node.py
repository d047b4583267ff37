"""hybrid_vo_node in-process: a test node publishes a simulated drive through real publishers,
one SingleThreadedExecutor spins both, and the tests check what the node publishes.

Each test has its own namespace, node name and frame names, so that other tests running at
the same time on this machine never cross its topics (``/tf`` and ``/diagnostics`` are
global: they are filtered by frame and by status name).
"""

from __future__ import annotations

import math
import re
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from bag_messages import to_rosbags
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.exceptions import InvalidParameterValueException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_dict_from_yaml_file
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_srvs.srv import SetBool, Trigger

import msg_adapters as ma
from hybrid_vo.errors import ConfigError
from hybrid_vo.node_config import VoNodeConfig
from hybrid_vo.sim.messages import DEFAULT_START_NS, StreamMessage, Topics, drive_messages
from hybrid_vo.sim.world import Drive, make_drive, scenario, wrap_angle
from hybrid_vo.vo_node import HybridVoNode, main
from ros_node_base.params import param_specs

REPO = Path(__file__).resolve().parents[2]
TURN = (math.pi / 2) / 3.0
PITCH = 0.03  # the simulated drives' camera pitch
WAIT_S = 20.0  # generous: the machine is shared with benchmarks


def _diag_values(status: Any) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


@dataclass
class Rig:
    """The node under test, a tester node with publishers and subscribers, one executor."""

    context: Context
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        tag = uuid.uuid4().hex[:8]
        self.ns = f"/vo_{tag}"
        self.name = f"hybrid_vo_{tag}"
        self.odom_frame, self.base_frame = f"odom_{tag}", f"base_{tag}"
        params = {"camera_pitch": PITCH, "odom_frame": self.odom_frame,
                  "base_frame": self.base_frame, **self.params}
        self.node = HybridVoNode(
            self.name, namespace=self.ns, context=self.context,
            parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
            cli_args=["--ros-args", "-r", "odom:=wheel/odom"],  # remapped like a robot would
        )
        self.tester = Node(f"tester_{tag}", namespace=self.ns, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.tester)
        self.topics = Topics(*(f"{self.ns}{name}" for name in (
            "/left/image_rect", "/right/image_rect", "/left/camera_info",
            "/right/camera_info", "/wheel/odom", "/gps/fix", "/loop_closure", "/truth")))
        sensor, reliable = qos_profile_sensor_data, QoSProfile(depth=100)
        self.pubs = {
            self.topics.left_image: self.tester.create_publisher(Image, self.topics.left_image,
                                                                 sensor),
            self.topics.right_image: self.tester.create_publisher(
                Image, self.topics.right_image, sensor),
            self.topics.left_info: self.tester.create_publisher(
                CameraInfo, self.topics.left_info, sensor),
            self.topics.right_info: self.tester.create_publisher(
                CameraInfo, self.topics.right_info, sensor),
            self.topics.wheel_odom: self.tester.create_publisher(
                Odometry, self.topics.wheel_odom, reliable),
        }
        self.odometry: list[Any] = []
        self.diagnostics: list[Any] = []
        self.transforms: list[Any] = []
        self.debug_images: list[Any] = []
        self.tester.create_subscription(Odometry, f"{self.ns}/odometry/hybrid",
                                        self.odometry.append, reliable)
        self.tester.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, reliable)
        if self.node.tf_message is not None:
            self.tester.create_subscription(self.node.tf_message, "/tf", self._on_tf, reliable)
        self.tester.create_subscription(Image, f"{self.ns}/{self.name}/debug_image",
                                        self.debug_images.append, sensor)
        self.spin_until(self._connected, "discovery")

    def _connected(self) -> bool:
        return (all(p.get_subscription_count() > 0 for p in self.pubs.values())
                and self.node.publishers_by_key["odometry"].get_subscription_count() > 0)

    def _on_diag(self, msg: Any) -> None:
        stamp = ma.stamp_ns(msg.header)
        self.diagnostics += [(stamp, s) for s in msg.status if s.name.startswith(self.name + ":")]

    def _on_tf(self, msg: Any) -> None:
        self.transforms += [t for t in msg.transforms if t.child_frame_id == self.base_frame]

    def spin_until(self, done: Callable[[], bool], what: str, timeout_s: float = WAIT_S) -> None:
        deadline = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
            self.executor.spin_once(timeout_sec=0.01)

    def publish(self, item: StreamMessage) -> None:
        pub = self.pubs.get(item.topic)
        if pub is not None:
            pub.publish(item.msg)
            self.executor.spin_once(timeout_sec=0.0)

    def feed(self, items: list[StreamMessage] | Iterator[StreamMessage],
             wait_each_frame: bool = True) -> None:
        """Publish in stamp order; after each right image wait for its odometry output."""
        for item in items:
            self.publish(item)
            if wait_each_frame and item.topic == self.topics.right_image:
                stamp = item.stamp_ns
                self.spin_until(lambda s=stamp: self._has_output(s), f"output at {stamp}")

    def _has_output(self, stamp_ns: int) -> bool:
        return bool(self.odometry) and ma.stamp_ns(self.odometry[-1].header) >= stamp_ns

    def call(self, srv_type: Any, name: str, request: Any) -> Any:
        client = self.tester.create_client(srv_type, f"{self.ns}/{self.name}/{name}")
        self.spin_until(client.service_is_ready, f"service {name}")
        future = client.call_async(request)
        self.spin_until(future.done, f"answer of {name}")
        return future.result()

    def diagnostics_after(self, after_ns: int) -> dict[str, str]:
        """Message and values of the first report stamped at or after ``after_ns``."""
        def found() -> Any:
            # Reports of silence before the first input carry the clock's time: skipped.
            return next((s for t, s in self.diagnostics
                         if t >= after_ns and not s.message.startswith("no input")), None)
        self.spin_until(lambda: found() is not None, f"diagnostics at {after_ns} ns or later")
        status = found()
        return {"message": status.message, "level": str(status.level[0]),
                **_diag_values(status)}

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.tester.destroy_node()


@pytest.fixture
def rig_factory(context: Context) -> Iterator[Callable[..., Rig]]:
    rigs: list[Rig] = []

    def make(**params: Any) -> Rig:
        rigs.append(Rig(context, params))
        return rigs[-1]

    yield make
    for rig in rigs:
        rig.close()


def _slip_drive() -> Drive:
    # 12 s of the slip scenario: heading drift from 4 s, a false 0.4 rad turn at 8 s.
    segments = ((6.0, 1.3, 0.0), (3.0, 1.0, TURN), (3.0, 1.3, 0.0))
    return make_drive(scenario("slip", segments=segments))


def _straight_drive(seconds: float) -> Drive:
    # No near posts: every frame can be tracked, so a wheel-only frame has a reason to test.
    return make_drive(scenario("straight", segments=((seconds, 1.3, 0.0),), num_objects=0))


def _messages(rig: Rig, drive: Drive) -> list[StreamMessage]:
    return [m for m in drive_messages(drive, topics=rig.topics) if m.topic in rig.pubs]


def _planar(msg: Any) -> tuple[int, float, float, float]:
    sample = ma.odometry_from_msg(msg)
    return sample.stamp_ns, float(sample.t[0]), float(sample.t[1]), sample.yaw_rad


def _reserialized(msg: Any) -> Any:
    """An independent copy of an rclpy message (through CDR)."""
    return deserialize_message(serialize_message(msg), type(msg))


# ----------------------------------------------------------------------------- the drive


def test_corrected_odometry_beats_wheel_odometry_under_slip(rig_factory) -> None:
    rig = rig_factory(publish_debug_image=True)
    drive = _slip_drive()
    rig.feed(drive_messages(drive, topics=rig.topics))
    assert len(rig.odometry) == len(drive)
    frame_stamps = [int(s) + DEFAULT_START_NS for s in drive.stamps_ns]
    rows = [_planar(m) for m in rig.odometry]
    assert [r[0] for r in rows] == frame_stamps  # stamps are the images' stamps
    yaw = np.array([r[3] for r in rows])
    wheel = drive.wheel_poses()
    err_vo = np.abs(wrap_angle(yaw - drive.truth[:, 2]))
    err_wheel = np.abs(wrap_angle(wheel[:, 2] - drive.truth[:, 2]))
    assert err_wheel.max() > 0.5
    assert math.sqrt(np.mean(err_vo**2)) < 0.25 * math.sqrt(np.mean(err_wheel**2))
    assert err_vo.max() < 0.25 * err_wheel.max()
    end_vo = math.hypot(rows[-1][1] - drive.truth[-1, 0], rows[-1][2] - drive.truth[-1, 1])
    end_wheel = float(np.hypot(*(wheel[-1, :2] - drive.truth[-1, :2])))
    assert end_vo < 0.5 * end_wheel
    # Frames and covariance as documented: odom -> base, yaw variance growing, never zero.
    first, last = rig.odometry[0], rig.odometry[-1]
    assert (last.header.frame_id, last.child_frame_id) == (rig.odom_frame, rig.base_frame)
    assert 0.0 < first.pose.covariance[35] < last.pose.covariance[35]
    assert last.twist.twist.linear.x == pytest.approx(1.3, abs=0.2)
    # TF (when tf2_msgs is installed) and the debug image follow the odometry.
    if rig.node.tf_message is not None:
        rig.spin_until(lambda: len(rig.transforms) == len(drive), "every transform")
        assert ma.stamp_ns(rig.transforms[-1].header) == frame_stamps[-1]
        assert rig.transforms[-1].header.frame_id == rig.odom_frame
        assert rig.transforms[-1].transform.translation.x == last.pose.pose.position.x
    rig.spin_until(lambda: bool(rig.debug_images), "a debug image")
    assert rig.debug_images[-1].encoding == "mono8"
    # Diagnostics: frames processed, few wheel-only frames, nothing rejected.
    values = rig.diagnostics_after(frame_stamps[-1] - 10**9)
    assert int(values["frames"]) >= len(drive) - 12  # sent before the last second's frames
    assert float(values["fallback_fraction"]) < 0.1
    assert values["rejected_total"] == "0" and values["level"] == "0"
    assert float(values["frame_time_ms_mean"]) > 0.0


# ----------------------------------------------------------------------------- bad input


def _bad_inputs(rig: Rig, item: StreamMessage, frame: int) -> list[StreamMessage]:
    """What to publish instead of ``item`` (a message of frame ``frame``)."""
    msg = item.msg
    if item.topic == rig.topics.wheel_odom and frame == 5:
        nan = _reserialized(msg)
        nan.pose.pose.position.x = math.nan
        zero = _reserialized(msg)
        zero.pose.pose.orientation.w = 0.0
        zero.pose.pose.orientation.x = zero.pose.pose.orientation.y = 0.0
        zero.pose.pose.orientation.z = 0.0
        return [replace_msg(item, nan), replace_msg(item, zero), item]
    if item.topic == rig.topics.left_image and frame == 7:
        bad = _reserialized(msg)
        bad.encoding = "yuv9"
        return [replace_msg(item, bad)]
    if item.topic == rig.topics.left_image and frame == 9:
        small = ma.fill_image(Image, np.zeros((60, 80), np.uint8), stamp_ns=item.stamp_ns,
                              frame_id=msg.header.frame_id)
        return [replace_msg(item, small)]
    if item.topic == rig.topics.right_info and frame == 12:
        uncalibrated = _reserialized(msg)
        uncalibrated.k = [0.0] * 9
        return [replace_msg(item, uncalibrated)]
    return [item]


def replace_msg(item: StreamMessage, msg: Any) -> StreamMessage:
    return StreamMessage(item.topic, item.type_name, item.stamp_ns, msg)


def test_bad_inputs_are_rejected_counted_and_survived(rig_factory) -> None:
    rig = rig_factory(diagnostics_period=0.5)
    drive = _straight_drive(3.0)
    messages = _messages(rig, drive)
    stale: dict[str, StreamMessage] = {}
    for item in messages:
        frame = int(round((item.stamp_ns - DEFAULT_START_NS) / 1e8))
        if frame == 3:
            stale.setdefault(item.topic, item)
        rig.feed(_bad_inputs(rig, item, frame))
        if item.topic == rig.topics.right_image and frame == 11:
            # Time going backwards: an old wheel sample and an old left image.
            rig.feed([stale[rig.topics.wheel_odom], stale[rig.topics.left_image]],
                     wait_each_frame=False)
    # Every frame has an output, the two with bad images from the wheels alone.
    assert len(rig.odometry) == len(drive)
    _, x, y, yaw = _planar(rig.odometry[-1])
    assert x == pytest.approx(drive.truth[-1, 0], abs=0.15) and abs(y) < 0.15
    values = rig.diagnostics_after(DEFAULT_START_NS + int(drive.stamps_ns[-1]) - 5 * 10**8)
    rejected = {k[len("rejected."):]: int(v) for k, v in values.items()
                if k.startswith("rejected.")}
    assert rejected == {
        "odom: Odometry.pose.pose.position: contains NaN or inf": 1,
        "odom: Odometry.pose.pose.orientation: zero quaternion": 1,
        "left_image: Image.encoding: unsupported": 1,
        "left_image: Image: size": 1,
        "left_image: Image.header.stamp: time went backwards": 1,
        "wheel_time_backwards": 1,
        "right_info: CameraInfo.k: all zero": 1,
    }, rejected
    assert values["rejected_total"] == "7"
    assert values["fallback.bad_image"] == "2"
    assert values["calibrated"] == "true"  # the uncalibrated info did not replace a good one
    # Vision resumes after each bad frame: wheel-only frames are the first, the two bad
    # ones and the two after them (tracking restarts), and one more if the first pair beat
    # its camera info.
    assert int(values["vision_frames"]) >= int(values["frames"]) - 6


# ----------------------------------------------------------------------------- services


def test_reset_and_pause_services(rig_factory) -> None:
    rig = rig_factory()
    drive = _straight_drive(2.0)
    messages = _messages(rig, drive)

    def frames(lo: int, hi: int) -> list[StreamMessage]:
        return [m for m in messages
                if lo <= round((m.stamp_ns - DEFAULT_START_NS) / 1e8) < hi]

    rig.feed(frames(0, 10))
    assert _planar(rig.odometry[-1])[1] == pytest.approx(9 * 0.13, abs=0.05)
    answer = rig.call(Trigger, "reset", Trigger.Request())
    assert answer.success
    count = len(rig.odometry)
    rig.feed(frames(0, 5))  # a replay from the start is accepted after a reset
    after = [_planar(m) for m in rig.odometry[count:]]
    assert len(after) == 5 and after[0][1:] == (0.0, 0.0, 0.0)
    assert after[-1][1] == pytest.approx(4 * 0.13, abs=0.03)
    assert rig.call(SetBool, "pause", SetBool.Request(data=True)).message == "paused"
    count = len(rig.odometry)
    rig.feed(frames(5, 10), wait_each_frame=False)
    rig.spin_until(lambda: rig.node.frontend.stats.dropped_paused == 5, "paused frames")
    assert len(rig.odometry) == count
    assert rig.call(SetBool, "pause", SetBool.Request(data=False)).message == "resumed"
    rig.feed(frames(10, 12))
    # odom stays continuous over the pause: the wheels' motion in it is added.
    assert _planar(rig.odometry[-1])[1] == pytest.approx(11 * 0.13, abs=0.05)


# ----------------------------------------------------------------------------- starvation


def test_starvation_warning_names_the_starving_topic(rig_factory) -> None:
    rig = rig_factory(starvation_timeout=1.0)
    drive = _straight_drive(2.5)
    without_right = [m for m in _messages(rig, drive) if m.topic != rig.topics.right_image]
    rig.feed(without_right, wait_each_frame=False)
    values = rig.diagnostics_after(DEFAULT_START_NS + 2 * 10**9)
    assert values["level"] == "1"  # WARN
    assert f"no {rig.ns}/right/image_rect for" in values["message"]
    assert re.search(r"while \S+/left/image_rect arrives at \d+ Hz", values["message"])
    assert rig.odometry == []  # never a pose without a frame


# ----------------------------------------------------------------------------- replay


def _replay(context: Context, messages: list[StreamMessage], topics: Topics,
            **params: Any) -> list[tuple[str, Any]]:
    """Construct the node, set its sink and call its on_* methods in stamp order, as a bag
    replay tool does (no executor, no DDS traffic needed)."""
    tag = uuid.uuid4().hex[:8]
    node = HybridVoNode(f"replay_{tag}", namespace=f"/replay_{tag}", context=context,
                        parameter_overrides=[Parameter(k, value=v) for k, v in
                                             {"camera_pitch": PITCH, **params}.items()])
    got: list[tuple[str, Any]] = []
    node.sink = lambda topic, msg: got.append((topic, msg))
    handlers = {topics.left_image: node.on_left_image, topics.right_image: node.on_right_image,
                topics.left_info: node.on_left_info, topics.right_info: node.on_right_info,
                topics.wheel_odom: node.on_wheel_odom}
    try:
        for item in messages:
            if item.topic in handlers:
                handlers[item.topic](item.msg)
    finally:
        node.destroy_node()
    return got


def _odometry_rows(got: list[tuple[str, Any]]) -> list[tuple[int, float, float, float]]:
    return [_planar(msg) for topic, msg in got if topic.endswith("/odometry/hybrid")]


def test_replay_through_on_methods_and_sink_is_deterministic_for_bag_messages(context) -> None:
    drive = _straight_drive(1.5)
    topics = Topics()
    rclpy_messages = list(drive_messages(drive, topics=topics))
    bag_messages = [replace_msg(m, to_rosbags(m.msg)) for m in rclpy_messages
                    if m.topic in {topics.left_image, topics.right_image, topics.left_info,
                                   topics.right_info, topics.wheel_odom}]
    first = _replay(context, bag_messages, topics)
    second = _replay(context, bag_messages, topics)
    live = _replay(context, rclpy_messages, topics)
    rows = _odometry_rows(first)
    assert len(rows) == len(drive)
    assert [r[0] for r in rows] == [int(s) + DEFAULT_START_NS for s in drive.stamps_ns]
    assert rows == _odometry_rows(second) == _odometry_rows(live)  # bit for bit
    assert rows[-1][1] == pytest.approx(drive.truth[-1, 0], abs=0.05)
    diag_stamps = [ma.stamp_ns(msg.header) for topic, msg in first if topic == "/diagnostics"]
    assert diag_stamps[0] == DEFAULT_START_NS and len(diag_stamps) == 2  # 0 s and 1 s
    assert {topic for topic, _ in first} >= {"/diagnostics", next(
        t for t, _ in first if t.endswith("/odometry/hybrid"))}


def test_missing_tf2_msgs_is_reported_not_fatal(context, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)  # import fails as if not installed
    drive = _straight_drive(1.2)
    topics = Topics()
    got = _replay(context, list(drive_messages(drive, topics=topics)), topics, publish_tf=True)
    assert len(_odometry_rows(got)) == len(drive)
    assert not any(topic == "/tf" for topic, _ in got)
    status = [msg for topic, msg in got if topic == "/diagnostics"][-1].status[0]
    values = _diag_values(status)
    assert int(values["tf_skipped"]) >= 10
    assert "tf2_msgs not installed" in status.message


def _compressed(item: StreamMessage) -> StreamMessage:
    pixels = ma.image_to_numpy(item.msg)
    msg = CompressedImage()
    msg.header = item.msg.header
    msg.format = "mono8; png compressed mono8"
    msg.data = cv2.imencode(".png", pixels)[1].tobytes()
    return StreamMessage(item.topic + "/compressed", "sensor_msgs/msg/CompressedImage",
                         item.stamp_ns, msg)


def test_compressed_images(context) -> None:
    drive = _straight_drive(1.0)
    topics = Topics()
    messages = [_compressed(m) if m.type_name.endswith("/Image") else m
                for m in drive_messages(drive, topics=topics)]
    compressed_topics = Topics(left_image=topics.left_image + "/compressed",
                               right_image=topics.right_image + "/compressed")
    got = _replay(context, messages, compressed_topics, use_compressed=True)
    rows = _odometry_rows(got)
    assert len(rows) == len(drive)
    assert rows[-1][1] == pytest.approx(drive.truth[-1, 0], abs=0.05)
    values = _diag_values([m for t, m in got if t == "/diagnostics"][-1].status[0])
    assert values["fallback.first_frame"] == "1" and "fallback.no_calibration" not in values


# ----------------------------------------------------------------------------- parameters


def test_config_yaml_lists_every_parameter_and_starts_the_node(context) -> None:
    loaded = parameter_dict_from_yaml_file(str(REPO / "config" / "hybrid_vo.yaml"))
    specs = param_specs(VoNodeConfig)
    assert set(loaded) == {spec.name for spec in specs}
    node = HybridVoNode(f"yaml_{uuid.uuid4().hex[:8]}", context=context,
                        parameter_overrides=[Parameter.from_parameter_msg(p)
                                             for p in loaded.values()])
    try:
        for spec in specs:  # the YAML repeats the defaults
            assert node.get_parameter(spec.name).value == spec.ros_default, spec.name
        assert node.config == VoNodeConfig()
        descriptor = node.describe_parameter("odometer.num_patches")
        assert descriptor.description and descriptor.integer_range[0].to_value == 64
        assert node.describe_parameter("camera_pitch").floating_point_range[0].to_value == 1.5
        assert node.input_topics["odom"] == "/odom"
        assert node.input_topics["left_image"] == Topics().left_image  # the simulator's names
        assert node.output_topics["odometry"] == "/odometry/hybrid"
    finally:
        node.destroy_node()


def test_bad_parameters_fail_at_start_up(context, capsys) -> None:
    def start(**params: Any) -> None:
        HybridVoNode(f"bad_{uuid.uuid4().hex[:8]}", context=context,
                     parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])

    with pytest.raises(InvalidParameterValueException):
        start(camera_pitch=2.0)  # outside the declared range
    with pytest.raises(ConfigError, match="odd integer"):
        start(**{"odometer.patch_width_px": 12})
    assert main(["hybrid_vo_node", "--ros-args", "-p", "odometer.patch_width_px:=12"]) == 1
    assert "patch_width_px must be an odd integer" in capsys.readouterr().err
