"""The condensed loop solve: chains between junctions as single edges, then filled in."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import loop_graph
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import condensed as cd
from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import PoseGraph, chi2, edge_chi2
from h2o_slam.core.loop_spread import dead_reckon
from h2o_slam.core.modes import solve_exact
from h2o_slam.io.synthetic import manhattan

coords = st.floats(-50.0, 50.0)
angles = st.floats(-3.1, 3.1)
poses = st.tuples(coords, coords, angles).map(np.array)


@settings(max_examples=50, deadline=None)
@given(poses, poses, poses)
def test_relative_jacobians_are_the_errors_derivatives(a, b, meas) -> None:
    _, Ja, Jb = cd.relative_jacobians(a[None], b[None], meas[None])
    h = 1e-6
    for x, J, at_a in ((a, Ja[0], True), (b, Jb[0], False)):
        for j in range(3):
            d = np.zeros(3)
            d[j] = h

            def err(shift, x=x, at_a=at_a):
                pa, pb = (x + shift, b) if at_a else (a, x + shift)
                return cd.relative_jacobians(pa[None], pb[None], meas[None])[0][0]
            diff = geo.wrap_angle(err(d) - err(-d)) / (2 * h)
            diff[:2] = (err(d) - err(-d))[:2] / (2 * h)
            np.testing.assert_allclose(J[:, j], diff, atol=1e-5)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_planar_chi2_is_the_graphs_weighted_edge_chi2(seed) -> None:
    g = manhattan(60, seed=seed % 1000).graph
    rng = np.random.default_rng(seed)
    R, t = g.R.copy(), g.t.copy()
    t[:, :2] += rng.normal(0, 0.5, (len(t), 2))
    R = geo.yaw_to_matrix(geo.matrix_to_yaw(R) + rng.normal(0, 0.3, len(R)))
    weight = rng.uniform(0, 1, g.num_edges)
    moved = PoseGraph(g.planar, g.ids, R, t, g.kind, g.a, g.b, g.meas_R, g.meas_t, g.info)
    pose = cd.planar_poses(R, t)
    S = g.info[:, geo.PLANAR_DOF[:, None], geo.PLANAR_DOF[None, :]]
    meas = np.column_stack([g.meas_t[:, :2], geo.matrix_to_yaw(g.meas_R)])
    assert cd.planar_chi2(g.a, g.b, meas, S, weight, pose) == pytest.approx(
        float(weight @ edge_chi2(moved)), rel=1e-9)


def test_a_chains_covariance_is_its_increments_carried_to_its_end() -> None:
    """First order: ``J Σ Jᵀ`` with ``J`` the composition's derivative by each increment's
    right perturbation, taken numerically."""
    rng = np.random.default_rng(1)
    inc = np.column_stack([np.ones(30), rng.normal(0, 0.2, 30), rng.normal(0, 0.4, 30)])
    cov = np.array([np.diag(rng.uniform(0.01, 0.1, 3)) for _ in range(30)])
    chains = cd.condense(0, np.array([30]), inc, cov)
    end = dead_reckon(np.zeros(3), inc)[-1]
    expected = np.zeros((3, 3))
    h = 1e-6
    for i in range(30):
        J = np.zeros((3, 3))
        for j in range(3):
            d = np.zeros((30, 3))
            d[i, j] = h
            plus = dead_reckon(np.zeros(3), geo.planar_compose(inc, d))[-1]
            minus = dead_reckon(np.zeros(3), geo.planar_compose(inc, -d))[-1]
            J[:, j] = (geo.planar_between(end, plus) - geo.planar_between(end, minus)) / (2 * h)
        expected += J @ cov[i] @ J.T
    np.testing.assert_allclose(chains.cov[0], expected, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(chains.meas[0], end, atol=1e-12)


def _parts(g: PoseGraph, lo: int) -> tuple[np.ndarray, np.ndarray, cd.Reduced]:
    """The odometry increments after ``lo``, their covariances and the other edges."""
    dof = g.dof
    odo = np.flatnonzero(g.b - g.a == 1)
    order = odo[np.argsort(g.b[odo])][lo:]
    other = np.setdiff1d(np.arange(g.num_edges), odo)
    other = other[np.maximum(g.a[other], g.b[other]) > lo]
    info = g.info[:, dof[:, None], dof[None, :]]
    return (_meas(g, order), np.linalg.inv(info[order]),
            cd.Reduced(g.a[other], g.b[other], _meas(g, other), info[other],
                       np.empty(0, np.int64)))


def _meas(g: PoseGraph, edges: np.ndarray) -> np.ndarray:
    return np.column_stack([g.meas_t[edges, :2], geo.matrix_to_yaw(g.meas_R[edges])])


def _chi2(g: PoseGraph, pose: np.ndarray) -> float:
    t = np.column_stack([pose[:, :2], np.zeros(len(pose))])
    return chi2(PoseGraph(g.planar, g.ids, geo.yaw_to_matrix(pose[:, 2]), t, g.kind, g.a, g.b,
                          g.meas_R, g.meas_t, g.info))


def test_filling_in_given_the_optimal_junctions_is_the_optimum() -> None:
    """Each chain's inner poses given its ends: the chain's own least squares, so the
    junctions of the optimum give back the optimum."""
    g = loop_graph(3, True, 300, reverse=True, closures=((150, 40), (260, 120)))
    optimum = solve_exact(g)
    best = cd.planar_poses(optimum.R, optimum.t)
    inc, cov, cross = _parts(g, 0)
    junctions = np.unique(np.append(np.concatenate([cross.a, cross.b]), 299))
    chains = cd.condense(0, junctions[junctions > 0], inc, cov)
    filled = best.copy()
    filled[1:] = cd.fill(chains, best, inc)
    np.testing.assert_allclose(filled, best, atol=1e-3)  # three steps, not to the last bit
    assert _chi2(g, filled) == pytest.approx(optimum.chi2_final, rel=1e-3)


def test_the_condensed_solve_of_a_whole_graph_reaches_its_optimum() -> None:
    g = manhattan(200, seed=1).graph
    inc, cov, cross = _parts(g, 0)
    start = cd.planar_poses(g.R, g.t)
    start[1:] = dead_reckon(start[0], inc)[1:]
    solved, converged = cd.solve_loop(start, 0, inc, cov, cross, 30, 1e-12, lambda: False)
    assert converged
    assert _chi2(g, solved) / solve_exact(g).chi2_final < 1.0001


def _turned_loop(n: int = 300, bias: float = 1.6 / 300) -> PoseGraph:
    """A circle whose odometry turns ``bias`` rad a step too much, closed by its
    first-to-last edge, with one closure across it (the closure is 1.6 rad off), every
    measurement with noise of its stated σ (0.1)."""
    from h2o_slam.core.graph import EdgeKind, make_graph
    step = np.array([1.0, 0.0, 2 * np.pi / n])
    truth = dead_reckon(np.zeros(3), np.tile(step, (n - 1, 1)))
    a = np.concatenate([np.arange(n - 1), [n // 2, n - 1]])
    b = np.concatenate([np.arange(1, n), [n // 4, 0]])
    meas = geo.planar_between(truth[a], truth[b])
    meas[: n - 1, 2] += bias
    meas += np.random.default_rng(0).normal(0.0, 0.1, meas.shape)
    start = dead_reckon(np.zeros(3), meas[: n - 1])
    info = np.zeros((len(a), 6, 6))
    info[:, g_dof := geo.PLANAR_DOF, g_dof] = 100.0
    R, t = geo.yaw_to_matrix(start[:, 2]), np.column_stack([start[:, :2], np.zeros(n)])
    return make_graph(True, np.arange(n), R, t, np.full(len(a), EdgeKind.RELATIVE), a, b,
                      geo.yaw_to_matrix(meas[:, 2]),
                      np.column_stack([meas[:, :2], np.zeros(len(a))]), info)


def test_a_closure_far_off_in_yaw_starts_from_the_rotations(monkeypatch) -> None:
    """1.6 rad of yaw error: Gauss–Newton on the junctions from the dead reckoning stalls
    hundreds of times above the optimum's χ²; from LAGO's rotations first it ends near it
    (to first order only: two chains bent 0.8 rad each, against an optimum of χ² 9.7)."""
    g = _turned_loop()
    best = solve_exact(g).chi2_final
    inc, cov, cross = _parts(g, 0)
    start = cd.planar_poses(g.R, g.t)
    solved, _ = cd.solve_loop(start, 0, inc, cov, cross, 10, 1e-12, lambda: False)
    monkeypatch.setattr(cd, "ROTATION_FIRST_RAD", np.inf)
    stalled, _ = cd.solve_loop(start, 0, inc, cov, cross, 10, 1e-12, lambda: False)
    assert _chi2(g, solved) / best < 2.0
    assert _chi2(g, stalled) / best > 100.0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_the_sparse_step_is_the_dense_damped_gauss_newton_step(seed) -> None:
    """The compiled pattern, its slots and the assembly against ``(JᵀΩJ + λ diag) δ = −JᵀΩe``
    built densely: held ends, repeated and reversed edges, edges between held nodes."""
    rng = np.random.default_rng(seed)
    nodes, m = 12, 20
    free = np.sort(rng.choice(nodes, 7, replace=False))
    a, b = rng.integers(0, nodes, m), rng.integers(0, nodes, m)
    a, b = np.append(a[a != b], free), np.append(b[a != b], (free + 1) % nodes)
    Ja, Jb = rng.normal(size=(len(a), 3, 3)), rng.normal(size=(len(a), 3, 3))
    L = rng.normal(size=(len(a), 3, 3))
    info = L @ L.transpose(0, 2, 1) + np.eye(3)
    err = rng.normal(size=(len(a), 3))
    got = cd._Pattern(a, b, free, 3).solve(Ja, Jb, info, err, 0.1)

    col = {node: i for i, node in enumerate(free)}
    H, g = np.zeros((3 * len(free),) * 2), np.zeros(3 * len(free))
    for e in range(len(a)):
        J = np.zeros((3, 3 * len(free)))
        for node, Jn in ((a[e], Ja[e]), (b[e], Jb[e])):
            if node in col:
                J[:, 3 * col[node]:3 * col[node] + 3] += Jn
        H += J.T @ info[e] @ J
        g += J.T @ info[e] @ err[e]
    H[np.diag_indices_from(H)] *= 1.1
    np.testing.assert_allclose(got, np.linalg.solve(H, -g), rtol=1e-7, atol=1e-9)


def _dense_step(J_rows, err, info):
    """argmin Σ (e + J δ)ᵀ Ω (e + J δ) over the free unknowns, as one dense solve."""
    H = sum(J.T @ W @ J for J, W in zip(J_rows, info, strict=True))
    g = sum(J.T @ W @ e for J, e, W in zip(J_rows, err, info, strict=True))
    return np.linalg.solve(H, -g)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_rotations_first_is_lagos_two_solves_with_the_held_nodes_fixed(seed) -> None:
    """The yaws from the yaw errors alone, then the positions at those yaws: each the least
    squares of its own unknowns, solved here densely, one node's columns at a time."""
    rng = np.random.default_rng(seed)
    n, m = 8, 10
    a, b = rng.integers(0, n, m), rng.integers(0, n, m)
    keep = a != b  # and a chain through every node, so that each solve is determined
    a, b = np.append(np.arange(n - 1), a[keep]), np.append(np.arange(1, n), b[keep])
    pose = np.column_stack([rng.uniform(-5, 5, (n, 2)), rng.uniform(-3, 3, n)])
    meas = geo.planar_between(pose[a], pose[b]) + rng.normal(0.0, 0.3, (len(a), 3))
    L = rng.normal(0.0, 1.0, (len(a), 3, 3))
    info = L @ L.transpose(0, 2, 1) + 3.0 * np.eye(3)
    free = np.arange(2, n)  # nodes 0 and 1 held
    reduced = cd.Reduced(a, b, meas, info, free)
    got = reduced.rotations_first(pose)

    col = {node: i for i, node in enumerate(free)}

    def rows(Ja, Jb, dofs):
        out = []
        for e in range(len(a)):
            J = np.zeros((len(dofs), len(dofs) * len(free)))
            for node, Jn in ((a[e], Ja[e]), (b[e], Jb[e])):
                if node in col:
                    J[:, col[node] * len(dofs):(col[node] + 1) * len(dofs)] += Jn
            out.append(J)
        return out

    yaw_err = geo.wrap_angle(pose[b, 2] - pose[a, 2] - meas[:, 2])[:, None]
    yaw_info = (1.0 / np.linalg.inv(info)[:, 2, 2])[:, None, None]
    one = np.ones((len(a), 1, 1))
    turned = pose.copy()
    turned[free, 2] = geo.wrap_angle(
        pose[free, 2] + _dense_step(rows(-one, one, [2]), yaw_err, yaw_info))
    err, Ja, Jb = cd.relative_jacobians(turned[a], turned[b], meas)
    dxy = _dense_step(rows(Ja[:, :2, :2], Jb[:, :2, :2], [0, 1]), err[:, :2],
                      info[:, :2, :2])
    want = turned.copy()
    want[free, :2] += dxy.reshape(-1, 2)
    np.testing.assert_allclose(got, want, atol=1e-8)
    np.testing.assert_array_equal(got[:2], pose[:2])


def test_out_of_time_stops_after_the_first_iteration_and_still_fills_in() -> None:
    g = loop_graph(3, True, 300, reverse=True, closures=((150, 40), (260, 120)))
    inc, cov, cross = _parts(g, 0)
    start = cd.planar_poses(g.R, g.t)
    calls = []
    solved, converged = cd.solve_loop(start, 0, inc, cov, cross, 10, 1e-12,
                                      lambda: calls.append(1) or True)
    assert calls == [1] and not converged
    assert _chi2(g, solved) < _chi2(g, start)
