"""Replay I/O on real files: bags written by the simulator in both rosbag2 storages and as
a ROS 1 bag, damaged bags, topic maps, the output bag, TUM files (read back by evo), ATE,
the summary and the plots."""

from __future__ import annotations

import io
import json
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from rosbags.convert.converter import migrate_bytes
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from h2o_slam.core.errors import InputError
from h2o_slam.core.geometry import matrix_to_quat, yaw_to_matrix
from h2o_slam.io.bag_reader import BagMessage, BagReader, read_bag
from h2o_slam.io.bag_writer import BagWriter, message_type_name, write_bag
from h2o_slam.io.bags import ReplayError, jazzy_typestore
from h2o_slam.io.replay_outputs import (
    Progress,
    align_planar,
    ate_m,
    final_error_m,
    match_stamps,
    node_callbacks,
    plot_callback_times,
    plot_chi2,
    plot_trajectories,
    read_tum,
    seconds_to_ns,
    write_summary,
    write_tum,
    yaw_of_quaternions,
)
from h2o_slam.io.topic_map import DEFAULT_TOPICS, ROLES, load_topic_map, topic_map
from hybrid_vo.world import make_drive, scenario
from hybrid_vo.world_messages import StreamMessage, Topics, drive_messages, rclpy_message_types

REPO = Path(__file__).resolve().parents[2]
JAZZY = jazzy_typestore()
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def canonical(type_name: str, cdr: bytes) -> bytes:
    """CDR bytes as rosbags writes them: Fast-CDR leaves padding bytes uninitialized, so
    two serializations of one message compare equal only after a round trip."""
    return bytes(JAZZY.serialize_cdr(JAZZY.deserialize_cdr(cdr, type_name), type_name))


def key(m: BagMessage) -> tuple[Any, ...]:
    return (m.role, m.topic, m.type_name, m.stamp_ns, m.header_stamp_ns,
            bytes(JAZZY.serialize_cdr(m.msg, m.type_name)))


@pytest.fixture(scope="module")
def drive() -> Any:
    return make_drive(scenario("straight", segments=((3.0, 1.3, 0.0),)))


@pytest.fixture(scope="module")
def written(drive: Any) -> list[tuple[str, str, int, bytes]]:
    """The simulated stream as (topic, type, stamp, canonical CDR)."""
    return [(m.topic, m.type_name, m.stamp_ns, canonical(m.type_name, serialize_message(m.msg)))
            for m in drive_messages(drive)]


@pytest.fixture(scope="module")
def bags(drive: Any, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    out = {}
    for storage in ("mcap", "sqlite3"):
        counts = write_bag(root / storage, drive_messages(drive), storage)  # type: ignore[arg-type]
        assert counts["/left/image_rect"] == len(drive.stamps_ns)
        out[storage] = root / storage
    return out


def copy_bag(src: Path, dst: Path) -> Path:
    """A copy of a rosbag2 directory whose storage file keeps its name (metadata lists it)."""
    shutil.copytree(src, dst)
    return dst


def storage_file(bag: Path) -> Path:
    (found,) = [p for p in bag.iterdir() if p.suffix in (".mcap", ".db3")]
    return found


# --- reading what the simulator wrote ----------------------------------------------------


def test_mcap_and_sqlite3_read_back_the_written_stream(
    bags: dict[str, Path], written: list[tuple[str, str, int, bytes]]
) -> None:
    streams = {}
    for storage, path in bags.items():
        with BagReader(path) as bag:
            streams[storage] = [key(m) for m in bag.messages()]
            assert bag.stats.error is None
            assert bag.stats.missing_roles == ["loop_closure"]  # a straight drive has none
            assert sum(bag.stats.out_of_order.values()) == 0
            assert bag.start_ns == written[0][2]
    assert streams["mcap"] == streams["sqlite3"]
    assert [(k[1], k[2], k[3], k[5]) for k in streams["mcap"]] == written
    roles = {v: k for k, v in DEFAULT_TOPICS.items()}
    assert all(k[0] == roles[k[1]] for k in streams["mcap"])


def test_read_order_is_bag_time_and_header_stamps_are_reported(bags: dict[str, Path]) -> None:
    messages = list(read_bag(bags["mcap"]))
    stamps = [m.stamp_ns for m in messages]
    assert stamps == sorted(stamps)
    # The simulator records each message at its header stamp.
    assert all(m.header_stamp_ns == m.stamp_ns for m in messages)


def test_raw_mcap_file_reads_like_its_directory(bags: dict[str, Path]) -> None:
    direct = [key(m) for m in read_bag(storage_file(bags["mcap"]))]
    assert direct == [key(m) for m in read_bag(bags["mcap"])]


def test_ros1_bag_reads_the_same_stream(
    drive: Any, tmp_path: Path, written: list[tuple[str, str, int, bytes]]
) -> None:
    noetic = get_typestore(Stores.ROS1_NOETIC)
    path = tmp_path / "drive.bag"
    cache: dict[str, object] = {}
    with Writer1(path) as writer:
        connections: dict[str, Any] = {}
        for topic, type_name, stamp, cdr in written:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, type_name, typestore=noetic)
            ros1 = migrate_bytes(JAZZY, noetic, type_name, type_name, cache, cdr,
                                 src_is2=True, dst_is2=False)
            writer.write(connections[topic], stamp, ros1)
    with BagReader(path) as bag:
        got = list(bag.messages())
    assert [(m.topic, m.type_name, m.stamp_ns) for m in got] == [w[:3] for w in written]
    first_image = next(m for m in got if m.role == "left_image")
    original = next(w for w in written if w[0] == "/left/image_rect")
    expect = JAZZY.deserialize_cdr(original[3], original[1])
    assert bytes(first_image.msg.data) == bytes(expect.data)  # type: ignore[attr-defined]
    assert first_image.header_stamp_ns == original[2]


