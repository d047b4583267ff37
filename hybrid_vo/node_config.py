"""The configuration tree of ``hybrid_vo_node``: every parameter it declares, one frozen
snapshot (no rclpy here: the tree is read and documented without ROS).

The node's own settings (frames, outputs, diagnostics) sit at the root; the stereo
synchronizer's (:class:`hybrid_vo.sync.SyncConfig`) and the front end's
(:class:`hybrid_vo.frontend.FrontendConfig`) keep their names, the odometer's are
``odometer.*``. Each field's ``metadata`` holds its description and range
(:mod:`ros_node_base.params`); ``config/hybrid_vo.yaml`` and the table in ``doc/nodes.md``
are written from this tree. Every parameter is read at start-up only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from h2o_slam.core.parameters import parameter
from hybrid_vo.frontend import FrontendConfig
from hybrid_vo.sync import SyncConfig


@dataclass(frozen=True)
class VoNodeConfig:
    """Every parameter of ``hybrid_vo_node`` (module docstring)."""

    odom_frame: str = parameter(
        "odom", "Frame of the published pose (REP-105 odom; continuous, never jumps except on "
        "reset).")
    base_frame: str = parameter(
        "base_link", "Frame whose pose is published (child_frame_id of odometry/hybrid and of the "
        "TF).")
    publish_tf: bool = parameter(
        True, "Publish odom_frame -> base_frame on /tf. Needs tf2_msgs; without it the node "
        "warns once and counts the skipped transforms in /diagnostics (tf_skipped).")
    use_compressed: bool = parameter(
        False, "Subscribe to sensor_msgs/CompressedImage (JPEG or PNG) on "
        "<image topic>/compressed instead of sensor_msgs/Image.")
    publish_debug_image: bool = parameter(
        False, "Publish ~/debug_image: the horizon band (mono8) with the sampling region and "
        "the sampled patches.")
    debug_image_scale: int = parameter(4, "Enlargement of the debug image.", bounds=(1, 16))
    diagnostics_period: float = parameter(
        1.0, "Seconds of message time between /diagnostics reports; when no input arrives, "
        "a report saying so is sent on the node clock with the same period.", bounds=(0.1, 60.0))
    starvation_timeout: float = parameter(
        2.0, "Seconds of silence on an input, while others still arrive, before a warning "
        "that names it (measured in message time).", bounds=(0.1, 60.0))
    sync: SyncConfig = field(default_factory=SyncConfig, metadata={"flat": True})
    frontend: FrontendConfig = field(default_factory=FrontendConfig, metadata={"flat": True})
