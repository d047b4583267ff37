"""H₂O core: Jacobians against finite differences, the single-edge update against a dense
least-squares solve of (3.34), and the batch of all edges against Gauss–Newton."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import geometry as geo
from h2o_slam.core import jacobians
from h2o_slam.core.exact import ExactSystem
from h2o_slam.core.graph import EARTH, EdgeKind, chi2, edge_errors
from h2o_slam.core.hybrid import NULL_TOLERANCE
from h2o_slam.core.jacobians import endpoint_jacobians
from h2o_slam.core.modes import build_solver
from h2o_slam.core.solver import (
    H2OSolver,
    SolverConfig,
    _blocks_without,
    _gram,
    _store_contribution,
)

UNCAPPED = SolverConfig(max_rotation_step_rad=1e9)


def _perturb_global(R, x, k, h):
    x, R = x.copy(), R.copy()
    if k < 3:
        x[k] += h
    else:
        w = np.zeros(3)
        w[k - 3] = h
        R = geo.so3_exp(w) @ R
    return R, x


@pytest.mark.parametrize("kind", list(EdgeKind))
def test_endpoint_jacobians_match_finite_differences(kind):
    rng = np.random.default_rng(int(kind))
    for _ in range(5):
        Ra, Rb, Rk = geo.so3_exp(rng.normal(size=(3, 3)))
        xa, xb, tk = rng.normal(size=(3, 3))
        kinds = np.array([kind])

        def err(Ra, xa, Rb, xb, Rk=Rk, tk=tk, kinds=kinds):
            return endpoint_jacobians(kinds, Ra[None], xa[None], Rb[None], xb[None],
                                      Rk[None], tk[None])[0][0]

        _, Ja, Jb = endpoint_jacobians(kinds, Ra[None], xa[None], Rb[None], xb[None],
                                       Rk[None], tk[None])
        h = 1e-6
        for k in range(6):
            Rp, xp = _perturb_global(Ra, xa, k, h)
            Rm, xm = _perturb_global(Ra, xa, k, -h)
            num_a = (err(Rp, xp, Rb, xb) - err(Rm, xm, Rb, xb)) / (2 * h)
            Rp, xp = _perturb_global(Rb, xb, k, h)
            Rm, xm = _perturb_global(Rb, xb, k, -h)
            num_b = (err(Ra, xa, Rp, xp) - err(Ra, xa, Rm, xm)) / (2 * h)
            if kind != EdgeKind.RELATIVE:
                num_a[:] = 0.0  # a global edge's first endpoint is the fixed earth
            assert np.allclose(Ja[0][:, k], num_a, atol=1e-7)
            assert np.allclose(Jb[0][:, k], num_b, atol=1e-7)


def _whitened_residuals(solver, graph):
    R, t = solver.world_poses()
    e = edge_errors(graph, R, t)[:, solver.dof]
    return np.einsum("mij,mj->mi", np.array(solver.W), e)


def _perturb_local(solver, node, k, h):
    full = np.zeros((1, 6))
    full[0, k] = h
    solver.tree.t[node] += full[0, :3]
    solver.tree.R[node] = solver.tree.R[node] @ geo.so3_exp(full[0, 3:])


def _numeric_jacobian(solver, graph, nodes):
    """d(whitened residuals of all edges) / d(local perturbations of nodes), central FD."""
    h = 1e-6
    cols = []
    for node in nodes:
        for k in solver.dof:
            saved = solver.tree.R[node].copy(), solver.tree.t[node].copy()
            _perturb_local(solver, node, k, h)
            plus = _whitened_residuals(solver, graph)
            solver.tree.R[node], solver.tree.t[node] = saved
            _perturb_local(solver, node, k, -h)
            minus = _whitened_residuals(solver, graph)
            solver.tree.R[node], solver.tree.t[node] = saved
            cols.append(((plus - minus) / (2 * h)).ravel())
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("planar", [True, False])
def test_domain_jacobian_blocks_match_finite_differences(planar):
    graph = random_graph(11, planar, n=9, loops=5, gps=2, orientation=2)
    solver, _ = build_solver(graph)
    nodes = np.arange(graph.num_nodes)
    numeric = _numeric_jacobian(solver, graph, nodes)
    p = solver.p
    for e in range(graph.num_edges):
        lin = solver.linearize(e)
        rows = numeric[e * p:(e + 1) * p].reshape(p, len(nodes), p)
        analytic = np.zeros_like(rows)
        analytic[:, lin.domain, :] = np.swapaxes(lin.J, 0, 1)
        assert np.allclose(analytic, rows, atol=1e-6 * max(1.0, np.abs(rows).max())), e
        assert np.allclose(lin.r, _whitened_residuals(solver, graph)[e])


def test_edge_root_is_outside_the_domain():
    graph = random_graph(2, False, n=10, loops=6)
    solver, _ = build_solver(graph)
    for e in range(graph.num_edges):
        path = solver.path(e)
        assert path.root not in set(path.domain.tolist())
        assert len(set(path.domain.tolist())) == len(path.domain)


def _local_step(before, after):
    (R0, t0), (R1, t1) = before, after
    dt = t1 - t0
    dth = geo.so3_log(np.swapaxes(R0, -1, -2) @ R1)
    return np.concatenate([dt, dth], axis=-1)


def _dense_hybrid_reference(lin, B_c, p):
    d = len(lin.domain)
    lam, U = np.linalg.eigh(B_c)
    scale = max(lam.max(), np.abs(lin.J).max() ** 2)
    lam = np.where(lam > NULL_TOLERANCE * scale, lam, 0.0)
    gamma = np.zeros((d * p, d * p))
    for i in range(d):
        gamma[i * p:(i + 1) * p, i * p:(i + 1) * p] = np.sqrt(lam[i])[:, None] * U[i].T
    lhs = np.vstack([np.concatenate(list(lin.J), axis=1), gamma])
    rhs = np.concatenate([-lin.r, np.zeros(d * p)])
    return np.linalg.lstsq(lhs, rhs, rcond=None)[0].reshape(d, p)


@pytest.mark.parametrize("planar", [True, False])
def test_single_edge_update_equals_dense_least_squares(planar):
    graph = random_graph(5, planar, n=10, loops=5, gps=2)
    solver = H2OSolver.from_graph(graph, _chain_parents(graph.num_nodes), UNCAPPED)
    for e in range(graph.num_edges):
        lin = solver.linearize(e)
        nodes, blocks = solver._contrib[e]
        B_c = solver.B[lin.domain] - blocks
        expected = _dense_hybrid_reference(lin, B_c, solver.p)
        before = solver.tree.R[lin.domain].copy(), solver.tree.t[lin.domain].copy()
        solver.relax(e)
        after = solver.tree.R[lin.domain], solver.tree.t[lin.domain]
        got = _local_step(before, after)[:, solver.dof]
        assert np.allclose(got, expected, rtol=1e-9, atol=1e-14 + 1e-9 * np.abs(expected).max()), e


def test_single_edge_update_with_singular_regularizer_blocks():
    # Online, a new leaf's only edge is the one relaxed: its B_c block is exactly zero, and a
    # position edge alone leaves a rank-deficient block. The update must match lstsq.
    graph = random_graph(8, False, n=6, loops=0, gps=3)
    solver = H2OSolver(planar=False, config=UNCAPPED)
    solver.add_pose(graph.R[0], graph.t[0])
    for e in range(graph.num_edges):
        solver.add_edge(int(graph.kind[e]), int(graph.a[e]), int(graph.b[e]),
                        graph.meas_R[e], graph.meas_t[e], graph.info[e])
    for e in range(graph.num_edges):
        lin = solver.linearize(e)
        B_c = solver.B[lin.domain] - solver._contrib[e][1]
        expected = _dense_hybrid_reference(lin, B_c, solver.p)
        before = solver.tree.R[lin.domain].copy(), solver.tree.t[lin.domain].copy()
        solver.relax(e)
        got = _local_step(before, (solver.tree.R[lin.domain], solver.tree.t[lin.domain]))
        assert np.allclose(got, expected, rtol=1e-9, atol=1e-14 + 1e-9 * np.abs(expected).max()), e


def _chain_parents(n):
    return np.concatenate([[EARTH], np.arange(n - 1)])


def _gauss_newton_reference(solver, graph):
    free = np.flatnonzero(solver.tree.parent[: solver.num_nodes] != EARTH)
    J = _numeric_jacobian(solver, graph, free)
    r = _whitened_residuals(solver, graph).ravel()
    return np.linalg.lstsq(J, -r, rcond=None)[0].reshape(len(free), solver.p), free


@pytest.mark.parametrize("planar", [True, False])
def test_batch_of_all_edges_is_the_gauss_newton_step(planar):
    graph = random_graph(21, planar, n=9, loops=5)
    solver, _ = build_solver(graph, UNCAPPED)
    expected, free = _gauss_newton_reference(solver, graph)

    x_world, nodes = ExactSystem(solver).step()
    assert np.array_equal(nodes, free)
    assert np.allclose(x_world, expected, rtol=1e-5, atol=1e-6)

    before = solver.tree.R[free].copy(), solver.tree.t[free].copy()
    solver.relax_batch(range(graph.num_edges))
    got = _local_step(before, (solver.tree.R[free], solver.tree.t[free]))[:, solver.dof]
    assert np.allclose(got, x_world, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("planar", [True, False])
def test_world_linearization_scores_the_estimate_as_the_graph_chi2(planar):
    # Exact mode accepts or refuses a step by the linearization's χ² (Σ r²): it must be the
    # graph's χ², the metric every report and benchmark uses.
    graph = random_graph(8, planar, n=11, loops=6, gps=3, orientation=1)
    solver, _ = build_solver(graph, UNCAPPED)
    step, nodes = ExactSystem(solver).step()
    solver.apply_step(nodes, 0.5 * step)
    R, t = solver.world_poses()
    expected = chi2(graph, R, t)
    assert expected > 1e-3
    assert ExactSystem(solver).linearize().chi2 == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("planar", [True, False])
def test_exact_mode_moves_each_pose_by_its_own_world_step(planar):
    # Taken in the tree's coordinates, a rotation near the root would swing its subtree along
    # an arc the linearization never saw (city10000 from its odometry start: 100 iterations
    # ended 860x above the optimum); each pose retracts on its own, as GTSAM's do.
    graph = random_graph(5, planar, n=10, loops=5, gps=2)
    solver, _ = build_solver(graph, UNCAPPED)
    exact = ExactSystem(solver)
    lin = exact.linearize()
    step = exact._world_step(lin, 0.0)
    assert np.abs(step).max() > 1e-3
    exact.move(lin)
    R, t = solver.world_poses()
    np.testing.assert_allclose(t, lin.x + step[:, :3], atol=1e-10)
    np.testing.assert_allclose(R, geo.so3_exp(step[:, 3:]) @ lin.R, atol=1e-10)


def test_batch_with_gps_edges_moves_the_subtree_top():
    graph = random_graph(4, False, n=7, loops=2, gps=4)
    solver, _ = build_solver(graph, UNCAPPED)
    expected, _ = _gauss_newton_reference_all(solver, graph)
    x_world, nodes = ExactSystem(solver).step()
    assert 0 in nodes.tolist() or solver.tree.parent[0] != EARTH
    assert np.allclose(x_world, expected, rtol=1e-5, atol=1e-6)


def _gauss_newton_reference_all(solver, graph):
    nodes = np.arange(solver.num_nodes)
    J = _numeric_jacobian(solver, graph, nodes)
    r = _whitened_residuals(solver, graph).ravel()
    return np.linalg.lstsq(J, -r, rcond=None)[0].reshape(len(nodes), solver.p), nodes


def test_regularizer_is_the_sum_of_edge_contributions():
    graph = random_graph(9, False, n=10, loops=6, gps=2)
    solver, _ = build_solver(graph)
    for e in [3, 7, 1, 12, 5]:
        solver.relax(e)
    solver.relax_batch([0, 2, 4])
    total = np.zeros_like(solver.B[: solver.num_nodes])
    for nodes, blocks in solver._contrib:
        np.add.at(total, nodes, blocks)
    assert np.allclose(solver.B[: solver.num_nodes], total)


def test_relaxing_an_edge_lowers_its_own_error():
    graph = random_graph(13, True, n=12, loops=6)
    solver, _ = build_solver(graph)
    for e in range(graph.num_edges):
        before = np.sum(solver.linearize(e).r ** 2)
        solver.relax(e)
        assert np.sum(solver.linearize(e).r ** 2) <= before + 1e-12


def test_rotation_step_is_capped():
    graph = random_graph(17, False, n=6, loops=3)
    solver, _ = build_solver(graph, SolverConfig(max_rotation_step_rad=1e-3))
    for e in range(graph.num_edges):
        lin = solver.linearize(e)
        before = solver.tree.R[lin.domain].copy(), solver.tree.t[lin.domain].copy()
        solver.relax(e)
        step = _local_step(before, (solver.tree.R[lin.domain], solver.tree.t[lin.domain]))
        assert np.linalg.norm(step[:, 3:], axis=1).max() <= 1e-3 + 1e-12


def test_world_poses_survive_a_solver_round_trip():
    graph = random_graph(3, False, n=10, loops=4)
    solver, _ = build_solver(graph, init="input")
    R, t = solver.world_poses()
    assert np.allclose(R, graph.R) and np.allclose(t, graph.t)
    assert np.isclose(solver.chi2(graph), chi2(graph))


@pytest.mark.parametrize("seed", range(4))
def test_relative_pose_along_the_tree_path_equals_the_world_poses(seed):
    graph = random_graph(seed, seed % 2 == 0, n=40, loops=10)
    solver, _ = build_solver(graph, init="input")
    R_world, t_world = solver.world_poses()
    rng = np.random.default_rng(seed)
    for a, b in rng.integers(0, graph.num_nodes, size=(20, 2)):
        R, t = solver.relative_pose(int(a), int(b))
        R_ab, t_ab = geo.between(R_world[a], t_world[a], R_world[b], t_world[b])
        assert np.allclose(R, R_ab, atol=1e-10) and np.allclose(t, t_ab, atol=1e-9)
    R, t = solver.relative_pose(EARTH, 7)
    assert np.allclose(R, R_world[7]) and np.allclose(t, t_world[7])


def test_tree_path_from_an_edge_cache_matches_the_walk_either_way_round():
    graph = random_graph(5, True, n=30, loops=8)
    solver, _ = build_solver(graph, init="input")
    for e in range(solver.num_edges):
        a, b = int(solver.a[e]), int(solver.b[e])
        for x, y in ((a, b), (b, a)):
            cached, walked = solver.tree_path(x, y, e), solver.tree.path(x, y)
            assert cached.root == walked.root
            assert np.array_equal(cached.a_chain, walked.a_chain)
            assert np.array_equal(cached.b_chain, walked.b_chain)


def test_planar_updates_keep_every_rotation_exactly_about_z():
    """Long planar chains are composed by adding angles only while every rotation has exact
    zeros off the plane; full and interpolated updates, with the guard, must keep them."""
    graph = random_graph(4, planar=True, n=120, loops=30)
    solver, _ = build_solver(graph)
    for edge in range(solver.num_edges):
        solver.relax(edge, d_max=3 if edge % 2 else None, guard=True)
    R = solver.tree.R[: solver.tree.n]
    assert np.all(R[:, 2, 2] == 1.0)
    assert not np.any(R[:, 2, :2]) and not np.any(R[:, :2, 2])


def test_edges_added_at_once_equal_edges_added_one_by_one():
    graph = random_graph(41, False, n=10, loops=5, gps=3, orientation=2)
    parents = np.concatenate([[EARTH], np.arange(graph.num_nodes - 1)])
    bulk = H2OSolver.from_graph(graph, parents)
    single = H2OSolver(planar=graph.planar)
    for e in range(graph.num_edges):
        single._append_edge(int(graph.kind[e]), int(graph.a[e]), int(graph.b[e]),
                            graph.meas_R[e], graph.meas_t[e], graph.info[e])
    for name in ("kind", "a", "b", "meas_R", "meas_t", "info", "W"):
        np.testing.assert_array_equal(getattr(bulk, name), getattr(single, name), err_msg=name)
    assert bulk._incident == single._incident
    assert bulk._gps_at == single._gps_at
    assert len(bulk._paths) == len(bulk._contrib) == graph.num_edges


def test_world_poses_follow_every_change_of_the_tree():
    graph = random_graph(43, True, n=8, loops=3)
    solver, _ = build_solver(graph)
    R, t = solver.world_poses()
    R[:] = 0.0  # the caller's copy: the kept answer is not touched
    R2, t2 = solver.world_poses()
    np.testing.assert_array_equal(t2, t)
    assert not np.any(np.all(R2 == 0.0, axis=(1, 2)))
    solver.tree.t[3, 0] += 1.0  # changed in place
    R3, t3 = solver.world_poses()
    expected = solver.tree.__class__.world_poses(solver.tree)
    np.testing.assert_array_equal(t3, expected[1])
    np.testing.assert_array_equal(R3, expected[0])
    assert not np.array_equal(t3, t2)


@pytest.mark.parametrize("planar", [True, False])
def test_exact_steps_do_not_need_the_regularizer(planar):
    graph = random_graph(47, planar, n=10, loops=5, gps=2)
    parents = np.concatenate([[EARTH], np.arange(graph.num_nodes - 1)])
    full = H2OSolver.from_graph(graph, parents, UNCAPPED)
    bare = H2OSolver.from_graph(graph, parents, UNCAPPED, regularizer=False)
    assert not np.any(bare.B[: bare.num_nodes]) and bare.contribution_size(0) == 0
    for solver in (full, bare):
        step, nodes = ExactSystem(solver).step()
        solver.apply_step(nodes, step)
    np.testing.assert_array_equal(bare.world_poses()[1], full.world_poses()[1])
    bare.relax(graph.num_edges - 1)  # an edge without a contribution yet relaxes as usual
    assert bare.contribution_size(graph.num_edges - 1) > 0


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), planar=st.booleans(), as_tuple=st.booleans())
def test_chain_block_is_the_endpoint_jacobian_times_the_chain_jacobian(seed, planar, as_tuple):
    """``chain_block_into`` forms ``(A M)[:, dof]`` without ``M``: against the product with
    ``chain_jacobians``' block."""
    rng = np.random.default_rng(seed)
    dof = geo.PLANAR_DOF if planar else np.arange(6)
    A = rng.normal(size=(len(dof), 6))
    R_parent, R_node = geo.so3_exp(rng.normal(size=(2, 3)))
    x_node, x_end = rng.normal(size=(2, 3))
    M = jacobians.chain_jacobians(R_parent[None], R_node[None], x_node[None], x_end)[0]
    got = np.empty((len(dof), len(dof)))
    jacobians.chain_block_into(A, R_parent, R_node, x_end - x_node,
                               tuple(int(q) for q in dof) if as_tuple else dof, got)
    np.testing.assert_allclose(got, (A @ M)[:, dof], rtol=1e-12, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), shape=st.sampled_from([(3, 3), (6, 6), (2, 3), (4, 4)]))
