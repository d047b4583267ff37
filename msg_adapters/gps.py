"""``sensor_msgs/NavSatFix`` → local ENU about a datum, on the WGS-84 ellipsoid.

Exact conversions (no flat-earth approximation): geodetic → ECEF → ENU at the datum, and
back (ECEF → geodetic by fixed-point iteration on the latitude, converged to machine
precision). ENU axes: x east, y north, z up (REP-103; heading 0 = east).

A fix becomes a :class:`GpsFix` with its ENU covariance (the message's covariance is in
the ENU frame tangent at the fix; it is rotated into the datum's ENU frame). Fixes that
must not reach the solver are rejected with the reason: status ``NO_FIX``, NaN/inf or
out-of-range coordinates (altitude beyond ±:data:`MAX_ALTITUDE_M`), covariance entries
beyond :data:`MAX_VARIANCE_M2`, an unknown covariance without a configured sigma, a
covariance that is not symmetric positive semi-definite, and a horizontal sigma above
``max_sigma_m``. Covariance eigenvalues below ``sigma_floor_m²`` are raised to it, so a
zero covariance never becomes infinite stiffness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from msg_adapters._util import (
    Array,
    covariance,
    finite_array,
    finite_float,
    new_message,
    set_float_array,
    variance,
)
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import fill_header, stamp_ns

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

# sensor_msgs/NavSatStatus and NavSatFix constants (same in rclpy and rosbags).
STATUS_UNKNOWN = -2
STATUS_NO_FIX = -1
COVARIANCE_TYPE_UNKNOWN = 0
COVARIANCE_TYPE_APPROXIMATED = 1
COVARIANCE_TYPE_DIAGONAL_KNOWN = 2
COVARIANCE_TYPE_KNOWN = 3

#: Default lower bound on any GPS standard deviation (m).
SIGMA_FLOOR_M = 0.01
#: Default largest accepted horizontal standard deviation (m).
MAX_SIGMA_M = 10.0
#: Largest accepted ellipsoidal altitude magnitude, m: the deepest ocean floor is 1.1e4 m
#: below the ellipsoid and no vehicle that reports NavSatFix to this package flies above
#: 1e5 m; beyond it, ENU coordinates only carry garbage into the solver.
MAX_ALTITUDE_M = 1e5
#: Largest accepted entry of a fix's covariance, m² (σ = 1e6 m: no position at all). A
#: larger one cannot be rotated into the datum's frame without overflowing.
MAX_VARIANCE_M2 = 1e12


def geodetic_to_ecef(lat_deg: Any, lon_deg: Any, alt_m: Any) -> Array:
    """ECEF coordinates ``(..., 3)`` in metres of WGS-84 latitude, longitude (degrees)
    and ellipsoidal altitude (metres)."""
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    alt = np.asarray(alt_m, dtype=float)
    sin_lat = np.sin(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    return np.stack(
        [
            (n + alt) * np.cos(lat) * np.cos(lon),
            (n + alt) * np.cos(lat) * np.sin(lon),
            (n * (1.0 - WGS84_E2) + alt) * sin_lat,
        ],
        axis=-1,
    )


def ecef_to_geodetic(ecef: Any) -> tuple[Array, Array, Array]:
    """``(lat_deg, lon_deg, alt_m)`` of ECEF points ``(..., 3)``.

    Iterates ``φ ← atan2(z + e² N(φ) sin φ, p)``, which contracts by about ``e²`` per step
    near the surface; ten steps reach machine precision from the surface to orbit. The
    altitude uses ``h = p cos φ + z sin φ − a √(1 − e² sin² φ)``, which stays exact at
    the poles.
    """
    xyz = np.asarray(ecef, dtype=float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(10):
        sin_lat = np.sin(lat)
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
        lat = np.arctan2(z + WGS84_E2 * n * sin_lat, p)
    sin_lat, cos_lat = np.sin(lat), np.cos(lat)
    alt = p * cos_lat + z * sin_lat - WGS84_A * np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    return np.degrees(lat), np.degrees(np.arctan2(y, x)), alt


def enu_rotation(lat_deg: float, lon_deg: float) -> Array:
    """Rotation ``(3, 3)`` whose rows are the east, north and up axes (in ECEF) at a point;
    ``enu = M (ecef − ecef₀)``."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def _check_lat_lon(lat_deg: float, lon_deg: float, what: str) -> None:
    if not -90.0 <= lat_deg <= 90.0:
        raise AdapterError(f"{what}.latitude: {lat_deg} outside [-90, 90]")
    if not -180.0 <= lon_deg <= 180.0:
        raise AdapterError(f"{what}.longitude: {lon_deg} outside [-180, 180]")


