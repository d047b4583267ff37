"""What ``h2o-replay`` and ``h2o-demo`` write besides bags: TUM trajectories, ATE and
final error, the summary JSON, PNG plots, and a progress bar on a terminal.

Everything here takes plain arrays and dicts, so the replay can call it with whatever it
collected, and nothing here needs ROS. Trajectories are planar or 3-D: stamps ``(N,)``
int ns, positions ``(N, 3)`` m (``(N, 2)`` is padded with z = 0), orientations as yaw
``(N,)`` rad or rotation matrices ``(N, 3, 3)``, all in one fixed world frame.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from h2o_slam.geometry import matrix_to_quat, quat_to_matrix, yaw_to_matrix
from h2o_slam.replay_io import ReplayError

NS_PER_S = 1_000_000_000

#: First line of every TUM file written here; evo and most tools skip ``#`` lines.
TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"


# --- TUM trajectories ------------------------------------------------------------------


def write_tum(
    path: str | os.PathLike[str],
    stamps_ns: Any,
    positions_m: Any,
    *,
    yaw_rad: Any = None,
    rotations: Any = None,
) -> Path:
    """Write a trajectory as TUM text: ``t tx ty tz qx qy qz qw`` per line, ``t`` in s.

    The stamp is written as exact decimal seconds (``sec.nanosec``, nine digits), so the
    integer nanoseconds read back unchanged; the other numbers at round-trip precision
    (``repr``), so the float64 values read back bit for bit (DESIGN §2).

    Args:
        stamps_ns: ``(N,)`` int ns.
        positions_m: ``(N, 3)`` or ``(N, 2)`` (z = 0).
        yaw_rad: ``(N,)`` headings about z; or give ``rotations``.
        rotations: ``(N, 3, 3)`` rotation matrices (body to world).

    Returns:
        The path written.

    Raises:
        ReplayError: shapes that do not agree, non-finite values, negative stamps, or
            both or neither of ``yaw_rad`` and ``rotations``.
    """
    stamps, xyz, quats = _tum_arrays(path, stamps_ns, positions_m, yaw_rad, rotations)
    lines = [TUM_HEADER]
    for stamp, p, q in zip(stamps, xyz, quats, strict=True):
        sec, nanosec = divmod(int(stamp), NS_PER_S)
        numbers = " ".join(repr(float(v)) for v in (*p, *q))
        lines.append(f"{sec}.{nanosec:09d} {numbers}")
    out = Path(path)
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return out


def _tum_arrays(
    path: str | os.PathLike[str], stamps_ns: Any, positions_m: Any, yaw_rad: Any, rotations: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    xyz = np.asarray(positions_m, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] not in (2, 3) or len(xyz) != len(stamps):
        raise ReplayError(path, f"positions must be ({len(stamps)}, 2 or 3), got {xyz.shape}")
    if xyz.shape[1] == 2:
        xyz = np.hstack([xyz, np.zeros((len(xyz), 1))])
    if (yaw_rad is None) == (rotations is None):
        raise ReplayError(path, "give the orientation as exactly one of yaw_rad or rotations")
    if yaw_rad is not None:
        R = yaw_to_matrix(np.asarray(yaw_rad, dtype=float).reshape(-1))
    else:
        R = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    if len(R) != len(stamps):
        raise ReplayError(path, f"{len(R)} orientations for {len(stamps)} stamps")
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(R))) or np.any(stamps < 0):
        raise ReplayError(path, "trajectory has non-finite values or negative stamps")
    quats = matrix_to_quat(R) if len(R) else np.zeros((0, 4))
    return stamps, xyz, quats


def read_tum(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a TUM trajectory: stamps ``(N,)`` int ns, positions ``(N, 3)``, quaternions
    ``(N, 4)`` as ``x, y, z, w``.

    Lines starting with ``#`` and blank lines are skipped. Stamps in decimal seconds are
    converted exactly (no float rounding) to int ns; digits past the ns are dropped.

    Raises:
        ReplayError: unreadable file, or a line without eight numbers (names the line).
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ReplayError(path, f"cannot read: {exc}") from None
    stamps: list[int] = []
    rows: list[list[float]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        fields = line.split()
        try:
            if len(fields) != 8:
                raise ValueError(f"expected 8 fields, found {len(fields)}")
            stamps.append(seconds_to_ns(fields[0]))
            rows.append([float(v) for v in fields[1:]])
        except ValueError as exc:
            raise ReplayError(path, f"line {number}: {exc}") from None
    data = np.array(rows, dtype=float).reshape(-1, 7)
    return np.array(stamps, dtype=np.int64), data[:, :3], data[:, 3:]


def seconds_to_ns(text: str) -> int:
    """Exact int ns of decimal seconds such as ``1700000000.000000042`` or ``1.5e-3``.

    Raises:
        ValueError: not a finite number.
    """
    whole, dot, frac = text.partition(".")
    if whole.lstrip("+-").isdigit() and (not dot or frac.isdigit()):
        sign = -1 if whole.startswith("-") else 1
        nanos = int((frac + "000000000")[:9]) if dot else 0
        return sign * (abs(int(whole)) * NS_PER_S + nanos)
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"stamp {text!r} is not finite")
    return round(value * NS_PER_S)


def yaw_of_quaternions(quats_xyzw: Any) -> np.ndarray:
    """Yaw (rad) of quaternions ``(N, 4)`` ``x, y, z, w``: the heading of each body x axis."""
    R = quat_to_matrix(np.asarray(quats_xyzw, dtype=float).reshape(-1, 4))
    return np.asarray(np.arctan2(R[:, 1, 0], R[:, 0, 0]))


# --- accuracy --------------------------------------------------------------------------


def align_planar(est_xy: Any, truth_xy: Any) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``(2, 2)`` and translation ``(2,)`` that best map ``est`` onto ``truth``.

    Least squares over corresponding points (Umeyama/Horn without scale): minimizes
    ``Σ ‖R eᵢ + t − gᵢ‖²``. Points are ``(N, 2)`` or wider (only x, y are used).

    Raises:
        ValueError: fewer than two points, or shapes that do not match.
    """
    a = np.asarray(est_xy, dtype=float)[:, :2]
    b = np.asarray(truth_xy, dtype=float)[:, :2]
    if a.shape != b.shape or len(a) < 2:
        raise ValueError(f"alignment needs two or more matching points, got {a.shape}, {b.shape}")
    mean_a, mean_b = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - mean_a).T @ (b - mean_b))
    # The sign fix keeps a proper rotation when the best orthogonal map is a reflection.
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    R = vt.T @ np.diag([1.0, d]) @ u.T
    return R, mean_b - R @ mean_a