def test_gram_blocks_and_their_store(seed, shape):
    rng = np.random.default_rng(seed)
    d = 7
    J = rng.normal(size=(d, *shape))
    want = np.swapaxes(J, 1, 2) @ J
    np.testing.assert_allclose(_gram(J), want, rtol=1e-13, atol=1e-13)
    p = shape[1]
    B = rng.normal(size=(20, p, p))
    nodes = rng.permutation(20)[:d]
    B_c = rng.normal(size=(d, p, p))
    np.testing.assert_allclose(_blocks_without(B, nodes, B_c), B[nodes] - B_c, rtol=1e-15)
    expected = B.copy()
    expected[nodes] = B_c + want
    np.testing.assert_allclose(_store_contribution(B, nodes, B_c, J), want, rtol=1e-13,
                               atol=1e-13)
    np.testing.assert_allclose(B, expected, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("planar", [True, False])
def test_single_node_contributions_are_mirrored_per_edge(planar):
    """``_own_node``/``_own_block`` (read by the interpolated update for eq. 3.36's α) agree
    with ``_contrib`` after updates of every kind and re-parentings."""
    graph = random_graph(4, planar, n=25, loops=8, gps=2)
    solver, _ = build_solver(graph)

    def check():
        for e, contrib in enumerate(solver._contrib):
            if contrib is None or len(contrib[0]) != 1:
                assert solver._own_node[e] == -1 or contrib is None, e
                continue
            assert solver._own_node[e] == contrib[0][0], e
            np.testing.assert_array_equal(solver._own_block[e], contrib[1][0])

    check()
    for e in range(solver.num_edges):
        if solver.kind[e] == EdgeKind.POSITION:
            solver.relax_batch([e])
        else:
            solver.relax(e, d_max=3 if e % 2 else None)
    check()
    edge = next(e for e in range(solver.num_edges) if solver.kind[e] == EdgeKind.RELATIVE
                and len(solver.path(e).domain) > 2)
    a, b = int(solver.a[edge]), int(solver.b[edge])
    node, parent = (b, a) if solver.tree.depth[b] > solver.tree.depth[a] else (a, b)
    solver.reparent(node, parent, edge)
    check()
