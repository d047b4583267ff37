"""Writing bags: rclpy messages into a rosbag2 bag, one message at a time.

Messages are serialized with ``rclpy.serialization`` and each topic is registered with its
type from the ROS 2 Jazzy type store. rclpy is imported by the writer alone, when a bag is
opened, so nothing else in :mod:`h2o_slam.io` needs ROS.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from rosbags.rosbag2 import StoragePlugin, Writer

from h2o_slam.io.bags import ClosedOnExit, ReplayError, Storage, error_reason, jazzy_typestore


class BagWriter(ClosedOnExit):
    """A rosbag2 bag written one rclpy message at a time; a context manager.

    Leaving the ``with`` block closes the bag properly even when an exception ends it,
    so a replay that fails half-way leaves a readable partial output.

    Args:
        path: the bag directory to create (must not exist).
        storage: ``"mcap"`` or ``"sqlite3"``.
        custom_data: key → text for ``metadata.yaml``'s ``custom_data`` (e.g.
            :data:`~h2o_slam.io.bags.DATUM_KEY`).

    Raises:
        ReplayError: the path exists or cannot be created, or an unknown storage.
    """

    def __init__(self, path: str | os.PathLike[str], storage: Storage = "mcap",
                 custom_data: Mapping[str, str] | None = None) -> None:
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
            for key, value in (custom_data or {}).items():
                writer.set_custom_data(key, value)
            writer.open()
        except Exception as exc:  # WriterError, OSError: one message naming the file
            raise ReplayError(self.path, f"cannot create bag: {error_reason(exc)}") from None
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
    path: str | os.PathLike[str], messages: Iterable[Any], storage: Storage = "mcap",
    custom_data: Mapping[str, str] | None = None,
) -> dict[str, int]:
    """Write a stream of messages into a new rosbag2 bag; returns messages per topic.

    Args:
        messages: objects with ``topic``, ``type_name``, ``stamp_ns`` and an rclpy ``msg``
            (:class:`hybrid_vo.sim.messages.StreamMessage`), written as they come (the
            stream may be lazy: nothing is held in memory). Each ``stamp_ns`` is the bag
            time.
        storage: ``"mcap"`` or ``"sqlite3"``.
        custom_data: as :class:`BagWriter`.

    Raises:
        ReplayError: as :class:`BagWriter`; the bag written so far is closed and readable.
    """
    with BagWriter(path, storage, custom_data) as bag:
        for item in messages:
            bag.write(item.topic, item.msg, item.stamp_ns, item.type_name)
        return dict(bag.counts)


def message_type_name(msg: Any) -> str:
    """``package/msg/Name`` of an rclpy message instance (its class's module and name)."""
    cls = type(msg)
    package = cls.__module__.split(".")[0]
    return f"{package}/msg/{cls.__name__}"
