"""The full-VO baselines of bench/vo_full.py and the drift metric of bench/vo_kitti.py."""

from __future__ import annotations

import importlib
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from h2o_slam.core.geometry import planar_between
from hybrid_vo.sim.world import integrate, make_drive, scenario

_BENCH = Path(__file__).resolve().parent.parent / "bench"
if str(_BENCH) not in sys.path:
    sys.path.insert(0, str(_BENCH))
vo_full = importlib.import_module("vo_full")
vo_kitti = importlib.import_module("vo_kitti")

K = np.array([[400.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
BASELINE_M = 0.3


def _motion(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    rot, _ = cv2.Rodrigues(rng.normal(0.0, 0.05, 3))
    return rot, rng.normal(0.0, 0.3, 3)


def _points(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.c_[rng.uniform(-5, 5, n), rng.uniform(-2, 2, n), rng.uniform(4, 40, n)]


def _observe(rot: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    res, _ = vo_full.stereo_residuals(rot, t, pts, np.zeros((len(pts), 4)), K, BASELINE_M)
    return np.asarray(res)


def test_best_matches_respects_the_mask_and_the_distance():
    rng = np.random.default_rng(0)
    desc = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    allowed = np.ones((5, 5), dtype=bool)
    assert list(vo_full.best_matches(desc, desc, allowed, 0)) == [0, 1, 2, 3, 4]
    allowed[2, 2] = False
    allowed[2] = False
    out = vo_full.best_matches(desc, desc, allowed, 256)
    assert out[2] == -1 and out[0] == 0
    # Nothing within 0 bits once the identical partner is masked out.
    allowed = ~np.eye(5, dtype=bool)
    assert np.all(vo_full.best_matches(desc, desc, allowed, 0) == -1)


def test_windowed_matches_equal_the_masked_brute_force():
    rng = np.random.default_rng(1)
    n = 300
    xy_a = rng.uniform(0, 640, (n, 2)).astype(np.float32)
    xy_b = (xy_a + rng.normal(0, 10, (n, 2))).astype(np.float32)
    desc_a = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    desc_b = desc_a.copy()
    flip = rng.uniform(size=desc_b.shape) < 0.05
    desc_b[flip] ^= 0xFF

    def near(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.asarray(np.hypot(a[:, None, 0] - b[None, :, 0],
                                   a[:, None, 1] - b[None, :, 1]) <= 50.0)

    windowed = vo_full.windowed_matches(xy_a, desc_a, xy_b, desc_b, near, 0, 50.0, 256,
                                        band_px=12.5)
    brute = vo_full.best_matches(desc_a, desc_b, near(xy_a, xy_b), 256)
    assert np.array_equal(windowed, brute)
    assert np.mean(windowed == np.arange(n)) > 0.9


def test_circular_matches_keep_only_closed_circles():
    p_l2r = np.array([0, 1, -1, 2])
    pr_to_cr = np.array([1, 0, 2])
    cr_to_cl = np.array([3, 0, 1])
    cl_to_pl = np.array([1, 2, 0, 0])  # corner 0 closes (0→0→1→0→… no), see below
    # pl 0 → pr 0 → cr 1 → cl 0 → pl 1: open. pl 1 → pr 1 → cr 0 → cl 3 → pl 0: open.
    # pl 3 → pr 2 → cr 2 → cl 1 → pl 2: open.
    assert all(len(x) == 0 for x in vo_full.circular_matches(p_l2r, pr_to_cr, cr_to_cl,
                                                             cl_to_pl))
    cl_to_pl = np.array([0, 3, 0, 1])
    pl, pr, cr, cl = vo_full.circular_matches(p_l2r, pr_to_cr, cr_to_cl, cl_to_pl)
    assert list(pl) == [0, 1, 3] and list(pr) == [0, 1, 2] and list(cr) == [1, 0, 2]
    assert list(cl) == [0, 3, 1]


def test_bucket_keeps_at_most_per_cell_in_order():
    xy = np.array([[1, 1], [2, 2], [3, 3], [60, 1], [61, 2], [1, 60]], dtype=float)
    assert list(vo_full.bucket(xy, 50, 2)) == [0, 1, 3, 4, 5]
    assert list(vo_full.bucket(xy, 50, 1)) == [0, 3, 5]
    assert len(vo_full.bucket(np.zeros((0, 2)), 50, 2)) == 0


def test_stereo_jacobian_matches_central_differences():
    rng = np.random.default_rng(2)
    rot, t = _motion(rng)
    pts = _points(rng, 7)
    obs = rng.normal(300, 50, (7, 4))
    _, jac = vo_full.stereo_residuals(rot, t, pts, obs, K, BASELINE_M)
    eps = 1e-6
    for k in range(6):
        step = np.zeros(6)
        step[k] = eps
        out = []
        for sign in (1.0, -1.0):
            d_rot, _ = cv2.Rodrigues(sign * step[:3])
            r, _ = vo_full.stereo_residuals(d_rot @ rot, d_rot @ t + sign * step[3:], pts, obs,
                                            K, BASELINE_M)
            out.append(r)
        numeric = (out[0] - out[1]) / (2 * eps)
        np.testing.assert_allclose(jac[:, :, k], numeric, rtol=1e-5, atol=1e-4)


def test_gauss_newton_recovers_the_motion_from_stereo_observations():
    rng = np.random.default_rng(3)
    rot, t = _motion(rng)
    pts = _points(rng, 40)
    obs = _observe(rot, t, pts) + rng.normal(0.0, 0.05, (40, 4))
    est_rot, est_t = vo_full.gauss_newton(np.eye(3), np.zeros(3), pts, obs, K, BASELINE_M, 10)
    angle = np.linalg.norm(cv2.Rodrigues(est_rot @ rot.T)[0])
    assert angle < 1e-3
    np.testing.assert_allclose(est_t, t, atol=0.02)


@pytest.mark.parametrize("rate_rad_s", [0.0, math.pi / 2])
def test_circular_vo_tracks_a_short_synthetic_drive(rate_rad_s):
    # 0.9 s straight or turning at 9°/frame, 320×240: every increment within 0.3° and 3 cm.
    cfg = scenario("sharp_turns", segments=((0.9, 1.0, rate_rad_s),), width_px=320,
                   height_px=240, fx_px=250.0, num_objects=4)
    drive = make_drive(cfg)
    info = drive.camera_info
    vo = vo_full.CircularStereoVO(info.intrinsics, info.mounting,
                                  vo_full.CircularVOConfig(max_features=800, bucket_px=40))
    for i, frame in enumerate(drive.frames()):
        inc = vo.process(frame.left, frame.right, np.full(3, np.nan))
        if i == 0:
            continue
        assert np.all(np.isfinite(inc)), f"frame {i} fell back"
        assert abs(inc[2] - drive.true_deltas[i, 2]) < math.radians(0.3)
        assert np.hypot(*(inc[:2] - drive.true_deltas[i, :2])) < 0.03
    assert vo.stats.failed == 0 and vo.stats.frames == len(drive)


def test_circular_vo_falls_back_to_the_wheels_on_a_blank_view():
    cfg = scenario("straight", segments=((0.3, 1.0, 0.0),), width_px=160, height_px=120)
    info = make_drive(cfg).camera_info
    vo = vo_full.CircularStereoVO(info.intrinsics, info.mounting)
    blank = np.full((120, 160), 128, dtype=np.uint8)
    wheel = np.array([0.1, 0.0, 0.01])
    vo.process(blank, blank, wheel)
    np.testing.assert_array_equal(vo.process(blank, blank, wheel), wheel)
    assert vo.stats.failed == 1


def test_segment_drift_is_zero_on_truth_and_the_scale_error_when_scaled():
    steps = np.tile([0.5, 0.0, 0.05], (200, 1))
    truth = integrate(np.zeros(3), steps)
    assert vo_kitti.segment_drift(truth, truth, (5.0, 10.0)) == pytest.approx((0.0, 0.0))
    scaled = integrate(np.zeros(3), steps * np.array([1.02, 1.0, 1.0]))
    # Two percent more travel per step: about two percent translation error per segment.
    pct, _ = vo_kitti.segment_drift(scaled, truth, (5.0, 10.0))
    assert pct == pytest.approx(2.0, rel=0.1)
    assert math.isnan(vo_kitti.segment_drift(truth, truth, (1e6,))[0])
    # Rotation error per metre: a constant extra yaw per step.
    turned = integrate(np.zeros(3), steps + np.array([0.0, 0.0, 0.001]))
    _, deg_m = vo_kitti.segment_drift(turned, truth, (10.0,))
    assert deg_m == pytest.approx(math.degrees(0.001 / 0.5), rel=0.05)
    assert planar_between(truth[0], truth[0]).tolist() == [0.0, 0.0, 0.0]
