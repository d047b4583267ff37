"""Which topic of a recording feeds which input of the nodes: roles and topic maps.

A topic map is role → topic: the defaults (:data:`DEFAULT_TOPICS`), then a YAML file
(``config/replay_topics.yaml``), then ``ROLE=TOPIC`` options.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import yaml

from h2o_slam.io.bags import ReplayError

#: The nodes' inputs a recording's topics are mapped to (plus ground truth, for scoring).
ROLES = (
    "left_image",
    "right_image",
    "left_info",
    "right_info",
    "wheel_odom",
    "gps",
    "loop_closure",
    "ground_truth",
)

#: Roles a replay cannot run without, unless the caller says otherwise.
REQUIRED_ROLES = ("left_image", "right_image", "left_info", "right_info", "wheel_odom")

_IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_ODOMETRY = ("nav_msgs/msg/Odometry",)

#: Message types each role accepts (ROS 1 names are normalized by rosbags to this form).
ROLE_TYPES: dict[str, tuple[str, ...]] = {
    "left_image": _IMAGE_TYPES,
    "right_image": _IMAGE_TYPES,
    "left_info": ("sensor_msgs/msg/CameraInfo",),
    "right_info": ("sensor_msgs/msg/CameraInfo",),
    "wheel_odom": _ODOMETRY,
    "gps": ("sensor_msgs/msg/NavSatFix",),
    "loop_closure": _ODOMETRY,
    "ground_truth": _ODOMETRY,
}

#: Default topic of each role: the names :class:`hybrid_vo.sim.messages.Topics` uses.
DEFAULT_TOPICS: dict[str, str] = {
    "left_image": "/left/image_rect",
    "right_image": "/right/image_rect",
    "left_info": "/left/camera_info",
    "right_info": "/right/camera_info",
    "wheel_odom": "/wheel/odom",
    "gps": "/gps/fix",
    "loop_closure": "/loop_closure",
    "ground_truth": "/ground_truth/odom",
}

TopicMap = dict[str, str | None]


def topic_map(
    yaml_path: str | os.PathLike[str] | None = None, overrides: Iterable[str] = ()
) -> TopicMap:
    """Role → topic: the defaults, then a YAML file, then ``ROLE=TOPIC`` options.

    Args:
        yaml_path: a file with a ``topics:`` mapping (see ``config/replay_topics.yaml``).
        overrides: ``ROLE=TOPIC`` strings, e.g. from repeated ``--topic`` options; an empty
            topic (``gps=``) turns the role off.

    Raises:
        ReplayError: unreadable YAML, an unknown role, or a topic that is not a string.
    """
    topics: TopicMap = dict(DEFAULT_TOPICS)
    if yaml_path is not None:
        topics.update(load_topic_map(yaml_path))
    for option in overrides:
        role, sep, topic = option.partition("=")
        if not sep:
            raise ReplayError("--topic", f"expected ROLE=TOPIC, got {option!r}")
        topics[_checked_role(role.strip(), "--topic")] = topic.strip() or None
    return topics


def load_topic_map(path: str | os.PathLike[str]) -> TopicMap:
    """The roles a YAML file maps: ``{"topics": {role: topic or null}}``.

    Raises:
        ReplayError: unreadable file or YAML, an unknown role, a topic not a string.
    """
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        reason = str(exc).replace("\n", " ")
        raise ReplayError(path, f"cannot read topic map: {reason}") from None
    if not isinstance(data, dict) or not isinstance(data.get("topics"), dict):
        raise ReplayError(path, "a topic map needs a 'topics:' mapping of role to topic")
    out: TopicMap = {}
    for role, topic in data["topics"].items():
        if topic is not None and not isinstance(topic, str):
            raise ReplayError(path, f"topic of {role!r} must be a string or null")
        out[_checked_role(str(role), path)] = topic or None
    return out


def _checked_role(role: str, where: str | os.PathLike[str]) -> str:
    if role not in ROLES:
        raise ReplayError(where, f"unknown role {role!r}; roles are {', '.join(ROLES)}")
    return role
