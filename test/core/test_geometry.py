"""Property tests of the rigid-body geometry (hypothesis), including its awkward angles."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from h2o_slam.core import geometry as geo

# Few examples per property keep the suite fast; the strategies aim at the awkward cases.
fast = settings(max_examples=40, deadline=None)

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
vec3 = arrays(np.float64, 3, elements=finite)
quat = arrays(np.float64, 4, elements=st.floats(-1.0, 1.0)).filter(
    lambda q: np.linalg.norm(q) > 1e-3
)


@st.composite
def axes(draw: st.DrawFn) -> np.ndarray:
    v = draw(arrays(np.float64, 3, elements=st.floats(-1.0, 1.0)))
    assume(np.linalg.norm(v) > 1e-3)
    return v / np.linalg.norm(v)


@st.composite
def rotvecs(draw: st.DrawFn, lo: float = 0.0, hi: float = np.pi) -> np.ndarray:
    return draw(axes()) * draw(st.floats(lo, hi))


poses = st.tuples(arrays(np.float64, 3, elements=st.floats(-3.0, 3.0)), vec3).map(
    lambda p: (geo.so3_exp(p[0]), p[1])
)


def is_rotation(R: np.ndarray, atol: float = 1e-12) -> bool:
    return bool(
        np.allclose(R.T @ R, np.eye(3), atol=atol) and np.isclose(np.linalg.det(R), 1.0)
    )


# --- exp / log -----------------------------------------------------------------------------


@fast
@given(rotvecs(0.0, np.pi - 1e-6))
def test_log_inverts_exp_below_pi(w: np.ndarray) -> None:
    R = geo.so3_exp(w)
    assert is_rotation(R)
    np.testing.assert_allclose(geo.so3_log(R), w, atol=1e-9)


@fast
@given(rotvecs(np.pi - 1e-6, np.pi))
def test_log_near_pi_returns_the_same_rotation(w: np.ndarray) -> None:
    # At exactly π, w and -w are the same rotation; compare rotations, and the angle.
    R = geo.so3_exp(w)
    v = geo.so3_log(R)
    assert np.linalg.norm(v) <= np.pi + 1e-12
    np.testing.assert_allclose(np.linalg.norm(v), np.linalg.norm(w), atol=1e-9)
    np.testing.assert_allclose(geo.so3_exp(v), R, atol=1e-12)


@fast
@given(rotvecs(0.0, 1e-5))
def test_log_inverts_exp_near_zero_relative(w: np.ndarray) -> None:
    np.testing.assert_allclose(geo.so3_log(geo.so3_exp(w)), w, rtol=0, atol=1e-12 * max(
        np.linalg.norm(w), 1e-300))


@fast
@given(vec3)
def test_exp_of_log_is_identity_map_on_rotations(w: np.ndarray) -> None:
    R = geo.so3_exp(w)
    v = geo.so3_log(R)
    assert np.linalg.norm(v) <= np.pi + 1e-12
    np.testing.assert_allclose(geo.so3_exp(v), R, atol=1e-12)


def test_exp_log_batched_shapes() -> None:
    w = np.random.default_rng(0).normal(size=(4, 5, 3))
    assert geo.so3_exp(w).shape == (4, 5, 3, 3)
    np.testing.assert_allclose(geo.so3_exp(geo.so3_log(geo.so3_exp(w))), geo.so3_exp(w),
                               atol=1e-12)


def test_log_exactly_pi_about_each_axis() -> None:
    for k in range(3):
        w = np.zeros(3)
        w[k] = np.pi
        v = geo.so3_log(geo.so3_exp(w))
        np.testing.assert_allclose(np.abs(v), np.abs(w), atol=1e-12)


# --- quaternions ---------------------------------------------------------------------------


@fast
@given(quat)
def test_quaternion_matrix_round_trip(q: np.ndarray) -> None:
    R = geo.quat_to_matrix(q)
    assert is_rotation(R)
    np.testing.assert_allclose(geo.quat_to_matrix(-q), R, atol=1e-15)
    back = geo.matrix_to_quat(R)
    assert back[3] >= 0.0
    qn = q / np.linalg.norm(q)
    sign = 1.0 if qn[3] >= 0 else -1.0
    # When w ≈ 0 both signs are valid; the rotation is what must agree.
    if abs(qn[3]) > 1e-9:
        np.testing.assert_allclose(back, sign * qn, atol=1e-14)
    np.testing.assert_allclose(geo.quat_to_matrix(back), R, atol=1e-14)


def test_quaternion_convention_is_scalar_last() -> None:
    # 90° about z: (x, y, z, w) = (0, 0, sin 45°, cos 45°).
    q = np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])
    np.testing.assert_allclose(geo.quat_to_matrix(q), geo.yaw_to_matrix(np.pi / 2), atol=1e-15)


def test_zero_quaternion_is_rejected() -> None:
    import pytest

    with pytest.raises(ValueError, match="zero or non-finite norm"):
        geo.quat_to_matrix(np.zeros(4))


# --- pose algebra --------------------------------------------------------------------------


@fast
@given(poses, poses, poses)
def test_compose_is_associative(A: tuple, B: tuple, C: tuple) -> None:
    left = geo.compose(*geo.compose(*A, *B), *C)
    right = geo.compose(*A, *geo.compose(*B, *C))
    np.testing.assert_allclose(left[0], right[0], atol=1e-12)
    np.testing.assert_allclose(left[1], right[1], atol=1e-11)


@fast
@given(poses)
def test_inverse_axioms(A: tuple) -> None:
    R, t = geo.compose(*A, *geo.inverse(*A))
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t, 0.0, atol=1e-12)
    Ri, ti = geo.inverse(*geo.inverse(*A))
    np.testing.assert_allclose(Ri, A[0], atol=1e-15)
    np.testing.assert_allclose(ti, A[1], atol=1e-12)


@fast
@given(poses, poses)
def test_between_is_inverse_then_compose(A: tuple, B: tuple) -> None:
    R1, t1 = geo.between(*A, *B)
    R2, t2 = geo.compose(*geo.inverse(*A), *B)
    np.testing.assert_allclose(R1, R2, atol=1e-12)
    np.testing.assert_allclose(t1, t2, atol=1e-11)
    # And B = A · (A⁻¹ B).
    R3, t3 = geo.compose(*A, R1, t1)
    np.testing.assert_allclose(R3, B[0], atol=1e-12)
    np.testing.assert_allclose(t3, B[1], atol=1e-11)


@fast
@given(poses, poses)
def test_relative_error_is_zero_for_exact_measurement(A: tuple, B: tuple) -> None:
    K = geo.between(*A, *B)
    np.testing.assert_allclose(geo.relative_error(*A, *B, *K), 0.0, atol=1e-10)


@fast
@given(st.integers(1, 40), st.integers(0, 2**32 - 1))
def test_cumulative_compose_equals_loop(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = geo.so3_exp(rng.normal(size=(n, 3)))
    t = rng.normal(size=(n, 3))
    PR, Pt = geo.cumulative_compose(R, t)
    acc_R, acc_t = R[0], t[0]
    np.testing.assert_allclose(PR[0], acc_R)
    for k in range(1, n):
        acc_R, acc_t = geo.compose(acc_R, acc_t, R[k], t[k])
        np.testing.assert_allclose(PR[k], acc_R, atol=1e-12)
        np.testing.assert_allclose(Pt[k], acc_t, atol=1e-11)


def test_cumulative_compose_leaves_inputs_alone() -> None:
    R = geo.so3_exp(np.random.default_rng(1).normal(size=(5, 3)))
    t = np.ones((5, 3))
    R0, t0 = R.copy(), t.copy()
    geo.cumulative_compose(R, t)
    np.testing.assert_array_equal(R, R0)
    np.testing.assert_array_equal(t, t0)


# --- Jacobians -----------------------------------------------------------------------------


def _fd_right_jacobian_inv(w: np.ndarray, h: float = 1e-6) -> np.ndarray:
    J = np.zeros((3, 3))
    Rw = geo.so3_exp(w)
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        plus = geo.so3_log(Rw @ geo.so3_exp(d))
        minus = geo.so3_log(Rw @ geo.so3_exp(-d))
        J[:, i] = (plus - minus) / (2 * h)
    return J


@fast
@given(rotvecs(0.0, np.pi - 0.1))
def test_right_jacobian_inv_matches_finite_differences(w: np.ndarray) -> None:
    np.testing.assert_allclose(geo.so3_right_jacobian_inv(w), _fd_right_jacobian_inv(w),
                               atol=1e-6)


def test_right_jacobian_inv_small_angle_branch() -> None:
    # Both sides of the series switch at |w| = 1e-4, and zero itself.
    for angle in (0.0, 1e-9, 5e-5, 1e-4, 2e-4):
        w = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]) * angle
        np.testing.assert_allclose(geo.so3_right_jacobian_inv(w), _fd_right_jacobian_inv(w),
                                   atol=1e-7)


# --- orthonormalize, yaw, wrap -------------------------------------------------------------


@fast
@given(arrays(np.float64, (3, 3), elements=finite))
def test_orthonormalize_gives_rotations(M: np.ndarray) -> None:
    with np.errstate(all="ignore"):
        assume(abs(np.linalg.det(M)) > 1e-3)
    assert is_rotation(geo.orthonormalize(M), atol=1e-10)


@fast
@given(rotvecs(), arrays(np.float64, (3, 3), elements=st.floats(-1e-6, 1e-6)))
def test_orthonormalize_fixes_small_drift(w: np.ndarray, noise: np.ndarray) -> None:
    R = geo.so3_exp(w)
    np.testing.assert_allclose(geo.orthonormalize(R + noise), R, atol=1e-5)
    np.testing.assert_allclose(geo.orthonormalize(R), R, atol=1e-14)


@fast
@given(st.floats(-100.0, 100.0))
def test_yaw_round_trip(yaw: float) -> None:
    R = geo.yaw_to_matrix(yaw)
    assert is_rotation(R)
    back = geo.matrix_to_yaw(R)
    assert -np.pi < back <= np.pi
    assert abs(geo.wrap_angle(back - yaw)) < 1e-12


def test_yaw_matrix_is_rotation_about_z() -> None:
    np.testing.assert_allclose(geo.yaw_to_matrix(0.3), geo.so3_exp([0.0, 0.0, 0.3]),
                               atol=1e-15)


@fast
@given(st.floats(-1e6, 1e6))
def test_wrap_angle_range(a: float) -> None:
    w = geo.wrap_angle(a)
    assert -np.pi <= w < np.pi
    k = (a - w) / (2 * np.pi)
    assert abs(k - round(k)) < 1e-6


def test_wrap_angle_edges() -> None:
    below = np.nextafter(-np.pi, -np.inf)
    values = geo.wrap_angle(np.array([np.pi, -np.pi, below, 3 * np.pi, 0.0, -0.0]))
    assert np.all(values >= -np.pi) and np.all(values < np.pi)
    np.testing.assert_allclose(values[:4], -np.pi, atol=1e-15)


@settings(max_examples=200, deadline=None)
@given(w=st.lists(st.floats(-3.1, 3.1), min_size=3, max_size=3))
def test_single_versions_match_batched(w):
    w = np.array(w)
    R = geo.so3_exp(w)
    assert np.allclose(geo.so3_log_one(R), geo.so3_log(R), atol=1e-12)
    assert np.allclose(geo.so3_right_jacobian_inv_one(w), geo.so3_right_jacobian_inv(w),
                       atol=1e-9)


def test_renormalize_squares_the_drift():
    rng = np.random.default_rng(0)
    R = geo.so3_exp(rng.normal(size=(20, 3))) + 1e-6 * rng.normal(size=(20, 3, 3))
    drift = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max()
    fixed = geo.renormalize(R)
    assert np.abs(np.swapaxes(fixed, 1, 2) @ fixed - np.eye(3)).max() < 10 * drift**2


@given(st.integers(1, 40), st.integers(0, 2**31 - 1))
def test_chain_product_is_the_last_prefix_product(n, seed):
    rng = np.random.default_rng(seed)
    R = geo.so3_exp(rng.normal(size=(n, 3)))
    t = rng.normal(size=(n, 3))
    R_all, t_all = geo.cumulative_compose(R, t)
    R_end, t_end = geo.chain_product(R, t)
    assert np.allclose(R_end, R_all[-1]) and np.allclose(t_end, t_all[-1])


@fast
@given(st.integers(1, 300), st.integers(1, 3), st.integers(0, 2**31 - 1))
def test_rotations_about_z_compose_by_adding_angles(n, batch, seed):
    """The angle path (taken for long chains of z-rotations, as every planar graph's are)
    gives what the general scan gives."""
    rng = np.random.default_rng(seed)
    R = geo.yaw_to_matrix(rng.uniform(-np.pi, np.pi, (n, batch)))
    t = rng.normal(size=(n, batch, 3))
    fast_R, fast_t = geo.cumulative_compose(R, t)
    # A tilt of 1e-300 rad is invisible to the products but sends them down the scan.
    tilted = R.copy()
    tilted[..., 2, 0] = 1e-300
    scan_R, scan_t = geo.cumulative_compose(tilted, t)
    np.testing.assert_allclose(fast_R, scan_R, atol=1e-12)
    np.testing.assert_allclose(fast_t, scan_t, atol=1e-10 * n)
    end_R, end_t = geo.chain_product(R[:, 0], t[:, 0])
    np.testing.assert_allclose(end_R, scan_R[-1, 0], atol=1e-12)
    np.testing.assert_allclose(end_t, scan_t[-1, 0], atol=1e-10 * n)


def test_planar_rotations_stay_exactly_about_z():
    """What keeps planar chains on the angle path: products, exponentials of (0, 0, θ) and
    renormalization leave the off-plane entries exactly zero."""
    rng = np.random.default_rng(3)
    R = geo.yaw_to_matrix(rng.uniform(-3.0, 3.0, 64))
    R = geo.renormalize(R @ geo.so3_exp(np.c_[np.zeros((64, 2)), rng.normal(size=64)]))
    R_all, _ = geo.cumulative_compose(R, np.zeros((64, 3)))
    for M in (R, R_all):
        assert np.all(M[:, 2, 2] == 1.0)
        assert not np.any(M[:, 2, :2]) and not np.any(M[:, :2, 2])


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=6, max_size=6))
def test_planar_compose_and_between_are_se2_composition_and_its_inverse(v):
    """``a ⊕ (a⁻¹ b) = b``, and both agree with the 3-D composition of the poses as
    rotations about z."""
    a = np.array([v[0], v[1], v[2] % 6.0 - 3.0])
    b = np.array([v[3], v[4], v[5] % 6.0 - 3.0])
    d = geo.planar_between(a, b)
    back = geo.planar_compose(a, d)
    np.testing.assert_allclose(back[:2], b[:2], atol=1e-9)
    assert abs(float(geo.wrap_angle(back[2] - b[2]))) < 1e-12
    Ra, Rd = geo.yaw_to_matrix(a[2]), geo.yaw_to_matrix(d[2])
    R, t = geo.compose(Ra, np.array([a[0], a[1], 0.0]), Rd, np.array([d[0], d[1], 0.0]))
    np.testing.assert_allclose(t[:2], b[:2], atol=1e-9)
    assert abs(float(geo.wrap_angle(geo.matrix_to_yaw(R) - b[2]))) < 1e-12
    stacked = geo.planar_between(np.stack([a, a]), np.stack([b, a]))
    np.testing.assert_allclose(stacked, [d, [0.0, 0.0, 0.0]], atol=1e-12)
