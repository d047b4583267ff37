"""Validation and message-construction helpers shared by the adapters (private)."""

from __future__ import annotations

import importlib
import re
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msg_adapters.errors import AdapterError

Array = NDArray[np.float64]

#: Relative tolerance for symmetry and for negative eigenvalues of a covariance.
COV_RTOL = 1e-6
#: Absolute tolerance (in the covariance's units) below which asymmetry is rounding.
COV_ATOL = 1e-12
#: Largest accepted coordinate of a position in a message, m. Physics bounds it: a frame on
#: or about the Earth (ECEF: 6.4e6 m; UTM northings: < 1e7 m; a local ``odom`` or ``map``)
#: never holds a point 1e8 m away. Beyond it, squares of distances and of the noise that
#: grows with them lose the headroom the solvers need (1e200 overflows a squared sigma).
MAX_POSITION_M = 1e8


def new_message(msg_or_cls: Any) -> Any:
    """An instance: ``msg_or_cls`` itself, or a default instance of the class given."""
    if isinstance(msg_or_cls, type):
        return msg_or_cls()
    return msg_or_cls


def finite_array(
    values: Any, field: str, shape: tuple[int, ...] | None = None, max_abs: float | None = None
) -> Array:
    """``values`` as a float array, checked for shape, for NaN/inf and, with ``max_abs``,
    for magnitude."""
    try:
        out = np.array(values, dtype=float)
    except (TypeError, ValueError, OverflowError) as exc:
        raise AdapterError(f"{field}: not numeric ({exc})") from None
    if shape is not None and out.shape != shape:
        raise AdapterError(f"{field}: expected shape {shape}, got {out.shape}")
    if not np.all(np.isfinite(out)):
        raise AdapterError(f"{field}: contains NaN or inf")
    if max_abs is not None and out.size and float(np.max(np.abs(out))) > max_abs:
        raise AdapterError(
            f"{field}: magnitude {float(np.max(np.abs(out))):.3g} beyond the bound {max_abs:.3g}"
        )
    return out


