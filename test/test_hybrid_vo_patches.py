"""Per-patch steps: r_min (2.3), NCC search, σ from the peak, vote, σ merge, (2.4)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hybrid_vo import patches as pt


def _texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, shape).astype(np.float32)
    return cv2.GaussianBlur(img, (0, 0), 1.5)


# ----------------------------------------------------------------------------- (2.3)


def test_r_min_matches_the_thesis_numbers() -> None:
    # §2.3.2: θ_max 0.09 / 0.14 rad, d = 0.13 m, θ_p of a 160-px camera -> 2.42 m / 3.69 m.
    # θ_p: 13 px span 7.6° (§2.3.2), so θ_p = 7.6° / 13.
    theta_p = math.radians(7.6) / 13
    assert pt.r_min_m(0.13, 0.09, theta_p) == pytest.approx(2.42, abs=0.03)
    assert pt.r_min_m(0.13, 0.14, theta_p) == pytest.approx(3.69, abs=0.04)


@settings(max_examples=200, deadline=None)
@given(
    d=st.floats(0.01, 1.0),
    theta=st.floats(0.01, 0.6),  # at θ = 0 a point ahead never shifts: (2.3) degenerates
    theta_p=st.floats(0.002, 0.02),
)
def test_r_min_is_where_parallax_equals_half_a_pixel(d, theta, theta_p) -> None:
    r = pt.r_min_m(d, theta, theta_p)
    # Fig. 2.2: at r_min the bearing moves by exactly θ_p/2; farther, by less; nearer, more.
    assert pt.bearing_shift_rad(r, theta, d) == pytest.approx(theta_p / 2, rel=1e-6)
    assert pt.bearing_shift_rad(1.2 * r, theta, d) < theta_p / 2
    assert pt.bearing_shift_rad(0.8 * r, theta, d) > theta_p / 2


def test_r_min_grows_with_bearing() -> None:
    values = [pt.r_min_m(0.13, t, 0.008) for t in (0.0, 0.05, 0.1, 0.2)]
    assert values == sorted(values)


# ----------------------------------------------------------------------------- NCC


@pytest.mark.parametrize("shift", [-3.3, -0.5, 0.0, 0.25, 1.7, 4.45])
def test_ncc_finds_a_known_shift_to_sub_pixel_accuracy(shift) -> None:
    base = _texture((9, 200), 3)
    # Shift by a fraction of a pixel with bilinear-free Fourier interpolation along rows.
    freqs = np.fft.rfftfreq(base.shape[1])
    moved = np.fft.irfft(
        np.fft.rfft(base, axis=1) * np.exp(-2j * np.pi * freqs * shift), n=base.shape[1], axis=1
    ).astype(np.float32)
    r, c = 4, 100
    tmpl = base[r - 1 : r + 2, c - 6 : c + 7]
    window = moved[r - 2 : r + 3, c - 20 : c + 21]
    found = pt.ncc_search(tmpl, window)
    assert found is not None
    row, col, peak, sigma = found
    estimate = (c - 20) + col + 6 - c
    assert estimate == pytest.approx(shift, abs=0.15)
    assert row == pytest.approx(1.0, abs=0.2)
    assert peak > 0.9
    assert 0 < sigma < 3


def test_ncc_peak_on_window_edge_is_rejected() -> None:
    base = _texture((3, 60), 5)
    tmpl = base[:, 0:13]
    assert pt.ncc_search(tmpl, base[:, 0:30]) is None  # best match at column 0: the edge


def test_peak_sigma_of_a_gaussian_profile_is_its_sigma() -> None:
    sigma = 1.7
    x = np.array([-1.0, 0.0, 1.0])
    left, mid, right = np.exp(-(x**2) / (2 * sigma**2))
    # Numerical curvature of a sampled Gaussian: exact up to the O(h²) term.
    assert pt.peak_sigma_px(left, mid, right) == pytest.approx(sigma, rel=0.1)
    assert pt.peak_sigma_px(0.5, 0.5, 0.5) == math.inf


def test_parabola_offset_recovers_a_parabola_vertex() -> None:
    x0 = 0.3
    f = [-((x - x0) ** 2) for x in (-1.0, 0.0, 1.0)]
    assert pt.parabola_offset(*f) == pytest.approx(x0)


# ----------------------------------------------------------------------------- vote


def test_vote_rejects_a_planted_outlier_patch() -> None:
    theta_p = 0.008
    est = np.array([0.0500, 0.0503, 0.0497, 0.0501, 0.0499, 0.0500])
    est[3] = 0.0500 + 1.5 * theta_p  # one patch matched the wrong place
    inliers = pt.vote(est, theta_p)
    assert inliers.tolist() == [True, True, True, False, True, True]


def test_vote_without_majority_has_no_inliers() -> None:
    est = np.array([0.0, 0.0, 0.02, 0.02, 0.04, 0.04])
    assert not pt.vote(est, 0.008).any()


@settings(max_examples=100, deadline=None)
@given(
    truth=st.floats(-0.2, 0.2),
    noise=st.lists(st.floats(-0.003, 0.003), min_size=6, max_size=6),
    outlier=st.floats(0.02, 0.3),
)
def test_vote_keeps_agreeing_patches_and_drops_the_odd_one(truth, noise, outlier) -> None:
    est = truth + np.array(noise)
    est[0] = truth + outlier
    inliers = pt.vote(est, 0.008)
    assert not inliers[0]
    assert inliers[1:].all()


# ----------------------------------------------------------------------------- σ, (2.4)


def test_merge_sigmas_as_printed_and_inverse_variance() -> None:
    s = np.array([0.002, 0.002, 0.004])
    assert pt.merge_sigmas(s) == pytest.approx(1 / (500 + 500 + 250))
    assert pt.merge_sigmas(s, "inverse_variance") == pytest.approx(
        1 / math.sqrt(2 / 0.002**2 + 1 / 0.004**2)
    )
    with pytest.raises(ValueError, match="positive"):
        pt.merge_sigmas(np.array([0.0]))
    with pytest.raises(ValueError, match="unknown sigma merge rule"):
        pt.merge_sigmas(s, "median")  # type: ignore[arg-type]


def test_localize_is_equation_2_4() -> None:
    p = np.array([1.0, 2.0])
    dp_w = np.array([0.1, 0.02])
    theta_v, theta_w = 0.05, 0.3
    rot = lambda a: np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])  # noqa: E731
    expected = p + rot(theta_v / 2) @ rot(-theta_w) @ dp_w
    np.testing.assert_allclose(pt.localize(p, theta_v, theta_w, dp_w), expected, atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(ds=st.floats(0.0, 0.5), w=st.floats(-0.5, 0.5))
def test_localize_with_agreeing_rotations_keeps_an_arc(ds, w) -> None:
    # A wheel step that applied its full rotation: translation along θ_w. When vision agrees
    # (θ_v = θ_w) the midpoint rule sends it along θ_w/2, the chord of the true arc.
    dp_w = ds * np.array([math.cos(w), math.sin(w)])
    out = pt.localize(np.zeros(2), w, w, dp_w)
    np.testing.assert_allclose(out, ds * np.array([math.cos(w / 2), math.sin(w / 2)]), atol=1e-12)


def test_stereo_range_from_a_known_disparity() -> None:
    left = _texture((30, 120), 9)
    disparity = 7
    right = np.zeros_like(left)
    right[:, : 120 - disparity] = left[:, disparity:]
    z = pt.stereo_range_m(left, right, 60.0, 15.0, 130.0, 0.12, 40, 4, 2, 0.6)
    assert z == pytest.approx(130.0 * 0.12 / disparity, rel=0.05)
    flat = np.full_like(left, 100.0)
    assert math.isnan(pt.stereo_range_m(flat, flat, 60.0, 15.0, 130.0, 0.12, 40, 4, 2, 0.6))
