"""LAGO (Carlone et al., unstructured covariance): the paper's equations written out densely
and compared with the sparse implementation, Theorem 1, regularization, degenerate input,
error paths and the command line.

The dense references below follow the paper's notation: ``A`` is the reduced incidence
matrix (node 0 removed; ``Aᵀθ`` gives ``θ_j - θ_i``), ``A2 = A ⊗ I₂``, measurements are
stacked ``[Δ̄ˡ (2m); δ̄ (m)]`` and ``Ω`` is their ``3m × 3m`` information matrix (5).
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse

from h2o_slam.app.cli.solve import main
from h2o_slam.core import geometry as geo
from h2o_slam.core import lago as lago_mod
from h2o_slam.core import spd
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, chi2, make_graph
from h2o_slam.core.lago import (
    FACTORIZATIONS,
    lago,
    lago_estimate,
    paper_information,
    regularize,
    solve_spd,
    spanning_forest,
)
from h2o_slam.core.modes import solve_exact
from h2o_slam.io.g2o import read_g2o, write_g2o
from h2o_slam.io.synthetic import grid3d, manhattan

PLANAR = [0, 1, 5]
S90 = np.array([[0.0, -1.0], [1.0, 0.0]])  # d R(θ) / dθ = R(θ) S90

#: Factorizations whose backend is installed here (cvxopt and qdldl are in requirements.txt).
INSTALLED = [f for f in FACTORIZATIONS if f not in ("cholmod", "qdldl")
             or spd.available(f)]
#: The factorizations every path-dependent test runs with: SuperLU always, and "auto"
#: (CHOLMOD from cvxopt's wheel in the default install).
PATHS = ["splu-mmd", "auto"]


# --- graph builders ----------------------------------------------------------------------------


def rot2(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def planar_graph(
    yaw: np.ndarray,
    xy: np.ndarray,
    pairs: list[tuple[int, int]],
    info3: np.ndarray,
    rng: np.random.Generator,
    noise: float = 0.0,
) -> PoseGraph:
    """Relative edges ``pairs`` measured from the truth ``(yaw, xy)`` with noise drawn
    (``noise`` × the covariance of ``info3``, one 3×3 matrix or one per edge); the
    estimate is all zeros (LAGO needs none)."""
    n, m = len(yaw), len(pairs)
    info3 = np.broadcast_to(info3, (m, 3, 3))
    a = np.array([p[0] for p in pairs])
    b = np.array([p[1] for p in pairs])
    meas_R = np.zeros((m, 3, 3))
    meas_t = np.zeros((m, 3))
    info = np.zeros((m, 6, 6))
    for k, (i, j) in enumerate(pairs):
        e = np.zeros(3)
        if noise:
            e = noise * rng.multivariate_normal(np.zeros(3), np.linalg.inv(info3[k]))
        meas_t[k, :2] = rot2(yaw[i]).T @ (xy[j] - xy[i]) + e[:2]
        meas_R[k] = geo.yaw_to_matrix(geo.wrap_angle(yaw[j] - yaw[i] + e[2]))
        info[k][np.ix_(PLANAR, PLANAR)] = info3[k]
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    return make_graph(True, np.arange(n), eye, np.zeros((n, 3)),
                      np.full(m, EdgeKind.RELATIVE), a, b, meas_R, meas_t, info)


def block_diagonal(graph: PoseGraph) -> PoseGraph:
    """The graph with its position–yaw information cross terms removed (structured (4))."""
    out = graph.copy()
    out.info[:, 0:2, 5] = 0.0
    out.info[:, 5, 0:2] = 0.0
    return out


def truth_estimate(yaw: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.zeros((len(yaw), 3))
    t[:, :2] = xy
    return geo.yaw_to_matrix(yaw), t


# --- the paper, densely ------------------------------------------------------------------------


def paper_arrays(graph: PoseGraph, delta: np.ndarray):
    """``a, b, Δ̄ˡ (m, 2), δ̄ (m,), Ω_k (m, 3, 3)`` of the paper's model (1)–(3).

    ``Ω_k`` is the project's information rotated into the frame of node ``a`` by the
    measured rotation (the project measures translation errors in the measurement's frame;
    see ``test_paper_cost_with_rotated_information_is_the_project_chi2``).
    """
    S = graph.info[:, PLANAR][:, :, PLANAR]
    rot = np.zeros_like(S)
    rot[:, :2, :2] = graph.meas_R[:, :2, :2]
    rot[:, 2, 2] = 1.0
    omega = rot @ S @ rot.transpose(0, 2, 1)
    return graph.a, graph.b, graph.meas_t[:, :2], delta, omega


def incidence(a: np.ndarray, b: np.ndarray, num_nodes: int) -> np.ndarray:
    """Reduced incidence matrix ``A`` (n × m), node 0 removed: ``(Aᵀθ)_k = θ_b - θ_a``."""
    A = np.zeros((num_nodes, len(a)))
    A[a, np.arange(len(a))] = -1.0
    A[b, np.arange(len(a))] = 1.0
    return A[1:]


def stacked_information(omega: np.ndarray) -> np.ndarray:
    """``Ω`` (5): the information of ``[Δ̄ˡ; δ̄]``, ``3m × 3m``."""
    m = len(omega)
    big = np.zeros((3 * m, 3 * m))
    for k in range(m):
        pos = [2 * k, 2 * k + 1, 2 * m + k]
        big[np.ix_(pos, pos)] = omega[k]
    return big


def rotation_blocks(yaw_of_edges: np.ndarray) -> np.ndarray:
    """``R`` of (6): block diagonal, block ``k`` the rotation of the edge's first node."""
    m = len(yaw_of_edges)
    R = np.zeros((2 * m, 2 * m))
    for k in range(m):
        R[2 * k:2 * k + 2, 2 * k:2 * k + 2] = rot2(yaw_of_edges[k])
    return R


