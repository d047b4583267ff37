"""The files ``h2o-replay`` and ``h2o-demo`` write besides bags: TUM trajectories and the
summary JSON.

Trajectories are planar or 3-D: stamps ``(N,)`` int ns, positions ``(N, 3)`` m (``(N, 2)``
is padded with z = 0), orientations as yaw ``(N,)`` rad or rotation matrices
``(N, 3, 3)``, all in one fixed world frame.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from h2o_slam.core.geometry import matrix_to_quat, quat_to_matrix, yaw_to_matrix
from h2o_slam.io.bags import ReplayError

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
    (``repr``), so the float64 values read back bit for bit (doc/design.md, Conventions).

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


# --- summary ---------------------------------------------------------------------------


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
