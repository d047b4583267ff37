"""Covariance variants of Carlone et al.'s Table 1: the odometry model, its Jacobian against
central differences, P_f symmetric positive definite, the frame change and the variants."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.baselines import covariance_variants as cv
from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import chi2
from h2o_slam.core.lago import paper_information
from h2o_slam.io.synthetic import grid3d, manhattan

PLANAR = [0, 1, 5]

relative = st.tuples(
    st.floats(-20.0, 20.0), st.floats(-20.0, 20.0), st.floats(-np.pi, np.pi),
)


def _params(dx: float, dy: float, yaw: float) -> np.ndarray:
    return cv.odometry_parameters(np.array([[dx, dy]]), np.array([yaw]))


def _central_differences(params: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """∂ odometry_pose / ∂ params at ``params`` (3,), by central differences."""
    G = np.zeros((3, 3))
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        G[:, k] = (cv.odometry_pose(params + step)[0] - cv.odometry_pose(params - step)[0]) / (
            2 * h)
    return G


@settings(max_examples=200, deadline=None)
@given(relative)
def test_odometry_parameters_round_trip(rel):
    dx, dy, yaw = rel
    pose = cv.odometry_pose(_params(dx, dy, yaw))[0]
    np.testing.assert_allclose(pose[:2], [dx, dy], rtol=0, atol=1e-12)
    assert abs(geo.wrap_angle(pose[2] - yaw)) < 1e-12


@settings(max_examples=200, deadline=None)
@given(st.floats(-np.pi, np.pi), st.floats(cv.MIN_TRANS_M, 30.0), st.floats(-np.pi, np.pi))
def test_jacobian_matches_central_differences(rot1, trans, rot2):
    params = np.array([rot1, trans, rot2])
    fd = _central_differences(params)
    np.testing.assert_allclose(cv.odometry_jacobian(params)[0], fd, rtol=0, atol=1e-8)


@settings(max_examples=200, deadline=None)
@given(relative)
def test_full_covariance_is_the_propagated_one(rel):
    """P_f equals G diag(σ²) Gᵀ with G from central differences of the odometry model
    (at the floored translation) and is symmetric positive definite."""
    dx, dy, yaw = rel
    P = cv.odometry_covariance(np.array([[dx, dy]]), np.array([yaw]))[0]
    params = _params(dx, dy, yaw)[0]
    params[1] = max(params[1], cv.MIN_TRANS_M)
    G = _central_differences(params)
    expect = G @ np.diag(np.square(cv.ODOMETRY_SIGMAS)) @ G.T
    np.testing.assert_allclose(P, expect, rtol=1e-6, atol=1e-8 * np.abs(P).max())
    np.testing.assert_array_equal(P, P.T)
    assert np.linalg.eigvalsh(P).min() > 0.0
    np.linalg.cholesky(P)


def test_full_covariance_matches_sampling():
    """The first-order covariance is what sampling the odometry noise gives, to first
    order: small σ, a 2 m step with a 30° heading."""
    rng = np.random.default_rng(3)
    sig = np.array([0.002, 0.002, 0.001])
    base = np.array([np.pi / 6, 2.0, 0.2])
    noise = rng.normal(size=(200_000, 3)) * sig
    poses = cv.odometry_pose(base + noise)
    P = cv.odometry_covariance(cv.odometry_pose(base)[:, :2], cv.odometry_pose(base)[:, 2],
                               tuple(sig))[0]
    np.testing.assert_allclose(np.cov(poses.T), P, rtol=0.02, atol=1e-9)


def test_pure_rotation_is_positive_definite():
    """At zero translation the model's Jacobian is singular; the floor keeps P_f SPD."""
    P = cv.odometry_covariance(np.zeros((1, 2)), np.array([0.7]))[0]
    assert np.linalg.eigvalsh(P).min() > 0.0
    # Along the (arbitrary) heading the translation's variance is σ_t².
    assert P[0, 0] == pytest.approx(cv.ODOMETRY_SIGMAS[1] ** 2)


def test_forward_step_correlates_lateral_position_and_yaw():
    """A straight 1 m step: lateral position and yaw both follow γ_r1 (correlation ≈ 0.98),
    the structure the unstructured LAGO exists for."""
    P = cv.odometry_covariance(np.array([[1.0, 0.0]]), np.array([0.0]))[0]
    s1, st_, s2 = cv.ODOMETRY_SIGMAS
    np.testing.assert_allclose(P, [[st_**2, 0, 0], [0, s1**2, s1**2],
                                   [0, s1**2, s1**2 + s2**2]], rtol=0, atol=1e-15)


