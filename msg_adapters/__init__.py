"""Pure functions between ROS 2 messages and the cores' types, with validation.

The only code that knows message layouts (doc/design.md, Layering). Every function works on rclpy
message objects and on messages deserialized from bags by ``rosbags`` (it reads fields by
name), and nothing here imports rclpy or a message package at import time: outputs are
written into a message instance, or a new instance of a class, passed in by the caller.
Bad input raises :class:`AdapterError` naming the field and the problem (doc/nodes.md, bad input).

Modules: :mod:`~msg_adapters.stamps` (time stamps), :mod:`~msg_adapters.rotations`
(quaternions), :mod:`~msg_adapters.odometry`, :mod:`~msg_adapters.images`,
:mod:`~msg_adapters.camera_info`, :mod:`~msg_adapters.gps` (NavSatFix → ENU),
:mod:`~msg_adapters.loop_closure` (the loop-closure convention) and
:mod:`~msg_adapters.outputs` (PoseArray, Path, MarkerArray, TF, diagnostics).
"""

from msg_adapters.camera_info import (
    CameraModel,
    camera_info_from_msg,
    check_stereo_pair,
    fill_camera_info,
    stereo_baseline_m,
)
from msg_adapters.errors import AdapterError
from msg_adapters.gps import (
    Datum,
    GpsFix,
    datum_from_fix,
    ecef_to_geodetic,
    fill_navsat_fix,
    geodetic_to_ecef,
    gps_fix_from_msg,
)
from msg_adapters.images import (
    compressed_image_to_numpy,
    fill_image,
    image_msg_to_gray8,
    image_to_numpy,
)
from msg_adapters.loop_closure import (
    LoopClosure,
    NodeRef,
    PoseRef,
    StampRef,
    fill_loop_closure,
    format_pose_ref,
    loop_closure_from_msg,
    make_loop_closure,
    parse_pose_ref,
)
from msg_adapters.odometry import (
    OdometrySample,
    fill_odometry,
    odometry_from_msg,
    planar_covariance,
    planar_odometry_sample,
)
from msg_adapters.outputs import (
    DiagnosticReport,
    GraphMarkers,
    fill_diagnostic_array,
    fill_graph_markers,
    fill_path,
    fill_pose_array,
    fill_tf_message,
    fill_transform,
    map_to_odom,
)
from msg_adapters.rotations import (
    fill_pose,
    fill_quaternion,
    matrix_to_quaternion,
    pose_to_matrix,
    quaternion_to_matrix,
)
from msg_adapters.stamps import check_stamp_order, fill_header, fill_stamp, stamp_ns, to_stamp

__all__ = [
    "AdapterError",
    "CameraModel",
    "Datum",
    "DiagnosticReport",
    "GpsFix",
    "GraphMarkers",
    "LoopClosure",
    "NodeRef",
    "OdometrySample",
    "PoseRef",
    "StampRef",
    "camera_info_from_msg",
    "check_stamp_order",
    "check_stereo_pair",
    "compressed_image_to_numpy",
    "datum_from_fix",
    "ecef_to_geodetic",
    "fill_camera_info",
    "fill_diagnostic_array",
    "fill_graph_markers",
    "fill_header",
    "fill_image",
    "fill_loop_closure",
    "fill_navsat_fix",
    "fill_odometry",
    "fill_path",
    "fill_pose",
    "fill_pose_array",
    "fill_quaternion",
    "fill_stamp",
    "fill_tf_message",
    "fill_transform",
    "format_pose_ref",
    "geodetic_to_ecef",
    "gps_fix_from_msg",
    "image_msg_to_gray8",
    "image_to_numpy",
    "loop_closure_from_msg",
    "make_loop_closure",
    "map_to_odom",
    "matrix_to_quaternion",
    "odometry_from_msg",
    "parse_pose_ref",
    "planar_covariance",
    "planar_odometry_sample",
    "pose_to_matrix",
    "quaternion_to_matrix",
    "stamp_ns",
    "stereo_baseline_m",
    "to_stamp",
]
