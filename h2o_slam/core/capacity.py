"""Arrays that grow by doubling, and growing them ahead of need in a step's spare time.

The solver keeps its nodes and edges in preallocated arrays whose capacity doubles when
full: appends cost O(1) on average, but the append that finds an array full copies all of
it. On city10000 that copy, with the page faults of the fresh memory, was one callback of
22 ms at node 8,193 (5 ms budget). A budgeted step with time to spare therefore grows, one
array at a time, each array that is three quarters full (:class:`GrowAhead`), so that an
append finds room. Each array is grown whole or not at all, and an owner's arrays may
differ in capacity meanwhile: whoever appends checks each array it writes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

#: A growable array as ``(owner, attribute name, fill of new rows)``.
ArrayRef = tuple[Any, str, Any]


@dataclass(frozen=True)
class Growable:
    """One growable array: ``getattr(owner, name)``, rows beyond the old end set to
    ``fill``; ``used`` is how many rows are in use (the owner's count of nodes or edges)."""

    owner: Any
    name: str
    fill: Any
    used: int


def grow(owner: Any, name: str, capacity: int, fill: Any) -> int:
    """Replace ``owner.name`` by a copy with ``capacity`` rows (when it has fewer); the new
    rows are ``fill``. Returns the bytes allocated (0 when it was large enough)."""
    old = getattr(owner, name)
    if len(old) >= capacity:
        return 0
    new = np.empty((capacity, *old.shape[1:]), dtype=old.dtype)
    new[: len(old)] = old
    new[len(old):] = fill
    setattr(owner, name, new)
    return new.nbytes


def ensure(arrays: Iterable[ArrayRef], size: int) -> None:
    """Room for ``size`` rows in each ``(owner, name, fill)``: those with fewer grow to
    twice the smallest of them (or to ``size``), so that appends stay O(1) on average."""
    short = [item for item in arrays if len(getattr(item[0], item[1])) < size]
    if not short:
        return
    capacity = max(size, 2 * min(len(getattr(owner, name)) for owner, name, _ in short))
    for owner, name, fill in short:
        grow(owner, name, capacity, fill)


class GrowAhead:
    """Doubles arrays that are three quarters full while the time predicted for the copy
    fits before a deadline; learns the time per byte from the copies it makes."""

    #: Seconds per byte allocated before any copy was timed: 1 GB/s, pessimistic for a
    #: copy into warm memory, optimistic for fresh pages of a virtual machine (50 ms for
    #: 19 MB measured) — the first copy's time corrects it.
    FIRST_RATE = 1e-9
    #: Predictions are this many times the learnt rate.
    MARGIN = 2.0

    def __init__(self) -> None:
        self.rate = self.FIRST_RATE
        self.grown = 0  # arrays grown ahead of need
        # No array is three quarters full before the rows in use add up to this many: the
        # step skips building the list of arrays (~0.1 ms) until then.
        self._next_total = 0

    def due(self, total: int) -> bool:
        """Whether an array may be three quarters full, ``total`` being the rows in use
        summed over the kinds of row (nodes + edges): each kind grows by at most that."""
        return total >= self._next_total

    def run(self, arrays: Iterable[Growable], total: int, deadline: float,
            clock: Callable[[], float]) -> bool:
        """Grow the arrays that need it, in order, while each fits before ``deadline`` (on
        ``clock``); False when one did not fit (the rest wait for a later step). ``total``
        is the rows in use as :meth:`due` counts them."""
        slack = math.inf  # rows to add before the first array is three quarters full
        for item in arrays:
            old = getattr(item.owner, item.name)
            room = _three_quarters(len(old)) - item.used
            if room > 0:
                slack = min(slack, room)
                continue
            capacity = max(2 * len(old), 1)
            if clock() + self.MARGIN * self.rate * capacity * old[:1].nbytes > deadline:
                self._next_total = 0
                return False
            start = clock()
            nbytes = grow(item.owner, item.name, capacity, item.fill)
            seconds = clock() - start
            if nbytes:
                # Quick to rise, slow to fall: one slow copy (fresh pages) is the one to
                # plan for.
                observed = seconds / nbytes
                self.rate = max(observed, 0.9 * self.rate + 0.1 * observed)
            self.grown += 1
            slack = min(slack, _three_quarters(capacity) - item.used)
        self._next_total = total + (0 if slack == math.inf else int(slack))
        return True


def _three_quarters(capacity: int) -> int:
    """The fewest rows in use at which an array of ``capacity`` rows is grown ahead."""
    return -(-3 * capacity // 4)
