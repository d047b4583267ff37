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


def _shifted(img: np.ndarray, shift: float) -> np.ndarray:
    """``img`` moved right by ``shift`` columns (Fourier interpolation: no bilinear blur)."""
    freqs = np.fft.rfftfreq(img.shape[1])
    spec = np.fft.rfft(img, axis=1) * np.exp(-2j * np.pi * freqs * shift)
    return np.fft.irfft(spec, n=img.shape[1], axis=1).astype(np.float32)


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
    moved = _shifted(base, shift)
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


# ----------------------------------------------------------------------------- parallax


@settings(max_examples=200, deadline=None)
@given(r=st.floats(1.0, 500.0), theta=st.floats(0.0, 0.6), d=st.floats(0.0, 0.5))
def test_parallax_of_forward_travel_is_fig_2_2(r, theta, d) -> None:
    # Forward travel: the general parallax is the construction of Fig. 2.2 / (2.3).
    assert pt.parallax_rad(r, theta, d, 0.0) == pytest.approx(
        pt.bearing_shift_rad(r, theta, d), abs=1e-12
    )
    # Mirror image: a point on the left shifts left by as much.
    assert pt.parallax_rad(r, -theta, d, 0.0) == pytest.approx(
        -pt.parallax_rad(r, theta, d, 0.0), abs=1e-12
    )


def test_parallax_of_sideways_travel_and_far_points() -> None:
    # Step 1 m to the left past a point 10 m straight ahead: it moves right by atan(1/10).
    assert pt.parallax_rad(10.0, 0.0, 0.0, 1.0) == pytest.approx(math.atan(0.1))
    assert pt.parallax_rad(math.inf, 0.1, 0.13, 0.0) == 0.0
    # At r_min of (2.3) the shift is θ_p/2 — the half pixel the thesis calls invisible.
    r = pt.r_min_m(0.13, 0.14, 0.008)
    assert pt.parallax_rad(r, 0.14, 0.13, 0.0) == pytest.approx(0.004)


def test_alternate_sides_keeps_strength_order_per_side() -> None:
    picks = [(1, 10), (2, 12), (3, 30), (4, 11), (5, 40)]
    assert pt.alternate_sides(picks, 20.0) == [(1, 10), (3, 30), (2, 12), (5, 40), (4, 11)]
    # The strongest pick leads whichever side it is on; a lone side is kept as it was.
    assert pt.alternate_sides(picks[2:], 20.0)[0] == (3, 30)
    assert pt.alternate_sides(picks[:2], 20.0) == picks[:2]


def test_balance_weights_cancel_a_common_outward_parallax() -> None:
    theta = np.array([-0.12, -0.1, 0.05, 0.08, 0.13, 0.02])
    w = np.array([1.0, 4.0, 1.0, 2.0, 1.0, 3.0])
    left = theta < 0
    bw = pt.balance_weights(w, left)
    assert bw[left].sum() == pytest.approx(bw[~left].sum())
    # Same ratios within a side; one-sided sets are left alone.
    assert bw[0] / bw[1] == pytest.approx(0.25)
    np.testing.assert_array_equal(pt.balance_weights(w, np.zeros(6, bool)), w)


# ----------------------------------------------------------------------------- tracking


def _lopsided_texture(seed: int) -> np.ndarray:
    return _texture((9, 80), seed)


@pytest.mark.parametrize("seed", range(6))
def test_symmetric_match_of_an_unmoved_patch_is_exactly_zero(seed) -> None:
    img = _lopsided_texture(seed)
    fwd = pt.track_patch(img, img, 4, 40, 13, 3, 20, 61, symmetric=False)
    sym = pt.track_patch(img, img, 4, 40, 13, 3, 20, 61, symmetric=True)
    assert fwd is not None and sym is not None
    assert sym[0] == pytest.approx(0.0, abs=1e-3)  # float32 NCC sums, nothing more
    # The parabola alone is pulled off zero by the lopsided NCC peak of most textures.
    if seed == 0:
        assert abs(fwd[0]) > 1e-3


def test_symmetric_match_averages_out_lopsided_peaks_over_textures() -> None:
    biases = {True: [], False: []}
    for seed in range(40):
        img = _lopsided_texture(100 + seed)
        for symmetric in (True, False):
            found = pt.track_patch(img, img, 4, 40, 13, 3, 20, 61, symmetric=symmetric)
            assert found is not None
            biases[symmetric].append(abs(found[0]))
    assert max(biases[True]) < 1e-3
    assert np.mean(biases[False]) > 0.01


@pytest.mark.parametrize("shift", [-2.0, 0.5, 3.0, 6.25])
def test_track_patch_finds_a_known_shift(shift) -> None:
    base = _texture((9, 200), 7)
    moved = _shifted(base, shift)
    found = pt.track_patch(base, moved, 4, 100, 13, 3, 80, 125)
    assert found is not None
    assert found[0] == pytest.approx(shift, abs=0.08)
    assert found[1] > 0.9


def test_track_patch_rejects_a_match_that_does_not_match_back() -> None:
    rng = np.random.default_rng(3)
    prev = _texture((9, 80), 11)
    cur = rng.uniform(0, 255, (9, 80)).astype(np.float32)  # unrelated view
    results = [pt.track_patch(prev, cur, 4, c, 13, 3, c - 12, c + 13) for c in range(20, 60)]
    # Noise matches somewhere, but the back match rarely lands where it came from.
    assert sum(r is None for r in results) > len(results) // 3
