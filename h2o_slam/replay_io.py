"""Bag I/O for ``h2o-replay``: topic maps, reading recordings, writing bags.

Reading goes through ``rosbags`` (rosbag2 with sqlite3 or mcap storage, raw ``.mcap`` and
``.db3`` files, ROS 1 ``.bag`` files); messages come back deserialized by ``rosbags``,
which :mod:`msg_adapters` reads like rclpy messages. Replay order is **bag time**: the
time each message was recorded (its receive or log time, int nanoseconds), which is
the order a live robot saw them in. Header stamps are reported beside it and checked per
topic: a header stamp going backwards is counted in :class:`BagStats` and the message is
still delivered, so the node that receives it is the one that rejects and counts it
(DESIGN §7).

A damaged bag is read up to the damage: :meth:`BagReader.messages` yields every message
it can, then raises :class:`ReplayError`, so the caller still writes out what it
processed. When ``rosbags`` cannot open a bag, the reader falls back to its storage file
alone (an unusable ``metadata.yaml``), then to reading that file record by record: an MCAP
file from its start (a cut file, or a recording that never closed, has lost its index),
an sqlite3 database by row id (its insertion order). ``BagStats.salvaged`` says why.

Writing serializes rclpy messages with ``rclpy.serialization`` into a rosbag2 bag, one
message at a time (:class:`BagWriter`), registering each topic with its type from the
ROS 2 Jazzy type store. rclpy is imported only by the writer, so reading needs no ROS.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import struct
import tempfile
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, Literal, Self

import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from h2o_slam.errors import InputError

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

#: Default topic of each role: the names :class:`hybrid_vo.world_messages.Topics` uses.
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

Storage = Literal["mcap", "sqlite3"]
TopicMap = dict[str, str | None]
#: ``(topic, type name, bag time ns, message)`` as read, before the role is attached.
_Raw = tuple[str, str, int, Any]

_MCAP_MAGIC = b"\x89MCAP0\r\n"


class ReplayError(InputError):
    """A bag, topic map or trajectory file that cannot be used; names the file and reason."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


# --- topic maps ------------------------------------------------------------------------


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


# --- reading ---------------------------------------------------------------------------


@dataclass(frozen=True)
class BagMessage:
    """One message of a recording, mapped to the role its topic plays.

    Attributes:
        role: one of :data:`ROLES`.
        topic: the topic in the bag.
        type_name: ROS 2 type name, e.g. ``sensor_msgs/msg/Image``.
        stamp_ns: bag time (recorded receive/log time), int ns: the replay order.
        header_stamp_ns: ``header.stamp`` in int ns, ``None`` for a message without one.
        msg: the message as deserialized by ``rosbags``.
    """

    role: str
    topic: str
    type_name: str
    stamp_ns: int
    header_stamp_ns: int | None
    msg: Any


@dataclass
class BagStats:
    """What a :class:`BagReader` found and delivered.

    Attributes:
        path: the bag.
        topics: every topic in the bag → its type name.
        roles: role → topic, for the roles found in the bag.
        missing_roles: optional roles whose topic is not in the bag.
        counts: messages delivered per role.
        out_of_order: per topic, messages whose header stamp went back in time.
        bag_time_backwards: messages whose bag time went back (only read record by
            record, from a file without index; those are still delivered in file order).
        salvaged: why the bag is read record by record (``None`` when it is not).
        error: the error that ended reading, if one did.
        declared: messages per topic the bag declares (its ``metadata.yaml``, or the
            storage's own index); empty when the bag states none (a file read record by
            record without metadata).
        read: messages delivered per topic.
    """

    path: str
    topics: dict[str, str] = field(default_factory=dict)
    roles: dict[str, str] = field(default_factory=dict)
    missing_roles: list[str] = field(default_factory=list)
    counts: Counter[str] = field(default_factory=Counter)
    out_of_order: Counter[str] = field(default_factory=Counter)
    bag_time_backwards: int = 0
    salvaged: str | None = None
    error: str | None = None
    declared: dict[str, int] = field(default_factory=dict)
    read: Counter[str] = field(default_factory=Counter)

    def shortfall(self) -> dict[str, tuple[int, int]]:
        """Mapped topics whose delivered count differs from the declared one:
        topic → (declared, read)."""
        return {topic: (self.declared[topic], self.read[topic])
                for topic in sorted(set(self.roles.values()))
                if topic in self.declared and self.declared[topic] != self.read[topic]}


