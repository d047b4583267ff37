"""Bag I/O on real files: bags written by the simulator in both rosbag2 storages and as a
ROS 1 bag, damaged bags, topic maps, and the output bag."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rclpy.serialization import serialize_message
from rosbags.convert.converter import migrate_bytes
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from h2o_slam.core.errors import InputError
from h2o_slam.io.bag_reader import BagMessage, BagReader, read_bag
from h2o_slam.io.bag_writer import BagWriter, message_type_name, write_bag
from h2o_slam.io.bags import DATUM_KEY, ReplayError, jazzy_typestore
from h2o_slam.io.topic_map import DEFAULT_TOPICS, ROLES, load_topic_map, topic_map
from hybrid_vo.sim.messages import StreamMessage, Topics, drive_messages, rclpy_message_types
from hybrid_vo.sim.world import make_drive, scenario

REPO = Path(__file__).resolve().parents[2]
JAZZY = jazzy_typestore()


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


def test_a_bag_states_its_datum_in_its_metadata(drive: Any, tmp_path: Path) -> None:
    stream = list(drive_messages(drive, with_images=False))
    stated = write_bag(tmp_path / "stated", stream, custom_data={DATUM_KEY: "[48.1, 11.5, 520]"})
    assert stated == write_bag(tmp_path / "plain", stream)
    wheels = ("wheel_odom",)
    with BagReader(tmp_path / "stated", required=wheels) as reader:
        assert reader.stats.datum == [48.1, 11.5, 520.0]
    with BagReader(tmp_path / "plain", required=wheels) as reader:
        assert reader.stats.datum is None
    write_bag(tmp_path / "bad", stream, custom_data={DATUM_KEY: "[48.1, 11.5]"})
    with pytest.raises(ReplayError, match=r"bad/metadata\.yaml: custom_data h2o_slam/datum: "
                                          r"expected \[lat_deg, lon_deg, alt_m\]"):
        BagReader(tmp_path / "bad", required=wheels)


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
