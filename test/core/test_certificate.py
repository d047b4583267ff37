"""SE-Sync's global-optimality certificate (h2o_slam.core.certificate)."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph

from h2o_slam.core import certificate as C
from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import EdgeKind, PoseGraph, chi2, make_graph
from h2o_slam.core.modes import solve_exact
from h2o_slam.io.synthetic import grid3d, manhattan


def dense_q(problem: C.SyncProblem) -> np.ndarray:
    """``Q`` from the cost itself, edge by edge: ``F = [T X] M [T X]ᵀ`` summed per edge,
    translations eliminated with a pseudo-inverse (independent of ReducedProblem)."""
    d, n = problem.d, problem.n
    size = n + d * n  # T's n columns (one translation coordinate), then X's dn columns
    M = np.zeros((size, size))
    for e in range(len(problem.i)):
        i, j = problem.i[e], problem.j[e]
        # rotation: κ ‖R_j − R_i R̃‖² = κ tr(X c cᵀ Xᵀ) summed over the d columns c of
        # the selector (e_j ⊗ I − e_i ⊗ R̃)
        sel = np.zeros((size, d))
        sel[n + d * j:n + d * j + d] = np.eye(d)
        sel[n + d * i:n + d * i + d] = -problem.R[e]
        M += problem.kappa[e] * sel @ sel.T
        # translation: τ ‖T(e_j − e_i) − X (e_i ⊗ t̃)‖²
        v = np.zeros(size)
        v[j] += 1.0
        v[i] -= 1.0
        v[n + d * i:n + d * i + d] = -problem.t[e]
        M += problem.tau[e] * np.outer(v, v)
    L, B, A = M[:n, :n], M[:n, n:], M[n:, n:]
    return A - B.T @ np.linalg.pinv(L) @ B


def solved(graph: PoseGraph) -> tuple[np.ndarray, np.ndarray]:
    result = solve_exact(graph, init="input")
    assert result.converged
    return result.R, result.t


@pytest.mark.parametrize("planar", [True, False])
@pytest.mark.parametrize("absolute", [0, 2])
def test_implicit_q_equals_dense_q(planar: bool, absolute: int) -> None:
    graph = random_graph(3, planar, n=7, loops=3, gps=absolute, orientation=absolute)
    problem = C.sync_problem(graph)
    assert problem.earth == bool(absolute)
    reduced = C.ReducedProblem(problem)
    Q = dense_q(problem)
    V = np.random.default_rng(0).normal(size=(Q.shape[0], 4))
    assert np.allclose(reduced.apply_q(V), Q @ V, rtol=1e-9, atol=1e-9 * np.abs(Q).max())
    # tr(X Q Xᵀ) is F at its optimal translations, for any rotations
    R, t = C.sync_poses(graph, problem, graph.R, graph.t)
    X = np.swapaxes(R, 1, 2).reshape(-1, problem.d).T
    t_opt = reduced.optimal_translations(R)
    assert np.trace(X @ Q @ X.T) == pytest.approx(C.sesync_cost(problem, R, t_opt), rel=1e-9)
    assert C.sesync_cost(problem, R, t_opt) <= C.sesync_cost(problem, R, t)


def test_weights_are_sesync_rule_and_exact_for_isotropic_information() -> None:
    graph = random_graph(5, False, n=5, loops=2)
    info = np.zeros((graph.num_edges, 6, 6))
    info[:, :3, :3] = 40.0 * np.eye(3)
    info[:, 3:, 3:] = 900.0 * np.eye(3)
    graph.info = info
    problem = C.sync_problem(graph)
    assert np.allclose(problem.tau, 40.0)
    assert np.allclose(problem.kappa, 450.0)
    # then F is the χ² to second order: equal at a point near the measurements
    R, t = solved(graph)
    Rs, ts = C.sync_poses(graph, problem, R, t)
    assert C.sesync_cost(problem, Rs, ts) == pytest.approx(chi2(graph, R, t), rel=2e-2)
    # anisotropic: harmonic means of the blocks' eigenvalues
    graph.info[0, :3, :3] = np.diag([10.0, 20.0, 40.0])
    assert C.sync_problem(graph).tau[0] == pytest.approx(3.0 / (0.1 + 0.05 + 0.025))


@pytest.mark.parametrize("planar", [True, False])
def test_jacobian_and_newton_hessian_by_central_differences(planar: bool) -> None:
    graph = random_graph(7, planar, n=5, loops=2, gps=1, orientation=1, noise=0.3)
    problem = C.sync_problem(graph)
    R, t = C.sync_poses(graph, problem, graph.R, graph.t)
    d, p = problem.d, problem.p
    k = d + p

    def moved(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = x.reshape(problem.n, k)
        return C._retract(R, x[:, d:]), t + x[:, :d]

    def residual(x: np.ndarray) -> np.ndarray:
        return C._jacobian(problem, *moved(x))[1]

    size = problem.n * k
    J = C._jacobian(problem, R, t)[0].toarray()
    h = 1e-6
    num = np.column_stack([(residual(h * e) - residual(-h * e)) / (2 * h)
                           for e in np.eye(size)])
    assert np.allclose(J, num, atol=1e-7)
    H, g = C._newton_system(problem, R, t)

    def cost(x: np.ndarray) -> float:
        return C.sesync_cost(problem, *moved(x))

    E = np.eye(size) * 1e-4
    num_g = np.array([(cost(e) - cost(-e)) / 2e-4 for e in E])
    assert np.allclose(2 * g, num_g, atol=1e-5 * max(1.0, np.abs(num_g).max()))
    num_H = np.array([[(cost(a + b) - cost(a - b) - cost(b - a) + cost(-a - b)) / 4e-8
                       for b in E] for a in E])
    assert np.allclose(2 * H.toarray(), num_H, atol=1e-4 * np.abs(num_H).max())


@pytest.mark.parametrize("planar", [True, False])
def test_min_eigenvalue_matches_dense_eigvalsh(planar: bool) -> None:
    graph = random_graph(11, planar, n=7, loops=4, gps=1, orientation=1)
    problem = C.sync_problem(graph)
    reduced = C.ReducedProblem(problem)
    Q = dense_q(problem)
    for R in (C.sync_poses(graph, problem, *solved(graph))[0],  # near a minimum
              C.sync_poses(graph, problem, graph.R, graph.t)[0]):  # far from one
        Lam = reduced.lambda_blocks(R)
        S = Q.copy()
        for node in range(problem.n):
            blk = slice(problem.d * node, problem.d * node + problem.d)
            S[blk, blk] -= Lam[node]
        lam = np.linalg.eigvalsh(S)[0]
        eta = C.tolerance(reduced)
        spectrum = C.min_eigenvalue(reduced, Lam, eta)
        assert spectrum.converged
        assert spectrum.lambda_min == pytest.approx(lam, abs=1e-7 * np.abs(S).max())
        assert spectrum.psd == (lam > -eta)


def test_certifies_the_optimum_of_a_planar_graph() -> None:
    graph = manhattan(60, seed=1).graph
    R, t = solved(graph)
    cert = C.certify(graph, R, t)
    assert cert.certified, cert.message
    assert cert.message.startswith("certified globally optimal")
    assert cert.refine_converged
    assert -cert.tolerance <= cert.lambda_min <= cert.tolerance
    assert cert.suboptimality_bound <= cert.tolerance * 2 * graph.num_nodes
    # the refined point is h2o's up to the difference of the two costs, and no worse on F
    assert cert.sesync_cost <= cert.cost_at_solution
    assert cert.max_rotation_moved_rad < 0.05
    assert cert.chi2_refined == pytest.approx(cert.chi2_solution, rel=0.1)


def test_a_point_short_of_the_optimum_in_its_basin_is_not_certified() -> None:
    """SE-Sync's cost certifies its optimum from there too, but Gauss–Newton on the χ² from
    that optimum ends lower than the point given: the round trip refuses it."""
    graph = manhattan(60, seed=1).graph
    R, t = solved(graph)
    rng = np.random.default_rng(3)
    shifted = t + np.concatenate([rng.normal(0.0, 0.05, (len(t), 2)), np.zeros((len(t), 1))],
                                 axis=1)
    cert = C.certify(graph, R, shifted)
    assert not cert.certified
    assert cert.message.startswith("could not certify: Gauss–Newton from the certified")
    assert cert.chi2_returned < cert.chi2_solution * (1 - C.ROUND_TRIP_TOLERANCE)
    assert cert.lambda_min >= -cert.tolerance  # SE-Sync's own test passed
    assert C.certify(graph, R, t).chi2_returned == pytest.approx(cert.chi2_returned, rel=1e-4)


def test_certifies_the_optimum_of_a_3d_graph() -> None:
    graph = grid3d(27, seed=2).graph
    R, t = solved(graph)
    cert = C.certify(graph, R, t)
    assert cert.certified, cert.message
    assert cert.refine_converged and cert.eig_converged
    assert cert.nodes == graph.num_nodes and cert.edges == graph.num_edges


@pytest.mark.parametrize("planar", [True, False])
def test_certifies_a_graph_with_gps_and_compass_edges(planar: bool) -> None:
    graph = random_graph(2, planar, n=12, loops=5, gps=4, orientation=2, noise=0.05)
    R, t = solved(graph)
    cert = C.certify(graph, R, t)
    assert cert.certified, cert.message
    assert cert.nodes == graph.num_nodes + 1  # the earth frame


def test_kept_edges_only() -> None:
    graph = random_graph(2, True, n=12, loops=5, noise=0.05)
    R, t = solved(graph)
    keep = np.ones(graph.num_edges, bool)
    keep[-2:] = False
    cert = C.certify(graph, R, t, keep)
    assert cert.edges == graph.num_edges - 2


# A planted local minimum: a ring of six poses whose measured turns do not add up to one
# revolution (rotation noise of 0.6 rad a step). Gauss–Newton from a start that winds once
# more than the odometry settles in a local minimum 300 times above the global one.


def ring(seed: int = 0, n: int = 6) -> PoseGraph:
    rng = np.random.default_rng(seed)
    yaw = 2 * np.pi / n + rng.normal(0.0, 0.6, n)
    a = np.arange(n)
    mt = np.column_stack([np.ones(n), rng.normal(0.0, 0.1, n), np.zeros(n)])
    info = np.zeros((n, 6, 6))
    info[:, 0, 0] = info[:, 1, 1] = 10.0
    info[:, 5, 5] = 100.0
    # the start winds `extra` more than the odometry (set by ring_start)
    return make_graph(True, a, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)),
                      np.full(n, EdgeKind.RELATIVE), a, (a + 1) % n, geo.yaw_to_matrix(yaw),
                      mt, info)


def ring_start(graph: PoseGraph, extra: float) -> PoseGraph:
    n = graph.num_nodes
    yaw = geo.matrix_to_yaw(graph.meas_R)
    theta = np.concatenate([[0.0], np.cumsum(yaw[:-1])]) + np.arange(n) * extra / n
    t = np.zeros((n, 3))
    t[:, 0], t[:, 1] = np.cos(theta), np.sin(theta)
    return graph.with_estimate(geo.yaw_to_matrix(theta), t)


def planar_gradient_and_hessian(graph: PoseGraph, R: np.ndarray, t: np.ndarray,
                                h: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of the g2o χ² in (x, y, yaw) of every node but the first."""
    n = graph.num_nodes
    x0 = np.column_stack([t[:, 0], t[:, 1], geo.matrix_to_yaw(R)])

    def f(dx: np.ndarray) -> float:
        x = x0.copy()
        x[1:] += dx.reshape(n - 1, 3)
        return chi2(graph, geo.yaw_to_matrix(x[:, 2]), np.column_stack([x[:, :2],
                                                                         np.zeros(n)]))

    E = np.eye(3 * (n - 1)) * h
    g = np.array([(f(e) - f(-e)) / (2 * h) for e in E])
    H = np.array([[(f(a + b) - f(a - b) - f(b - a) + f(-a - b)) / (4 * h * h) for b in E]
                  for a in E])
    return g, H


