"""msg_adapters.gps: WGS-84 geodetic ⇄ ECEF ⇄ ENU and NavSatFix validation."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bag_messages import SOURCES, as_source
from hypothesis import given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import NavSatFix, NavSatStatus

from msg_adapters import (
    AdapterError,
    Datum,
    datum_from_fix,
    ecef_to_geodetic,
    geodetic_to_ecef,
    gps_fix_from_msg,
)
from msg_adapters.gps import WGS84_A, WGS84_E2

# A comma2k19 segment (real u-blox fixes and fused poses), when the environment gives its
# folder; the test that reads it is skipped otherwise.
COMMA_ENV = "H2O_COMMA2K19"
B = 6356752.314245  # WGS-84 semi-minor axis (m)
SF = Datum(37.7749, -122.4194, 10.0)


def meridian_radius(lat_deg: float) -> float:
    s = math.sin(math.radians(lat_deg))
    return WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s * s) ** 1.5


def prime_vertical_radius(lat_deg: float) -> float:
    s = math.sin(math.radians(lat_deg))
    return WGS84_A / math.sqrt(1 - WGS84_E2 * s * s)


def test_ecef_known_points() -> None:
    np.testing.assert_allclose(geodetic_to_ecef(0, 0, 0), [WGS84_A, 0, 0], atol=1e-9)
    np.testing.assert_allclose(geodetic_to_ecef(0, 90, 100), [0, WGS84_A + 100, 0], atol=1e-9)
    np.testing.assert_allclose(geodetic_to_ecef(90, 0, 0), [0, 0, B], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(-90, 0, 5), [0, 0, -B - 5], atol=1e-6)
    # 42° N, 82° W, 200 m, worked by hand: N = a / sqrt(1 - e² sin²φ).
    n = prime_vertical_radius(42.0)
    lat, lon = math.radians(42.0), math.radians(-82.0)
    expected = [
        (n + 200) * math.cos(lat) * math.cos(lon),
        (n + 200) * math.cos(lat) * math.sin(lon),
        (n * (1 - WGS84_E2) + 200) * math.sin(lat),
    ]
    np.testing.assert_allclose(geodetic_to_ecef(42, -82, 200), expected, atol=1e-8)
    np.testing.assert_allclose(expected, [660675.2518, -4700948.6832, 4245737.6622], atol=1e-3)
    lat_b, lon_b, alt_b = ecef_to_geodetic([0.0, 0.0, B + 3.0])
    assert float(lat_b) == 90.0
    assert float(alt_b) == pytest.approx(3.0, abs=1e-6)  # B above is rounded to 1 µm


def test_one_km_north_and_east() -> None:
    d = Datum(48.0, 11.0, 0.0)  # on the ellipsoid, where the radii below apply
    # 1 km of meridian arc: Δφ = L / M(φ at mid-arc) (M varies along the arc).
    dlat = 1000.0 / meridian_radius(48.0)
    dlat = 1000.0 / meridian_radius(48.0 + math.degrees(dlat) / 2)
    m = meridian_radius(48.0)
    north = d.to_enu(48.0 + math.degrees(dlat), 11.0, 0.0)
    # An arc of 1 km: 1 km north (less L³/6R² ≈ 4 µm) and L²/2R below the tangent plane.
    np.testing.assert_allclose(north, [0.0, 1000.0, -(1000.0**2) / (2 * m)], atol=2e-5)
    n = prime_vertical_radius(48.0)
    dlon = math.degrees(1000.0 / (n * math.cos(math.radians(48.0))))
    east = d.to_enu(48.0, 11.0 + dlon, 0.0)
    assert east[0] == pytest.approx(1000.0, abs=1e-3)
    assert east[2] == pytest.approx(-(1000.0**2) / (2 * n), abs=1e-3)
    # The parallel curves toward the pole: a point due east lies slightly north of the
    # tangent plane's east axis.
    assert east[1] == pytest.approx(1000.0**2 * math.tan(math.radians(48.0)) / (2 * n), rel=1e-2)
    np.testing.assert_allclose(d.to_enu(48.0, 11.0, 100.0), [0, 0, 100.0], atol=1e-8)


@given(
    st.floats(-89.9, 89.9),
    st.floats(-180.0, 180.0),
    st.floats(-100.0, 3000.0),
    st.lists(st.floats(-5e4, 5e4), min_size=3, max_size=3),
)
@settings(max_examples=200)
def test_enu_round_trip(lat: float, lon: float, alt: float, enu: list[float]) -> None:
    datum = Datum(lat, lon, alt)
    back_lat, back_lon, back_alt = datum.to_geodetic(enu)
    np.testing.assert_allclose(datum.to_enu(back_lat, back_lon, back_alt), enu, atol=1e-6)
    np.testing.assert_allclose(datum.to_enu(lat, lon, alt), [0, 0, 0], atol=1e-6)


@given(st.floats(-90.0, 90.0), st.floats(-180.0, 180.0), st.floats(-1e3, 1e6))
def test_geodetic_round_trip(lat: float, lon: float, alt: float) -> None:
    back = ecef_to_geodetic(geodetic_to_ecef(lat, lon, alt))
    assert float(back[0]) == pytest.approx(lat, abs=1e-9)
    if abs(lat) < 89.999:
        assert math.remainder(float(back[1]) - lon, 360.0) == pytest.approx(0.0, abs=1e-9)
    assert float(back[2]) == pytest.approx(alt, abs=1e-6)


def fix(lat: float = 37.7849, lon: float = -122.4194, alt: float = 12.0, **kw: Any) -> Any:
    msg = NavSatFix(latitude=lat, longitude=lon, altitude=alt)
    msg.header.stamp.sec = 100
    msg.header.frame_id = "gps"
    msg.status.status = kw.pop("status", NavSatStatus.STATUS_FIX)
    msg.position_covariance_type = kw.pop("cov_type", NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN)
    msg.position_covariance = np.asarray(kw.pop("cov", np.diag([1.0, 4.0, 9.0]))).ravel()
    assert not kw
    return msg


@pytest.mark.parametrize("source", SOURCES)
def test_navsatfix_to_enu(source: str) -> None:
    out = gps_fix_from_msg(as_source(fix(), source), SF)
    assert out.stamp_ns == 100 * 10**9 and out.frame_id == "gps"
    assert out.status == NavSatStatus.STATUS_FIX
    assert out.enu[1] == pytest.approx(0.01 * math.pi / 180 * meridian_radius(37.78), rel=1e-4)
    drop = out.enu[1] ** 2 / (2 * meridian_radius(37.78))  # below the datum's tangent plane
    assert abs(out.enu[0]) < 1e-6
    assert out.enu[2] == pytest.approx(2.0 - drop, abs=1e-3)
    # The covariance is rotated from the fix's tangent plane into the datum's: ~unchanged.
    np.testing.assert_allclose(out.covariance, np.diag([1.0, 4.0, 9.0]), atol=2e-3)


def test_navsatfix_covariance_types() -> None:
    full = np.array([[1.0, 0.5, 0.0], [0.5, 2.0, 0.0], [0.0, 0.0, 3.0]])
    known = gps_fix_from_msg(fix(lat=SF.lat_deg, cov=full, cov_type=3), SF)
    np.testing.assert_allclose(known.covariance, full, atol=1e-9)
    diag = gps_fix_from_msg(fix(lat=SF.lat_deg, cov=full, cov_type=2), SF)
    np.testing.assert_allclose(diag.covariance, np.diag([1.0, 2.0, 3.0]), atol=1e-9)
    unknown = gps_fix_from_msg(fix(lat=SF.lat_deg, cov_type=0), SF, unknown_sigma_m=2.0)
    np.testing.assert_allclose(unknown.covariance, 4.0 * np.eye(3), atol=1e-9)
    # The floor: a zero covariance never reaches the solver.
    floored = gps_fix_from_msg(fix(cov=np.zeros(9), cov_type=1), SF, sigma_floor_m=0.5)
    assert np.linalg.eigvalsh(floored.covariance).min() == pytest.approx(0.25)


def test_navsatfix_zero_altitude_and_datum() -> None:
    out = gps_fix_from_msg(fix(alt=float("nan")), SF, zero_altitude=True)
    assert out.enu[2] == 0.0
    datum = datum_from_fix(fix(lat=1.0, lon=2.0, alt=3.0))
    assert datum == Datum(1.0, 2.0, 3.0)
    np.testing.assert_allclose(gps_fix_from_msg(fix(1.0, 2.0, 3.0), datum).enu, 0, atol=1e-9)


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize(
    ("msg", "kw", "match"),
    [
        (fix(status=NavSatStatus.STATUS_NO_FIX), {}, "STATUS_NO_FIX"),
        (fix(status=-5), {}, "-5 is not a fix"),
        (fix(status=NavSatStatus.STATUS_UNKNOWN), {"accept_unknown_status": False}, "not a fix"),
        (fix(lat=float("nan")), {}, "latitude: is nan"),
        (fix(lon=float("inf")), {}, "longitude: is inf"),
        (fix(alt=float("nan")), {}, "altitude: is nan"),
        (fix(lat=91.0), {}, r"latitude: 91.0 outside \[-90, 90\]"),
        (fix(lon=-181.0), {}, "longitude: -181.0 outside"),
        (fix(cov_type=0), {}, "UNKNOWN and no default sigma"),
        (fix(cov_type=7), {}, "unknown value 7"),
        (fix(cov=np.diag([-1.0, 1, 1]), cov_type=3), {}, "indefinite"),
        (fix(cov=np.triu(np.ones((3, 3))), cov_type=3), {}, "not symmetric"),
        (fix(cov=np.full(9, np.nan)), {}, "position_covariance: contains NaN"),
        (fix(cov=np.diag([400.0, 1, 1])), {}, r"horizontal sigma 20 m exceeds max_sigma_m 10"),
        (fix(), {"sigma_floor_m": 0.0}, "sigma_floor_m: 0.0 must be > 0"),
    ],
)
def test_navsatfix_rejects(source: str, msg: Any, kw: dict[str, Any], match: str) -> None:
    with pytest.raises(AdapterError, match=match):
        gps_fix_from_msg(as_source(msg, source), SF, **kw)


def test_datum_errors() -> None:
    with pytest.raises(AdapterError, match="datum.latitude: is nan"):
        Datum(float("nan"), 0.0)
    with pytest.raises(AdapterError, match="datum.longitude: 200.0 outside"):
        Datum(0.0, 200.0)
    with pytest.raises(AdapterError, match="STATUS_NO_FIX"):
        datum_from_fix(fix(status=NavSatStatus.STATUS_NO_FIX))


def comma_segment() -> Path:
    """The folder H2O_COMMA2K19 names; the test is skipped when it is not set, and fails
    when it names no folder (the segment was asked for)."""
    folder = os.environ.get(COMMA_ENV, "")
    if not folder:
        pytest.skip(f"comma2k19 segment not given (set {COMMA_ENV} to its folder)")
    assert Path(folder).is_dir(), f"{COMMA_ENV}={folder} is not a folder"
    return Path(folder)


def test_comma2k19_fixes_follow_the_fused_pose() -> None:
    """u-blox fixes turned into ENU agree with comma's fused ECEF pose, horizontally."""
    comma = comma_segment()
    gnss = np.load(comma / "processed_log/GNSS/live_gnss_ublox/value")
    gnss_t = np.load(comma / "processed_log/GNSS/live_gnss_ublox/t")
    ecef = np.load(comma / "global_pose/frame_positions")
    ecef_t = np.load(comma / "global_pose/frame_times")
    datum = datum_from_fix(fix(*gnss[0, :3]))
    enu = np.array([gps_fix_from_msg(fix(*row[:3]), datum, max_sigma_m=100.0).enu for row in gnss])
    lat, lon, alt = ecef_to_geodetic(ecef)
    np.testing.assert_allclose(geodetic_to_ecef(lat, lon, alt), ecef, atol=1e-6)
    fused = datum.to_enu(lat, lon, alt)
    fused_at_fix = np.stack([np.interp(gnss_t, ecef_t, fused[:, k]) for k in range(2)], -1)
    inside = (gnss_t >= ecef_t[0]) & (gnss_t <= ecef_t[-1])
    err = np.linalg.norm(enu[inside, :2] - fused_at_fix[inside], axis=1)
    travelled = np.sum(np.linalg.norm(np.diff(enu[:, :2], axis=0), axis=1))
    assert travelled > 100.0  # the car moved: this is not comparing a point with itself
    assert np.median(err) < 5.0, f"median horizontal error {np.median(err):.2f} m"