def jacobian_j(a: np.ndarray, yaw: np.ndarray, delta_l: np.ndarray, num_nodes: int):
    """``J = ∂(R(θ) Δˡ)/∂θ`` (12) at ``(Δˡ, θ)``, ``2m × n`` (node 0 is no unknown)."""
    m = len(a)
    J = np.zeros((2 * m, num_nodes))
    for k in range(m):
        J[2 * k:2 * k + 2, a[k]] = rot2(yaw[a[k]]) @ S90 @ delta_l[k]
    return J[:, 1:]


def algorithm1_dense(graph: PoseGraph, delta: np.ndarray, jacobian: str = "estimate"):
    """Algorithm 1 exactly as written, (8)–(14), with dense matrices; node 0 is the anchor."""
    a, b, dbar, dlt, omega = paper_arrays(graph, delta)
    N, m = graph.num_nodes, len(a)
    n = N - 1
    A = incidence(a, b, N)
    Om = stacked_information(omega)
    Z = np.block([[np.eye(2 * m), np.zeros((2 * m, n))], [np.zeros((m, 2 * m)), A.T]])
    meas = np.concatenate([dbar.ravel(), dlt])
    Om_z = Z.T @ Om @ Z  # (9)
    b_z = Z.T @ Om @ meas
    z = np.linalg.solve(Om_z, b_z)  # (8)
    D_hat, th_hat = z[:2 * m].reshape(m, 2), np.concatenate([[0.0], z[2 * m:]])
    R_hat = rotation_blocks(th_hat[a])
    J = jacobian_j(a, th_hat, D_hat if jacobian == "estimate" else dbar, N)
    T = np.block([[R_hat, J], [np.zeros((n, 2 * m)), np.eye(n)]])  # (12)
    y = np.concatenate([R_hat @ D_hat.ravel(), th_hat[1:]])  # (10)
    T_inv = np.linalg.inv(T)
    Om_y = T_inv.T @ Om_z @ T_inv  # (11), second form
    Om_y_cov = np.linalg.inv(T @ np.linalg.inv(Om_z) @ T.T)  # (11), first form
    A2 = np.kron(A, np.eye(2))
    B = np.block([[A2.T, np.zeros((2 * m, n))], [np.zeros((n, 2 * n)), np.eye(n)]])
    Om_x = B.T @ Om_y @ B  # (14)
    b_x = B.T @ Om_y @ y
    x = np.linalg.solve(Om_x, b_x)  # (13)
    return {
        "Om_z": Om_z, "Om_y": Om_y, "Om_y_cov": Om_y_cov, "Om_x": Om_x, "b_x": b_x,
        "D_hat": D_hat, "th_hat": th_hat,
        "p": np.vstack([[0.0, 0.0], x[:2 * n].reshape(n, 2)]),
        "th": np.concatenate([[0.0], x[2 * n:]]),
    }


def theorem1_start(graph: PoseGraph, delta: np.ndarray):
    """``(p̂, θ̂)`` of Theorem 1, by its formulas."""
    a, b, dbar, dlt, omega = paper_arrays(graph, delta)
    N, m = graph.num_nodes, len(a)
    A = incidence(a, b, N)
    Om = stacked_information(omega)
    O_D, O_Dd, O_d = Om[:2 * m, :2 * m], Om[:2 * m, 2 * m:], Om[2 * m:, 2 * m:]
    marg = O_d - O_Dd.T @ np.linalg.solve(O_D, O_Dd)  # P_δ⁻¹
    th = np.linalg.solve(A @ marg @ A.T, A @ marg @ dlt)
    th_hat = np.concatenate([[0.0], th])
    R_hat = rotation_blocks(th_hat[a])
    A2 = np.kron(A, np.eye(2))
    M = A2 @ R_hat @ O_D @ R_hat.T
    p = np.linalg.solve(M @ A2.T, M @ dbar.ravel())
    return np.vstack([[0.0, 0.0], p.reshape(-1, 2)]), th_hat


def gauss_newton_step(graph: PoseGraph, delta: np.ndarray, p0: np.ndarray, th0: np.ndarray):
    """One Gauss–Newton step on the cost (6) from ``(p0, th0)`` (node 0 fixed).

    As in the appendix, (17)–(18): the residual ``[p_j - p_i - R(θ_i) Δ̄ˡ; θ_j - θ_i - δ̄]``
    (regularized δ̄, no wrapping: linear in θ) is linearized at the start, and its weight
    ``diag(R(θ_i), 1) Ω diag(R(θ_i), 1)ᵀ`` is evaluated at ``θ = th0`` and held fixed. The
    Jacobian is taken by central differences, independent of any formula above.
    """
    a, b, dbar, dlt, omega = paper_arrays(graph, delta)
    N, m = graph.num_nodes, len(a)

    def residual(v: np.ndarray) -> np.ndarray:
        p = np.vstack([[0.0, 0.0], v[:2 * (N - 1)].reshape(-1, 2)])
        th = np.concatenate([[0.0], v[2 * (N - 1):]])
        out = np.empty((m, 3))
        for k in range(m):
            i, j = a[k], b[k]
            out[k, :2] = p[j] - p[i] - rot2(th[i]) @ dbar[k]
            out[k, 2] = th[j] - th[i] - dlt[k]
        return out.ravel()

    W = np.zeros((3 * m, 3 * m))
    for k in range(m):
        rk = np.eye(3)
        rk[:2, :2] = rot2(th0[a[k]])
        W[3 * k:3 * k + 3, 3 * k:3 * k + 3] = rk @ omega[k] @ rk.T
    x0 = np.concatenate([p0[1:].ravel(), th0[1:]])
    h = 1e-6
    Jac = np.column_stack([
        (residual(x0 + h * e) - residual(x0 - h * e)) / (2 * h) for e in np.eye(len(x0))
    ])
    r0 = residual(x0)
    x = x0 - np.linalg.solve(Jac.T @ W @ Jac, Jac.T @ W @ r0)
    return (np.vstack([[0.0, 0.0], x[:2 * (N - 1)].reshape(-1, 2)]),
            np.concatenate([[0.0], x[2 * (N - 1):]]))


