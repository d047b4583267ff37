"""The callbacks' thread under a real-time scheduling policy, for a node sharing its computer
with CPU-bound work (perception) at the default priority.

Under Linux's default scheduler (EEVDF) a callback beside such work is cut once it has run
its slice (0.75 ms × (1 + log₂ CPUs)) and waits at least a scheduler tick (4 ms at 250 Hz)
for its core back, whatever its nice value: ``bench/online.py --busy 2`` measured callback
p99 of 7.5-8.6 ms at a 5 ms budget at nice 0 and -5, and 4.2-4.5 ms with the callbacks'
thread under ``SCHED_FIFO`` (bench/RESULTS.md, Online, "Under load").
"""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass
class Realtime:
    """What :func:`fifo_callbacks` did, and what to restore."""

    applied: bool
    words: str  # for the start-up line and /diagnostics
    saved: tuple[int, int] | None = None  # the thread's (policy, priority) before


def fifo_callbacks(priority: int) -> Realtime:
    """Run the calling thread (the executor's, which runs every callback) under ``SCHED_FIFO``
    at ``priority`` (1-99; 0: leave it as it is). Threads it starts later inherit the policy;
    processes it starts (the exact solver's worker) do not (``SCHED_RESET_ON_FORK``), and the
    threads that exist already (DDS's) keep theirs. Refused without ``CAP_SYS_NICE`` or an
    ``rtprio`` limit: then nothing changes and the words say why."""
    if not priority:
        return Realtime(False, "off")
    if not hasattr(os, "SCHED_FIFO"):
        return Realtime(False, f"SCHED_FIFO {priority} refused: not on this system")
    saved = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK,
                              os.sched_param(priority))
    except OSError as err:
        return Realtime(False, f"SCHED_FIFO {priority} refused ({err.strerror}: needs "
                               f"CAP_SYS_NICE or an rtprio limit)")
    return Realtime(True, f"SCHED_FIFO {priority}", saved)


def restore(state: Realtime) -> None:
    """Put the thread back under the policy it had before :func:`fifo_callbacks`."""
    if state.saved is None:
        return
    policy, priority = state.saved
    try:
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except OSError:  # a lower priority needs no privilege; nothing else to do
        pass