class _ClosedOnExit:
    """``with`` support: leaving the block calls ``close()``, also when an error ends it."""

    def close(self) -> None:
        """Release what the object holds."""
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class BagReader(_ClosedOnExit):
    """A recording opened for replay; a context manager.

    Opening checks everything that can be checked before the first message: the file,
    its metadata, that each required role's topic is there, that each mapped topic has a
    type the role accepts and that type has a definition. Then :meth:`messages` yields
    the mapped topics in bag-time order.

    Args:
        path: a rosbag2 directory, a ``.mcap``/``.db3`` file, or a ROS 1 ``.bag`` file.
        topics: role → topic (:func:`topic_map`); roles not given keep their default
            topic, a role given as ``None`` is off.
        required: roles without which the bag is refused; others may be missing.

    Raises:
        ReplayError: the bag cannot be opened, a required role has no topic in the bag
            (the message lists the bag's topics), or a mapped topic's type is wrong or
            unknown.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        topics: Mapping[str, str | None] | None = None,
        required: Sequence[str] = REQUIRED_ROLES,
    ) -> None:
        self.path = Path(path)
        self.stats = BagStats(str(self.path))
        self._reader: AnyReader | None = None
        self._salvage: _McapScan | _Sqlite3Scan | None = None
        self._open()
        try:
            self._map_roles({**DEFAULT_TOPICS, **(topics or {})}, required)
        except ReplayError:
            self.close()
            raise

    def close(self) -> None:
        """Release the files; safe to call twice."""
        if self._reader is not None:
            reader, self._reader = self._reader, None
            reader.close()
        if isinstance(self._salvage, _Sqlite3Scan):
            self._salvage.close()

    @property
    def start_ns(self) -> int:
        """Bag time of the first message (0 when unknown, e.g. a salvaged file)."""
        return self._reader.start_time if self._reader is not None else 0

    @property
    def end_ns(self) -> int:
        """Bag time just after the last message (0 when unknown)."""
        return self._reader.end_time if self._reader is not None else 0

    def _open(self) -> None:
        if not self.path.exists():
            raise ReplayError(self.path, "no such file or directory")
        try:
            self._reader = _any_reader(self.path)
        except Exception as exc:  # rosbags fails in many ways on damaged files
            self._open_damaged(_reason(exc))
        if self._reader is not None:
            self.stats.topics = {
                name: info.msgtype or "?" for name, info in sorted(self._reader.topics.items())
            }
            self.stats.declared = {name: int(info.msgcount)
                                   for name, info in self._reader.topics.items()}
        else:
            assert self._salvage is not None
            self.stats.topics = self._salvage.topics()
        if self.stats.salvaged is not None:  # metadata.yaml still says what was recorded
            self.stats.declared = _declared_counts(self.path) or self.stats.declared

    def _open_damaged(self, reason: str) -> None:
        """Fall back to the storage file alone: without ``metadata.yaml`` when that is what
        failed, else record by record; raise the original reason if nothing works."""
        data = _storage_file(self.path)
        if data is None:
            raise ReplayError(self.path, f"cannot open bag: {reason}")
        if data != self.path:
            try:
                self._reader = _any_reader(data)
                self.stats.salvaged = f"{reason}; read {data.name} without it"
                return
            except Exception:  # the storage itself is damaged: read it record by record
                pass
        try:
            self._salvage = _McapScan(data) if data.suffix == ".mcap" else _Sqlite3Scan(data)
        except Exception:  # not even the start of the file is readable
            raise ReplayError(self.path, f"cannot open bag: {reason}") from None
        self.stats.salvaged = f"{reason}; reading {data.name} record by record"

    def _map_roles(self, topics: dict[str, str | None], required: Sequence[str]) -> None:
        present = self.stats.topics
        for role in ROLES:
            topic = topics.get(role)
            if topic is None or topic not in present:
                if role in required:
                    raise ReplayError(self.path, _missing(role, topic, present))
                self.stats.missing_roles.append(role)
                continue
            self._check_type(role, topic, present[topic])
            self.stats.roles[role] = topic

    def _check_type(self, role: str, topic: str, type_name: str) -> None:
        if type_name not in ROLE_TYPES[role]:
            raise ReplayError(
                self.path,
                f"topic {topic} ({role}) has type {type_name}; "
                f"{role} needs {' or '.join(ROLE_TYPES[role])}",
            )
        store = self._reader.typestore if self._reader is not None else self._salvage_types()
        if type_name not in store.types:
            raise ReplayError(
                self.path, f"topic {topic} ({role}): no definition of message type {type_name}"
            )

    def _salvage_types(self) -> Typestore:
        assert self._salvage is not None
        return self._salvage.typestore

    def messages(self) -> Iterator[BagMessage]:
        """The mapped topics' messages in bag-time order (file order when salvaged).

        Raises:
            ReplayError: after the last message that could be read, when the bag is
                damaged or a message cannot be deserialized; ``stats.error`` holds the
                reason too.
        """
        by_topic = {topic: role for role, topic in self.stats.roles.items()}
        last_header: dict[str, int] = {}
        last_bag = -1
        for topic, type_name, stamp_ns, msg in self._raw(by_topic):
            header_ns = _header_ns(msg)
            if header_ns is not None:
                if header_ns < last_header.get(topic, header_ns):
                    self.stats.out_of_order[topic] += 1
                last_header[topic] = header_ns
            if stamp_ns < last_bag:
                self.stats.bag_time_backwards += 1
            last_bag = max(last_bag, stamp_ns)
            role = by_topic[topic]
            self.stats.counts[role] += 1
            self.stats.read[topic] += 1
            yield BagMessage(role, topic, type_name, stamp_ns, header_ns, msg)

    def _raw(self, by_topic: Mapping[str, str]) -> Iterator[_Raw]:
        if self._salvage is not None:
            source = self._salvage.messages(set(by_topic))
        else:
            source = self._rosbags_messages(by_topic)
        while True:
            try:
                item = next(source, None)
            except Exception as exc:  # damage shows up as any error deep in rosbags
                reason = exc.reason if isinstance(exc, ReplayError) else _reason(exc)
                delivered = sum(self.stats.counts.values())
                self.stats.error = f"stopped after {delivered} messages: {reason}"
                raise ReplayError(self.path, self.stats.error) from None
            if item is None:
                return
            yield item

    def _rosbags_messages(self, by_topic: Mapping[str, str]) -> Iterator[_Raw]:
        reader = self._reader
        assert reader is not None
        connections = [c for c in reader.connections if c.topic in by_topic]
        if not connections:
            return
        for connection, stamp_ns, raw in reader.messages(connections=connections):
            topic, type_name = connection.topic, connection.msgtype
            yield topic, type_name, stamp_ns, _decode(reader.deserialize, raw, topic, type_name)


def read_bag(
    path: str | os.PathLike[str],
    topics: Mapping[str, str | None] | None = None,
    required: Sequence[str] = REQUIRED_ROLES,
) -> Iterator[BagMessage]:
    """The messages of a bag's mapped topics (see :class:`BagReader`, which also counts).

    Raises:
        ReplayError: as :class:`BagReader` and :meth:`BagReader.messages`; the messages
            before the damage are yielded first.
    """
    with BagReader(path, topics, required) as bag:
        yield from bag.messages()


def jazzy_typestore() -> Typestore:
    """The ROS 2 Jazzy message types known to ``rosbags``."""
    return get_typestore(Stores.ROS2_JAZZY)


def _missing(role: str, topic: str | None, present: Mapping[str, str]) -> str:
    have = ", ".join(f"{name} ({kind})" for name, kind in present.items()) or "none"
    if topic is None:
        return f"required role {role} has no topic mapped; topics in the bag: {have}"
    return f"no topic {topic} for {role} in the bag; topics in the bag: {have}"


def _decode(deserialize: Any, data: bytes, topic: str, type_name: str) -> Any:
    """``deserialize(data, type_name)``, failing with the topic and type named."""
    try:
        return deserialize(data, type_name)
    except Exception as exc:  # rosbags' serde raises several kinds on bad bytes
        raise InputError(f"a {type_name} message on {topic} does not deserialize: "
                         f"{_reason(exc)}") from None


def _header_ns(msg: Any) -> int | None:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return None
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if isinstance(exc, InputError) else f"{text} ({type(exc).__name__})"


# --- opening; damaged files read record by record --------------------------------------


def _declared_counts(path: Path) -> dict[str, int]:
    """Messages per topic a rosbag2 folder's ``metadata.yaml`` declares ({} if unreadable)."""
    try:
        meta = yaml.safe_load((path / "metadata.yaml").read_text(encoding="utf-8"))
        topics = meta["rosbag2_bagfile_information"]["topics_with_message_count"]
        return {str(t["topic_metadata"]["name"]): int(t["message_count"]) for t in topics}
    except Exception:  # no folder, no file, or not the rosbag2 layout: nothing declared
        return {}


