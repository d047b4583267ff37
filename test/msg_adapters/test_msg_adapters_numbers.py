"""The covariance and number builders of msg_adapters at the ends of the float range: any
finite input yields a finite, symmetric, positive semi-definite matrix (a finite number)
or raises InputError naming the field; never inf or NaN (1e200² overflows)."""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import CameraInfo, NavSatFix

from h2o_slam.core.errors import InputError
from msg_adapters import (
    CameraModel,
    Datum,
    camera_info_from_msg,
    fill_camera_info,
    fill_navsat_fix,
    gps_fix_from_msg,
    planar_covariance,
    planar_odometry_sample,
    stereo_baseline_m,
)
from msg_adapters._util import COV_ATOL, COV_RTOL, covariance

MAX = sys.float_info.max
#: Magnitudes whose squares or sums overflow, and their neighbours.
EXTREMES = [0.0, 5e-324, 1e-200, 1e-12, 1.0, 1e12, 1e154, 1.4e154, 1e200, 1e300, MAX]
finite = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from(EXTREMES + [-v for v in EXTREMES]),
)
SF = Datum(37.7749, -122.4194, 10.0)


def assert_covariance(cov: Any, n: int) -> None:
    """Finite, exactly symmetric, and positive semi-definite within the tolerance the
    validator allows (relative to the largest entry, checked on the scaled matrix)."""
    cov = np.asarray(cov)
    assert cov.shape == (n, n)
    assert np.all(np.isfinite(cov)), cov
    np.testing.assert_array_equal(cov, cov.T)
    scale = float(np.max(np.abs(cov)))
    if scale > 0.0:
        low = float(np.linalg.eigvalsh(cov / scale)[0])
        assert low >= -COV_RTOL * max(1.0, COV_ATOL / scale), (low, cov)


def test_planar_covariance_refuses_a_sigma_whose_square_overflows() -> None:
    with pytest.raises(InputError, match="sigma_x_m: 1e\\+200 squared"):
        planar_covariance(1e200, 0.1, 0.1)
    with pytest.raises(InputError, match="sigma_yaw_rad"):
        planar_covariance(0.1, 0.1, MAX)
    with pytest.raises(InputError, match="unobserved_variance"):
        planar_covariance(0.1, 0.1, 0.1, unobserved_variance=float("inf"))
    with pytest.raises(InputError, match="cov_xy"):
        planar_covariance(1e150, 1e150, 0.1, cov_xy=MAX)


@given(finite, finite, finite, finite, finite)
@settings(max_examples=300)
def test_planar_covariance_is_a_covariance_or_refused(
    sx: float, sy: float, syaw: float, cxy: float, unobserved: float
) -> None:
    try:
        cov = planar_covariance(sx, sy, syaw, cov_xy=cxy, unobserved_variance=unobserved)
    except InputError:
        return
    assert_covariance(cov, 6)


@given(st.lists(finite, min_size=9, max_size=9))
@settings(max_examples=300)
def test_a_planar_sample_carries_a_covariance_or_is_refused(values: list[float]) -> None:
    try:
        sample = planar_odometry_sample(0, "odom", "base_link", 0.0, 0.0, 0.0,
                                        np.reshape(values, (3, 3)))
    except InputError:
        return
    assert_covariance(sample.covariance, 6)


@given(st.lists(finite, min_size=9, max_size=9), st.booleans())
@settings(max_examples=300)
def test_the_covariance_validator_returns_a_covariance_or_refuses(
    values: list[float], symmetric: bool
) -> None:
    m = np.reshape(values, (3, 3))
    if symmetric:  # most random matrices are refused as asymmetric: try symmetric ones too
        m = np.triu(m) + np.triu(m, 1).T
    try:
        cov = covariance(m.ravel(), 3, "cov")
    except InputError:
        return
    assert_covariance(cov, 3)


def _fix(cov: list[float], cov_type: int) -> NavSatFix:
    msg = fill_navsat_fix(NavSatFix, stamp_ns=10**18, frame_id="gps", lat_deg=37.775,
                          lon_deg=-122.42, alt_m=10.0, covariance_enu=np.eye(3))
    msg.position_covariance = np.asarray(cov, dtype=float)
    msg.position_covariance_type = cov_type
    return msg


@given(st.lists(finite, min_size=9, max_size=9), st.integers(0, 3), finite, finite, finite)
@settings(max_examples=300)
def test_a_gps_fix_carries_a_covariance_or_is_refused(
    cov: list[float], cov_type: int, unknown: float, floor: float, max_sigma: float
) -> None:
    try:
        fix = gps_fix_from_msg(_fix(cov, cov_type), SF, unknown_sigma_m=unknown,
                               sigma_floor_m=floor, max_sigma_m=max_sigma)
    except InputError:
        return
    assert_covariance(fix.covariance, 3)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"unknown_sigma_m": 1e200}, "unknown_sigma_m: 1e\\+200 squared"),
        ({"unknown_sigma_m": 1.0, "sigma_floor_m": 1e200}, "sigma_floor_m: 1e\\+200 squared"),
        ({"unknown_sigma_m": 1.0, "sigma_floor_m": 1.3e154, "max_sigma_m": float("inf")},
         "sigma_floor_m: .*NaN or inf"),
        ({"unknown_sigma_m": 1.0, "max_sigma_m": float("nan")}, "max_sigma_m"),
    ],
)
def test_gps_sigmas_that_overflow_are_refused_naming_them(kwargs: dict[str, float],
                                                          match: str) -> None:
    with pytest.raises(InputError, match=match):
        gps_fix_from_msg(_fix([0.0] * 9, 0), SF, **kwargs)


@given(st.lists(finite, min_size=9, max_size=9))
@settings(max_examples=300)
def test_rotating_a_covariance_into_the_datum_frame_stays_finite_or_is_refused(
    values: list[float]
) -> None:
    m = np.reshape(values, (3, 3))
    try:
        cov = covariance((np.triu(m) + np.triu(m, 1).T).ravel(), 3, "cov")
        rotated = SF.rotate_covariance(cov, 37.775, -122.42)
    except InputError:
        return
    assert_covariance(rotated, 3)


def test_rotating_a_covariance_of_max_float_is_refused() -> None:
    with pytest.raises(InputError, match="datum's ENU frame: contains NaN or inf"):
        SF.rotate_covariance(np.full((3, 3), MAX), 37.775, -122.42)


def _right_camera(fx: float, tx: float) -> CameraModel:
    k = [fx, 0.0, 320.0, 0.0, fx, 240.0, 0.0, 0.0, 1.0]
    p = [fx, 0.0, 320.0, tx, 0.0, fx, 240.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    model = CameraModel(width=640, height=480, K=np.reshape(k, (3, 3)), D=np.zeros(5),
                       R=np.eye(3), P=np.reshape(p, (3, 4)), distortion_model="plumb_bob",
                       frame_id="right", stamp_ns=0)
    return camera_info_from_msg(fill_camera_info(CameraInfo, model))


def test_a_stereo_baseline_that_overflows_is_refused() -> None:
    # A subnormal focal length divides a legal P[0, 3] into inf.
    with pytest.raises(InputError, match="baseline"):
        stereo_baseline_m(_right_camera(5e-324, -1e9))
    assert stereo_baseline_m(_right_camera(500.0, -60.0)) == pytest.approx(0.12)
