"""Damaged bags read record by record, up to the damage.

An MCAP file is read from its start (a cut file, or a recording that never closed, has
lost its index); an sqlite3 database by row id (its insertion order). Both yield
``(topic, type name, bag time ns, message)`` and raise
:class:`~h2o_slam.io.bags.ReplayError` where the file stops being readable.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import struct
import tempfile
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path
from typing import Any, BinaryIO

from rosbags.typesys import get_types_from_idl, get_types_from_msg

from h2o_slam.io.bags import (
    RawMessage,
    ReplayError,
    decode_message,
    error_reason,
    jazzy_typestore,
)

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
#: What each storage file starts with, and what it is then.
STORAGE_MAGIC = {".mcap": (_MCAP_MAGIC, "an MCAP file"),
                 ".db3": (_SQLITE_MAGIC, "an SQLite database")}


class McapScan:
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

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
        """``(topic, type, log time ns, message)`` in file order, then the damage.

        Raises:
            ReplayError: at the damage (or the missing footer) after the last message.
                A file that reads to its footer ends without error.
        """
        for channel_id, log_ns, data in self._records():
            topic, schema = self.channels[channel_id]
            if topic in topics:
                type_name = self.schemas[schema][0]
                msg = decode_message(self.typestore.deserialize_cdr, data, topic, type_name)
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
                reason = str(exc) if isinstance(exc, _Truncated) else error_reason(exc)
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


class Sqlite3Scan:
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
        if not header.startswith(_SQLITE_MAGIC):
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

    def messages(self, topics: set[str]) -> Iterator[RawMessage]:
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
                    msg = decode_message(self.typestore.deserialize_cdr, data, topic, kind)
                    yield topic, kind, int(stamp_ns), msg
        except sqlite3.DatabaseError as exc:
            raise ReplayError(self.path, f"database damaged: {exc}") from None
        finally:
            db.close()
