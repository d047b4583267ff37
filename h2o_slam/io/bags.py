"""What reading and writing bags share: the error, the type store, decoding, ``with``.

``rosbags`` reads and writes rosbag2 (sqlite3 or mcap storage), raw ``.mcap``/``.db3`` files
and ROS 1 ``.bag`` files, with the ROS 2 Jazzy type store.
"""

from __future__ import annotations

import os
from types import TracebackType
from typing import Any, Literal, Self

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from h2o_slam.core.errors import InputError

Storage = Literal["mcap", "sqlite3"]
#: The ``custom_data`` key of a rosbag2 ``metadata.yaml`` that holds the GPS datum the bag's
#: GPS fixes and ground truth are about, ``[lat_deg, lon_deg, alt_m]`` as JSON. A replay
#: gives it to h2o_node, so its map frame is the ground truth's (without it the node takes
#: the first fix, which is off by that fix's noise).
DATUM_KEY = "h2o_slam/datum"
#: ``(topic, type name, bag time ns, message)`` as read, before the role is attached.
RawMessage = tuple[str, str, int, Any]


class ReplayError(InputError):
    """A bag, topic map or trajectory file that cannot be used; names the file and reason."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


class ClosedOnExit:
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


def jazzy_typestore() -> Typestore:
    """The ROS 2 Jazzy message types known to ``rosbags``."""
    return get_typestore(Stores.ROS2_JAZZY)


def decode_message(deserialize: Any, data: bytes, topic: str, type_name: str) -> Any:
    """``deserialize(data, type_name)``, failing with the topic and type named."""
    try:
        return deserialize(data, type_name)
    except Exception as exc:  # rosbags' serde raises several kinds on bad bytes
        raise InputError(f"a {type_name} message on {topic} does not deserialize: "
                         f"{error_reason(exc)}") from None


def error_reason(exc: BaseException) -> str:
    """``exc`` as one line for an error message; the exception's type is named unless it is
    one of ours (whose message already says what was wrong)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if isinstance(exc, InputError) else f"{text} ({type(exc).__name__})"
