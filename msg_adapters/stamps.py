"""Timestamps: ``builtin_interfaces/Time`` ⇄ integer nanoseconds since the epoch.

The cores carry time as ``int`` nanoseconds (``stamp_ns``); floats lose nanoseconds after
about 104 days of epoch time, so these helpers never go through seconds as a float.
"""

from __future__ import annotations

from typing import Any

from msg_adapters.errors import AdapterError

NS_PER_S = 1_000_000_000


def stamp_ns(header_or_stamp: Any, field: str = "header.stamp") -> int:
    """Nanoseconds of a ``std_msgs/Header`` (its ``stamp``) or a ``builtin_interfaces/Time``.

    Raises:
        AdapterError: ``nanosec`` outside ``[0, 10⁹)`` or a negative time.
    """
    stamp = getattr(header_or_stamp, "stamp", header_or_stamp)
    try:
        sec = int(stamp.sec)
        nanosec = int(stamp.nanosec)
    except (AttributeError, TypeError, ValueError) as exc:
        raise AdapterError(f"{field}: not a time stamp ({exc})") from None
    if not 0 <= nanosec < NS_PER_S:
        raise AdapterError(f"{field}: nanosec {nanosec} outside [0, 1e9)")
    if sec < 0:
        raise AdapterError(f"{field}: negative time (sec {sec})")
    return sec * NS_PER_S + nanosec


def to_stamp(ns: int) -> dict[str, int]:
    """``{"sec": ..., "nanosec": ...}`` of ``ns`` nanoseconds (``Time(**to_stamp(ns))``).

    Raises:
        AdapterError: ``ns`` negative or beyond the ``int32`` seconds of ``Time``.
    """
    ns = int(ns)
    if ns < 0:
        raise AdapterError(f"stamp: negative time {ns} ns")
    sec, nanosec = divmod(ns, NS_PER_S)
    if sec >= 2**31:
        raise AdapterError(f"stamp: {ns} ns does not fit builtin_interfaces/Time (int32 sec)")
    return {"sec": sec, "nanosec": nanosec}


def fill_stamp(stamp: Any, ns: int) -> Any:
    """Set ``sec``/``nanosec`` of a ``builtin_interfaces/Time`` in place; returns it."""
    parts = to_stamp(ns)
    stamp.sec = parts["sec"]
    stamp.nanosec = parts["nanosec"]
    return stamp


def fill_header(header: Any, ns: int, frame_id: str) -> Any:
    """Set stamp and ``frame_id`` of a ``std_msgs/Header`` in place; returns it."""
    fill_stamp(header.stamp, ns)
    header.frame_id = str(frame_id)
    return header


def check_stamp_order(
    previous_ns: int | None, ns: int, *, field: str = "header.stamp", strict: bool = False
) -> None:
    """Reject time going backwards (or standing still, with ``strict``) on one stream.

    Keeping ``previous_ns`` per topic is the node's business; this names the problem.

    Raises:
        AdapterError: ``ns`` before ``previous_ns`` (or equal, with ``strict``).
    """
    if previous_ns is None:
        return
    if ns < previous_ns or (strict and ns == previous_ns):
        raise AdapterError(
            f"{field}: time went backwards ({ns} ns after {previous_ns} ns, "
            f"{(ns - previous_ns) / NS_PER_S:+.9f} s)"
        )