def ate_m(est_xy: Any, truth_xy: Any) -> float:
    """Absolute trajectory error: position RMSE (m) after :func:`align_planar`."""
    a = np.asarray(est_xy, dtype=float)[:, :2]
    b = np.asarray(truth_xy, dtype=float)[:, :2]
    R, t = align_planar(a, b)
    residual = a @ R.T + t - b
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def final_error_m(est_xy: Any, truth_xy: Any) -> float:
    """Distance (m) between the last estimated and the last true position, unaligned.

    Both trajectories start in the same frame (the robot's start), which is what makes the
    end point's drift meaningful without alignment.
    """
    a = np.asarray(est_xy, dtype=float)
    b = np.asarray(truth_xy, dtype=float)
    return float(np.hypot(*(a[-1, :2] - b[-1, :2])))


def match_stamps(stamps_ns: Any, truth_stamps_ns: Any, tolerance_ns: int) -> tuple[Any, Any]:
    """Index pairs ``(i, j)`` of each stamp and the nearest truth stamp within tolerance.

    Args:
        stamps_ns: ``(N,)`` int ns of an estimate.
        truth_stamps_ns: ``(M,)`` int ns, increasing.
        tolerance_ns: largest accepted ``|stamp − truth stamp|``.

    Returns:
        Two int arrays of equal length: estimate indices and truth indices.
    """
    s = np.asarray(stamps_ns, dtype=np.int64)
    g = np.asarray(truth_stamps_ns, dtype=np.int64)
    if not len(s) or not len(g):
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    right = np.clip(np.searchsorted(g, s), 0, len(g) - 1)
    left = np.clip(right - 1, 0, len(g) - 1)
    nearest = np.where(np.abs(g[left] - s) <= np.abs(g[right] - s), left, right)
    keep = np.abs(g[nearest] - s) <= tolerance_ns
    return np.flatnonzero(keep), nearest[keep]


# --- summary and plots -----------------------------------------------------------------


def write_summary(path: str | os.PathLike[str], summary: Mapping[str, Any]) -> Path:
    """Write ``summary`` as indented JSON; numpy scalars and arrays become JSON values,
    NaN and infinities become ``null`` (JSON has no such numbers)."""
    out = Path(path)
    text = json.dumps(_jsonable(summary), indent=2, sort_keys=False, allow_nan=False)
    out.write_text(text + "\n", encoding="utf-8")
    return out


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray | list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


@contextmanager
def _figure(path: str | os.PathLike[str], size: tuple[float, float]) -> Iterator[Any]:
    """Axes to draw on; saved as a PNG at ``path`` when the block ends without error."""
    import matplotlib

    matplotlib.use("Agg")  # files only: no display on a robot or in CI
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=size)
    try:
        yield ax
        ax.grid(True, alpha=0.3)
        if ax.get_legend_handles_labels()[0]:  # an empty plot has nothing to explain
            ax.legend(fontsize=8, loc="best")
        fig.tight_layout()
        fig.savefig(Path(path), dpi=110, format="png")
    finally:
        plt.close(fig)  # pyplot keeps every open figure alive otherwise