def structured_lago_dense(graph: PoseGraph, delta: np.ndarray):
    """The original LAGO for structured covariance (Carlone et al. 2014), in covariance
    form: θ̂ = (A Ω_δ Aᵀ)⁻¹ A Ω_δ δ̄ with P_θ its inverse; ŷ = [R̂ Δ̄ˡ; θ̂] with
    P_y = [[R̂ P_Δ R̂ᵀ + J P_θ Jᵀ, J P_θ], [P_θ Jᵀ, P_θ]]; x* = (Bᵀ P_y⁻¹ B)⁻¹ Bᵀ P_y⁻¹ ŷ.
    Ignores any position–orientation correlation (uses the Ω_Δ and Ω_δ blocks)."""
    a, b, dbar, dlt, omega = paper_arrays(graph, delta)
    N, m = graph.num_nodes, len(a)
    n = N - 1
    A = incidence(a, b, N)
    O_d = np.diag(omega[:, 2, 2])
    P_th = np.linalg.inv(A @ O_d @ A.T)
    th_hat = np.concatenate([[0.0], P_th @ A @ O_d @ dlt])
    P_D = np.zeros((2 * m, 2 * m))
    for k in range(m):
        P_D[2 * k:2 * k + 2, 2 * k:2 * k + 2] = np.linalg.inv(omega[k, :2, :2])
    R_hat = rotation_blocks(th_hat[a])
    J = jacobian_j(a, th_hat, dbar, N)
    P_y = np.block([[R_hat @ P_D @ R_hat.T + J @ P_th @ J.T, J @ P_th], [P_th @ J.T, P_th]])
    y = np.concatenate([R_hat @ dbar.ravel(), th_hat[1:]])
    A2 = np.kron(A, np.eye(2))
    B = np.block([[A2.T, np.zeros((2 * m, n))], [np.zeros((n, 2 * n)), np.eye(n)]])
    W = np.linalg.inv(P_y)
    x = np.linalg.solve(B.T @ W @ B, B.T @ W @ y)
    return np.vstack([[0.0, 0.0], x[:2 * n].reshape(n, 2)]), np.concatenate([[0.0], x[2 * n:]])


def paper_to_node_major(n: int) -> np.ndarray:
    """Index into the paper's ``[p (2n); θ (n)]`` of each node-major ``(x, y, θ)`` unknown."""
    out = np.empty(3 * n, dtype=np.int64)
    out[0::3] = 2 * np.arange(n)
    out[1::3] = 2 * np.arange(n) + 1
    out[2::3] = 2 * n + np.arange(n)
    return out


def assert_poses(result, p: np.ndarray, th: np.ndarray, rtol: float) -> None:
    scale = max(1.0, float(np.abs(p).max()))
    np.testing.assert_allclose(result.t[:, :2], p, rtol=0, atol=rtol * scale)
    np.testing.assert_allclose(result.yaw_rad, th, rtol=0, atol=rtol * max(1.0, np.abs(th).max()))


# --- fixtures ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def city():
    return manhattan(300, seed=5)


def correlated(seed: int, n: int = 9, loops: int = 5) -> PoseGraph:
    """A random planar graph (test/graphs.py): random poses, random full 3×3 information
    with position–yaw correlation, noisy measurements."""
    return random_graph(seed, planar=True, n=n, loops=loops)


# --- the information in the paper's frame ------------------------------------------------------


@pytest.mark.parametrize("seed", range(3))
def test_paper_cost_with_rotated_information_is_the_project_chi2(seed):
    """The paper's cost (3) with Ω = diag(R_K, 1) S diag(R_K, 1)ᵀ equals chi2() exactly at
    any estimate (yaw errors wrapped as chi2 wraps them): LAGO minimizes the project's χ²."""
    graph = correlated(seed)
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-4, 4, graph.num_nodes)
    xy = rng.normal(scale=3.0, size=(graph.num_nodes, 2))
    a, b = graph.a, graph.b
    meas_yaw = geo.matrix_to_yaw(graph.meas_R)
    _, _, dbar, _, omega = paper_arrays(graph, meas_yaw)
    cost = 0.0
    for k in range(graph.num_edges):
        r = np.empty(3)
        r[:2] = rot2(yaw[a[k]]).T @ (xy[b[k]] - xy[a[k]]) - dbar[k]
        r[2] = geo.wrap_angle(yaw[b[k]] - yaw[a[k]] - meas_yaw[k])
        cost += r @ omega[k] @ r
    assert cost == pytest.approx(chi2(graph, *truth_estimate(yaw, xy)), rel=1e-12)
    np.testing.assert_allclose(paper_information(graph.info, graph.meas_R), omega, rtol=1e-13,
                               atol=1e-13 * np.abs(omega).max())