def finite_float(value: Any, field: str) -> float:
    """``value`` as a finite float."""
    try:
        out = float(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise AdapterError(f"{field}: not a number ({exc})") from None
    if not np.isfinite(out):
        raise AdapterError(f"{field}: is {out}")
    return out


def variance(sigma: Any, field: str) -> float:
    """``sigma²`` of a finite standard deviation ``sigma ≥ 0``; refused when the square is
    not finite (a sigma beyond about 1.3e154 squares to inf)."""
    value = finite_float(sigma, field)
    if value < 0.0:
        raise AdapterError(f"{field}: negative value {value:.6g}")
    out = value * value
    if not np.isfinite(out):
        raise AdapterError(f"{field}: {value:.3g} squared is not a finite variance")
    return out


def covariance(values: Any, n: int, field: str, *, definite: bool = False) -> Array:
    """A validated ``(n, n)`` covariance from a flat row-major array of ``n²`` numbers.

    Symmetric within :data:`COV_RTOL` (relative to its largest entry) and positive
    semi-definite within the same tolerance; the symmetric part is returned. With
    ``definite``, zero eigenvalues are rejected as well (the matrix must be invertible).
    Any finite magnitude is handled: the checks run on the matrix scaled by its largest
    entry, so 1.7e308 neither overflows nor reaches LAPACK as inf.
    """
    flat = finite_array(values, field).ravel()
    if flat.size != n * n:
        raise AdapterError(f"{field}: expected {n * n} values, got {flat.size}")
    cov = flat.reshape(n, n)
    scale = float(np.max(np.abs(cov)))
    unit = cov / scale if scale > 0.0 else cov
    asym = float(np.max(np.abs(unit - unit.T))) * scale
    if asym > COV_ATOL + COV_RTOL * scale:
        raise AdapterError(f"{field}: not symmetric (largest asymmetry {asym:.3g})")
    cov = 0.5 * cov + 0.5 * cov.T
    unit = 0.5 * (unit + unit.T)
    # Eigenvalues of the scaled matrix (the tests are scale-free); reported in real units.
    eig = np.linalg.eigvalsh(unit)
    scale = scale if scale > 0.0 else 1.0
    low, high = float(eig[0]) * scale, float(eig[-1]) * scale  # python floats: inf, no warning
    if eig[0] < -COV_RTOL * max(1.0, COV_ATOL / scale):
        raise AdapterError(
            f"{field}: indefinite (smallest eigenvalue {low:.3g}, largest {high:.3g})"
        )
    if definite and eig[0] <= COV_RTOL * eig[-1]:
        raise AdapterError(
            f"{field}: singular (eigenvalues {low:.3g} .. {high:.3g}); "
            "a measurement needs a positive definite covariance"
        )
    return cov


def inverse_spd(cov: Array, field: str = "covariance") -> Array:
    """Inverse of a symmetric positive definite matrix, through its eigen-decomposition.

    Raises:
        AdapterError: an inverse that is not finite (eigenvalues so small, e.g. subnormal,
            that their reciprocals overflow).
    """
    eig, vec = np.linalg.eigh(cov)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        out: Array = (vec / eig) @ vec.T
        out = 0.5 * (out + out.T)
    if not np.all(np.isfinite(out)):
        raise AdapterError(
            f"{field}: its inverse is not finite (smallest eigenvalue {float(eig[0]):.3g})"
        )
    return out


def set_float_array(msg: Any, field: str, values: Array) -> None:
    """Assign a fixed- or variable-size float64 array field on an rclpy or rosbags message."""
    setattr(msg, field, np.ascontiguousarray(values, dtype=np.float64).ravel())


def set_bytes(msg: Any, field: str, data: bytes | NDArray[np.uint8]) -> None:
    """Assign a ``uint8[]`` field: numpy for rosbags messages, ``bytes`` for rclpy ones.

    rclpy copies ``bytes`` into its ``array('B')`` in one go but iterates over a numpy
    array element by element (seconds for a VGA image), hence the distinction.
    """
    if isinstance(getattr(msg, field, None), np.ndarray):
        setattr(msg, field, np.frombuffer(bytes(data), dtype=np.uint8).copy())
    else:
        setattr(msg, field, bytes(data))


_SEQUENCE = re.compile(r"^sequence<([A-Za-z0-9_]+)/([A-Za-z0-9_]+)(?:, *\d+)?>$")


def element_class(msg: Any, field: str) -> Any:
    """The message class of the elements of sequence field ``field`` of an rclpy message.

    Resolved from the generated type description and imported lazily (``<pkg>.msg``), so
    this module never imports a message package (or rclpy) at import time.
    """
    get_types = getattr(type(msg), "get_fields_and_field_types", None)
    if get_types is None:
        raise AdapterError(
            f"{type(msg).__name__}.{field}: building sequences of messages needs an rclpy "
            "message class"
        )
    spec = get_types().get(field, "")
    match = _SEQUENCE.match(spec)
    if match is None:
        raise AdapterError(f"{type(msg).__name__}.{field}: not a sequence of messages ({spec})")
    module = importlib.import_module(f"{match.group(1)}.msg")
    return getattr(module, match.group(2))


def as_rotations(R: Any, t: Any, field: str) -> tuple[Array, Array]:
    """Validated pose arrays ``R (n, 3, 3)`` and ``t (n, 3)``."""
    R_arr = finite_array(R, f"{field} R")
    t_arr = finite_array(t, f"{field} t")
    if R_arr.ndim != 3 or R_arr.shape[1:] != (3, 3):
        raise AdapterError(f"{field} R: expected shape (n, 3, 3), got {R_arr.shape}")
    if t_arr.shape != (len(R_arr), 3):
        raise AdapterError(f"{field} t: expected shape ({len(R_arr)}, 3), got {t_arr.shape}")
    return R_arr, t_arr


def vector3(values: Sequence[float] | Array) -> tuple[float, float, float]:
    """Three Python floats."""
    return float(values[0]), float(values[1]), float(values[2])
