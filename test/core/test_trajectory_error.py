"""ATE, alignment and stamp matching against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from h2o_slam.core.geometry import yaw_to_matrix
from h2o_slam.core.trajectory_error import align_planar, ate_m, final_error_m, match_stamps


def test_ate_is_zero_for_a_rigidly_moved_copy_and_the_rms_otherwise() -> None:
    rng = np.random.default_rng(0)
    truth = np.cumsum(rng.normal(size=(200, 2)), axis=0)
    R = yaw_to_matrix(0.7)[:2, :2]
    moved = truth @ R.T + [5.0, -3.0]
    assert ate_m(moved, truth) < 1e-9
    R_fit, t_fit = align_planar(moved, truth)
    np.testing.assert_allclose(R_fit, R.T, atol=1e-12)
    # Noise of known RMS, with mean and rotation removed so alignment cannot absorb it.
    noise = rng.normal(size=truth.shape) * 0.3
    noise -= noise.mean(axis=0)
    noisy = truth + noise
    assert ate_m(noisy, truth) <= np.sqrt(np.mean(np.sum(noise**2, axis=1))) + 1e-12
    assert ate_m(noisy, truth) > 0.25


def test_alignment_never_reflects() -> None:
    truth = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [2.0, 3.0]])
    mirrored = truth * [1.0, -1.0]
    R, _ = align_planar(mirrored, truth)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert ate_m(mirrored, truth) > 0.5


def test_final_error_and_stamp_matching() -> None:
    est = np.array([[0.0, 0.0], [1.0, 1.0], [3.0, 4.0]])
    truth = np.zeros((3, 2))
    assert final_error_m(est, truth) == 5.0
    i, j = match_stamps([100, 205, 290, 900], [0, 100, 200, 300], tolerance_ns=10)
    assert i.tolist() == [0, 1, 2] and j.tolist() == [1, 2, 3]
    with pytest.raises(ValueError, match="two or more"):
        ate_m(est[:1], truth[:1])
