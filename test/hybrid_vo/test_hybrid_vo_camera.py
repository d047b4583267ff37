"""Spherical remap (thesis §2.3.1, eqs. 2.1–2.2) and the camera model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybrid_vo.camera import (
    CameraIntrinsics,
    CameraMounting,
    SphericalMap,
    pixel_rays_base,
    project_base_rays,
    ray_angles,
    rays_from_angles,
)
from hybrid_vo.errors import ConfigError

INTR = CameraIntrinsics(160, 120, 130.0, 130.0, 79.5, 59.5)
# Fig. 2.1: "the camera is pointed off to the left and down, with some axial roll".
MOUNT = CameraMounting(yaw_rad=0.25, pitch_rad=0.12, roll_rad=0.06)
# The four yellow dots of Fig. 2.1: (pitch, yaw) = (±0.03, ±0.1) rad.
DOTS = [(0.03, 0.1), (0.03, -0.1), (-0.03, -0.1), (-0.03, 0.1)]


def _dot_pixels(smap: SphericalMap) -> tuple[np.ndarray, np.ndarray]:
    phi = np.array([p for p, _ in DOTS])
    theta = np.array([t for _, t in DOTS])
    u, v, inside = project_base_rays(INTR, MOUNT, rays_from_angles(phi, theta))
    assert inside.all()
    return u, v


def test_fig21_rays_form_axis_aligned_rectangle_about_the_frontal_direction() -> None:
    smap = SphericalMap.build(INTR, MOUNT, 0.1)
    u, v = _dot_pixels(smap)
    # In the planar image the rectangle is skewed by the mounting (not axis-aligned) ...
    assert abs(v[0] - v[1]) > 1.0
    k, col = smap.forward(u, v)
    a = smap.a_rad_per_px
    # ... after (2.1)-(2.2) it is an axis-aligned rectangle, 0.2 rad wide and 0.06 rad tall,
    # centred on the frontal direction (φ, θ) = (0, 0).
    np.testing.assert_allclose(k, [(p - smap.phi_o_rad) / a for p, _ in DOTS], atol=1e-9)
    np.testing.assert_allclose(col, [(t - smap.theta_o_rad) / a for _, t in DOTS], atol=1e-9)
    assert k[0] == pytest.approx(k[1]) and k[2] == pytest.approx(k[3])
    assert col[1] == pytest.approx(col[2]) and col[0] == pytest.approx(col[3])
    assert col[0] - col[1] == pytest.approx(0.2 / a)
    assert k[0] - k[2] == pytest.approx(0.06 / a)
    assert np.mean(col) == pytest.approx(-smap.theta_o_rad / a)
    assert np.mean(k) == pytest.approx(-smap.phi_o_rad / a)
    # a is the radians-per-pixel of the planar image's centre pixel.
    assert a == pytest.approx(2 * math.atan(0.5 / INTR.fx_px))


def test_lookup_table_moves_dots_to_the_predicted_spherical_pixels() -> None:
    smap = SphericalMap.build(INTR, MOUNT, 0.1)
    u, v = _dot_pixels(smap)
    vv, uu = np.mgrid[0 : INTR.height_px, 0 : INTR.width_px]
    image = np.zeros((INTR.height_px, INTR.width_px), np.float32)
    for ui, vi in zip(u, v, strict=True):
        image += 200.0 * np.exp(-((uu - ui) ** 2 + (vv - vi) ** 2) / (2 * 1.2**2))
    sph = smap.remap(image)
    k_pred, l_pred = smap.forward(u, v)
    for kp, lp in zip(k_pred, l_pred, strict=True):
        r0, c0 = int(round(kp)), int(round(lp))
        win = sph[r0 - 3 : r0 + 4, c0 - 3 : c0 + 4].astype(float)
        rr, cc = np.mgrid[r0 - 3 : r0 + 4, c0 - 3 : c0 + 4]
        kc = float((win * rr).sum() / win.sum())
        lc = float((win * cc).sum() / win.sum())
        assert kc == pytest.approx(kp, abs=0.3)
        assert lc == pytest.approx(lp, abs=0.3)


@settings(max_examples=40, deadline=None)
@given(
    yaw=st.floats(-0.3, 0.3),
    pitch=st.floats(-0.2, 0.2),
    roll=st.floats(-0.1, 0.1),
    uf=st.floats(0.2, 0.8),
    vf=st.floats(0.2, 0.8),
)
def test_lookup_table_inverts_the_forward_map(yaw, pitch, roll, uf, vf) -> None:
    mount = CameraMounting(yaw_rad=yaw, pitch_rad=pitch, roll_rad=roll)
    smap = SphericalMap.build(INTR, mount, 0.1)
    rows, cols = smap.shape
    k, col = rows * vf, cols * uf
    # The table's planar pixel, pushed through (2.1)-(2.2), lands back on (k, l).
    ki, li = int(k), int(col)
    kb, lb = smap.forward(smap.map_u[ki, li], smap.map_v[ki, li])
    assert float(kb) == pytest.approx(ki, abs=1e-3)
    assert float(lb) == pytest.approx(li, abs=1e-3)


def test_pixel_rays_and_angles_agree_with_the_mounting() -> None:
    rays = pixel_rays_base(INTR, CameraMounting(yaw_rad=0.2, pitch_rad=0.1))
    centre = rays[60, 80]  # near the principal point (79.5, 59.5)
    phi, theta = ray_angles(centre)
    assert float(theta) == pytest.approx(-0.2, abs=0.01)  # yaw left = θ to the left (negative)
    assert float(phi) == pytest.approx(0.1, abs=0.01)  # pitched down: below the horizon


def test_band_out_of_view_is_rejected() -> None:
    with pytest.raises(ConfigError, match="horizon band"):
        SphericalMap.build(INTR, CameraMounting(pitch_rad=1.2), 0.1)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"width_px": 4}, "width_px"),
        ({"fx_px": 0.0}, "fx_px"),
        ({"cy_px": math.nan}, "cy_px"),
    ],
)
def test_bad_intrinsics_raise(kwargs, match) -> None:
    base = {
        "width_px": 160,
        "height_px": 120,
        "fx_px": 130.0,
        "fy_px": 130.0,
        "cx_px": 79.5,
        "cy_px": 59.5,
    }
    base.update(kwargs)
    with pytest.raises(ConfigError, match=match):
        CameraIntrinsics(**base)


def test_bad_mounting_raises() -> None:
    with pytest.raises(ConfigError, match="baseline_m"):
        CameraMounting(baseline_m=-0.1)
    with pytest.raises(ConfigError, match="pitch_rad and roll_rad"):
        CameraMounting(roll_rad=2.0)


def test_remap_rejects_wrong_image_size() -> None:
    smap = SphericalMap.build(INTR, MOUNT, 0.1)
    with pytest.raises(ConfigError, match="built for 160x120"):
        smap.remap(np.zeros((10, 10), np.uint8))


def test_scaled_intrinsics_match_cv2_resize_pixel_centres() -> None:
    big = CameraIntrinsics(640, 480, 520.0, 520.0, 319.5, 239.5)
    small = big.scaled(160, 120)
    assert small.fx_px == pytest.approx(130.0)
    assert small.cx_px == pytest.approx(79.5)