def _any_reader(path: Path) -> AnyReader:
    reader = AnyReader([path], default_typestore=jazzy_typestore())
    reader.open()
    return reader


def _storage_file(path: Path) -> Path | None:
    """The one ``.mcap``/``.db3`` file of a bag (``path`` itself if it is one)."""
    if path.is_file():
        return path if path.suffix in (".mcap", ".db3") else None
    found = sorted(p for p in path.glob("*") if p.suffix in (".mcap", ".db3"))
    return found[0] if len(found) == 1 else None


class _McapScan:
    """Records of an MCAP file read from its start, for files whose index is lost.

    Chunks are opened in place; schemas and channels are collected as they appear, so
    the messages before the damage are all reachable. Only the records the replay needs
    are decoded (MCAP spec: opcode u8, length u64, content).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        with path.open("rb") as f:
            if f.read(8) != _MCAP_MAGIC:
                raise ReplayError(path, "not an MCAP file")
        self.schemas: dict[int, tuple[str, str, str]] = {}
        self.channels: dict[int, tuple[str, int]] = {}
        self.typestore = jazzy_typestore()
        self.damage: str | None = None
        self.complete = False  # the footer was reached: only the index was unreadable
        for _ in self._records():  # first pass: schemas, channels and where damage starts
            pass
        self._register_schemas()

    def topics(self) -> dict[str, str]:
        """Topic → type name of every channel found."""
        return dict(sorted(
            (topic, self.schemas.get(schema, ("?", "", ""))[0])
            for topic, schema in self.channels.values()
        ))

    def messages(self, topics: set[str]) -> Iterator[_Raw]:
        """``(topic, type, log time ns, message)`` in file order, then the damage.

        Raises:
            ReplayError: at the damage (or the missing footer) after the last message.
                A file that reads to its footer ends without error.
        """
        for channel_id, log_ns, data in self._records():
            topic, schema = self.channels[channel_id]
            if topic in topics:
                type_name = self.schemas[schema][0]
                msg = _decode(self.typestore.deserialize_cdr, data, topic, type_name)
                yield topic, type_name, log_ns, msg
        if not self.complete:
            raise ReplayError(self.path, self.damage or "ends without MCAP footer")

    def _register_schemas(self) -> None:
        for name, encoding, text in self.schemas.values():
            if name in self.typestore.types or not text:
                continue
            parse = get_types_from_msg if encoding == "ros2msg" else _idl_types
            self.typestore.register(parse(text, name))

    def _records(self) -> Iterator[tuple[int, int, bytes]]:
        with self.path.open("rb") as f:
            f.seek(8)
            try:
                yield from self._scan(f, self.path.stat().st_size)
            except Exception as exc:  # a cut record fails in struct, decode or decompress
                reason = str(exc) if isinstance(exc, _Truncated) else _reason(exc)
                self.damage = f"MCAP file damaged or cut off near byte {f.tell()}: {reason}"

    def _scan(self, f: BinaryIO, end: int) -> Iterator[tuple[int, int, bytes]]:
        while f.tell() < end:
            head = f.read(9)
            if len(head) < 9:
                raise _Truncated(f"record header cut after {len(head)} of 9 bytes")
            opcode, length = struct.unpack("<BQ", head)
            body = f.read(length)
            if opcode == 0x02:  # footer: the file is whole after all
                self.complete = True
                return
            if opcode == 0x06:  # a chunk: its records; a cut one still gives its whole ones
                yield from self._chunk(body)
            elif len(body) == length:
                yield from self._record(opcode, body)
            if len(body) != length:
                raise _Truncated(f"record of {length} bytes cut after {len(body)}")

    def _chunk(self, body: bytes) -> Iterator[tuple[int, int, bytes]]:
        size = struct.unpack_from("<Q", body, 16)[0]
        compression, pos = _string(body, 28)
        (length,) = struct.unpack_from("<Q", body, pos)
        data = body[pos + 8:pos + 8 + length]
        if compression:
            from rosbags.rosbag2.storage_mcap import decompress

            data = decompress(data, compression, size, 0)
        pos = 0
        while pos + 9 <= len(data):
            opcode, length = struct.unpack_from("<BQ", data, pos)
            if pos + 9 + length > len(data):
                break
            yield from self._record(opcode, data[pos + 9:pos + 9 + length])
            pos += 9 + length

    def _record(self, opcode: int, body: bytes) -> Iterator[tuple[int, int, bytes]]:
        if opcode == 0x03:  # schema: id, name, encoding, data
            (schema_id,) = struct.unpack_from("<H", body, 0)
            name, pos = _string(body, 2)
            encoding, pos = _string(body, pos)
            (length,) = struct.unpack_from("<I", body, pos)
            text = body[pos + 4:pos + 4 + length].decode()
            self.schemas[schema_id] = (name, encoding, text)
        elif opcode == 0x04:  # channel: id, schema id, topic
            channel_id, schema_id = struct.unpack_from("<HH", body, 0)
            topic, _ = _string(body, 4)
            self.channels[channel_id] = (topic, schema_id)
        elif opcode == 0x05:  # message: channel, sequence, log time, publish time, data
            channel_id, _, log_ns, _ = struct.unpack_from("<HIQQ", body, 0)
            yield channel_id, log_ns, body[22:]


class _Truncated(Exception):
    pass


def _string(body: bytes, pos: int) -> tuple[str, int]:
    (length,) = struct.unpack_from("<I", body, pos)
    return body[pos + 4:pos + 4 + length].decode(), pos + 4 + length


def _idl_types(text: str, name: str) -> Any:
    return get_types_from_idl(text)


class _Sqlite3Scan:
    """Rows of a rosbag2 sqlite3 file read in insertion order, for damaged databases.

    rosbags needs the whole ``messages`` table at open (it counts it); a cut database
    still gives its first rows when walked by row id, which is the order rosbag2
    inserted them in (arrival order). SQLite refuses a file shorter than its header says,
    so a cut file is read from a copy padded with zeros (sparse) to that length.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.typestore = jazzy_typestore()
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._db_path = self._padded(path)
        with closing(self._connect()) as db:
            rows = db.execute("SELECT id, name, type FROM topics").fetchall()
        self.channels = {int(i): (str(name), str(kind)) for i, name, kind in rows}

    def _padded(self, path: Path) -> Path:
        with path.open("rb") as f:
            header = f.read(100)
        if not header.startswith(b"SQLite format 3\x00"):
            raise ReplayError(path, "not an SQLite database")
        page_size = int.from_bytes(header[16:18], "big")
        page_size = 65536 if page_size == 1 else page_size
        size = page_size * int.from_bytes(header[28:32], "big")
        if path.stat().st_size >= size:
            return path
        self._tmp = tempfile.TemporaryDirectory(prefix="h2o_replay_")
        copy = Path(self._tmp.name) / path.name
        shutil.copyfile(path, copy)
        os.truncate(copy, size)
        return copy

    def _connect(self) -> sqlite3.Connection:
        return sqlite3.connect(f"file:{self._db_path}?mode=ro&immutable=1", uri=True)

    def close(self) -> None:
        """Remove the padded copy, if one was made."""
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def topics(self) -> dict[str, str]:
        """Topic → type name of every topic in the ``topics`` table."""
        return dict(sorted(self.channels.values()))

    def messages(self, topics: set[str]) -> Iterator[_Raw]:
        """``(topic, type, stamp ns, message)`` by row id, then the damage.

        Raises:
            ReplayError: where the database stops being readable.
        """
        ids = {i for i, (topic, _) in self.channels.items() if topic in topics}
        db = self._connect()
        try:
            cursor = db.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id")
            for topic_id, stamp_ns, data in cursor:
                if topic_id in ids:
                    topic, kind = self.channels[topic_id]
                    msg = _decode(self.typestore.deserialize_cdr, data, topic, kind)
                    yield topic, kind, int(stamp_ns), msg
        except sqlite3.DatabaseError as exc:
            raise ReplayError(self.path, f"database damaged: {exc}") from None
        finally:
            db.close()