# --- damaged bags ---------------------------------------------------------------------------


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_truncated_bag_delivers_messages_up_to_the_damage_then_fails(
    bags: dict[str, Path], tmp_path: Path, storage: str
) -> None:
    full = [key(m) for m in read_bag(bags[storage])]
    cut = copy_bag(bags[storage], tmp_path / "cut")
    data = storage_file(cut)
    os.truncate(data, data.stat().st_size // 2)
    got = []
    with BagReader(cut) as bag:
        assert bag.stats.salvaged is not None
        with pytest.raises(ReplayError, match=r"cut: stopped after \d+ messages: "
                                              r".*(cut off|malformed)") as info:
            for m in bag.messages():
                got.append(key(m))
        assert bag.stats.error is not None
    assert "\n" not in str(info.value)
    assert isinstance(info.value, InputError)
    assert len(full) // 4 < len(got) < len(full)
    assert got == full[: len(got)]


def test_mcap_without_footer_delivers_everything_then_says_so(
    bags: dict[str, Path], tmp_path: Path
) -> None:
    # A recording killed before it closed: whole chunks, no summary and no footer.
    bag = copy_bag(bags["mcap"], tmp_path / "unclosed")
    data = storage_file(bag)
    blob = data.read_bytes()
    data.write_bytes(blob[:_summary_start(blob)])
    got = []
    with pytest.raises(ReplayError, match="unclosed: .*ends without MCAP footer"):
        for m in read_bag(bag):
            got.append(key(m))
    assert got == [key(m) for m in read_bag(bags["mcap"])]


def _summary_start(blob: bytes) -> int:
    """Offset of the data-end record: the footer's summary offset points past it."""
    summary_start = int.from_bytes(blob[-37 + 9:-37 + 17], "little")
    return summary_start - 13  # data end record: opcode, u64 length 4, u32 crc


def test_truncated_ros1_bag_is_a_clear_error(tmp_path: Path, bags: dict[str, Path]) -> None:
    path = tmp_path / "drive.bag"
    noetic = get_typestore(Stores.ROS1_NOETIC)
    with Writer1(path) as writer:
        conn = writer.add_connection("/wheel/odom", "nav_msgs/msg/Odometry", typestore=noetic)
        for m in read_bag(bags["mcap"], {"left_image": None, "right_image": None}, required=()):
            if m.role != "wheel_odom":
                continue
            writer.write(conn, m.stamp_ns, noetic.serialize_ros1(
                _to_noetic(m.msg, noetic), "nav_msgs/msg/Odometry"))
    os.truncate(path, path.stat().st_size - 200)
    with pytest.raises(ReplayError, match=r"drive\.bag: "):
        list(read_bag(path, required=("wheel_odom",)))


def _to_noetic(msg: Any, noetic: Any) -> Any:
    cdr = bytes(JAZZY.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
    ros1 = migrate_bytes(JAZZY, noetic, "nav_msgs/msg/Odometry", "nav_msgs/msg/Odometry", {},
                         cdr, src_is2=True, dst_is2=False)
    return noetic.deserialize_ros1(ros1, "nav_msgs/msg/Odometry")


@pytest.mark.parametrize("damage", ["garbage", "missing"])
def test_unusable_metadata_falls_back_to_the_storage_file(
    bags: dict[str, Path], tmp_path: Path, damage: str
) -> None:
    bag = copy_bag(bags["sqlite3"], tmp_path / "meta")
    meta = bag / "metadata.yaml"
    if damage == "garbage":
        meta.write_text("rosbag2_bagfile_information: [unclosed\n")
    else:
        meta.unlink()
    with BagReader(bag) as reader:
        assert reader.stats.salvaged is not None and "metadata" in reader.stats.salvaged
        got = [key(m) for m in reader.messages()]
    assert got == [key(m) for m in read_bag(bags["sqlite3"])]
    storage_file(bag).unlink()
    with pytest.raises(ReplayError, match=r"meta: cannot open bag: .*metadata"):
        BagReader(bag)


def test_missing_path_and_not_a_bag(tmp_path: Path) -> None:
    with pytest.raises(ReplayError, match="nope: no such file"):
        BagReader(tmp_path / "nope")
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(ReplayError, match="notes.txt: cannot open bag"):
        BagReader(text)


def test_missing_required_topic_names_role_and_lists_topics(bags: dict[str, Path]) -> None:
    topics = topic_map(overrides=["wheel_odom=/odom"])
    with pytest.raises(ReplayError, match=r"no topic /odom for wheel_odom in the bag; "
                                          r"topics in the bag: /gps/fix \(sensor_msgs/msg/"):
        BagReader(bags["mcap"], topics)
    with pytest.raises(ReplayError, match="required role gps has no topic mapped"):
        BagReader(bags["mcap"], topic_map(overrides=["gps="]), required=("gps",))


def test_optional_roles_may_be_missing(bags: dict[str, Path]) -> None:
    topics = topic_map(overrides=["gps=/not/recorded", "ground_truth="])
    with BagReader(bags["mcap"], topics) as bag:
        assert bag.stats.missing_roles == ["gps", "loop_closure", "ground_truth"]
        roles = {m.role for m in bag.messages()}
    assert roles == {"left_image", "right_image", "left_info", "right_info", "wheel_odom"}


def test_topic_of_the_wrong_type_is_refused(tmp_path: Path) -> None:
    from std_msgs.msg import String

    path = tmp_path / "wrong"
    with BagWriter(path) as out:
        out.write("/wheel/odom", String(data="not odometry"), 1)
    with pytest.raises(ReplayError, match="topic /wheel/odom \\(wheel_odom\\) has type "
                                          "std_msgs/msg/String; wheel_odom needs nav_msgs"):
        BagReader(path, required=("wheel_odom",))


def test_unknown_message_type_names_topic_and_type(tmp_path: Path) -> None:
    path = tmp_path / "custom"
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg("float64 lat", "my_msgs/msg/Fix"))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/gps/fix", "my_msgs/msg/Fix", typestore=store)
        writer.write(conn, 5, store.serialize_cdr(store.types["my_msgs/msg/Fix"](1.0),
                                                  "my_msgs/msg/Fix"))
    with pytest.raises(ReplayError, match="topic /gps/fix \\(gps\\) has type my_msgs/msg/Fix"):
        BagReader(path, required=("gps",))
    # Not mapped to a role, the same topic is simply not read.
    with BagReader(path, topic_map(overrides=["gps="]), required=()) as bag:
        assert bag.stats.topics == {"/gps/fix": "my_msgs/msg/Fix"}
        assert list(bag.messages()) == []


def test_message_that_does_not_deserialize_names_topic_and_type(tmp_path: Path) -> None:
    path = tmp_path / "garbled"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/wheel/odom", "nav_msgs/msg/Odometry", typestore=JAZZY)
        writer.write(conn, 5, b"\x00\x01\x00\x00garbage")
    with pytest.raises(ReplayError, match="garbled: stopped after 0 messages: a nav_msgs/msg/"
                                          "Odometry message on /wheel/odom does not deserialize"):
        list(read_bag(path, required=("wheel_odom",)))


def test_header_stamps_going_backwards_are_counted_and_delivered(
    drive: Any, tmp_path: Path
) -> None:
    stream = list(drive_messages(drive, with_images=False))
    odom = [m for m in stream if m.topic == Topics().wheel_odom]
    # Swap two wheel messages' header stamps; bag time stays increasing.
    a, b = odom[5].msg.header.stamp, odom[6].msg.header.stamp
    odom[5].msg.header.stamp, odom[6].msg.header.stamp = b, a
    path = tmp_path / "backwards"
    write_bag(path, stream)
    with BagReader(path, required=("wheel_odom",)) as bag:
        got = [m for m in bag.messages() if m.role == "wheel_odom"]
        assert bag.stats.out_of_order == {"/wheel/odom": 1}
    assert len(got) == len(odom)
    assert got[6].header_stamp_ns < got[5].header_stamp_ns


# --- topic maps -----------------------------------------------------------------------------


def test_sample_topic_map_is_the_default() -> None:
    assert load_topic_map(REPO / "config" / "replay_topics.yaml") == DEFAULT_TOPICS
    assert set(DEFAULT_TOPICS) == set(ROLES)
    assert DEFAULT_TOPICS == vars(Topics()) | {}


def test_topic_map_layers_yaml_and_options(tmp_path: Path) -> None:
    path = tmp_path / "topics.yaml"
    path.write_text("topics:\n  wheel_odom: /robot/odom\n  gps: null\n")
    topics = topic_map(path, ["left_image=/cam/left", "loop_closure="])
    assert topics["wheel_odom"] == "/robot/odom"
    assert topics["gps"] is None and topics["loop_closure"] is None
    assert topics["left_image"] == "/cam/left"
    assert topics["right_image"] == DEFAULT_TOPICS["right_image"]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("topics:\n  left_camera: /x\n", "unknown role 'left_camera'; roles are left_image"),
        ("topics:\n  gps: 5\n", "topic of 'gps' must be a string or null"),
        ("gps: /gps\n", "a topic map needs a 'topics:' mapping"),
        ("topics: [unclosed\n", "cannot read topic map"),
    ],
)
def test_bad_topic_map_file(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "topics.yaml"
    path.write_text(text)
    with pytest.raises(ReplayError, match=f"topics.yaml: {match}"):
        load_topic_map(path)


def test_bad_topic_option() -> None:
    with pytest.raises(ReplayError, match="--topic: expected ROLE=TOPIC"):
        topic_map(overrides=["/wheel/odom"])
    with pytest.raises(ReplayError, match="--topic: unknown role 'odom'"):
        topic_map(overrides=["odom=/x"])


# --- the output bag -------------------------------------------------------------------------


def test_output_bag_closed_after_an_exception_is_readable(tmp_path: Path) -> None:
    types = rclpy_message_types()
    path = tmp_path / "out"
    with pytest.raises(RuntimeError, match="node failed"), BagWriter(path) as out:
        for i in range(5):
            msg = types["odometry"]()
            msg.header.stamp.sec = 100 + i
            msg.pose.pose.position.x = float(i)
            out.write("/h2o/odom", msg, (100 + i) * 10**9)
        raise RuntimeError("node failed")
    got = list(read_bag(path, {"wheel_odom": "/h2o/odom"}, required=("wheel_odom",)))
    assert [m.msg.pose.pose.position.x for m in got] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert (path / "metadata.yaml").exists()


def test_write_bag_writes_as_the_stream_goes(drive: Any, tmp_path: Path) -> None:
    def failing() -> Iterator[StreamMessage]:
        for i, m in enumerate(drive_messages(drive)):
            if i == 40:
                raise RuntimeError("renderer crashed")
            yield m

    path = tmp_path / "partial"
    with pytest.raises(RuntimeError, match="renderer crashed"):
        write_bag(path, failing(), "sqlite3")
    assert sum(1 for _ in read_bag(path)) == 40


def test_writer_errors(tmp_path: Path) -> None:
    types = rclpy_message_types()
    path = tmp_path / "out"
    out = BagWriter(path)
    out.write("/a", types["navsat"](), 1)
    with pytest.raises(ReplayError, match="topic /a has type sensor_msgs/msg/NavSatFix, not"):
        out.write("/a", types["odometry"](), 2)
    out.close()
    out.close()
    with pytest.raises(ReplayError, match="out: bag is closed"):
        out.write("/a", types["navsat"](), 3)
    with pytest.raises(ReplayError, match="out: cannot create bag: .*exists"):
        BagWriter(path)
    with pytest.raises(ReplayError, match="unknown storage 'zip'"):
        BagWriter(tmp_path / "zip", "zip")  # type: ignore[arg-type]
    assert message_type_name(types["image"]()) == "sensor_msgs/msg/Image"


# --- TUM files ------------------------------------------------------------------------------


def _trajectory(n: int = 50, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    stamps = 1_700_000_000 * 10**9 + np.cumsum(rng.integers(1, 10**8, n))
    stamps[0] = 1_700_000_000 * 10**9 + 42  # a stamp float seconds cannot hold
    xyz = rng.normal(size=(n, 3)) * [100.0, 100.0, 1.0]
    yaw = rng.uniform(-np.pi, np.pi, n)
    return stamps, xyz, yaw


def test_tum_round_trip_is_bit_exact(tmp_path: Path) -> None:
    stamps, xyz, yaw = _trajectory()
    path = write_tum(tmp_path / "traj.tum", stamps, xyz, yaw_rad=yaw)
    got_stamps, got_xyz, got_q = read_tum(path)
    assert got_stamps.dtype == np.int64 and np.array_equal(got_stamps, stamps)
    assert np.array_equal(got_xyz, xyz)
    assert np.array_equal(got_q, matrix_to_quat(yaw_to_matrix(yaw)))
    np.testing.assert_allclose(yaw_of_quaternions(got_q), yaw, atol=1e-12)
    rotations = yaw_to_matrix(yaw)
    again = write_tum(tmp_path / "again.tum", got_stamps, got_xyz, rotations=rotations)
    assert again.read_text() == path.read_text()


def test_tum_files_load_with_evo(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    stamps, xyz, yaw = _trajectory()
    path = write_tum(tmp_path / "traj.tum", stamps, xyz[:, :2], yaw_rad=yaw)
    traj = file_interface.read_tum_trajectory_file(str(path))
    assert traj.num_poses == len(stamps)
    np.testing.assert_array_equal(traj.positions_xyz[:, :2], xyz[:, :2])
    np.testing.assert_array_equal(traj.positions_xyz[:, 2], 0.0)
    np.testing.assert_allclose(traj.timestamps, stamps / 1e9, rtol=0, atol=1e-6)
    wxyz = np.roll(matrix_to_quat(yaw_to_matrix(yaw)), 1, axis=1)
    np.testing.assert_array_equal(traj.orientations_quat_wxyz, wxyz)


def test_tum_errors(tmp_path: Path) -> None:
    stamps, xyz, yaw = _trajectory(5)
    with pytest.raises(ReplayError, match="exactly one of yaw_rad or rotations"):
        write_tum(tmp_path / "a.tum", stamps, xyz)
    with pytest.raises(ReplayError, match=r"positions must be \(5, 2 or 3\)"):
        write_tum(tmp_path / "a.tum", stamps, xyz[:4], yaw_rad=yaw)
    bad = xyz.copy()
    bad[2, 0] = np.nan
    with pytest.raises(ReplayError, match="non-finite"):
        write_tum(tmp_path / "a.tum", stamps, bad, yaw_rad=yaw)
    path = tmp_path / "b.tum"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n")
    with pytest.raises(ReplayError, match="b.tum: line 3: expected 8 fields, found 7"):
        read_tum(path)
    path.write_text("1.0 0 0 zero 0 0 0 1\n")
    with pytest.raises(ReplayError, match="line 1: could not convert"):
        read_tum(path)


@pytest.mark.parametrize(
    ("text", "ns"),
    [("1700000000.000000042", 1_700_000_000_000_000_042), ("12", 12 * 10**9),
     ("0.5", 500_000_000), ("-0.5", -500_000_000), ("1.5e-3", 1_500_000),
     ("3.1234567891", 3_123_456_789)],
)
def test_seconds_to_ns_is_exact(text: str, ns: int) -> None:
    assert seconds_to_ns(text) == ns


# --- accuracy -------------------------------------------------------------------------------


def test_ate_is_zero_for_a_rigidly_moved_copy_and_the_rms_otherwise() -> None:
    rng = np.random.default_rng(0)
    truth = np.cumsum(rng.normal(size=(200, 2)), axis=0)
    R = yaw_to_matrix(0.7)[:2, :2]
    moved = truth @ R.T + [5.0, -3.0]
    assert ate_m(moved, truth) < 1e-9
    R_fit, t_fit = align_planar(moved, truth)
    np.testing.assert_allclose(R_fit, R.T, atol=1e-12)
    # Noise of known RMS, with mean and rotation removed so alignment cannot absorb it.
    noise = rng.normal(size=truth.shape) * 0.3
    noise -= noise.mean(axis=0)
    noisy = truth + noise
    assert ate_m(noisy, truth) <= np.sqrt(np.mean(np.sum(noise**2, axis=1))) + 1e-12
    assert ate_m(noisy, truth) > 0.25


def test_alignment_never_reflects() -> None:
    truth = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [2.0, 3.0]])
    mirrored = truth * [1.0, -1.0]
    R, _ = align_planar(mirrored, truth)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert ate_m(mirrored, truth) > 0.5


def test_final_error_and_stamp_matching() -> None:
    est = np.array([[0.0, 0.0], [1.0, 1.0], [3.0, 4.0]])
    truth = np.zeros((3, 2))
    assert final_error_m(est, truth) == 5.0
    i, j = match_stamps([100, 205, 290, 900], [0, 100, 200, 300], tolerance_ns=10)
    assert i.tolist() == [0, 1, 2] and j.tolist() == [1, 2, 3]
    with pytest.raises(ValueError, match="two or more"):
        ate_m(est[:1], truth[:1])


# --- summary, plots, progress ---------------------------------------------------------------


def test_summary_json_takes_numpy_and_nan(tmp_path: Path) -> None:
    path = write_summary(tmp_path / "summary.json", {
        "ate_m": np.float64(0.25), "counts": {"gps": np.int64(3)}, "chi2": np.array([1.0, 2.0]),
        "overrun": float("nan"), "bag": tmp_path, "pair": (1, 2)})
    data = json.loads(path.read_text())
    assert data == {"ate_m": 0.25, "counts": {"gps": 3}, "chi2": [1.0, 2.0], "overrun": None,
                    "bag": str(tmp_path), "pair": [1, 2]}


def _png_size(path: Path) -> tuple[int, int]:
    blob = path.read_bytes()
    assert blob[:8] == PNG_MAGIC and len(blob) > 5000
    return int.from_bytes(blob[16:20], "big"), int.from_bytes(blob[20:24], "big")


@pytest.fixture
def saved_axes(monkeypatch: pytest.MonkeyPatch) -> list[list[Any]]:
    """The axes of every figure saved, as they were when saved (one list per figure)."""
    from matplotlib.figure import Figure

    saved: list[list[Any]] = []
    original = Figure.savefig

    def savefig(fig: Figure, *args: Any, **kwargs: Any) -> None:
        saved.append(list(fig.axes))
        original(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    return saved


def _labels(ax: Any) -> list[str]:
    return [str(line.get_label()) for line in ax.get_lines()]


def test_plots_are_png_files(tmp_path: Path) -> None:
    t = np.linspace(0, 10, 50)
    xy = np.stack([t, np.sin(t)], axis=1)
    calls = [(float(s), float(s) / 2, "odometry") for s in t]
    paths = [
        plot_trajectories(tmp_path / "traj.png", {"wheel": xy, "h2o": xy + 0.1},
                          gps_enu=xy[::5] + 0.3),
        plot_trajectories(tmp_path / "empty.png", {"wheel": np.zeros((0, 2))}),
        plot_callback_times(tmp_path / "cb.png", {"h2o_node": node_callbacks(calls, budget_ms=5.0),
                                                  "hybrid_vo_node": node_callbacks(calls)}),
        plot_callback_times(tmp_path / "cb_empty.png", {"h2o_node": node_callbacks([])}),
        plot_chi2(tmp_path / "chi2.png", {"run": (t, np.exp(-t) + 1.0)}),
        plot_chi2(tmp_path / "chi2_zero.png", {"tree": (t, np.full(len(t), 1e-27))}),
    ]
    for path in paths:
        width, height = _png_size(path)
        assert width > 300 and height > 200


def test_trajectory_plot_draws_the_truth_on_top_dashed_and_the_errors_beside(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    t_ns = np.arange(50, dtype=np.int64) * 100_000_000
    truth = np.stack([np.linspace(0, 10, 50), np.zeros(50)], axis=1)
    est = truth + [0.0, 0.2]
    plot_trajectories(tmp_path / "traj.png", {"estimate": est, "ground truth": truth},
                      stamps_ns={"estimate": t_ns, "ground truth": t_ns})
    xy_ax, error_ax = saved_axes[0]
    truth_line = next(ln for ln in xy_ax.get_lines() if ln.get_label() == "ground truth")
    assert truth_line.get_linestyle() == "--"
    assert truth_line.get_zorder() > max(ln.get_zorder() for ln in xy_ax.get_lines()
                                         if ln is not truth_line and ln.get_label() != "start")
    # A constant offset is removed by the ATE's alignment: the error is ~0, as the ATE is.
    assert _labels(error_ax) == ["estimate (ATE 0.000 m)"]
    assert "estimate (ATE 0.000 m)" in _labels(xy_ax)
    legend = [text.get_text() for text in xy_ax.figure.legends[0].get_texts()]
    assert legend == ["estimate (ATE 0.000 m)", "ground truth", "start"]  # each once, below
    assert _png_size(tmp_path / "traj.png")[0] > 1000


def test_chi2_axis_starts_at_the_first_meaningful_value(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    t = np.arange(0.0, 100.0, 1.0)
    # A run without GPS: a tree (χ² at rounding level) until the first loop closure at 34 s.
    chi2 = np.where(t < 34, 1e-27, 0.05 * 1.1 ** (t - 34))
    plot_chi2(tmp_path / "chi2.png", {"without GPS": (t, chi2)})
    (ax,) = saved_axes[0]
    low, high = ax.get_ylim()
    assert 0.01 < low < 0.1 and high > 10
    assert ax.get_yscale() == "log"
    (drawn,) = ax.get_lines()
    assert drawn.get_xdata()[0] == 34
    legend = [text.get_text() for text in ax.figure.legends[0].get_texts()]
    assert legend[0].startswith("without GPS: χ² ≈ 0 until 34 s")


def test_callback_plot_is_per_node_against_bag_time_with_the_budget(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    h2o = [(0.5 * i, 0.3 if i % 3 else 4.0, "odometry" if i % 3 else "GPS fix")
           for i in range(60)]
    vo = [(0.05 * i, 1.5 if i % 2 else 0.02, "stereo pair" if i % 2 else "image buffered")
          for i in range(600)]
    plot_callback_times(tmp_path / "cb.png", {
        "h2o_node": node_callbacks(h2o, budget_ms=5.0),
        "hybrid_vo_node": node_callbacks(vo, budget_ms=100.0, budget_label="frame interval",
                                         hidden_kinds=("image buffered",))})
    h2o_ax, vo_ax = saved_axes[0]
    assert h2o_ax.get_title(loc="left") == "h2o_node"
    # Cheapest kind first, each with its count; then the budget.
    assert [label.split(":")[0] for label in _labels(h2o_ax)] == ["odometry (40)",
                                                                   "GPS fix (20)",
                                                                   "budget 5 ms"]
    odometry = h2o_ax.get_lines()[0]
    assert odometry.get_xdata().max() == pytest.approx(29.5)  # bag time, not the index
    assert [label.split(":")[0] for label in _labels(vo_ax)] == ["stereo pair (300)",
                                                                  "frame interval"]
    assert "300 callbacks 'image buffered' not drawn" in vo_ax.get_title(loc="left")
    assert vo_ax.get_yscale() == "log"  # 1.5 ms against a 100 ms limit
    assert h2o_ax.get_xlabel() == "" and vo_ax.get_xlabel() == "bag time (s)"


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_draws_only_on_a_terminal() -> None:
    quiet = io.StringIO()
    bar = Progress(10.0, "replay", stream=quiet)
    bar.update(5.0)
    bar.close()
    assert quiet.getvalue() == ""
    tty = _Tty()
    bar = Progress(10.0, "replay", stream=tty, min_interval_s=0.0)
    bar.update(5.0, note="3 GPS")
    bar.update(10.0)
    bar.close()
    lines = tty.getvalue().split("\r")
    assert "replay [" in lines[1] and " 50% 5.0/10.0 s" in lines[1] and "3 GPS" in lines[1]
    assert "100%" in lines[-1] and lines[-1].endswith("\n") and "x real time" in lines[-1]
