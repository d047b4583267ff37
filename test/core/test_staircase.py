"""SE-Sync's Riemannian staircase (h2o_slam.core.staircase): the rank-restricted cost's
derivatives, the manifold's operations, the rounding, and the way out of a planted local
minimum."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st
from test_certificate import ring, ring_start

from h2o_slam.core import certificate as C
from h2o_slam.core import geometry as geo
from h2o_slam.core.modes import solve_exact
from h2o_slam.core.staircase import (
    RankProblem,
    climb,
    escape,
    round_rotations,
    solve_rank,
    staircase_solve,
)


def rank_problem(seed: int, planar: bool) -> RankProblem:
    graph = random_graph(seed, planar, n=6, loops=3, gps=seed % 2)
    return RankProblem(C.ReducedProblem(C.sync_problem(graph)))


def random_point(problem: RankProblem, r: int, rng: np.random.Generator) -> np.ndarray:
    """Blocks with orthonormal rows, shape ``(n, d, r)``."""
    Q, _ = np.linalg.qr(rng.normal(size=(problem.n, r, problem.d)))
    return np.swapaxes(Q, 1, 2)


def tangent(problem: RankProblem, M: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    V = problem.project(M, rng.normal(size=M.shape))
    return V / np.linalg.norm(V)


def _inner(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.vdot(a, b))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), planar=st.booleans(), lift=st.integers(0, 2))
def test_gradient_and_hessian_are_the_cost_s_derivatives(seed: int, planar: bool,
                                                         lift: int) -> None:
    """Along a retracted curve ``M(h) = Retr(M, hV)`` (the polar retraction is second
    order): ``f'(0) = ⟨grad, V⟩`` and ``f''(0) = ⟨V, Hess[V]⟩``."""
    rng = np.random.default_rng(seed)
    problem = rank_problem(seed, planar)
    M = random_point(problem, problem.d + lift, rng)
    V = tangent(problem, M, rng)
    QM = problem.q(M)
    Lam = problem.lam(M, QM)

    def f(h: float) -> float:
        return problem.cost(problem.retract(M, h * V))

    h = 1e-4
    scale = max(1.0, abs(f(0.0)))
    slope = (f(h) - f(-h)) / (2 * h)
    assert _inner(problem.gradient(M, QM, Lam), V) == pytest.approx(slope, abs=1e-5 * scale)
    h = 1e-3
    curvature = (f(h) - 2 * f(0.0) + f(-h)) / (h * h)
    assert _inner(V, problem.hessian(M, Lam, V)) == pytest.approx(curvature,
                                                                  abs=1e-3 * scale)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), planar=st.booleans(), lift=st.integers(0, 2))