# --- Algorithm 1 against its equations ---------------------------------------------------------


@pytest.mark.parametrize("factorization", PATHS)
@pytest.mark.parametrize("jacobian", ["estimate", "measurement"])
@pytest.mark.parametrize("seed", range(4))
def test_phases_match_equations_8_to_14(seed, jacobian, factorization):
    graph = correlated(seed)
    res = lago(graph, jacobian=jacobian, factorization=factorization)
    ref = algorithm1_dense(graph, res.delta_rad, jacobian)
    # Well-conditioned random information (GGᵀ + 3I): agreement to rounding.
    np.testing.assert_allclose(res.yaw_hat_rad, ref["th_hat"], rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.delta_hat, ref["D_hat"], rtol=0, atol=1e-10)
    # (11): both forms of Ω_y agree (T̂ is invertible).
    np.testing.assert_allclose(ref["Om_y"], ref["Om_y_cov"], rtol=1e-8,
                               atol=1e-8 * np.abs(ref["Om_y"]).max())
    n = graph.num_nodes - 1
    perm = paper_to_node_major(n)
    info = res.information.toarray()
    np.testing.assert_allclose(info, ref["Om_x"][np.ix_(perm, perm)], rtol=0,
                               atol=1e-10 * np.abs(ref["Om_x"]).max())
    assert_poses(res, ref["p"], ref["th"], 1e-9)
    # Theorem 1, claim 1: Ω_z, Ω_y, Ω_x are full rank (positive definite here).
    for key in ("Om_z", "Om_y", "Om_x"):
        assert np.linalg.eigvalsh(ref[key]).min() > 0.0


def test_result_fields_are_consistent(city):
    graph = city.graph
    res = lago(graph)
    m = graph.num_edges
    assert res.edges.shape == res.k.shape == res.delta_rad.shape == (m,)
    assert res.delta_hat.shape == (m, 2)
    assert list(res.anchors) == [0] and list(res.free) == list(range(1, graph.num_nodes))
    meas_yaw = geo.matrix_to_yaw(graph.meas_R)
    np.testing.assert_allclose(res.delta_rad, meas_yaw - 2 * np.pi * res.k, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.R, geo.yaw_to_matrix(res.yaw_rad), rtol=0, atol=0)
    assert np.all(res.t[:, 2] == 0.0)
    assert sparse.issparse(res.information)
    assert res.information.shape == (3 * (graph.num_nodes - 1),) * 2
    R, t = lago_estimate(graph)
    np.testing.assert_array_equal(R, res.R)
    np.testing.assert_array_equal(t, res.t)


# --- structured covariance: the original LAGO --------------------------------------------------


@pytest.mark.parametrize("factorization", PATHS)
@pytest.mark.parametrize("seed", range(4))
def test_block_diagonal_covariance_gives_the_structured_lago(seed, factorization):
    """With Ω_Δδ = 0 the unstructured algorithm reduces to the original LAGO (the paper's
    Table 1, variants I and P_s): compared with the covariance-form reference."""
    graph = block_diagonal(correlated(seed))
    for jacobian in ("estimate", "measurement"):  # identical when Δ̂ˡ = Δ̄ˡ
        res = lago(graph, jacobian=jacobian, factorization=factorization)
        np.testing.assert_allclose(res.delta_hat, graph.meas_t[:, :2], rtol=0, atol=1e-12)
        p, th = structured_lago_dense(graph, res.delta_rad)
        assert_poses(res, p, th, 1e-9)


def test_correlations_change_the_answer():
    """The reference really ignores correlations: on a correlated graph the two differ."""
    graph = correlated(1)
    res = lago(graph)
    p, th = structured_lago_dense(graph, res.delta_rad)
    assert np.abs(res.t[:, :2] - p).max() > 1e-4


@pytest.mark.parametrize("factorization", PATHS)
@pytest.mark.parametrize("seed", range(4))
def test_structured_variant_is_the_2012_approximation(seed, factorization):
    """``covariance="structured"`` on a correlated graph is the covariance-form reference of
    the original LAGO (which reads the Ω_Δ and Ω_δ blocks only), and the same as the full
    algorithm on the graph with its cross terms removed."""
    graph = correlated(seed)
    res = lago(graph, covariance="structured", factorization=factorization)
    np.testing.assert_allclose(res.delta_hat, graph.meas_t[:, :2], rtol=0, atol=1e-12)
    p, th = structured_lago_dense(graph, res.delta_rad)
    assert_poses(res, p, th, 1e-9)
    plain = lago(block_diagonal(graph), factorization=factorization)
    np.testing.assert_allclose(res.t, plain.t, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.yaw_rad, plain.yaw_rad, rtol=0, atol=1e-10)


