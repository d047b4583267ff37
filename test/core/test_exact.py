"""Exact mode's world system: the kept pattern and symbolic factorization against a fresh
build, and its normal equations against a dense JᵀJ built edge by edge with numpy."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph

from h2o_slam.core import geometry as geo
from h2o_slam.core.exact import ExactSystem, converge_exact
from h2o_slam.core.graph import EARTH, PoseGraph, chi2
from h2o_slam.core.jacobians import endpoint_jacobians
from h2o_slam.core.modes import build_solver
from h2o_slam.core.solver import SolverConfig

UNCAPPED = SolverConfig(max_rotation_step_rad=1e9)


def _dense_jacobian(solver, free):
    """Whitened ``J`` (rows: edges × p; columns: free nodes × p) and ``r`` at the solver's
    estimate, from the batched numpy Jacobians, edge by edge."""
    R, x = solver.world_poses()
    a, b, p, dof = solver.a, solver.b, solver.p, solver.dof
    glob = a == EARTH
    ai = np.where(glob, 0, a)
    Ra = np.where(glob[:, None, None], np.eye(3), R[ai])
    xa = np.where(glob[:, None], 0.0, x[ai])
    e, Ja, Jb = endpoint_jacobians(solver.kind, Ra, xa, R[b], x[b], solver.meas_R,
                                   solver.meas_t)
    col = np.full(solver.num_nodes + 1, -1)
    col[free] = np.arange(len(free))
    J = np.zeros((len(a) * p, len(free) * p))
    r = np.zeros(len(a) * p)
    for k in range(len(a)):
        W = solver.W[k]
        r[k * p:(k + 1) * p] = W @ e[k, dof]
        for node, Jend in ((a[k], Ja[k]), (b[k], Jb[k])):
            c = col[node]
            if c >= 0:
                J[k * p:(k + 1) * p, c * p:(c + 1) * p] = W @ Jend[np.ix_(dof, dof)]
    return J, r


@pytest.mark.parametrize("planar", [True, False])
def test_exact_system_reused_across_steps_gives_the_fresh_step(planar):
    """The pattern and symbolic factorization kept from earlier iterations give the step a
    newly built system gives, damped or not; H, g and χ² are the dense JᵀJ, Jᵀr and rᵀr,
    and the damped matrix scales H's diagonal by 1 + damping."""
    graph = random_graph(31, planar, n=12, loops=6, gps=2, orientation=1)
    solver, _ = build_solver(graph, UNCAPPED)
    exact = ExactSystem(solver)
    for damping in (0.0, 1e-3, 0.0):
        step, nodes = exact.step(damping)
        solver.apply_step(nodes, step)  # the kept system moves on
        kept = exact.step(damping)
        H, g, free = exact.normal_equations()
        fresh = ExactSystem(solver).step(damping)  # a system built at the same estimate
        assert np.array_equal(kept[1], fresh[1]) and np.array_equal(free, fresh[1])
        np.testing.assert_allclose(kept[0], fresh[0], rtol=1e-12, atol=1e-12)
        J, r = _dense_jacobian(solver, free)
        H_dense = J.T @ J
        np.testing.assert_allclose(H.toarray(), H_dense, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(g, J.T @ r, rtol=1e-12, atol=1e-9)
        lin = exact.linearize()
        assert lin.chi2 == pytest.approx(float(r @ r), rel=1e-12)
        assert lin.chi2 == pytest.approx(chi2(graph, *solver.world_poses()), rel=1e-9)
        system = lin.system
        # The pattern is CSC with sorted, distinct rows in every column (what CHOLMOD reads).
        for j in range(system.size):
            rows = system.indices[system.indptr[j]:system.indptr[j + 1]]
            assert np.all(np.diff(rows) > 0) and rows[-1] == j
        damped = H_dense + damping * np.diag(np.diag(H_dense))
        np.testing.assert_allclose(system.matrix(system.damped(lin.data, damping)).toarray(),
                                   damped, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("planar", [True, False])
def test_a_world_step_moves_each_pose_by_its_own_perturbation(planar):
    """``move`` retracts every pose in world coordinates (R ← Exp(ω) R, x ← x + δx) and the
    tree's local transforms then compose to exactly those poses."""
    graph = random_graph(5, planar, n=10, loops=4, gps=1)
    solver, _ = build_solver(graph, UNCAPPED)
    exact = ExactSystem(solver)
    lin = exact.linearize()
    step = exact._world_step(lin, 0.0)
    exact.move(lin)
    R, x = solver.world_poses()
    np.testing.assert_allclose(R, geo.so3_exp(step[:, 3:]) @ lin.R, atol=1e-12)
    np.testing.assert_allclose(x, lin.x + step[:, :3], atol=1e-12)


def test_exact_mode_converges_to_a_lower_chi2_than_it_starts_from():
    graph = random_graph(8, False, n=30, loops=12, gps=2)
    solver, _ = build_solver(graph, UNCAPPED)
    history, converged = converge_exact(solver, 50)
    assert converged and history[-1] < 0.5 * history[0]
    assert np.all(np.diff(history) <= 1e-9 * history[0])


@pytest.mark.parametrize("planar", [True, False])
def test_edges_at_weight_zero_leave_the_pattern_and_the_solve_unchanged(planar):
    """A dropped closure adds no block to ``H`` (a false one between distant poses would
    add fill), and the solve is that of the graph without it."""
    graph = random_graph(11, planar, n=40, loops=16)
    closures = np.flatnonzero(np.abs(graph.a - graph.b) > 1)
    dropped = closures[::2]
    solver, _ = build_solver(graph, UNCAPPED)
    weights = np.ones(graph.num_edges)
    weights[dropped] = 0.0
    solver.set_weights(weights)
    kept = np.setdiff1d(np.arange(graph.num_edges), dropped)
    without = _without(graph, kept)
    alone, _ = build_solver(without.with_estimate(*solver.world_poses()), UNCAPPED,
                            init="input")
    full = ExactSystem(solver).system()
    assert full.nnz == ExactSystem(alone).system().nnz
    history, _ = converge_exact(solver, 30)
    expected, _ = converge_exact(alone, 30)
    np.testing.assert_allclose(history, expected, rtol=1e-9)
    np.testing.assert_allclose(solver.world_poses()[1], alone.world_poses()[1], atol=1e-9)


def _without(graph, keep):
    return PoseGraph(graph.planar, graph.ids, graph.R, graph.t, graph.kind[keep],
                     graph.a[keep], graph.b[keep], graph.meas_R[keep], graph.meas_t[keep],
                     graph.info[keep])
