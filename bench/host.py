"""Benchmark: how much of a callback's time this machine itself decides — the floor under every
p99 and max the other benchmarks report.

    .venv/bin/python bench/host.py [--seconds S] [--busy N] [--results FILE | --no-results]

Two measurements, each a burst of CPU work every ``PERIOD_MS`` ms (a callback's pattern):

1. **Fixed work**: the same computation (numpy products and a Python loop, about 4 ms) every
   period on an otherwise idle process. Its thread CPU time should not vary; where it does,
   the virtual CPU ran slower (a busy host core, its SMT sibling), which a budgeted callback
   sees as CPU time it did not plan. Its wall time adds the time the host did not run the
   virtual CPU (the steal counter of ``/proc/stat``).
2. **Bursts under load**: ``N`` CPU-bound processes at the same priority (``online.busy``:
   the load of ``bench/online.py --busy``) beside bursts that spin for a given CPU time.
   A burst whose wall time exceeds its CPU time by more than ``CUT_MS`` was cut: the kernel
   gave the core to another process mid-burst (Linux's EEVDF scheduler lets a task run a
   slice, 0.75 ms × (1 + log₂ CPUs), and preempts at the next scheduler tick after it).

The table goes to stdout and, unless ``--no-results``, replaces the section
``## Host (bench/host.py)`` of ``bench/RESULTS.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mapper_stream import host_steal_ticks
from online import busy
from results_md import DEFAULT_RESULTS, command, publish

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Host (bench/host.py)"
#: One burst per period, as one callback per arriving pose every 20 ms.
PERIOD_MS = 20.0
#: CPU time a fixed-work burst is calibrated to (about a 5 ms budget's planned work).
FIXED_MS = 4.0
#: CPU times of the bursts under load.
BURSTS_MS = (1.0, 2.0, 4.0)
#: A burst whose wall time exceeds its CPU time by more than this was cut.
CUT_MS = 0.5


@dataclass
class Row:
    """One measurement: wall and CPU times (ms) of its bursts, and the host's steal."""

    name: str
    wall_ms: np.ndarray
    cpu_ms: np.ndarray
    steal_ms: float


def _fixed_work(repeats: int, a: np.ndarray) -> float:
    total = 0.0
    for _ in range(repeats):
        total += float((a @ a)[0, 0])
        for i in range(200):
            total += i * 0.5
    return total


def _calibrated(a: np.ndarray) -> int:
    """Repeats of :func:`_fixed_work` that take about ``FIXED_MS`` of CPU time."""
    for _ in range(20):  # warm caches and the allocator first
        _fixed_work(1, a)
    start = time.thread_time()
    _fixed_work(20, a)
    per = (time.thread_time() - start) / 20
    return max(1, round(FIXED_MS * 1e-3 / per))


def _spinner(cpu_s: float) -> Callable[[], None]:
    """A burst that spins for ``cpu_s`` seconds of CPU time."""
    def spin() -> None:
        start = time.thread_time()
        while time.thread_time() - start < cpu_s:
            pass
    return spin


def measure(name: str, burst: Callable[[], object], seconds: float) -> Row:
    """``burst()`` once every ``PERIOD_MS`` for ``seconds``."""
    count = max(1, int(seconds * 1e3 / PERIOD_MS))
    wall, cpu = np.zeros(count), np.zeros(count)
    ticks = host_steal_ticks()
    for i in range(count):
        time.sleep(PERIOD_MS * 1e-3 * 0.8)
        c, t = time.thread_time(), time.perf_counter()
        burst()
        wall[i], cpu[i] = time.perf_counter() - t, time.thread_time() - c
    steal = 1e3 * (host_steal_ticks() - ticks) / os.sysconf("SC_CLK_TCK")
    return Row(name, 1e3 * wall, 1e3 * cpu, steal)


def run(seconds: float, busy_count: int) -> list[Row]:
    """The fixed-work row, then a row per burst length under ``busy_count`` processes."""
    a = np.random.default_rng(0).random((200, 200))
    repeats = _calibrated(a)
    rows = [measure(f"fixed work, idle ({repeats} repeats)",
                    lambda: _fixed_work(repeats, a), seconds)]
    with busy(busy_count):
        time.sleep(0.5)  # the load running before the first burst
        for ms in BURSTS_MS:
            rows.append(measure(f"{ms:g} ms bursts, {busy_count} busy",
                                _spinner(ms * 1e-3), seconds))
    return rows


def _q(x: np.ndarray, q: float) -> str:
    return f"{np.percentile(x, q):.2f}"


def render(rows: list[Row], seconds: float, busy_count: int) -> str:
    """The section: one table row per measurement."""
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    head = ("| bursts | count | CPU p50 / p99 / p99.9 / max (ms) | CPU max / p50 | wall p50 / "
            "p99 / p99.9 / max (ms) | cut (wall > CPU + 0.5 ms) | host steal (ms) |\n"
            "| --- | --- | --- | --- | --- | --- | --- |")
    lines = [head]
    for r in rows:
        cut = float(np.mean(r.wall_ms > r.cpu_ms + CUT_MS)) * 100
        lines.append(
            f"| {r.name} | {len(r.wall_ms)} | {_q(r.cpu_ms, 50)} / {_q(r.cpu_ms, 99)} / "
            f"{_q(r.cpu_ms, 99.9)} / {r.cpu_ms.max():.2f} | "
            f"{r.cpu_ms.max() / np.median(r.cpu_ms):.2f} | {_q(r.wall_ms, 50)} / "
            f"{_q(r.wall_ms, 99)} / {_q(r.wall_ms, 99.9)} / {r.wall_ms.max():.2f} | "
            f"{cut:.2f} % | {r.steal_ms:.0f} |")
    return (f"{SECTION}\n\nCommand (from the repo root): `{command(REPO)}`\n\nDate: {when}; "
            f"{seconds:g} s per row, one burst every {PERIOD_MS:g} ms, {busy_count} "
            f"CPU-bound processes at the same priority beside the bursts of the last rows.\n\n"
            + "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, measure, publish."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, metavar="S",
                        help="length of each measurement (default 60)")
    parser.add_argument("--busy", type=int, default=2, metavar="N",
                        help="CPU-bound processes beside the bursts under load (default 2)")
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS,
                        help=f"markdown file to update (default {DEFAULT_RESULTS})")
    parser.add_argument("--no-results", action="store_true",
                        help="print the section only; do not touch the results file")
    args = parser.parse_args(argv)
    if not args.seconds > 0.0 or args.busy < 0:
        parser.error("--seconds must be positive and --busy non-negative")
    rows = run(args.seconds, args.busy)
    publish(render(rows, args.seconds, args.busy), None if args.no_results else args.results,
            SECTION)
    return 0


if __name__ == "__main__":
    sys.exit(main())