# --- writing ---------------------------------------------------------------------------


class BagWriter(_ClosedOnExit):
    """A rosbag2 bag written one rclpy message at a time; a context manager.

    Leaving the ``with`` block closes the bag properly even when an exception ends it,
    so a replay that fails half-way leaves a readable partial output.

    Args:
        path: the bag directory to create (must not exist).
        storage: ``"mcap"`` or ``"sqlite3"``.

    Raises:
        ReplayError: the path exists or cannot be created, or an unknown storage.
    """

    def __init__(self, path: str | os.PathLike[str], storage: Storage = "mcap") -> None:
        from rclpy.serialization import serialize_message

        self.path = Path(path)
        plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
        if storage not in plugins:
            raise ReplayError(self.path, f"unknown storage {storage!r}; use mcap or sqlite3")
        self._serialize = serialize_message
        self._typestore = jazzy_typestore()
        self._connections: dict[str, Any] = {}
        self.counts: Counter[str] = Counter()
        self._writer: Writer | None = None
        try:
            writer = Writer(self.path, version=9, storage_plugin=plugins[storage])
            writer.open()
        except Exception as exc:  # WriterError, OSError: one message naming the file
            raise ReplayError(self.path, f"cannot create bag: {_reason(exc)}") from None
        self._writer = writer

    def write(self, topic: str, msg: Any, stamp_ns: int, type_name: str | None = None) -> None:
        """Append ``msg`` on ``topic`` at bag time ``stamp_ns`` (int ns).

        Args:
            type_name: ROS 2 type name; taken from the message's class when omitted.

        Raises:
            ReplayError: the bag is closed, or the type is unknown to the Jazzy type store
                or differs from the type the topic was first written with.
        """
        if self._writer is None:
            raise ReplayError(self.path, "bag is closed")
        type_name = type_name or message_type_name(msg)
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._add_connection(topic, type_name)
        elif connection.msgtype != type_name:
            raise ReplayError(
                self.path, f"topic {topic} has type {connection.msgtype}, not {type_name}"
            )
        self._writer.write(connection, int(stamp_ns), self._serialize(msg))
        self.counts[topic] += 1

    def _add_connection(self, topic: str, type_name: str) -> Any:
        assert self._writer is not None
        if type_name not in self._typestore.types:
            raise ReplayError(
                self.path, f"topic {topic}: message type {type_name} unknown to ROS 2 Jazzy"
            )
        connection = self._writer.add_connection(topic, type_name, typestore=self._typestore)
        self._connections[topic] = connection
        return connection

    def close(self) -> None:
        """Write the index and metadata; safe to call twice."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            writer.close()


def write_bag(
    path: str | os.PathLike[str], messages: Iterable[Any], storage: Storage = "mcap"
) -> dict[str, int]:
    """Write a stream of messages into a new rosbag2 bag; returns messages per topic.

    Args:
        messages: objects with ``topic``, ``type_name``, ``stamp_ns`` and an rclpy ``msg``
            (:class:`hybrid_vo.world_messages.StreamMessage`), written as they come (the
            stream may be lazy: nothing is held in memory). Each ``stamp_ns`` is the bag
            time.
        storage: ``"mcap"`` or ``"sqlite3"``.

    Raises:
        ReplayError: as :class:`BagWriter`; the bag written so far is closed and readable.
    """
    with BagWriter(path, storage) as bag:
        for item in messages:
            bag.write(item.topic, item.msg, item.stamp_ns, item.type_name)
        return dict(bag.counts)


def message_type_name(msg: Any) -> str:
    """``package/msg/Name`` of an rclpy message instance (its class's module and name)."""
    cls = type(msg)
    package = cls.__module__.split(".")[0]
    return f"{package}/msg/{cls.__name__}"