def test_structured_variant_changes_nothing_without_correlations():
    """Variants I and P_s of the paper's Table 1: both columns attain the same objective."""
    graph = block_diagonal(correlated(2))
    full, structured = lago(graph), lago(graph, covariance="structured")
    np.testing.assert_allclose(full.t, structured.t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(full.yaw_rad, structured.yaw_rad, rtol=0, atol=1e-12)


# --- Theorem 1: one Gauss–Newton step from (p̂, θ̂) ---------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_theorem1_measurement_jacobian_is_one_gauss_newton_step(seed):
    """With J evaluated at Δ̄ˡ, Algorithm 1 is exactly one GN step on (6) from (p̂, θ̂),
    for full (correlated) covariances."""
    graph = correlated(seed, n=10, loops=6)
    res = lago(graph, jacobian="measurement")
    p_hat, th_hat = theorem1_start(graph, res.delta_rad)
    np.testing.assert_allclose(res.yaw_hat_rad, th_hat, rtol=0, atol=1e-10)
    p, th = gauss_newton_step(graph, res.delta_rad, p_hat, th_hat)
    # Central differences of sin/cos with h = 1e-6: ~1e-10 in the Jacobian.
    assert_poses(res, p, th, 1e-7)
    # p̂ does not matter (the residual is linear in p): a GN step from (0, θ̂) is the same.
    p2, th2 = gauss_newton_step(graph, res.delta_rad, np.zeros_like(p_hat), th_hat)
    assert_poses(res, p2, th2, 1e-7)


@pytest.mark.parametrize("seed", range(5))
def test_theorem1_default_jacobian(seed):
    """Equation (12) evaluates J at ẑ, i.e. with Δ̂ˡ. That is the GN step exactly when the
    covariance is structured; with correlations it differs from it at second order: by
    J(Δ̂ˡ - Δ̄ˡ)(θ* - θ̂), where Δ̂ˡ - Δ̄ˡ = Ω_Δ⁻¹Ω_Δδ(δ̄ - Aᵀθ̂) is itself a residual."""
    structured = block_diagonal(correlated(seed, n=10, loops=6))
    res = lago(structured)
    p, th = gauss_newton_step(structured, res.delta_rad,
                              *theorem1_start(structured, res.delta_rad))
    assert_poses(res, p, th, 1e-7)

    graph = correlated(seed, n=10, loops=6)
    est, gn = lago(graph), lago(graph, jacobian="measurement")
    shift = np.abs(est.delta_hat - graph.meas_t[:, :2]).max()
    turn = np.abs(gn.yaw_rad - gn.yaw_hat_rad).max()
    diff = max(np.abs(est.t - gn.t).max(), np.abs(est.yaw_rad - gn.yaw_rad).max())
    # Second order: at most the product of the two first-order quantities times a modest
    # factor for how far a change spreads through the graph (0.2–2.8 on these seeds).
    assert 0.0 < diff <= 10.0 * shift * turn
    assert chi2(graph, est.R, est.t) == pytest.approx(chi2(graph, gn.R, gn.t), rel=1e-2)


# --- regularization ----------------------------------------------------------------------------


def spiral(turns: int, per_turn: int, noise: float, seed: int, closures: bool = True):
    """A robot driving ``turns`` times around a circle of radius 3 m, ``per_turn`` poses a
    turn; odometry ``(i, i+1)`` and, if ``closures``, loop closures ``(i, i + per_turn)``
    (same place, one turn later: true relative yaw 2π, measured ≈ 0)."""
    n = turns * per_turn + 1
    yaw = np.arange(n) * (2 * np.pi / per_turn)  # unwrapped: grows to 2π·turns
    xy = 3.0 * np.column_stack([np.sin(yaw), 1.0 - np.cos(yaw)])
    pairs = [(i, i + 1) for i in range(n - 1)]
    if closures:
        pairs += [(i, i + per_turn) for i in range(n - per_turn)]
    info = np.array([[400.0, 50.0, 20.0], [50.0, 300.0, -10.0], [20.0, -10.0, 900.0]])
    rng = np.random.default_rng(seed)
    return planar_graph(yaw, xy, pairs, info, rng, noise), yaw, xy


@pytest.mark.parametrize("factorization", PATHS)
def test_spiral_of_many_turns(factorization):
    graph, yaw, xy = spiral(turns=6, per_turn=10, noise=1.0, seed=3)
    res = lago(graph, factorization=factorization)
    # Every regularized relative yaw is the true difference plus noise (σ_yaw ≈ 0.03 rad),
    # up to a multiple of 2π that is the same for every path (a tree-consistent choice).
    a, b = graph.a, graph.b
    err = res.delta_rad - (res.yaw_hat_rad[b] - res.yaw_hat_rad[a])
    assert np.abs(err).max() < 0.2
    assert np.any(res.k != 0)
    # The solution is the truth up to the noise (σ ≈ 5 cm and 0.03 rad per edge, the gauge
    # fixed at a noisy pose 0): yaw wrapped within 0.05 rad, positions within 0.5 m, and a
    # χ² below the truth's, as an optimum's is.
    assert np.abs(geo.wrap_angle(res.yaw_rad - yaw)).max() < 0.05
    assert np.abs(res.t[:, :2] - xy).max() < 0.5
    assert chi2(graph, res.R, res.t) < chi2(graph, *truth_estimate(yaw, xy))
    # Without the 2π terms the loop closures pull against the odometry and wreck it.
    naive_delta = geo.matrix_to_yaw(graph.meas_R)
    p, th = structured_lago_dense(block_diagonal(graph), naive_delta)
    assert np.abs(geo.wrap_angle(th - yaw)).max() > 1.0


@pytest.mark.parametrize("turns", [1, 3, 7])
def test_ring_closure_gets_the_number_of_turns(turns):
    """A single loop wound ``turns`` times and closed once (the last pose back at pose 0's
    place, 2π·turns later): the measured yaws sum to 2π·turns around the cycle, the
    regularized ones to 0; the breadth-first tree leaves one chord, and its k is ``turns``."""
    per_turn = 8
    n = turns * per_turn
    yaw = np.arange(n) * (2 * np.pi / per_turn)
    xy = 3.0 * np.column_stack([np.sin(yaw), 1.0 - np.cos(yaw)])
    pairs = [(i, i + 1) for i in range(n - 1)] + [(n - 1, 0)]
    graph = planar_graph(yaw, xy, pairs, np.diag([100.0, 100.0, 400.0]),
                         np.random.default_rng(0))
    res = lago(graph)
    assert geo.matrix_to_yaw(graph.meas_R).sum() == pytest.approx(2 * np.pi * turns)
    assert res.delta_rad.sum() == pytest.approx(0.0, abs=1e-9)
    assert list(res.k[res.k != 0]) == [turns]
    # Noise-free: LAGO is exact.
    assert np.abs(geo.wrap_angle(res.yaw_rad - yaw)).max() < 1e-9
    assert np.abs(res.t[:, :2] - xy).max() < 1e-9


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 25), st.integers(0, 2**32 - 1))
def test_regularization_recovers_unwrapped_differences(n, seed):
    """Noise-free measurements of arbitrary (unwrapped, many-turn) yaws on a random
    connected graph: the regularized yaw of every edge is the tree's difference, and the
    tree's yaws are the truth relative to the anchor, up to one 2π multiple per node."""
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-40.0, 40.0, n)
    order = rng.permutation(n)
    pairs = [(int(order[rng.integers(i)]), int(order[i])) for i in range(1, n)]  # random tree
    pairs += [tuple(int(v) for v in rng.choice(n, 2, replace=False)) for _ in range(n)]
    a = np.array([p[0] for p in pairs])
    b = np.array([p[1] for p in pairs])
    meas = geo.wrap_angle(yaw[b] - yaw[a])
    _, anchors, parent, tree_edge = spanning_forest(n, a, b)
    assert list(anchors) == [0]
    k, delta = regularize(n, a, b, meas, parent, tree_edge)
    tree_yaw = lago_mod.tree_orientations(n, a, b, meas, parent, tree_edge)
    np.testing.assert_allclose(delta, tree_yaw[b] - tree_yaw[a], rtol=0, atol=1e-9)
    assert np.abs(geo.wrap_angle(tree_yaw - (yaw - yaw[0]))).max() < 1e-8
    assert np.all(k[tree_edge[parent != EARTH]] == 0)