@dataclass(frozen=True)
class Datum:
    """Origin of the local ENU frame (``map``): WGS-84 latitude, longitude (degrees) and
    ellipsoidal altitude (metres).

    Raises:
        AdapterError: NaN/inf or out-of-range coordinates.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0
    _ecef: Array = field(init=False, repr=False, compare=False)
    _rot: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        lat = finite_float(self.lat_deg, "datum.latitude")
        lon = finite_float(self.lon_deg, "datum.longitude")
        alt = _altitude(self.alt_m, "datum.altitude")
        _check_lat_lon(lat, lon, "datum")
        object.__setattr__(self, "_ecef", geodetic_to_ecef(lat, lon, alt))
        object.__setattr__(self, "_rot", enu_rotation(lat, lon))

    def to_enu(self, lat_deg: Any, lon_deg: Any, alt_m: Any) -> Array:
        """ENU coordinates ``(..., 3)`` in metres of geodetic points (degrees, metres)."""
        d = geodetic_to_ecef(lat_deg, lon_deg, alt_m) - self._ecef
        out: Array = d @ self._rot.T
        return out

    def to_geodetic(self, enu: Any) -> tuple[Array, Array, Array]:
        """``(lat_deg, lon_deg, alt_m)`` of ENU points ``(..., 3)`` about this datum."""
        ecef = np.asarray(enu, dtype=float) @ self._rot + self._ecef
        return ecef_to_geodetic(ecef)

    def rotate_covariance(self, cov_enu: Array, lat_deg: float, lon_deg: float) -> Array:
        """A covariance ``(3, 3)`` in the ENU frame tangent at ``(lat, lon)``, expressed in
        this datum's ENU frame."""
        m = self._rot @ enu_rotation(lat_deg, lon_deg).T
        with np.errstate(over="ignore", invalid="ignore"):  # entries near 1e308: refused below
            out: Array = m @ cov_enu @ m.T
            out = 0.5 * (out + out.T)
        return finite_array(out, "covariance rotated into the datum's ENU frame")


@dataclass(frozen=True, eq=False)
class GpsFix:
    """One usable GPS fix in the local ENU frame.

    Attributes:
        stamp_ns: header stamp, nanoseconds.
        frame_id: the antenna's frame (for the lever arm).
        enu: position ``(3,)`` in metres, east/north/up from the datum (``z = 0`` with
            ``zero_altitude``).
        covariance: ``(3, 3)`` ENU covariance in m², eigenvalues ≥ ``sigma_floor_m²``.
        status: ``NavSatStatus.status`` (``STATUS_UNKNOWN`` .. ``STATUS_GBAS_FIX``).
    """

    stamp_ns: int
    frame_id: str
    enu: Array
    covariance: Array
    status: int


def _navsat_geodetic(
    msg: Any, *, zero_altitude: bool, accept_unknown_status: bool
) -> tuple[int, float, float, float | None]:
    status = int(msg.status.status)
    if status == STATUS_NO_FIX:
        raise AdapterError("NavSatFix.status: STATUS_NO_FIX")
    if status < STATUS_UNKNOWN or (status == STATUS_UNKNOWN and not accept_unknown_status):
        raise AdapterError(f"NavSatFix.status: {status} is not a fix")
    lat = finite_float(msg.latitude, "NavSatFix.latitude")
    lon = finite_float(msg.longitude, "NavSatFix.longitude")
    _check_lat_lon(lat, lon, "NavSatFix")
    alt: float | None = None
    if not zero_altitude:
        alt = _altitude(msg.altitude, "NavSatFix.altitude")
    return status, lat, lon, alt


def _altitude(value: Any, field: str) -> float:
    alt = finite_float(value, field)
    if abs(alt) > MAX_ALTITUDE_M:
        raise AdapterError(f"{field}: {alt:.6g} m beyond ±{MAX_ALTITUDE_M:.0e} m")
    return alt


def datum_from_fix(msg: Any, *, accept_unknown_status: bool = True) -> Datum:
    """A :class:`Datum` at a ``NavSatFix`` (the "first good fix" datum).

    Raises:
        AdapterError: ``NO_FIX``, NaN/inf or out-of-range latitude, longitude or altitude.
    """
    _, lat, lon, alt = _navsat_geodetic(
        msg, zero_altitude=False, accept_unknown_status=accept_unknown_status
    )
    return Datum(lat, lon, 0.0 if alt is None else alt)


