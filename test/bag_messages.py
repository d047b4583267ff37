"""Messages as a bag gives them back: the rclpy message and its rosbags twin (the same CDR
bytes decoded by rosbags' Jazzy type store), for tests that check both sources."""

from __future__ import annotations

from typing import Any

import numpy as np
from rclpy.serialization import serialize_message
from rosbags.typesys import Stores, get_typestore

from h2o_slam.core.geometry import so3_exp

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
SOURCES = ["rclpy", "rosbags"]


def to_rosbags(msg: Any) -> Any:
    """The rclpy message as rosbags reads it from a bag: CDR bytes from rclpy, decoded by
    rosbags' Jazzy typestore."""
    module = type(msg).__module__.split(".")  # e.g. nav_msgs.msg._odometry
    msgtype = f"{module[0]}/msg/{type(msg).__name__}"
    return TYPESTORE.deserialize_cdr(serialize_message(msg), msgtype)


def as_source(msg: Any, source: str) -> Any:
    """``msg`` itself (rclpy) or its rosbags twin."""
    return msg if source == "rclpy" else to_rosbags(msg)


def random_rotation(seed: int) -> np.ndarray:
    """A rotation matrix drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    return so3_exp(rng.normal(size=3))
