"""Stereo pairing and input watchdog for ``hybrid_vo_node`` (pure Python, no ROS).

* :class:`StereoSync` pairs left and right images by stamp: exactly equal stamps, or with
  ``approx_sync`` the nearest stamps no more than ``approx_sync_max_interval`` apart (choose
  it below half the frame period). Each side keeps at most ``sync_queue_size`` unpaired
  messages; older ones are dropped and counted.
* :class:`StarvationMonitor` names the input that keeps the node waiting, e.g.
  ``"no /right/image_rect for 2.0 s while /left/image_rect arrives at 10 Hz"``. It reads
  message stamps, not the wall clock, so a replay reports the same as the live run.

Stamps are integer nanoseconds.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from h2o_slam.core.parameters import parameter
from hybrid_vo.errors import ConfigError

T = TypeVar("T")

NS_PER_S = 1_000_000_000
LEFT, RIGHT = 0, 1
SIDE_NAMES = ("left", "right")


@dataclass(frozen=True)
class SyncConfig:
    """Stereo synchronizer settings (each field's ``metadata`` describes it as the node's
    parameter: :mod:`ros_node_base.params`).

    Attributes:
        approx_sync: pair nearest stamps (True) or equal stamps only (False).
        approx_sync_max_interval: largest stamp difference of a pair (s), approx_sync only.
        sync_queue_size: unpaired messages kept per side.
    """

    approx_sync: bool = parameter(
        True, "Pair left and right images by nearest stamp (true) or by equal stamps only "
        "(false).")
    approx_sync_max_interval: float = parameter(
        0.02, "Largest left/right stamp difference of a pair, s; approx_sync only. Keep it "
        "below half the frame period (0.05 s at 10 Hz).", bounds=(0.0, 1.0))
    sync_queue_size: int = parameter(
        10, "Unpaired images kept per side before the oldest is dropped.", bounds=(1, 100))

    def __post_init__(self) -> None:
        interval = self.approx_sync_max_interval
        if not (math.isfinite(interval) and interval >= 0.0):
            raise ConfigError(f"approx_sync_max_interval must be >= 0, got {interval!r}")
        if self.sync_queue_size < 1:
            raise ConfigError(f"sync_queue_size must be >= 1, got {self.sync_queue_size!r}")

    @property
    def tolerance_ns(self) -> int:
        """Largest stamp difference of a pair, nanoseconds (0: exact)."""
        return int(round(self.approx_sync_max_interval * NS_PER_S)) if self.approx_sync else 0


@dataclass(frozen=True)
class StereoPair(Generic[T]):
    """A left and a right message that belong together; ``stamp_ns`` is the left's."""

    stamp_ns: int
    left: T
    right: T


@dataclass
class SyncStats:
    """Synchronizer counters: pairs made, messages dropped unpaired per side."""

    pairs: int = 0
    dropped: list[int] = field(default_factory=lambda: [0, 0])
    last_pair_ns: int | None = None


class StereoSync(Generic[T]):
    """Pairs left and right messages by stamp (see the module docstring).

    Args:
        config: settings; defaults when omitted.
    """

    def __init__(self, config: SyncConfig | None = None) -> None:
        self.config = config if config is not None else SyncConfig()
        self.stats = SyncStats()
        self._stamps: tuple[list[int], list[int]] = ([], [])
        self._items: tuple[list[T], list[T]] = ([], [])

    def add(self, side: int, stamp_ns: int, item: T) -> StereoPair[T] | None:
        """Offer a message from ``side`` (:data:`LEFT` or :data:`RIGHT`); returns the pair
        it completes, if any. Messages older than a pair, on either side, are dropped."""
        other = 1 - side
        match = self._nearest(other, stamp_ns)
        if match is None:
            self._insert(side, stamp_ns, item)
            return None
        partner, partner_ns = self._items[other][match], self._stamps[other][match]
        self._drop_through(other, match)
        self._drop_before(side, stamp_ns)
        left, right = (item, partner) if side == LEFT else (partner, item)
        stamp = stamp_ns if side == LEFT else partner_ns
        self.stats.pairs += 1
        self.stats.last_pair_ns = stamp
        return StereoPair(stamp, left, right)

    def clear(self) -> None:
        """Forget every queued message (counters are kept)."""
        for side in (LEFT, RIGHT):
            self._stamps[side].clear()
            self._items[side].clear()

    def queued(self, side: int) -> int:
        """Unpaired messages waiting on ``side``."""
        return len(self._stamps[side])

    def _nearest(self, side: int, stamp_ns: int) -> int | None:
        stamps = self._stamps[side]
        i = bisect.bisect_left(stamps, stamp_ns)
        best = min(
            (j for j in (i - 1, i) if 0 <= j < len(stamps)),
            key=lambda j: abs(stamps[j] - stamp_ns),
            default=None,
        )
        if best is None or abs(stamps[best] - stamp_ns) > self.config.tolerance_ns:
            return None
        return best

    def _insert(self, side: int, stamp_ns: int, item: T) -> None:
        stamps, items = self._stamps[side], self._items[side]
        i = bisect.bisect_right(stamps, stamp_ns)
        stamps.insert(i, stamp_ns)
        items.insert(i, item)
        excess = len(stamps) - self.config.sync_queue_size
        if excess > 0:
            del stamps[:excess]
            del items[:excess]
            self.stats.dropped[side] += excess

    def _drop_through(self, side: int, index: int) -> None:
        """Remove entries ``0..index``; all but the paired last one count as dropped."""
        del self._stamps[side][: index + 1]
        del self._items[side][: index + 1]
        self.stats.dropped[side] += index

    def _drop_before(self, side: int, stamp_ns: int) -> None:
        n = bisect.bisect_left(self._stamps[side], stamp_ns)
        del self._stamps[side][:n]
        del self._items[side][:n]
        self.stats.dropped[side] += n