def test_parallel_edges_pick_the_best_tree_edge():
    a = np.array([0, 0, 1])
    b = np.array([1, 1, 2])
    _, _, parent, tree_edge = spanning_forest(3, a, b, weight=np.array([1.0, 5.0, 1.0]))
    assert list(parent) == [EARTH, 0, 1]
    assert list(tree_edge) == [-1, 1, 2]


# --- degenerate input --------------------------------------------------------------------------


def test_disconnected_components_are_anchored_separately(city):
    """Two graphs side by side (the second's nodes shifted) and an isolated node: each
    component is solved as if alone, anchored at its first node; the isolated node stays
    at the origin."""
    g1 = city.graph
    g2 = manhattan(120, seed=9).graph
    n1, n2 = g1.num_nodes, g2.num_nodes
    n = n1 + n2 + 1
    ids = np.arange(n)
    union = make_graph(
        True, ids, np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3)),
        np.concatenate([g1.kind, g2.kind]), np.concatenate([g1.a, g2.a + n1 + 1]),
        np.concatenate([g1.b, g2.b + n1 + 1]), np.concatenate([g1.meas_R, g2.meas_R]),
        np.concatenate([g1.meas_t, g2.meas_t]), np.concatenate([g1.info, g2.info]),
    )
    res = lago(union)
    assert list(res.anchors) == [0, n1, n1 + 1]
    assert set(np.unique(res.component)) == {0, 1, 2}
    alone1, alone2 = lago(g1), lago(g2)
    np.testing.assert_allclose(res.t[:n1], alone1.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.t[n1 + 1:], alone2.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.yaw_rad[n1 + 1:], alone2.yaw_rad, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(res.t[n1], np.zeros(3))
    np.testing.assert_array_equal(res.R[n1], np.eye(3))
    assert chi2(union, res.R, res.t) == pytest.approx(
        chi2(g1, alone1.R, alone1.t) + chi2(g2, alone2.R, alone2.t), rel=1e-12)


def relabel(graph: PoseGraph, perm: np.ndarray, flip: np.ndarray) -> PoseGraph:
    """Node ``i`` becomes ``perm[i]``; edges with ``flip`` are reversed: the measurement
    inverted and the information carried to the other end (``e' ≈ -Ad_K e`` to first order,
    so ``S' = Ad_K⁻ᵀ S Ad_K⁻¹`` with the planar adjoint of ``K``)."""
    a, b = perm[graph.a], perm[graph.b]
    mR, mt, info = graph.meas_R.copy(), graph.meas_t.copy(), graph.info.copy()
    for k in np.flatnonzero(flip):
        Ad = np.eye(3)
        Ad[:2, :2] = mR[k][:2, :2]
        Ad[:2, 2] = [mt[k][1], -mt[k][0]]
        Ai = np.linalg.inv(Ad)
        info[k][np.ix_(PLANAR, PLANAR)] = Ai.T @ info[k][np.ix_(PLANAR, PLANAR)] @ Ai
    mR[flip], mt[flip] = geo.inverse(mR[flip], mt[flip])
    return make_graph(True, graph.ids, graph.R[np.argsort(perm)], graph.t[np.argsort(perm)],
                      graph.kind, np.where(flip, b, a), np.where(flip, a, b), mR, mt, info)


def test_no_odometry_chain_needed():
    """Nothing depends on edges (i, i+1). Shuffled labels (the anchor kept at 0): the same
    answer, node for node. Half the edges reversed as well: still exactly one GN step
    (Theorem 1) of the reversed problem, which equals the original to first order only."""
    graph = correlated(7, n=12, loops=8)
    rng = np.random.default_rng(1)
    n, m = graph.num_nodes, graph.num_edges
    perm = np.concatenate([[0], 1 + rng.permutation(n - 1)])
    shuffled = relabel(graph, perm, np.zeros(m, dtype=bool))
    assert np.sum(shuffled.b == shuffled.a + 1) < m // 2
    orig, res = lago(graph), lago(shuffled)
    np.testing.assert_allclose(res.t[perm], orig.t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.R[perm], orig.R, rtol=0, atol=1e-9)

    reversed_ = relabel(graph, perm, rng.random(m) < 0.5)
    res = lago(reversed_, jacobian="measurement")
    p, th = gauss_newton_step(reversed_, res.delta_rad,
                              *theorem1_start(reversed_, res.delta_rad))
    assert_poses(res, p, th, 1e-7)


@pytest.mark.parametrize("factorization", PATHS)
def test_near_singular_information_never_gives_nan(factorization, caplog):
    """Information matrices that are rank-deficient (a position axis or the yaw with no
    information at all) or extremely anisotropic: eigen-clamped by make_graph, and LAGO
    stays finite and sensible."""
    rng = np.random.default_rng(4)
    n = 40
    yaw = np.cumsum(rng.uniform(-0.5, 0.5, n))
    xy = np.cumsum(rng.normal(size=(n, 2)), axis=0)
    pairs = [(i, i + 1) for i in range(n - 1)] + [(i, i + 5) for i in range(0, n - 5, 3)]
    m = len(pairs)
    infos = np.empty((m, 3, 3))
    v = rng.normal(size=(m, 3))
    for k in range(m):
        kind = k % 4
        if kind == 0:
            infos[k] = np.diag([1e6, 0.0, 1e4])  # no information along y
        elif kind == 1:
            infos[k] = np.diag([100.0, 100.0, 0.0])  # no yaw information
        elif kind == 2:
            infos[k] = 1e5 * np.outer(v[k], v[k])  # rank one
        else:
            infos[k] = np.array([[3.6e5, 3.6e5 - 1, 0], [3.6e5 - 1, 3.6e5, 0], [0, 0, 1e3]])
    with caplog.at_level(logging.INFO):
        graph = planar_graph(yaw, xy, pairs, infos, rng, noise=0.0)
    assert len(graph.clamped_edges) > 0
    res = lago(graph, factorization=factorization)
    for arr in (res.R, res.t, res.yaw_rad, res.delta_hat, res.information.data):
        assert np.all(np.isfinite(arr))
    # Noise-free measurements: the truth has χ² 0 and LAGO finds it, to rounding amplified
    # by weights that span ten orders of magnitude (the clamp floor is 1e-10 × the largest
    # eigenvalue; cond(Ω_x) ~ 1e11 here, so ~1e-5 where exact input would give 1e-15).
    assert np.abs(geo.wrap_angle(res.yaw_rad - (yaw - yaw[0]))).max() < 1e-4
    R0 = rot2(yaw[0])
    assert np.abs(res.t[:, :2] - (xy - xy[0]) @ R0).max() < 1e-3


def test_marginal_yaw_information_floor():
    """A Schur complement that rounding pushes below zero is raised to the clamp floor."""
    omega = np.array([[[1.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 1.0]]])  # singular
    gain = lago_mod._solve2(omega[:, :2, :2], omega[:, :2, 2])
    out = lago_mod._marginal_yaw_information(omega, omega[:, 2, 2], omega[:, :2, 2], gain)
    assert out[0] > 0.0


def test_single_node_and_edgeless_graphs():
    one = make_graph(True, np.array([4]), np.eye(3)[None], np.ones((1, 3)),
                     np.zeros(0, np.int8), np.zeros(0, np.int64), np.zeros(0, np.int64),
                     np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 6, 6)))
    res = lago(one)
    np.testing.assert_array_equal(res.t, np.zeros((1, 3)))
    np.testing.assert_array_equal(res.R, np.eye(3)[None])
    assert res.information.shape == (0, 0)


