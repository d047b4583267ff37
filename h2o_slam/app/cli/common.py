"""What the three commands share: one-line argument errors, output checks, progress lines.

The convention of ``h2o-solve``, ``h2o-replay`` and ``h2o-demo``: a usage error (an
argument out of range, options that do not go together, an output that cannot be written)
exits 2, an input or data error (a file that cannot be read, a bag or graph that cannot be
used) exits 1; either prints one line on stderr, ``PROG: ...``, naming the argument or file.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn, TextIO

#: Exit codes of the commands.
EXIT_INPUT = 1
EXIT_USAGE = 2


class OneLineParser(argparse.ArgumentParser):
    """argparse with errors on one line (no usage block): ``PROG: error: ...``, exit 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``message`` on one line and exit 2."""
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def usage_error(prog: str, problem: str) -> int:
    """Print a usage problem found after parsing (``PROG: problem``); returns 2."""
    print(f"{prog}: {problem}", file=sys.stderr)
    return EXIT_USAGE


def number(low: float, high: float, low_open: bool = False,
           infinite: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite float in ``[low, high]`` (``(low, high]`` if low_open);
    with ``infinite``, ``inf`` too (an upper bound of ``inf`` meaning no limit)."""
    high_open = math.isinf(high) and not infinite

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        inside = (value > low if low_open else value >= low) and (
            value < high if high_open else value <= high)
        if not (inside and (math.isfinite(value) or infinite)):
            bracket = "(" if low_open else "["
            close = ")" if high_open else "]"
            raise argparse.ArgumentTypeError(
                f"expected a number in {bracket}{low:g}, {high:g}{close}, got {text!r}")
        return value
    return parse


def integer(low: int) -> Callable[[str], int]:
    """An argparse type: an integer of at least ``low``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
        return value
    return parse


def unwritable_file(option: str, path: Path | None) -> str | None:
    """Why the file ``path`` (given as ``option``) cannot be written, or ``None``."""
    if path is None:
        return None
    folder = path.parent
    if path.is_dir():
        return f"{option} {path}: is a folder, not a file"
    if not folder.is_dir():
        return f"{option} {path}: folder {folder} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK) or (path.exists()
                                                    and not os.access(path, os.W_OK)):
        return f"{option} {path}: not writable"
    return None


def unusable_folder(option: str, path: Path | None) -> str | None:
    """Why ``path`` (given as ``option``) cannot be a new or empty output folder, or
    ``None``."""
    if path is None:
        return None
    if path.exists() and not path.is_dir():
        return f"{option} {path}: is a file, not a folder"
    if path.is_dir():
        if any(path.iterdir()):
            return f"{option} {path}: output folder exists and is not empty"
        writable = os.access(path, os.W_OK | os.X_OK)
    else:
        existing = next(p for p in path.absolute().parents if p.exists())
        if not existing.is_dir():
            return f"{option} {path}: {existing} is a file, not a folder"
        writable = os.access(existing, os.W_OK | os.X_OK)
    return None if writable else f"{option} {path}: not writable"


def missing_folders(path: Path) -> list[Path]:
    """``path`` and its ancestors that do not exist yet, deepest first."""
    return [p for p in (path, *path.parents) if not p.exists()]


def remove_if_empty(folders: list[Path]) -> None:
    """Remove each of ``folders`` (deepest first) that exists and is empty: what a failed
    run created and left unused."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty, or already gone: keep what is there
            return


class ProgressLine:
    """A line on stderr, once a second, for work that takes more than a second.

    The work sets :attr:`status` as it goes; a daemon thread prints ``PROG: status (N s)``
    (rewritten in place on a terminal). Use as a context manager; ``enabled=False`` prints
    nothing. :meth:`start` starts the thread ahead of the work (a thread's start costs
    0.1-0.4 ms, a third of a small graph's solve): it prints once the block has run a
    period, and :meth:`close` ends it where the block is never entered.
    """

    def __init__(self, prog: str, enabled: bool = True, period_s: float = 1.0,
                 stream: TextIO | None = None) -> None:
        self.prog = prog
        self.status = "working"
        self.period_s = period_s
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.lines = 0
        self._stop = threading.Event()
        self._entered = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._start = 0.0
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())

    def start(self) -> ProgressLine:
        """Start the printing thread now; it waits for the block to be entered."""
        if self.enabled and not self._thread.is_alive() and not self._stop.is_set():
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread (and end the line on a terminal)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        if self.lines and self._tty:
            self.stream.write("\n")
            self.stream.flush()
            self.lines = 0

    def __enter__(self) -> ProgressLine:
        # A flag, not an event: waking the thread here would take the interpreter's lock
        # from the work as it starts.
        self._start = time.perf_counter()
        self._entered = True
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _until_next(self) -> float:
        """Seconds to the next whole period of the block (a tenth of a second's polls
        before it is entered)."""
        if not self._entered:
            return min(self.period_s, 0.1)
        elapsed = time.perf_counter() - self._start
        return (int(elapsed / self.period_s) + 1) * self.period_s - elapsed

    def _run(self) -> None:
        while not self._stop.wait(self._until_next()):
            elapsed = time.perf_counter() - self._start
            if not self._entered or elapsed < self.period_s:
                continue
            text = f"{self.prog}: {self.status} ({elapsed:.0f} s)"
            self.stream.write(f"\r{text}\x1b[K" if self._tty else text + "\n")
            self.stream.flush()
            self.lines += 1