class StarvationMonitor:
    """Tells which watched input has gone quiet while others still arrive.

    Args:
        timeout_s: an input is starving when its latest stamp is this much older than the
            newest stamp of any watched input.
        rate_window: stamps per input used to estimate its rate.
    """

    def __init__(self, timeout_s: float, rate_window: int = 20) -> None:
        if not (math.isfinite(timeout_s) and timeout_s > 0.0):
            raise ConfigError(f"starvation timeout must be > 0, got {timeout_s!r}")
        self.timeout_ns = int(timeout_s * NS_PER_S)
        self._window = rate_window
        self._stamps: dict[str, deque[int]] = {}
        self._once: dict[str, bool] = {}
        self._partner: dict[str, str | None] = {}
        self._first_ns: int | None = None
        self._newest_ns: int | None = None

    def watch(self, topic: str, *, once: bool = False, partner: str | None = None) -> None:
        """Watch ``topic``.

        Args:
            topic: the topic name, as the warning should show it.
            once: it only starves until its first message (e.g. a camera info that a
                driver publishes a single time).
            partner: the topic to name as "still arriving" when it does (the other image
                of a stereo pair); otherwise the fastest arriving topic is named.
        """
        self._stamps.setdefault(topic, deque(maxlen=self._window))
        self._once[topic] = once
        self._partner[topic] = partner

    def note(self, topic: str, stamp_ns: int) -> None:
        """Record a message on a watched topic (others are ignored)."""
        stamps = self._stamps.get(topic)
        if stamps is None:
            return
        if not stamps or stamp_ns > stamps[-1]:
            stamps.append(stamp_ns)
        self._first_ns = stamp_ns if self._first_ns is None else min(self._first_ns, stamp_ns)
        self._newest_ns = stamp_ns if self._newest_ns is None else max(self._newest_ns, stamp_ns)

    def reset(self) -> None:
        """Forget every stamp (after a node reset or a jump back in time)."""
        for stamps in self._stamps.values():
            stamps.clear()
        self._first_ns = self._newest_ns = None

    def rate_hz(self, topic: str) -> float:
        """Arrival rate of ``topic`` from its recent stamps (0 with fewer than two)."""
        stamps = self._stamps.get(topic)
        if stamps is None or len(stamps) < 2 or stamps[-1] == stamps[0]:
            return 0.0
        return (len(stamps) - 1) * NS_PER_S / (stamps[-1] - stamps[0])

    def starving(self) -> list[str]:
        """One sentence per starving topic, naming the topic that still arrives fastest."""
        if self._newest_ns is None or self._first_ns is None:
            return []
        now = self._newest_ns
        alive = [t for t, s in self._stamps.items() if s and now - s[-1] <= self.timeout_ns]
        messages = []
        for topic, stamps in self._stamps.items():
            if stamps and self._once[topic]:
                continue
            last = stamps[-1] if stamps else self._first_ns
            if now - last <= self.timeout_ns:
                continue
            others = sorted((t for t in alive if t != topic), key=self.rate_hz, reverse=True)
            if not others:
                continue
            named = self._partner[topic] if self._partner[topic] in others else others[0]
            assert named is not None
            quiet_s = (now - last) / NS_PER_S
            messages.append(
                f"no {topic} for {quiet_s:.1f} s while {named} arrives at "
                f"{self.rate_hz(named):.0f} Hz"
            )
        return messages