# --- global edges, 3-D graphs, bad arguments ---------------------------------------------------


def test_three_dimensional_graph_is_refused():
    with pytest.raises(InputError, match="LAGO handles planar graphs only; this graph is 3-D"):
        lago_estimate(grid3d(20, seed=1).graph)


def test_global_edges_are_refused_unless_ignored():
    gps = manhattan(60, seed=2, gps_every=10).graph
    with pytest.raises(InputError, match=r"relative edges only; this graph has 6 global"):
        lago(gps)
    res = lago(gps, ignore_global=True)
    rel = gps.kind == EdgeKind.RELATIVE
    plain = make_graph(True, gps.ids, gps.R, gps.t, gps.kind[rel], gps.a[rel], gps.b[rel],
                       gps.meas_R[rel], gps.meas_t[rel], gps.info[rel])
    ref = lago(plain)
    np.testing.assert_array_equal(res.edges, np.flatnonzero(rel))
    np.testing.assert_allclose(res.t, ref.t, rtol=0, atol=1e-12)


def test_unknown_options_are_refused(city):
    with pytest.raises(ValueError, match="unknown jacobian 'middle'"):
        lago(city.graph, jacobian="middle")
    with pytest.raises(ValueError, match="unknown factorization 'qr'"):
        lago(city.graph, factorization="qr")
    with pytest.raises(ValueError, match="unknown covariance 'diagonal'; choose one of full"):
        lago(city.graph, covariance="diagonal")
    with pytest.raises(ValueError, match="unknown factorization 'dense'"):
        solve_spd(sparse.eye(3, format="csc"), np.ones(3), "dense")


