"""Reading recordings for replay, in bag time, up to any damage.

Messages come back deserialized by ``rosbags``, which :mod:`msg_adapters` reads like rclpy
messages. Replay order is **bag time**: the time each message was recorded (its receive or
log time, int nanoseconds), which is the order a live robot saw them in. Header stamps are
reported beside it and checked per topic: a header stamp going backwards is counted in
:class:`BagStats` and the message is still delivered, so the node that receives it is the
one that rejects and counts it (doc/nodes.md, bad input).

A damaged bag is read up to the damage: :meth:`BagReader.messages` yields every message
it can, then raises :class:`~h2o_slam.io.bags.ReplayError`, so the caller still writes out
what it processed. When ``rosbags`` cannot open a bag, the reader falls back to its storage
file alone (an unusable ``metadata.yaml``), then to reading that file record by record
(:mod:`h2o_slam.io.bag_salvage`). ``BagStats.salvaged`` says why. Reading needs no ROS.
"""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys.store import Typestore

from h2o_slam.io.bag_salvage import STORAGE_MAGIC, McapScan, Sqlite3Scan
from h2o_slam.io.bags import (
    DATUM_KEY,
    ClosedOnExit,
    RawMessage,
    ReplayError,
    decode_message,
    error_reason,
    jazzy_typestore,
)
from h2o_slam.io.topic_map import DEFAULT_TOPICS, REQUIRED_ROLES, ROLE_TYPES, ROLES


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
        datum: the GPS datum ``[lat_deg, lon_deg, alt_m]`` the bag states
            (:data:`~h2o_slam.io.bags.DATUM_KEY` in its metadata's ``custom_data``); ``None``
            when it states none.
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
    datum: list[float] | None = None

    def shortfall(self) -> dict[str, tuple[int, int]]:
        """Mapped topics whose delivered count differs from the declared one:
        topic → (declared, read)."""
        return {topic: (self.declared[topic], self.read[topic])
                for topic in sorted(set(self.roles.values()))
                if topic in self.declared and self.declared[topic] != self.read[topic]}


class BagReader(ClosedOnExit):
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
        self._salvage: McapScan | Sqlite3Scan | None = None
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
        if isinstance(self._salvage, Sqlite3Scan):
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
        self.stats.datum = _datum(self.path)  # first: a bad one leaves nothing open
        try:
            self._reader = _any_reader(self.path)
        except Exception as exc:  # rosbags fails in many ways on damaged files
            self._open_damaged(error_reason(exc))
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
            self._salvage = McapScan(data) if data.suffix == ".mcap" else Sqlite3Scan(data)
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

    def _raw(self, by_topic: Mapping[str, str]) -> Iterator[RawMessage]:
        if self._salvage is not None:
            source = self._salvage.messages(set(by_topic))
        else:
            source = self._rosbags_messages(by_topic)
        while True:
            try:
                item = next(source, None)
            except Exception as exc:  # damage shows up as any error deep in rosbags
                reason = exc.reason if isinstance(exc, ReplayError) else error_reason(exc)
                delivered = sum(self.stats.counts.values())
                self.stats.error = f"stopped after {delivered} messages: {reason}"
                raise ReplayError(self.path, self.stats.error) from None
            if item is None:
                return
            yield item

    def _rosbags_messages(self, by_topic: Mapping[str, str]) -> Iterator[RawMessage]:
        reader = self._reader
        assert reader is not None
        connections = [c for c in reader.connections if c.topic in by_topic]
        if not connections:
            return
        for connection, stamp_ns, raw in reader.messages(connections=connections):
            topic, type_name = connection.topic, connection.msgtype
            msg = decode_message(reader.deserialize, raw, topic, type_name)
            yield topic, type_name, stamp_ns, msg


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


def bag_problem(path: Path) -> str | None:
    """Why ``path`` is surely no bag, as ``PATH: reason`` naming the file at fault; ``None``
    when :class:`BagReader` should try it.

    Cheap, so that a command can refuse before it creates anything: a path holding one
    ``.mcap``/``.db3`` storage file is left to the reader (which reads the storage alone
    when ``metadata.yaml`` is unusable, and a damaged file record by record) unless the file
    is not even its format from the first byte; only what has none is opened here, and
    refused if ``rosbags`` cannot open it.
    """
    meta = path / "metadata.yaml"
    if not path.exists():
        return f"{path}: no such file or folder"
    if path.is_dir() and not any(path.iterdir()):
        return f"{meta}: no such file (the bag folder is empty)"
    data = _storage_file(path)
    if data is not None:
        return _storage_problem(data)
    if path.is_file() and path.suffix != ".bag":
        return (f"{path}: not a bag (expected a rosbag2 folder, or an .mcap, .db3 or ROS 1 "
                ".bag file)")
    if path.is_dir() and not meta.is_file():
        return f"{path}: not a bag (no metadata.yaml and no .mcap or .db3 file)"
    try:
        _any_reader(path).close()
    except Exception as exc:  # rosbags fails in many ways on damaged files
        if path.is_file():
            return f"{path}: cannot open bag: {error_reason(exc)}"
        return f"{meta}: {_metadata_problem(meta, exc)}, and no .mcap or .db3 file to read " \
            "without it"
    return None


def _storage_problem(data: Path) -> str | None:
    """Why the storage file ``data`` has nothing to salvage (``PATH: reason``), or ``None``."""
    magic, kind = STORAGE_MAGIC[data.suffix]
    try:
        with data.open("rb") as f:
            start = f.read(len(magic))
    except OSError as err:
        return f"{data}: cannot be read ({err.strerror or err})"
    if start != magic:
        return f"{data}: not {kind} (it does not start as one; nothing to read or salvage)"
    return None


def _metadata_problem(meta: Path, exc: Exception) -> str:
    """What is wrong with a ``metadata.yaml`` that ``rosbags`` refused with ``exc``."""
    try:
        data = yaml.safe_load(meta.read_text(encoding="utf-8"))
    except yaml.MarkedYAMLError as err:
        line = f"line {err.problem_mark.line + 1}: " if err.problem_mark else ""
        return f"not YAML ({line}{err.problem or err.context})"
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        return f"unreadable ({error_reason(err)})"
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        return "not rosbag2 metadata (no rosbag2_bagfile_information)"
    files = info.get("relative_file_paths")
    if not isinstance(files, list) or not files:
        return "not rosbag2 metadata (no relative_file_paths)"
    missing = [str(name) for name in files if not (meta.parent / str(name)).exists()]
    if missing:
        return f"lists {', '.join(missing)}, which {'is' if len(missing) == 1 else 'are'} missing"
    return f"unusable ({error_reason(exc)})"


def _missing(role: str, topic: str | None, present: Mapping[str, str]) -> str:
    have = ", ".join(f"{name} ({kind})" for name, kind in present.items()) or "none"
    if topic is None:
        return f"required role {role} has no topic mapped; topics in the bag: {have}"
    return f"no topic {topic} for {role} in the bag; topics in the bag: {have}"


def _header_ns(msg: Any) -> int | None:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return None
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _declared_counts(path: Path) -> dict[str, int]:
    """Messages per topic a rosbag2 folder's ``metadata.yaml`` declares ({} if unreadable)."""
    try:
        meta = yaml.safe_load((path / "metadata.yaml").read_text(encoding="utf-8"))
        topics = meta["rosbag2_bagfile_information"]["topics_with_message_count"]
        return {str(t["topic_metadata"]["name"]): int(t["message_count"]) for t in topics}
    except Exception:  # no folder, no file, or not the rosbag2 layout: nothing declared
        return {}


def _datum(path: Path) -> list[float] | None:
    """The datum a rosbag2 folder's ``metadata.yaml`` states (``None``: none stated, or no
    readable metadata, whose absence the reader reports on its own).

    Raises:
        ReplayError: a datum is stated but is not three finite numbers.
    """
    meta = path / "metadata.yaml"
    try:
        info = yaml.safe_load(meta.read_text(encoding="utf-8"))["rosbag2_bagfile_information"]
        text = (info.get("custom_data") or {})[DATUM_KEY]
    except Exception:  # no folder, no file, not the rosbag2 layout, or no datum stated
        return None
    try:
        datum = [float(v) for v in json.loads(text)]
    except (TypeError, ValueError):
        datum = []
    if len(datum) != 3 or not all(math.isfinite(v) for v in datum):
        raise ReplayError(meta, f"custom_data {DATUM_KEY}: expected [lat_deg, lon_deg, "
                                f"alt_m] as JSON, got {text!r}")
    return datum


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