def plot_trajectories(
    path: str | os.PathLike[str],
    trajectories: Mapping[str, Any],
    gps_enu: Any = None,
    title: str = "trajectories",
) -> Path:
    """Plot planar trajectories over each other (and GPS fixes) into a PNG.

    Args:
        trajectories: label → positions ``(N, 2+)`` m, in one world frame (ENU).
        gps_enu: ``(K, 2+)`` east/north of GPS fixes, drawn as points; ``None`` for none.
    """
    with _figure(path, (7, 6)) as ax:
        if gps_enu is not None and len(gps_enu):
            gps = np.asarray(gps_enu, dtype=float)
            ax.plot(gps[:, 0], gps[:, 1], ".", color="grey", ms=4, label="GPS fixes")
        for label, xy in trajectories.items():
            xy = np.asarray(xy, dtype=float)
            if len(xy):
                ax.plot(xy[:, 0], xy[:, 1], "-", lw=1.2, label=label)
        ax.set(xlabel="east / x (m)", ylabel="north / y (m)", title=title, aspect="equal")
    return Path(path)


def plot_callback_times(
    path: str | os.PathLike[str],
    callback_ms: Mapping[str, Any],
    budget_ms: float | None,
    title: str = "time per callback",
) -> Path:
    """Plot each node's per-callback time (ms) in arrival order, with the budget line.

    Args:
        callback_ms: label (e.g. node) → ``(N,)`` callback durations in ms.
        budget_ms: the time budget; ``None`` draws no line.
    """
    with _figure(path, (8, 4.5)) as ax:
        for label, times in callback_ms.items():
            ms = np.asarray(times, dtype=float)
            ax.plot(np.arange(len(ms)), ms, ".", ms=2, label=f"{label} ({len(ms)} callbacks)")
        if budget_ms is not None:
            ax.axhline(budget_ms, color="red", ls="--", lw=1, label=f"budget {budget_ms:g} ms")
        ax.set(xlabel="callback", ylabel="time (ms)", title=title)
    return Path(path)


def plot_chi2(
    path: str | os.PathLike[str], stamps_s: Any, chi2: Any, title: str = "χ² over time"
) -> Path:
    """Plot the graph's χ² against time (s since the start of the bag) into a PNG."""
    with _figure(path, (8, 4.5)) as ax:
        t = np.asarray(stamps_s, dtype=float)
        values = np.asarray(chi2, dtype=float)
        ax.plot(t, values, "-", lw=1.2)
        if len(values) and np.all(values[np.isfinite(values)] > 0):
            ax.set_yscale("log")
        ax.set(xlabel="bag time (s)", ylabel="χ²", title=title)
    return Path(path)


# --- progress --------------------------------------------------------------------------


class Progress:
    """A one-line progress bar on stderr, drawn only when stderr is a terminal.

    Args:
        total: the amount that means done (e.g. the bag's duration in s).
        label: text before the bar.
        stream: where to draw; ``sys.stderr`` by default.
        unit: unit of ``total`` shown after the numbers.
        min_interval_s: least wall time between two redraws (drawing is not free).
    """

    WIDTH = 30

    def __init__(
        self,
        total: float,
        label: str = "",
        stream: TextIO | None = None,
        unit: str = "s",
        min_interval_s: float = 0.1,
    ) -> None:
        self.total = max(float(total), 0.0)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.unit = unit
        self.min_interval_s = min_interval_s
        self.enabled = _is_tty(self.stream)
        self._start = time.monotonic()
        self._last_draw = -math.inf
        self._done = 0.0

    def update(self, done: float, note: str = "") -> None:
        """Set how much is done (same unit as ``total``); redraws when due."""
        self._done = float(done)
        now = time.monotonic()
        if self.enabled and now - self._last_draw >= self.min_interval_s:
            self._last_draw = now
            self.stream.write("\r" + self.line(now - self._start, note))
            self.stream.flush()

    def line(self, elapsed_s: float, note: str = "") -> str:
        """The text of the bar after ``elapsed_s`` of wall time."""
        frac = min(self._done / self.total, 1.0) if self.total > 0 else 0.0
        filled = int(round(frac * self.WIDTH))
        bar = "#" * filled + "-" * (self.WIDTH - filled)
        rate = ""
        if elapsed_s > 0:
            speed = self._done / elapsed_s
            # Bag seconds per wall second is the replay's speed as a multiple of real time.
            unit = "x real time" if self.unit == "s" else f"{self.unit}/s"
            rate = f" {speed:.1f} {unit}"
        text = f"{self.label} [{bar}] {frac:4.0%} {self._done:.1f}/{self.total:.1f} {self.unit}"
        return f"{text}{rate} {note}".rstrip()

    def close(self) -> None:
        """Draw the final state and end the line (only if anything was drawn)."""
        if self.enabled:
            self.stream.write("\r" + self.line(time.monotonic() - self._start) + "\n")
            self.stream.flush()


def _is_tty(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or replaced streams (pytest capture)
        return False