def test_the_manifold_s_operations(seed: int, planar: bool, lift: int) -> None:
    rng = np.random.default_rng(seed)
    problem = rank_problem(seed, planar)
    M = random_point(problem, problem.d + lift, rng)
    V = problem.project(M, rng.normal(size=M.shape))
    U = tangent(problem, M, rng)
    eye = np.eye(problem.d)
    # tangent: sym(V_i M_iᵀ) = 0, and projecting again changes nothing
    B = V @ np.swapaxes(M, 1, 2)
    np.testing.assert_allclose(B + np.swapaxes(B, 1, 2), 0.0, atol=1e-12)
    np.testing.assert_allclose(problem.project(M, V), V, atol=1e-12)
    # the retraction stays on the manifold
    moved = problem.retract(M, V)
    np.testing.assert_allclose(moved @ np.swapaxes(moved, 1, 2), np.broadcast_to(
        eye, (problem.n, problem.d, problem.d)), atol=1e-12)
    # the Hessian is self-adjoint and maps tangents to tangents
    Lam = problem.lam(M, problem.q(M))
    HU, HV = problem.hessian(M, Lam, U), problem.hessian(M, Lam, V)
    assert _inner(U, HV) == pytest.approx(_inner(HU, V), rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(problem.project(M, HV), HV, atol=1e-9 * np.abs(HV).max())


@pytest.mark.parametrize("d", [2, 3])
def test_rounding_returns_the_rotations_of_a_lifted_point(d: int) -> None:
    """Rotations lifted to rank 5 by a common orthogonal map come back, up to the common
    rotation ``R_i → G R_i`` that the problem cannot see."""
    rng = np.random.default_rng(d)
    R = geo.so3_exp(rng.normal(size=(8, 3)))[:, :d, :d] if d == 3 else \
        geo.yaw_to_matrix(rng.uniform(-np.pi, np.pi, 8))[:, :2, :2]
    G, _ = np.linalg.qr(rng.normal(size=(5, 5)))
    M = np.concatenate([np.swapaxes(R, 1, 2), np.zeros((8, d, 5 - d))], axis=2) @ G
    back = round_rotations(M)
    np.testing.assert_allclose(np.linalg.det(back), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.swapaxes(back[:1], 1, 2) @ back,
                               np.swapaxes(R[:1], 1, 2) @ R, atol=1e-12)


def test_escape_lowers_the_cost_one_rank_up() -> None:
    graph = ring()
    local = solve_exact(ring_start(graph, 2 * np.pi), init="input")
    problem_data = C.sync_problem(graph)
    reduced = C.ReducedProblem(problem_data)
    problem = RankProblem(reduced)
    Rs, _ = C.sync_poses(graph, problem_data, local.R, local.t)
    M, _ = solve_rank(problem, np.swapaxes(Rs, 1, 2).copy())
    spectrum = C.min_eigenvalue(reduced, problem.lam(M, problem.q(M)), 0.0, vector=True)
    assert spectrum.lambda_min < 0.0 and spectrum.vector is not None
    lifted = escape(problem, M, spectrum.vector)
    assert lifted is not None and lifted.shape == (M.shape[0], M.shape[1], M.shape[2] + 1)
    assert problem.cost(lifted) < problem.cost(M)


def test_the_staircase_leaves_a_planted_local_minimum() -> None:
    """The ring's local minimum, 300 times above the optimum, is not certified; the
    staircase climbed from it solves the relaxation, and exact mode from its rounded point
    ends at the global optimum, which is certified."""
    graph = ring()
    best = solve_exact(ring_start(graph, 0.0), init="input")
    local = solve_exact(ring_start(graph, 2 * np.pi), init="input")
    assert not C.certify(graph, local.R, local.t).certified
    answer, stair, adopted = staircase_solve(graph, local)
    assert adopted
    assert stair.relaxation_solved and stair.rank >= 2
    assert answer.chi2_final == pytest.approx(best.chi2_final, rel=1e-6)
    assert answer.chi2_per_pass[: len(local.chi2_per_pass)] == local.chi2_per_pass
    assert C.certify(graph, answer.R, answer.t).certified


def test_an_optimal_solution_is_kept() -> None:
    graph = ring()
    best = solve_exact(ring_start(graph, 0.0), init="input")
    answer, stair, adopted = staircase_solve(graph, best)
    assert not adopted and answer is best
    assert stair.relaxation_solved


@pytest.mark.parametrize("planar", [True, False])
def test_the_climb_from_the_optimum_of_a_small_graph_stays_at_rank_d(planar: bool) -> None:
    graph = random_graph(4, planar, n=8, loops=3)
    optimum = solve_exact(graph, init="input")
    problem = C.sync_problem(graph)
    reduced = C.ReducedProblem(problem)
    Rs, ts = C.sync_poses(graph, problem, optimum.R, optimum.t)
    out = climb(reduced, Rs, C.tolerance(reduced))
    assert out.relaxation_solved and out.rank == problem.d
    # the rounded rotations are SE-Sync's optimum, the certificate's refined point, up to
    # the gauge
    refined = C.refine(problem, Rs, ts).R
    np.testing.assert_allclose(np.swapaxes(out.R[:1], 1, 2) @ out.R,
                               np.swapaxes(refined[:1], 1, 2) @ refined, atol=1e-5)


@pytest.mark.parametrize("planar", [True, False])
def test_the_start_keeps_the_earth_frame_of_gps_fixes(planar: bool) -> None:
    """With GPS fixes the rounded point is put back in the earth frame (the problem's last
    node at the identity): from the optimum its χ² is near the optimum's, where a start in
    another frame would miss every fix by metres."""
    from h2o_slam.core.graph import chi2, has_global
    from h2o_slam.core.staircase import staircase_start

    graph = random_graph(5, planar, n=8, loops=3, gps=4)
    assert has_global(graph)
    optimum = solve_exact(graph, init="input")
    R, t, out = staircase_start(graph, optimum.R, optimum.t)
    assert out.relaxation_solved
    assert chi2(graph, R, t) < 1.5 * chi2(graph, optimum.R, optimum.t)
    # the map turned as a whole: the relative edges do not see it, the fixes do
    G = geo.so3_exp(np.array([0.0, 0.0, 1.0]))
    assert chi2(graph, G @ R, t @ G.T) > 3.0 * chi2(graph, optimum.R, optimum.t)
