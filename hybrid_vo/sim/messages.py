"""A simulated drive (:mod:`hybrid_vo.sim.world`) as the ROS messages a robot would record.

One stream, in stamp order, of what the nodes subscribe to (stereo images and camera
info, wheel odometry, NavSatFix, loop closures in the package's convention) plus the
ground truth, each as a :class:`StreamMessage` with its topic and type name. Tests publish
it through real publishers; ``h2o-demo`` writes it into a bag. Message layouts stay in
``msg_adapters``: this module only chooses values and calls its ``fill_*`` functions,
on message classes the caller gives (rclpy's by default, imported lazily so the core
stays free of ROS at import time).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

import msg_adapters as ma
from hybrid_vo.sim.world import STATUS_NO_FIX, Drive, wrap_angle

#: Stamp of the first frame: a plausible epoch time, since 0 means "unset" to many tools.
DEFAULT_START_NS = 1_700_000_000 * 1_000_000_000

#: Wheel odometry's reported 1σ per axis (x m, y m, yaw rad), as a driver would state it.
WHEEL_SIGMAS = (0.02, 0.02, 0.01)

TYPE_NAMES = {
    "image": "sensor_msgs/msg/Image",
    "camera_info": "sensor_msgs/msg/CameraInfo",
    "odometry": "nav_msgs/msg/Odometry",
    "navsat": "sensor_msgs/msg/NavSatFix",
}


@dataclass(frozen=True)
class Topics:
    """Topic names of a simulated recording (the nodes' default input names)."""

    left_image: str = "/left/image_rect"
    right_image: str = "/right/image_rect"
    left_info: str = "/left/camera_info"
    right_info: str = "/right/camera_info"
    wheel_odom: str = "/wheel/odom"
    gps: str = "/gps/fix"
    loop_closure: str = "/loop_closure"
    ground_truth: str = "/ground_truth/odom"


@dataclass(frozen=True)
class StreamMessage:
    """One recorded message: where it goes, its ROS type name, its stamp, the message."""

    topic: str
    type_name: str
    stamp_ns: int
    msg: Any


def rclpy_message_types() -> dict[str, Any]:
    """The rclpy message classes :func:`drive_messages` fills, by kind."""
    types = {}
    for kind, name in TYPE_NAMES.items():
        package, _, cls = name.split("/")
        types[kind] = getattr(importlib.import_module(f"{package}.msg"), cls)
    return types


def wheel_track(drive: Drive, rate_hz: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Stamps ``(M,)`` (ns, from 0) and cumulative wheel poses ``(M, 3)`` at ``rate_hz``.

    Between frames the pose moves linearly in ``x, y`` and unwrapped yaw, which is what a
    faster wheel encoder would report to within its own noise.
    """
    poses = drive.wheel_poses()
    if rate_hz is None:
        return drive.stamps_ns.copy(), poses
    if rate_hz <= 0:
        raise ValueError(f"wheel rate_hz must be > 0, got {rate_hz!r}")
    stamps = drive.stamps_ns.astype(float)
    step_ns = 1e9 / rate_hz
    out_stamps = np.arange(0.0, stamps[-1] + 0.5, step_ns)
    yaw = np.unwrap(poses[:, 2])
    track = np.stack([np.interp(out_stamps, stamps, poses[:, 0]),
                      np.interp(out_stamps, stamps, poses[:, 1]),
                      wrap_angle(np.interp(out_stamps, stamps, yaw))], axis=-1)
    return out_stamps.astype(np.int64), track


def _planar_odometry(cls: Any, stamp: int, frame: str, child: str, pose: np.ndarray,
                     sigmas: tuple[float, float, float], speed: float, rate: float) -> Any:
    cov = ma.planar_covariance(*sigmas)
    sample = ma.planar_odometry_sample(stamp, frame, child, float(pose[0]), float(pose[1]),
                                       float(pose[2]), cov, v_x_mps=speed,
                                       yaw_rate_radps=rate)
    return ma.fill_odometry(cls, sample)


def _rates(stamps_ns: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dt = np.diff(stamps_ns.astype(float)) * 1e-9
    speed = np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1])) / np.maximum(dt, 1e-9)
    rate = wrap_angle(np.diff(poses[:, 2])) / np.maximum(dt, 1e-9)
    return np.concatenate([[0.0], speed]), np.concatenate([[0.0], rate])


def camera_models(drive: Drive, stamp_ns: int) -> tuple[ma.CameraModel, ma.CameraModel]:
    """Left and right rectified camera models of the drive's stereo camera."""
    info = drive.camera_info
    K = info.intrinsics.matrix()
    left_P = np.hstack([K, np.zeros((3, 1))])
    size = (info.intrinsics.width_px, info.intrinsics.height_px)

    def model(frame: str, P: np.ndarray) -> ma.CameraModel:
        return ma.CameraModel(stamp_ns, frame, size[0], size[1], K, np.zeros(5), np.eye(3),
                              P, "plumb_bob")

    return (model(info.frame_id, left_P),
            model(info.frame_id.replace("left", "right"), info.projection_right()))


def drive_messages(
    drive: Drive,
    *,
    topics: Topics | None = None,
    types: Mapping[str, Any] | None = None,
    start_ns: int = DEFAULT_START_NS,
    wheel_rate_hz: float | None = None,
    frames: tuple[str, str, str] = ("odom", "base_link", "gps"),
    with_images: bool = True,
) -> Iterator[StreamMessage]:
    """Every message of ``drive`` in stamp order (see the module docstring).

    Args:
        topics: topic names (defaults: :class:`Topics`).
        types: message classes by kind (``image``, ``camera_info``, ``odometry``,
            ``navsat``); rclpy's when omitted.
        start_ns: stamp of frame 0.
        wheel_rate_hz: wheel odometry rate; the camera's frame rate when ``None``.
        frames: ``(odom_frame, base_frame, gps_frame)`` written into headers.
        with_images: leave out images and camera info (a drive for the back end only).

    Within one stamp the order is wheel odometry, camera info, images, GPS, loop
    closures, ground truth: what a node needs to use a message has arrived before it.
    """
    topics = topics or Topics()
    types = dict(types) if types is not None else rclpy_message_types()
    items = list(_wheel_messages(drive, topics, types, start_ns, wheel_rate_hz, frames))
    if with_images:
        items += _camera_messages(drive, topics, types, start_ns)
    items += _gps_messages(drive, topics, types, start_ns, frames[2])
    items += _loop_messages(drive, topics, types, start_ns)
    items += _truth_messages(drive, topics, types, start_ns, frames[1])
    order = {name: i for i, name in enumerate(
        ("wheel", "info", "image", "gps", "loop", "truth"))}
    items.sort(key=lambda item: (item[0].stamp_ns, order[item[1]], item[2]))
    for message, _, _ in items:
        if callable(message.msg):  # images are rendered only when reached
            message = StreamMessage(message.topic, message.type_name, message.stamp_ns,
                                    message.msg())
        yield message


_Item = tuple[StreamMessage, str, int]


def _wheel_messages(drive: Drive, topics: Topics, types: Mapping[str, Any], start_ns: int,
                    rate_hz: float | None, frames: tuple[str, str, str]) -> Iterator[_Item]:
    stamps, poses = wheel_track(drive, rate_hz)
    speed, rate = _rates(stamps, poses)
    for i, (stamp, pose) in enumerate(zip(stamps, poses, strict=True)):
        ns = int(stamp) + start_ns
        msg = _planar_odometry(types["odometry"], ns, frames[0], frames[1], pose,
                               WHEEL_SIGMAS, float(speed[i]), float(rate[i]))
        yield StreamMessage(topics.wheel_odom, TYPE_NAMES["odometry"], ns, msg), "wheel", 0


def _camera_messages(drive: Drive, topics: Topics, types: Mapping[str, Any],
                     start_ns: int) -> Iterator[_Item]:
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def render(index: int, side: int) -> Any:
        def make() -> Any:
            if index not in cache:
                cache.clear()
                frame = drive.frame(index)
                cache[index] = (frame.left, frame.right)
            frame_id = drive.camera_info.frame_id
            if side:
                frame_id = frame_id.replace("left", "right")
            return ma.fill_image(types["image"], cache[index][side],
                                 stamp_ns=int(drive.stamps_ns[index]) + start_ns,
                                 frame_id=frame_id)
        return make

    image = TYPE_NAMES["image"]
    info = TYPE_NAMES["camera_info"]
    for index, stamp in enumerate(drive.stamps_ns):
        ns = int(stamp) + start_ns
        left, right = camera_models(drive, ns)
        yield StreamMessage(topics.left_info, info, ns,
                            ma.fill_camera_info(types["camera_info"], left)), "info", 0
        yield StreamMessage(topics.right_info, info, ns,
                            ma.fill_camera_info(types["camera_info"], right)), "info", 1
        yield StreamMessage(topics.left_image, image, ns, render(index, 0)), "image", 0
        yield StreamMessage(topics.right_image, image, ns, render(index, 1)), "image", 1


def _gps_messages(drive: Drive, topics: Topics, types: Mapping[str, Any], start_ns: int,
                  frame_id: str) -> Iterator[_Item]:
    for fix in drive.gps:
        ns = fix.stamp_ns + start_ns
        msg = ma.fill_navsat_fix(
            types["navsat"], stamp_ns=ns, frame_id=frame_id, lat_deg=fix.latitude_deg,
            lon_deg=fix.longitude_deg, alt_m=fix.altitude_m,
            covariance_enu=np.reshape(fix.covariance_enu, (3, 3)), status=fix.status,
            covariance_type=2 if fix.status != STATUS_NO_FIX else 0)
        yield StreamMessage(topics.gps, TYPE_NAMES["navsat"], ns, msg), "gps", 0


def _loop_messages(drive: Drive, topics: Topics, types: Mapping[str, Any],
                   start_ns: int) -> Iterator[_Item]:
    for closure in drive.loop_closures:
        dx, dy, dyaw = closure.delta
        cov3 = np.reshape(closure.covariance, (3, 3))
        cov = ma.planar_covariance(*np.sqrt(np.diag(cov3)), unobserved_variance=1e-4)
        found_ns = closure.to_stamp_ns + start_ns
        loop = ma.make_loop_closure(
            ma.StampRef(closure.from_stamp_ns + start_ns), ma.StampRef(found_ns),
            _yaw_matrix(dyaw), (dx, dy, 0.0), cov, found_ns)
        msg = ma.fill_loop_closure(types["odometry"], loop)
        yield StreamMessage(topics.loop_closure, TYPE_NAMES["odometry"], found_ns, msg), \
            "loop", 0


def _truth_messages(drive: Drive, topics: Topics, types: Mapping[str, Any], start_ns: int,
                    base_frame: str) -> Iterator[_Item]:
    speed, rate = _rates(drive.stamps_ns, drive.truth)
    for i, (stamp, pose) in enumerate(zip(drive.stamps_ns, drive.truth, strict=True)):
        ns = int(stamp) + start_ns
        msg = _planar_odometry(types["odometry"], ns, "map", base_frame, pose,
                               (0.0, 0.0, 0.0), float(speed[i]), float(rate[i]))
        yield StreamMessage(topics.ground_truth, TYPE_NAMES["odometry"], ns, msg), "truth", 0


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
