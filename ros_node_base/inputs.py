"""What became of every message of each input topic: received = accepted + rejected + dropped.

Both nodes keep one :class:`InputCounts` per input and report the four counts in
``/diagnostics``:

* **accepted** — taken by the subscription callback and taken in (an input held for a later
  step counts here until it is refused or discarded);
* **rejected** — refused, with a reason counted beside (bad input, or refused later);
* **dropped** — never handled: taken but discarded on purpose (while paused, an image that
  found no partner), or lost before the callback. A loss shows in up to three counts, each
  a lower bound of the same losses, so the largest is taken (never their sum):

  - the middleware's message-lost event (``message_lost``), where the RMW reports one
    (Fast DDS reports samples it knows it lost on the way, not those a full KEEP_LAST
    queue overwrote);
  - gaps in the publisher's sequence numbers (``publication_sequence_number`` of the
    message info) while exactly one publisher is matched: this counts a full queue's
    overwrites, except before the first message taken; with several publishers their
    numbers interleave and nothing is counted;
  - gaps in the stamps of a periodic input (:class:`h2o_slam.core.timing.InputHealth`),
    which also counts messages lost before they reached this node.

* **received** — the sum of the three: every message known to have reached the node.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

from rclpy.event_handler import SubscriptionEventCallbacks, UnsupportedEventTypeError
from rclpy.node import Node
from rclpy.qos import QoSProfile


@dataclass
class InputCounts:
    """The fate of one input topic's messages (module docstring)."""

    accepted: int = 0
    rejected: int = 0
    #: Taken, then dropped on purpose (paused, unpaired).
    discarded: int = 0
    #: Lost before the callback, as the RMW's message-lost event reports.
    lost_reported: int = 0
    #: Lost before the callback, by gaps in one publisher's sequence numbers.
    lost_in_sequence: int = 0
    #: Lost before the callback (or before this node), by gaps in a periodic input's stamps.
    lost_in_stamps: int = 0
    #: The last publication sequence number taken (``None``: none, or not one publisher).
    last_sequence: int | None = None

    @property
    def dropped(self) -> int:
        """Discarded, plus the largest count of lost messages."""
        return self.discarded + max(self.lost_reported, self.lost_in_sequence,
                                    self.lost_in_stamps)

    @property
    def received(self) -> int:
        """Every message known to have reached the node."""
        return self.accepted + self.rejected + self.dropped

    def values(self, prefix: str) -> dict[str, int]:
        """The four counts for ``/diagnostics``, named ``prefix`` + count."""
        return {prefix + name: getattr(self, name)
                for name in ("received", "accepted", "rejected", "dropped")}

    def move(self, to: str, count: int = 1) -> None:
        """``count`` messages counted accepted turned out otherwise: ``to`` is
        ``"rejected"`` (a held input refused later) or ``"discarded"`` (an image that found
        no partner)."""
        self.accepted -= count
        setattr(self, to, getattr(self, to) + count)

    def sequence(self, number: int | None, publishers: int) -> None:
        """A message with publication sequence number ``number`` taken while ``publishers``
        publishers were matched: the numbers skipped since the last one were lost."""
        if not number or publishers != 1:  # unsupported by the RMW, or interleaved numbers
            self.last_sequence = None
            return
        if self.last_sequence is not None and number > self.last_sequence + 1:
            self.lost_in_sequence += number - self.last_sequence - 1
        self.last_sequence = number

    def reset(self) -> None:
        """All counts back to zero."""
        for f in fields(self):
            setattr(self, f.name, f.default)


def counted_subscription(node: Node, counts: InputCounts, msg_type: Any, topic: str,
                         callback: Callable[[Any], None], qos: QoSProfile) -> Any:
    """``node.create_subscription`` whose losses before ``callback`` go to ``counts``: the
    message-lost event where the RMW offers it, and gaps in the publication sequence
    numbers."""
    subscription: Any = None

    def take(msg: Any, info: dict[str, Any]) -> None:
        counts.sequence(info.get("publication_sequence_number"),
                        subscription.get_publisher_count())
        callback(msg)

    def lost(status: Any) -> None:
        counts.lost_reported += int(status.total_count_change)

    # rclpy hands the message info to a callback of two arguments; its annotation names
    # only the one-argument form.
    with_info: Any = take
    events = SubscriptionEventCallbacks(message_lost=lost)
    try:
        subscription = node.create_subscription(msg_type, topic, with_info, qos,
                                                event_callbacks=events)
    except UnsupportedEventTypeError:  # an RMW without the event: sequence gaps only
        subscription = node.create_subscription(msg_type, topic, with_info, qos)
    return subscription
