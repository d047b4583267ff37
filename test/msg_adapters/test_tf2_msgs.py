"""tf2_msgs, built into the venv by tools/build_tf2_msgs.sh, is a real ROS 2 message type.

tf2_msgs is not on PyPI; `make venv` generates and compiles it from tools/tf2_msgs. These tests
fail (never skip) when that build is missing or broken: the nodes publish TF with it.
"""

from __future__ import annotations

import json
import time
import uuid
from pathlib import Path

import pytest
import rclpy
import tf2_msgs.msg
from geometry_msgs.msg import TransformStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from tf2_msgs.msg import TFMessage

REPO = Path(__file__).resolve().parents[2]
TIMEOUT_S = 10.0


def _transform(parent: str, child: str, k: int) -> TransformStamped:
    t = TransformStamped()
    t.header.stamp.sec = 100 + k
    t.header.stamp.nanosec = 500 + k
    t.header.frame_id = parent
    t.child_frame_id = child
    t.transform.translation.x = 1.0 + k
    t.transform.translation.y = -2.5
    t.transform.translation.z = 0.25
    t.transform.rotation.z = 0.6
    t.transform.rotation.w = 0.8
    return t


def _tf_message() -> TFMessage:
    return TFMessage(transforms=[_transform("map", "odom", 0), _transform("odom", "base_link", 1)])


def test_type_support_loads() -> None:
    TFMessage.__class__.__import_type_support__()
    assert TFMessage.__class__._TYPE_SUPPORT is not None, "tf2_msgs C type support did not load"
    assert TFMessage.get_fields_and_field_types() == {
        "transforms": "sequence<geometry_msgs/TransformStamped>"
    }


def test_wire_format_matches_ros2_jazzy_tf2_msgs() -> None:
    """The CDR bytes and the type hash are those of the real tf2_msgs/msg/TFMessage."""
    raw = serialize_message(_tf_message())
    store = get_typestore(Stores.ROS2_JAZZY)
    decoded = store.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage")
    assert [(t.header.frame_id, t.child_frame_id) for t in decoded.transforms] == [
        ("map", "odom"),
        ("odom", "base_link"),
    ]
    assert decoded.transforms[1].header.stamp.nanosec == 501
    assert decoded.transforms[1].transform.translation.x == 2.0
    # Both directions (the bytes themselves may differ in CDR alignment padding).
    assert deserialize_message(raw, TFMessage) == _tf_message()
    rosbags_raw = store.serialize_cdr(decoded, "tf2_msgs/msg/TFMessage").tobytes()
    assert deserialize_message(rosbags_raw, TFMessage) == _tf_message()

    venv_share = Path(tf2_msgs.msg.__file__).resolve().parents[5] / "share"
    description = json.loads((venv_share / "tf2_msgs/msg/TFMessage.json").read_text())
    ours = {h["type_name"]: h["hash_string"] for h in description["type_hashes"]}
    assert ours["tf2_msgs/msg/TFMessage"] == store.hash_rihs01("tf2_msgs/msg/TFMessage")


@pytest.fixture
def loopback_dds(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fast DDS on loopback only, as `make test` sets it, also when pytest runs alone."""
    profile = str(REPO / "config" / "fastdds_localhost.xml")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    for var in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        monkeypatch.setenv(var, profile)
    for var in ("ROS_LOCALHOST_ONLY", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS"):
        monkeypatch.delenv(var, raising=False)


@pytest.mark.usefixtures("loopback_dds")
def test_publish_and_receive_in_process() -> None:
    topic = f"/test_tf2_msgs_{uuid.uuid4().hex[:12]}/tf"
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node(f"test_tf2_msgs_{uuid.uuid4().hex[:8]}", context=context)
        received: list[TFMessage] = []
        node.create_subscription(TFMessage, topic, received.append, 10)
        publisher = node.create_publisher(TFMessage, topic, 10)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            sent = _tf_message()
            deadline = time.monotonic() + TIMEOUT_S
            while not received and time.monotonic() < deadline:
                publisher.publish(sent)
                executor.spin_once(timeout_sec=0.1)
            assert received, f"no TFMessage received on {topic} within {TIMEOUT_S} s"
            assert received[0] == sent
            types = dict(node.get_topic_names_and_types())
            assert types[topic] == ["tf2_msgs/msg/TFMessage"]
        finally:
            executor.shutdown()
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