def gps_fix_from_msg(
    msg: Any,
    datum: Datum,
    *,
    unknown_sigma_m: float | None = None,
    sigma_floor_m: float = SIGMA_FLOOR_M,
    max_sigma_m: float = MAX_SIGMA_M,
    zero_altitude: bool = False,
    accept_unknown_status: bool = True,
) -> GpsFix:
    """Validated :class:`GpsFix` of a ``sensor_msgs/NavSatFix`` (rclpy or rosbags).

    Args:
        msg: the message.
        datum: origin of the ENU frame.
        unknown_sigma_m: standard deviation (each axis) used when
            ``position_covariance_type`` is ``UNKNOWN``; ``None`` rejects such fixes.
        sigma_floor_m: smallest standard deviation along any direction.
        max_sigma_m: largest accepted horizontal standard deviation (the larger
            eigenvalue of the east/north block, after the floor).
        zero_altitude: ignore the altitude (it may then be NaN) and return ``z = 0``;
            east/north are computed at the datum's altitude.
        accept_unknown_status: take ``STATUS_UNKNOWN`` (the Jazzy default value) as a fix.

    Raises:
        AdapterError: with the reason the fix is not used.
    """
    status, lat, lon, alt = _navsat_geodetic(
        msg, zero_altitude=zero_altitude, accept_unknown_status=accept_unknown_status
    )
    if not sigma_floor_m > 0.0:
        raise AdapterError(f"sigma_floor_m: {sigma_floor_m} must be > 0")
    floor = variance(sigma_floor_m, "sigma_floor_m")
    if not max_sigma_m > 0.0:  # NaN would let every fix through
        raise AdapterError(f"max_sigma_m: {max_sigma_m} must be > 0")
    cov_type = int(msg.position_covariance_type)
    if cov_type == COVARIANCE_TYPE_UNKNOWN:
        if unknown_sigma_m is None:
            raise AdapterError(
                "NavSatFix.position_covariance_type: UNKNOWN and no default sigma configured"
            )
        cov = np.eye(3) * variance(unknown_sigma_m, "unknown_sigma_m")
    elif cov_type == COVARIANCE_TYPE_DIAGONAL_KNOWN:
        full = covariance(msg.position_covariance, 3, "NavSatFix.position_covariance")
        cov = np.diag(np.diag(full))
    elif cov_type in (COVARIANCE_TYPE_APPROXIMATED, COVARIANCE_TYPE_KNOWN):
        cov = covariance(msg.position_covariance, 3, "NavSatFix.position_covariance")
    else:
        raise AdapterError(f"NavSatFix.position_covariance_type: unknown value {cov_type}")
    if float(np.max(np.abs(cov))) > MAX_VARIANCE_M2:
        raise AdapterError(
            f"NavSatFix.position_covariance: entry {float(np.max(np.abs(cov))):.3g} m² beyond "
            f"{MAX_VARIANCE_M2:.0e} m² (no position at all)"
        )
    cov = datum.rotate_covariance(cov, lat, lon)
    eig, vec = np.linalg.eigh(cov)
    with np.errstate(over="ignore", invalid="ignore"):  # a floor near 1e154: refused below
        cov = (vec * np.maximum(eig, floor)) @ vec.T
        cov = 0.5 * (cov + cov.T)
    cov = finite_array(cov, "NavSatFix.position_covariance with sigma_floor_m")
    sigma_h = math.sqrt(float(np.linalg.eigvalsh(cov[:2, :2])[-1]))
    if sigma_h > max_sigma_m:
        raise AdapterError(
            f"NavSatFix.position_covariance: horizontal sigma {sigma_h:.3g} m exceeds "
            f"max_sigma_m {max_sigma_m:.3g} m"
        )
    enu = datum.to_enu(lat, lon, datum.alt_m if alt is None else alt)
    if zero_altitude:
        enu[2] = 0.0
    return GpsFix(
        stamp_ns=stamp_ns(msg.header, "NavSatFix.header.stamp"),
        frame_id=str(msg.header.frame_id),
        enu=finite_array(enu, "NavSatFix ENU position", (3,)),
        covariance=cov,
        status=status,
    )


def fill_navsat_fix(
    msg_or_cls: Any,
    *,
    stamp_ns: int,
    frame_id: str,
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    covariance_enu: Any,
    status: int = 0,
    covariance_type: int = COVARIANCE_TYPE_KNOWN,
) -> Any:
    """Fill a ``sensor_msgs/NavSatFix`` (an instance, or a new one of the class given).

    ``covariance_enu`` is ``(3, 3)`` in m², ENU at the fix, as the message carries it. A
    ``NO_FIX`` message may carry NaN coordinates, as receivers publish them; any other
    status needs finite ones.

    Raises:
        AdapterError: a fix status with NaN/inf coordinates, or a covariance that is not
            symmetric positive semi-definite.
    """
    msg = new_message(msg_or_cls)
    fill_header(msg.header, stamp_ns, frame_id)
    msg.status.status = int(status)
    msg.status.service = 1  # SERVICE_GPS
    coords = (float(lat_deg), float(lon_deg), float(alt_m))
    if int(status) != STATUS_NO_FIX:
        finite_array(coords, "NavSatFix position", (3,))
    msg.latitude, msg.longitude, msg.altitude = coords
    cov = covariance(np.asarray(covariance_enu, dtype=float).ravel(), 3, "covariance_enu")
    set_float_array(msg, "position_covariance", cov)
    msg.position_covariance_type = int(covariance_type)
    return msg
