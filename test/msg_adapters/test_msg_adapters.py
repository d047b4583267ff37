"""msg_adapters: stamps, quaternions, Odometry and loop closures, on rclpy messages and on
the same messages deserialized by rosbags (as read from a bag)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bag_messages import SOURCES, TYPESTORE, as_source, random_rotation, to_rosbags
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion
from hypothesis import given, settings
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from std_msgs.msg import Header

from h2o_slam.core.errors import InputError
from h2o_slam.core.geometry import yaw_to_matrix
from msg_adapters import (
    AdapterError,
    NodeRef,
    OdometrySample,
    StampRef,
    check_stamp_order,
    fill_loop_closure,
    fill_odometry,
    fill_stamp,
    format_pose_ref,
    loop_closure_from_msg,
    make_loop_closure,
    matrix_to_quaternion,
    odometry_from_msg,
    parse_pose_ref,
    planar_covariance,
    planar_odometry_sample,
    quaternion_to_matrix,
    stamp_ns,
    to_stamp,
)


def zero_quaternion(msg: Any) -> None:
    q = msg.pose.pose.orientation
    q.x = q.y = q.z = q.w = 0.0


def set_cov(index: Any, value: float) -> Any:
    """A mutation of ``pose.covariance[index]`` (rosbags arrays are read-only views)."""

    def mutate(msg: Any) -> None:
        cov = np.array(msg.pose.covariance)
        cov[index] = value
        msg.pose.covariance = cov

    return mutate


def spd(seed: int, n: int = 6) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(n, n))
    return a @ a.T + 0.1 * np.eye(n)


# ------------------------------------------------------------------------------ errors


def test_adapter_error_is_input_error_and_value_error() -> None:
    assert issubclass(AdapterError, InputError)
    assert issubclass(AdapterError, ValueError)


# ------------------------------------------------------------------------------ stamps


@pytest.mark.parametrize("source", SOURCES)
def test_stamp_ns_of_header_and_time(source: str) -> None:
    header = Header(stamp=Time(sec=1_700_000_000, nanosec=123_456_789), frame_id="x")
    odom = as_source(Odometry(header=header), source)
    assert stamp_ns(odom.header) == 1_700_000_000_123_456_789
    assert stamp_ns(odom.header.stamp) == 1_700_000_000_123_456_789


@given(st.integers(min_value=0, max_value=2**31 * 10**9 - 1))
def test_stamp_round_trip(ns: int) -> None:
    assert stamp_ns(Time(**to_stamp(ns))) == ns
    assert stamp_ns(fill_stamp(Time(), ns)) == ns


def test_stamp_errors() -> None:
    class Bad:
        sec = 1
        nanosec = 1_000_000_000

    with pytest.raises(AdapterError, match=r"nanosec 1000000000 outside"):
        stamp_ns(Bad())
    Bad.sec, Bad.nanosec = -1, 0
    with pytest.raises(AdapterError, match="negative time"):
        stamp_ns(Bad())
    with pytest.raises(AdapterError, match="not a time stamp"):
        stamp_ns(object())
    with pytest.raises(AdapterError, match="negative time"):
        to_stamp(-1)
    with pytest.raises(AdapterError, match="int32 sec"):
        to_stamp(2**31 * 10**9)


def test_check_stamp_order() -> None:
    check_stamp_order(None, 5)
    check_stamp_order(5, 5)
    check_stamp_order(5, 6, strict=True)
    with pytest.raises(AdapterError, match=r"/odom: time went backwards \(4 ns after 5 ns"):
        check_stamp_order(5, 4, field="/odom")
    with pytest.raises(AdapterError, match="time went backwards"):
        check_stamp_order(5, 5, strict=True)


# -------------------------------------------------------------------------- quaternions


unit_quats = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: float(np.linalg.norm(q)) > 0.1
)


@given(unit_quats)
@settings(max_examples=200)
def test_quaternion_round_trip(q: list[float]) -> None:
    qa = np.array(q) / np.linalg.norm(q)
    R = quaternion_to_matrix(Quaternion(x=qa[0], y=qa[1], z=qa[2], w=qa[3]))
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    back = np.array(matrix_to_quaternion(R))
    assert back[3] >= 0.0
    # q and -q are the same rotation.
    assert min(np.abs(back - qa).max(), np.abs(back + qa).max()) < 1e-9
    np.testing.assert_allclose(quaternion_to_matrix(back), R, atol=1e-12)


def test_quaternion_convention_is_x_y_z_w() -> None:
    s = np.sqrt(0.5)
    # 90° about z: x → y.
    R = quaternion_to_matrix((0.0, 0.0, s, s))
    np.testing.assert_allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(matrix_to_quaternion(yaw_to_matrix(np.pi / 2)), [0, 0, s, s])


def test_quaternion_errors() -> None:
    with pytest.raises(AdapterError, match="orientation: zero quaternion"):
        quaternion_to_matrix(Quaternion(x=0.0, y=0.0, z=0.0, w=0.0))
    with pytest.raises(AdapterError, match="NaN or inf"):
        quaternion_to_matrix((0.0, 0.0, float("nan"), 1.0))
    with pytest.raises(AdapterError, match=r"norm 2 is not 1"):
        quaternion_to_matrix((0.0, 0.0, 0.0, 2.0))
    np.testing.assert_allclose(quaternion_to_matrix((0, 0, 0, 2.0), norm_tol=None), np.eye(3))
    with pytest.raises(AdapterError, match=r"expected shape \(4,\)"):
        quaternion_to_matrix((0.0, 1.0))
    with pytest.raises(AdapterError, match="not a rotation matrix"):
        matrix_to_quaternion(2.0 * np.eye(3))
    with pytest.raises(AdapterError, match="not a rotation matrix"):
        matrix_to_quaternion(np.diag([1.0, 1.0, -1.0]))


# ----------------------------------------------------------------------------- odometry


def make_sample(seed: int = 1) -> OdometrySample:
    rng = np.random.default_rng(seed)
    return OdometrySample(
        stamp_ns=1_600_000_000_000_000_123,
        frame_id="odom",
        child_frame_id="base_link",
        R=random_rotation(seed),
        t=rng.normal(size=3),
        twist_linear=rng.normal(size=3),
        twist_angular=rng.normal(size=3),
        covariance=spd(seed),
    )


@pytest.mark.parametrize("source", SOURCES)
def test_odometry_round_trip(source: str) -> None:
    sample = make_sample()
    msg = as_source(fill_odometry(Odometry, sample), source)
    back = odometry_from_msg(msg)
    assert (back.stamp_ns, back.frame_id, back.child_frame_id) == (
        sample.stamp_ns,
        "odom",
        "base_link",
    )
    np.testing.assert_allclose(back.R, sample.R, atol=1e-12)
    for name in ("t", "twist_linear", "twist_angular", "covariance"):
        np.testing.assert_allclose(getattr(back, name), getattr(sample, name), rtol=1e-12)
    assert back.covariance_known


def test_fill_odometry_into_rosbags_instance() -> None:
    # A rosbags message (as deserialized) can be filled too, then serialized again.
    msg = to_rosbags(Odometry())
    sample = make_sample(3)
    fill_odometry(msg, sample)
    raw = TYPESTORE.serialize_cdr(msg, "nav_msgs/msg/Odometry")
    back = odometry_from_msg(TYPESTORE.deserialize_cdr(raw, "nav_msgs/msg/Odometry"))
    np.testing.assert_allclose(back.covariance, sample.covariance)


def test_odometry_unknown_covariance_and_default() -> None:
    msg = Odometry()
    sample = odometry_from_msg(msg)
    assert not sample.covariance_known
    default = np.diag([1.0, 1, 1, 2, 2, 2])
    sample = odometry_from_msg(msg, default_covariance=default)
    assert sample.covariance_known
    np.testing.assert_array_equal(sample.covariance, default)


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda m: setattr(m.pose.pose.position, "x", float("nan")), r"pose\.position: .*NaN"),
        (zero_quaternion, "orientation: zero quaternion"),
        (lambda m: setattr(m.pose.pose.orientation, "w", 5.0), r"norm \S+ is not 1"),
        (lambda m: setattr(m.twist.twist.linear, "y", float("inf")), r"twist\.linear: .*inf"),
        (lambda m: setattr(m.twist.twist.angular, "z", float("nan")), r"angular: .*NaN"),
        (set_cov(0, -1.0), r"covariance: indefinite"),
        (set_cov(1, 0.5), r"covariance: not symmetric"),
        (set_cov(7, float("nan")), r"covariance: .*NaN"),
        (lambda m: setattr(m.header.stamp, "sec", -3), "negative time"),
    ],
)
def test_odometry_rejects(source: str, mutate: Any, match: str) -> None:
    msg = fill_odometry(Odometry(), make_sample(2))
    msg.pose.covariance = np.diag([1.0, 1, 1, 1, 1, 1]).ravel()
    msg = as_source(msg, source)
    mutate(msg)
    with pytest.raises(AdapterError, match=match):
        odometry_from_msg(msg)


def test_fill_odometry_rejects_bad_samples() -> None:
    sample = make_sample()
    bad_cov = OdometrySample(**{**sample.__dict__, "covariance": -np.eye(6)})
    with pytest.raises(AdapterError, match="OdometrySample.covariance: indefinite"):
        fill_odometry(Odometry, bad_cov)
    bad_R = OdometrySample(**{**sample.__dict__, "R": np.ones((3, 3))})
    with pytest.raises(AdapterError, match="not a rotation matrix"):
        fill_odometry(Odometry, bad_R)
    with pytest.raises(AdapterError, match="twist_covariance: not symmetric"):
        fill_odometry(Odometry, sample, twist_covariance=np.triu(np.ones((6, 6))))


def test_planar_helpers() -> None:
    cov = planar_covariance(0.1, 0.2, 0.05, cov_xy=0.01, unobserved_variance=1e3)
    np.testing.assert_allclose(np.diag(cov), [0.01, 0.04, 1e3, 1e3, 1e3, 0.0025])
    assert cov[0, 1] == cov[1, 0] == 0.01
    sample = planar_odometry_sample(
        5, "odom", "base_link", 1.0, 2.0, 3.0, cov, v_x_mps=0.5, yaw_rate_radps=0.1
    )
    msg = fill_odometry(Odometry, sample)
    x, y, yaw, cov3 = odometry_from_msg(msg).planar()
    assert (x, y) == (1.0, 2.0)
    assert yaw == pytest.approx(3.0, abs=1e-12)
    np.testing.assert_allclose(cov3, [[0.01, 0.01, 0], [0.01, 0.04, 0], [0, 0, 0.0025]])
    assert msg.twist.twist.linear.x == 0.5
    assert msg.twist.twist.angular.z == 0.1
    # A 3x3 covariance is embedded.
    s3 = planar_odometry_sample(5, "odom", "base_link", 0.0, 0.0, 0.0, np.eye(3))
    assert s3.covariance[2, 2] == 1e6
    assert s3.planar()[3].tolist() == np.eye(3).tolist()
    with pytest.raises(AdapterError, match="negative value"):
        planar_covariance(-0.1, 0.1, 0.1)
    with pytest.raises(AdapterError, match="exceeds σx·σy"):
        planar_covariance(0.1, 0.1, 0.1, cov_xy=0.5)
    with pytest.raises(AdapterError, match="unobserved_variance: is nan"):
        planar_covariance(0.1, 0.1, 0.1, unobserved_variance=float("nan"))
    with pytest.raises(AdapterError, match="unobserved_variance: -1.0 is not a variance"):
        planar_covariance(0.1, 0.1, 0.1, unobserved_variance=-1.0)
    with pytest.raises(AdapterError, match="planar pose: .*NaN"):
        planar_odometry_sample(5, "odom", "b", float("nan"), 0.0, 0.0, np.eye(3))


# ------------------------------------------------------------------------- loop closure


@pytest.mark.parametrize(
    ("text", "ref"),
    [
        ("node/0", NodeRef(0)),
        ("node/123", NodeRef(123)),
        ("stamp/0.000000000", StampRef(0)),
        ("stamp/1700000000.000000042", StampRef(1_700_000_000_000_000_042)),
    ],
)
def test_pose_refs(text: str, ref: Any) -> None:
    assert parse_pose_ref(text) == ref
    assert format_pose_ref(ref) == text


@pytest.mark.parametrize(
    "text",
    [
        "",
        "node/",
        "node/-1",
        "node/01",
        "node/1.5",
        " node/1",
        "node/1 ",
        "Node/1",
        "map",
        "stamp/1",
        "stamp/1.5",
        "stamp/1.0000000001",
        "stamp/-1.000000000",
        "h2o/3",
        "stamp/99999999999.000000000",
    ],
)
def test_malformed_pose_refs(text: str) -> None:
    with pytest.raises(AdapterError, match="frame_id|int32"):
        parse_pose_ref(text)


@pytest.mark.parametrize(
    ("digits", "what"),
    [
        ("9" * 4301, "node/"),  # beyond Python's int() limit of 4300 digits
        ("9" * 25, "node/"),
        (str(2**63), "node/"),  # one past int64
        ("1" * 5000, "stamp/"),
        (str(2**31), "stamp/"),
    ],
)
def test_out_of_range_numbers_in_pose_refs_are_rejected_naming_the_field(
    digits: str, what: str
) -> None:
    text = what + digits + (".000000000" if what == "stamp/" else "")
    with pytest.raises(InputError, match=r"child_frame_id: (node id|stamp sec) .* out of range"):
        parse_pose_ref(text, "loop closure child_frame_id")
    msg = fill_loop_closure(
        Odometry, make_loop_closure(NodeRef(1), NodeRef(2), np.eye(3), [1, 0, 0], np.eye(6))
    )
    msg.header.frame_id = text
    with pytest.raises(AdapterError, match="header.frame_id: .* out of range"):
        loop_closure_from_msg(msg)


def test_largest_node_id_round_trips() -> None:
    assert parse_pose_ref(f"node/{2**63 - 1}") == NodeRef(2**63 - 1)
    with pytest.raises(AdapterError, match="beyond"):
        format_pose_ref(NodeRef(2**63))


@given(st.integers(0, 2**31 * 10**9 - 1))
def test_stamp_ref_round_trip(ns: int) -> None:
    assert parse_pose_ref(format_pose_ref(StampRef(ns))) == StampRef(ns)


@pytest.mark.parametrize("source", SOURCES)
def test_loop_closure_round_trip(source: str) -> None:
    cov = spd(5)
    closure = make_loop_closure(
        NodeRef(3), StampRef(1_000_000_000_5), random_rotation(4), [1.0, 2.0, 3.0], cov, 77
    )
    np.testing.assert_allclose(closure.information @ cov, np.eye(6), atol=1e-9)
    msg = as_source(fill_loop_closure(Odometry, closure), source)
    assert msg.header.frame_id == "node/3"
    assert msg.child_frame_id == "stamp/10.000000005"
    back = loop_closure_from_msg(msg)
    assert (back.from_ref, back.to_ref, back.stamp_ns) == (NodeRef(3), StampRef(10**10 + 5), 77)
    np.testing.assert_allclose(back.R, closure.R, atol=1e-12)
    np.testing.assert_allclose(back.t, closure.t)
    np.testing.assert_allclose(back.covariance, cov)
    np.testing.assert_allclose(back.information, closure.information, rtol=1e-9)


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda m: setattr(m.header, "frame_id", "map"), "header.frame_id: 'map' is not a pose"),
        (lambda m: setattr(m, "child_frame_id", "node/x"), "child_frame_id: 'node/x' is not"),
        (lambda m: setattr(m, "child_frame_id", "node/1"), "the same pose"),
        (zero_quaternion, "zero quaternion"),
        (lambda m: setattr(m.pose.pose.position, "z", float("inf")), "NaN or inf"),
        (set_cov(35, 0.0), "singular"),
        (set_cov(35, -1.0), "indefinite"),
        (set_cov(slice(None), 0.0), "all zero"),
    ],
)
def test_loop_closure_rejects(source: str, mutate: Any, match: str) -> None:
    closure = make_loop_closure(NodeRef(1), NodeRef(2), np.eye(3), [1.0, 0, 0], np.eye(6))
    msg = as_source(fill_loop_closure(Odometry(), closure), source)
    mutate(msg)
    with pytest.raises(AdapterError, match=match):
        loop_closure_from_msg(msg)


def test_loop_closure_default_covariance() -> None:
    msg = fill_loop_closure(
        Odometry, make_loop_closure(NodeRef(1), NodeRef(2), np.eye(3), [1, 0, 0], np.eye(6))
    )
    msg.pose.covariance = np.zeros(36)
    closure = loop_closure_from_msg(msg, default_covariance=2.0 * np.eye(6))
    np.testing.assert_allclose(closure.information, 0.5 * np.eye(6))
    with pytest.raises(AdapterError, match="negative node id"):
        format_pose_ref(NodeRef(-1))


# ----------------------------------------------------------------------------- real bag


def test_adapters_on_a_real_bag(tmp_path: Path) -> None:
    """Write Odometry and loop closures into a rosbag2 file and adapt what is read back."""
    from rosbags.rosbag2 import Reader, Writer

    sample = make_sample(9)
    closure = make_loop_closure(StampRef(5), NodeRef(0), np.eye(3), [0, 1, 0], np.eye(6))
    path = tmp_path / "bag"
    with Writer(path, version=9) as writer:
        odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=TYPESTORE)
        loop = writer.add_connection("/loops", "nav_msgs/msg/Odometry", typestore=TYPESTORE)
        writer.write(odom, 1, serialize_message(fill_odometry(Odometry, sample)))
        writer.write(loop, 2, serialize_message(fill_loop_closure(Odometry, closure)))
    with Reader(path) as reader:
        got = {
            conn.topic: TYPESTORE.deserialize_cdr(raw, conn.msgtype)
            for conn, _, raw in reader.messages()
        }
    np.testing.assert_allclose(odometry_from_msg(got["/odom"]).R, sample.R, atol=1e-12)
    assert loop_closure_from_msg(got["/loops"]).from_ref == StampRef(5)


def test_importing_msg_adapters_loads_no_rclpy_nor_messages() -> None:
    """Layering: the adapters import neither rclpy nor a message package (nor OpenCV) up
    front; message classes come from the caller."""
    import subprocess
    import sys

    probe = (
        "import sys, msg_adapters\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in "
        "('rclpy', 'cv2', 'nav_msgs', 'sensor_msgs', 'geometry_msgs', 'rosbags')]\n"
        "print(','.join(bad))"
    )
    repo = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=repo, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == ""


@given(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
    lambda q: float(np.linalg.norm(q)) > 0.1))
def test_scalar_quaternion_path_equals_the_geometry_module(q: list[float]) -> None:
    # The adapter converts one quaternion with plain floats for speed; it must agree with
    # the batched conversion the cores use.
    from h2o_slam.core.geometry import quat_to_matrix
    from msg_adapters.rotations import quaternion_to_matrix

    unit = np.asarray(q) / np.linalg.norm(q)
    np.testing.assert_allclose(quaternion_to_matrix(unit), quat_to_matrix(unit), atol=1e-14)
    np.testing.assert_allclose(quaternion_to_matrix(q, norm_tol=None), quat_to_matrix(unit),
                               atol=1e-14)


@given(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
    lambda q: float(np.linalg.norm(q)) > 0.1))
def test_scalar_matrix_to_quaternion_equals_the_geometry_module(q: list[float]) -> None:
    from h2o_slam.core.geometry import matrix_to_quat, quat_to_matrix
    from msg_adapters.rotations import matrix_to_quaternion

    R = quat_to_matrix(np.asarray(q) / np.linalg.norm(q))
    got = np.array(matrix_to_quaternion(R))
    want = matrix_to_quat(R)
    assert got[3] >= 0.0
    # q and −q are one rotation; at w = 0 either sign is right.
    assert min(np.abs(got - want).max(), np.abs(got + want).max()) < 1e-12
    np.testing.assert_allclose(quat_to_matrix(got), R, atol=1e-12)