# --- factorizations ----------------------------------------------------------------------------


def test_factorizations_agree(city):
    graph = city.graph
    results = [lago(graph, factorization=f) for f in INSTALLED]
    for other in results[1:]:
        np.testing.assert_allclose(other.t, results[0].t, rtol=0, atol=1e-8)
        np.testing.assert_allclose(other.yaw_rad, results[0].yaw_rad, rtol=0, atol=1e-10)


@pytest.mark.filterwarnings("ignore::scipy.sparse.linalg.MatrixRankWarning")  # spsolve
@pytest.mark.parametrize("method", INSTALLED)
def test_singular_system_is_an_input_error(method):
    singular = sparse.csc_matrix(np.array([[1.0, 0.0], [0.0, 0.0]]))
    with pytest.raises(InputError, match="LAGO: singular linear system"):
        solve_spd(singular, np.ones(2), method)


def test_without_cvxopt_auto_falls_back_to_qdldl_then_superlu(city, monkeypatch):
    expected = {f: lago(city.graph, factorization=f) for f in ("qdldl", "splu-mmd")}
    real = spd.available
    monkeypatch.setattr(spd, "available", lambda m: m != "cholmod" and real(m))
    np.testing.assert_array_equal(lago(city.graph).t, expected["qdldl"].t)  # auto
    with pytest.raises(ValueError, match="needs the cvxopt package"):
        solve_spd(sparse.eye(2, format="csc"), np.ones(2), "cholmod")
    monkeypatch.setattr(spd, "available", lambda m: m == "splu")
    np.testing.assert_array_equal(lago(city.graph).t, expected["splu-mmd"].t)


# --- accuracy on a synthetic Manhattan world ---------------------------------------------------


def test_close_to_the_optimum_on_manhattan(city):
    """On a synthetic Manhattan world with correlated information, LAGO's χ² is within
    1e-4 of the optimum (the exact mode iterated to convergence; measured 5e-6), far below
    χ² at the truth (a χ²(3m) sample) and the odometry chain's."""
    graph = city.graph
    res = lago(graph)
    lago_chi2 = chi2(graph, res.R, res.t)
    optimum = solve_exact(graph, iterations=30).chi2_final
    assert optimum <= lago_chi2 < (1 + 1e-4) * optimum
    assert lago_chi2 < 0.5 * chi2(graph, city.truth_R, city.truth_t)
    assert lago_chi2 < 0.05 * chi2(graph)


# --- the command line --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def city_file(tmp_path_factory, city):
    path = tmp_path_factory.mktemp("lago") / "city.g2o"
    write_g2o(path, city.graph)
    return path


def test_cli_solver_lago(city_file, tmp_path, capsys):
    out, report = tmp_path / "out.g2o", tmp_path / "report.json"
    code = main([str(city_file), "--output", str(out), "--solver", "lago",
                 "--report", str(report)])
    assert code == 0
    data = json.loads(report.read_text())
    assert json.loads(capsys.readouterr().out) == data
    assert data["solver"] == "lago" and data["mode"] == "lago"
    graph = read_g2o(city_file)
    solved = read_g2o(out)
    assert np.array_equal(solved.ids, graph.ids)
    # The file holds the solution at round-trip precision.
    assert chi2(graph, solved.R, solved.t) == pytest.approx(data["chi2_final"], rel=1e-9)
    R, t = lago_estimate(graph)
    assert data["chi2_final"] == pytest.approx(chi2(graph, R, t), rel=1e-12)
    assert data["chi2_final"] < 0.05 * data["chi2_initial"]


def test_cli_init_lago(city_file, tmp_path):
    out, report = tmp_path / "out.g2o", tmp_path / "report.json"
    code = main([str(city_file), "--output", str(out), "--init", "lago", "--passes", "2",
                 "--report", str(report)])
    assert code == 0
    data = json.loads(report.read_text())
    R, t = lago_estimate(read_g2o(city_file))
    assert data["init"] == "lago"
    assert data["chi2_initial"] == pytest.approx(chi2(read_g2o(city_file), R, t), rel=1e-9)


@pytest.mark.parametrize(("graph_fn", "message"), [
    (lambda: grid3d(20, seed=1).graph, "LAGO handles planar graphs only; this graph is 3-D"),
    (lambda: manhattan(30, seed=1, gps_every=10).graph, "LAGO uses relative edges only"),
])
def test_cli_refusals_are_one_line(tmp_path, capsys, graph_fn, message):
    src = tmp_path / "in.g2o"
    write_g2o(src, graph_fn())
    out = tmp_path / "out.g2o"
    code = main([str(src), "--output", str(out), "--solver", "lago"])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1 and err.startswith(f"h2o-solve: {src}: {message}")
    assert not out.exists()