def test_rejects_a_planted_local_minimum() -> None:
    graph = ring()
    best = solve_exact(ring_start(graph, 0.0), init="input")
    local = solve_exact(ring_start(graph, 2 * np.pi), init="input")
    assert best.converged and local.converged
    # a local minimum of the χ²: no slope, positive curvature in every direction ...
    g, H = planar_gradient_and_hessian(graph, local.R, local.t)
    assert np.abs(g).max() < 1e-3
    assert np.linalg.eigvalsh(H)[0] > 1.0
    # ... far above the other start's
    assert local.chi2_final > 100 * best.chi2_final
    rejected = C.certify(graph, local.R, local.t)
    accepted = C.certify(graph, best.R, best.t)
    assert accepted.certified, accepted.message
    assert not rejected.certified
    assert rejected.message.startswith("could not certify: λ_min = ")
    assert rejected.lambda_min < -100 * rejected.tolerance
    # the bound holds: the global optimum of F lies within it below the local one
    assert rejected.sesync_cost - accepted.sesync_cost <= rejected.suboptimality_bound
    # the refinement stayed in the local minimum's basin
    assert rejected.chi2_refined > 100 * accepted.chi2_refined


def test_refine_keeps_the_gauge_and_lowers_f() -> None:
    graph = random_graph(4, False, n=8, loops=3, noise=0.05)
    R, t = solved(graph)
    problem = C.sync_problem(graph)
    Rs, ts = C.sync_poses(graph, problem, R, t)
    refined = C.refine(problem, Rs, ts)
    assert refined.converged
    assert refined.cost < C.sesync_cost(problem, Rs, ts)
    assert np.array_equal(refined.R[0], Rs[0]) and np.array_equal(refined.t[0], ts[0])
    # a minimum: F's gradient vanishes there
    _, g = C._newton_system(problem, refined.R, refined.t)
    assert np.abs(g[C.sync_problem(graph).d + C.sync_problem(graph).p:]).max() < 1e-8


def test_no_edges_is_not_certified() -> None:
    graph = random_graph(4, True, n=4, loops=1)
    cert = C.certify(graph, graph.R, graph.t, np.zeros(graph.num_edges, bool))
    assert not cert.certified
    assert cert.message == "could not certify: the graph has no edges"