def test_bad_sigmas_are_refused():
    with pytest.raises(ValueError, match="must be positive"):
        cv.odometry_covariance(np.ones((1, 2)), np.zeros(1), (0.0, 0.1, 0.1))
    with pytest.raises(ValueError, match="must be positive"):
        cv.odometry_covariance(np.ones((1, 2)), np.zeros(1), min_trans_m=0.0)


@pytest.mark.parametrize("seed", range(3))
def test_project_information_inverts_paper_information(seed):
    graph = random_graph(seed, planar=True, n=9, loops=5)
    omega = paper_information(graph.info, graph.meas_R)
    back = cv.project_information(omega, graph.meas_R)
    np.testing.assert_allclose(back, graph.info, rtol=0, atol=1e-9 * np.abs(graph.info).max())


@pytest.mark.parametrize("variant", cv.VARIANTS)
def test_variants_keep_measurements_and_use_their_covariance(variant):
    graph = random_graph(4, planar=True, n=10, loops=6)
    out = cv.with_variant(graph, variant)
    np.testing.assert_array_equal(out.meas_t, graph.meas_t)
    np.testing.assert_array_equal(out.meas_R, graph.meas_R)
    np.testing.assert_array_equal(out.t, graph.t)
    P = cv.variant_covariance(graph, variant)
    # The paper-frame information of the new graph is the inverse of the variant's P.
    omega = paper_information(out.info, out.meas_R)
    np.testing.assert_allclose(omega @ P, np.broadcast_to(np.eye(3), P.shape), atol=1e-8)
    assert np.all(np.linalg.eigvalsh(out.info[:, PLANAR][:, :, PLANAR]) > 0)
    # Rows the planar problem does not use stay zero.
    assert not np.any(out.info[:, 2:5, :]) and not np.any(out.info[:, :, 2:5])


def test_identity_variant_chi2_is_the_plain_sum_of_squares():
    graph = random_graph(5, planar=True, n=10, loops=6)
    out = cv.with_variant(graph, "I")
    # With identity information the χ² is the squared error in any frame.
    from h2o_slam.core.graph import edge_errors

    e = edge_errors(graph)[:, PLANAR]
    assert chi2(out) == pytest.approx(float(np.sum(e * e)), rel=1e-12)


def test_structured_variant_drops_only_cross_terms():
    graph = random_graph(6, planar=True, n=10, loops=6)
    P_full = np.linalg.inv(paper_information(graph.info, graph.meas_R))
    P_s = cv.variant_covariance(graph, "P_s")
    np.testing.assert_allclose(P_s[:, :2, :2], P_full[:, :2, :2], rtol=1e-12)
    np.testing.assert_allclose(P_s[:, 2, 2], P_full[:, 2, 2], rtol=1e-12)
    assert not np.any(P_s[:, :2, 2]) and not np.any(P_s[:, 2, :2])


def test_structured_variant_of_a_structured_graph_is_the_graph():
    """Manhattan-like graphs without position–yaw terms (as the public CSAIL and M3500
    files) are their own P_s variant."""
    graph = manhattan(80, seed=3).graph
    graph.info[:, 0:2, 5] = graph.info[:, 5, 0:2] = 0.0  # structured, as (4)
    out = cv.with_variant(graph, "P_s")
    np.testing.assert_allclose(out.info, graph.info, rtol=1e-9, atol=1e-9)


def test_full_variant_on_a_drive():
    """P_f of a Manhattan drive: every edge SPD, and the odometry edges (1 m steps) carry
    the lateral–yaw correlation."""
    graph = manhattan(80, seed=3).graph
    P = cv.variant_covariance(graph, "P_f")
    assert np.all(np.linalg.eigvalsh(P) > 0)
    np.testing.assert_allclose(P, P.transpose(0, 2, 1), rtol=0, atol=0)
    corr = P[:, 1, 2] / np.sqrt(P[:, 1, 1] * P[:, 2, 2])
    step = np.hypot(graph.meas_t[:, 0], graph.meas_t[:, 1]) > 0.5
    assert np.median(np.abs(corr[step])) > 0.5


def test_refusals():
    graph = random_graph(1, planar=True)
    with pytest.raises(ValueError, match="unknown variant 'P_x'; choose one of I, P_s, P_f"):
        cv.with_variant(graph, "P_x")
    with pytest.raises(InputError, match="planar graphs only"):
        cv.with_variant(grid3d(10, seed=1).graph, "I")
    with pytest.raises(InputError, match="relative edges only"):
        cv.with_variant(random_graph(1, planar=True, gps=2), "I")
