"""Interpolated solving (3.3.6): selection, merged constraints, distribution."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import geometry as geo
from h2o_slam.core import interpolate, jacobians
from h2o_slam.core.graph import EARTH
from h2o_slam.core.solver import H2OSolver, SolverConfig

UNCAPPED = SolverConfig(max_rotation_step_rad=1e9)


@settings(deadline=None)  # the first call may compile the kernel
@given(len_a=st.integers(0, 40), len_b=st.integers(1, 40), d_max=st.integers(1, 50))
def test_selection_keeps_endpoints_and_covers_the_domain(len_a, len_b, d_max):
    sel = interpolate.select(len_a, len_b, d_max)
    assert len(sel.kept) <= max(d_max, (len_a > 0) + 1)
    assert np.all(np.diff(sel.kept) > 0)
    assert len_a + len_b - 1 in sel.kept.tolist()
    if len_a:
        assert len_a - 1 in sel.kept.tolist()
    # Segments tile each chain exactly.
    covered = np.concatenate([np.arange(s, k + 1) for s, k in zip(sel.start, sel.kept,
                                                                     strict=True)])
    assert np.array_equal(covered, np.arange(len_a + len_b))


def _chain_solver(planar, n=30, loops=4, seed=0):
    graph = random_graph(seed, planar, n=n, loops=loops)
    parents = np.concatenate([[EARTH], np.arange(n - 1)])
    return H2OSolver.from_graph(graph, parents, UNCAPPED), graph


def _long_edge(solver):
    sizes = [len(solver.path(e).domain) for e in range(solver.num_edges)]
    return int(np.argmax(sizes)), max(sizes)


@pytest.mark.parametrize("planar", [True, False])
def test_d_max_at_least_the_domain_equals_the_full_update(planar):
    full, _ = _chain_solver(planar)
    interp, _ = _chain_solver(planar)
    edge, d = _long_edge(full)
    full.relax(edge)
    interp.relax(edge, d_max=d)
    assert np.allclose(full.tree.R[: full.num_nodes], interp.tree.R[: interp.num_nodes])
    assert np.allclose(full.tree.t[: full.num_nodes], interp.tree.t[: interp.num_nodes])
    assert np.allclose(full.B, interp.B)


@pytest.mark.parametrize("planar", [True, False])
@pytest.mark.parametrize("d_max", [1, 3, 7])
def test_interpolated_update_keeps_the_path_continuous(planar, d_max):
    solver, graph = _chain_solver(planar, seed=d_max)
    edge, d = _long_edge(solver)
    dom = solver.path(edge).domain
    R0, t0 = solver.world_poses()
    before = np.sum(solver.linearize(edge).r ** 2)
    solver.relax(edge, d_max=d_max)
    R1, t1 = solver.world_poses()
    assert np.sum(solver.linearize(edge).r ** 2) < before
    # Every node of the domain moves, not only the kept ones, and consecutive nodes move by
    # similar amounts: no single joint takes the whole bend.
    moved = np.linalg.norm(t1[dom] - t0[dom], axis=1)
    assert np.all(moved[1:] > 0)
    jumps = np.linalg.norm(geo.so3_log(np.swapaxes(R0[dom], 1, 2) @ R1[dom]), axis=1)
    local_turn = np.abs(np.diff(jumps))
    assert local_turn.max() < 0.5 * jumps.max() + 1e-12


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), length=st.integers(1, 12))
def test_distribution_lands_the_kept_node_on_its_target(seed, length):
    rng = np.random.default_rng(seed)
    R = geo.so3_exp(rng.normal(scale=0.3, size=(length, 3)))
    t = rng.normal(size=(length, 3))
    step = rng.normal(scale=0.2, size=(1, 6))
    sel = interpolate.Selection(np.array([length - 1]), np.array([0]))
    R_new, t_new = interpolate.distribute(sel, R, t, step, rng.uniform(0.1, 1.0, length))
    target_R = R.copy()
    target_t = t.copy()
    target_t[-1] += step[0, :3]
    target_R[-1] = R[-1] @ geo.so3_exp(step[0, 3:])
    want = geo.cumulative_compose(target_R, target_t)
    got = geo.cumulative_compose(R_new, t_new)
    assert np.allclose(got[0][-1], want[0][-1], atol=1e-10)
    assert np.allclose(got[1][-1], want[1][-1], atol=1e-10)


def test_stiff_nodes_take_less_of_the_turn():
    R = np.tile(np.eye(3), (4, 1, 1))
    t = np.tile([1.0, 0.0, 0.0], (4, 1))
    step = np.array([[0, 0, 0, 0, 0, 0.4]])
    sel = interpolate.Selection(np.array([3]), np.array([0]))
    R_new, _ = interpolate.distribute(sel, R, t, step, np.array([1.0, 1e-3, 1.0, 1.0]))
    turns = geo.matrix_to_yaw(R_new)
    assert turns[1] < 0.01 * turns[0]
    assert np.isclose(turns.sum(), 0.4)


def test_merged_constraint_of_a_chain_multiplies_the_measurements():
    rng = np.random.default_rng(5)
    k_R = geo.so3_exp(rng.normal(scale=0.5, size=(3, 3)))
    k_t = rng.normal(size=(3, 3))
    S = np.tile(np.eye(6), (3, 1, 1))
    sel = interpolate.Selection(np.array([2]), np.array([0]))
    R_b, t_b, S_b = interpolate.merge_segments(sel, k_R, k_t, S)
    want = geo.cumulative_compose(k_R, k_t)
    assert np.allclose(R_b[0], want[0][-1]) and np.allclose(t_b[0], want[1][-1])
    # Eq. 3.38 sums stiffnesses; isotropic ones stay isotropic under rotation.
    assert np.allclose(S_b[0], 3 * np.eye(6))


def test_interpolated_offline_passes_still_converge():
    solver, graph = _chain_solver(True, n=40, loops=8, seed=3)
    from h2o_slam.core.graph import chi2

    start = chi2(graph)
    for _ in range(5):
        for e in range(solver.num_edges):
            solver.relax(e, d_max=4)
    assert solver.chi2(graph) < 0.5 * start


def test_repeated_interpolated_updates_keep_rotations_orthonormal():
    solver, _ = _chain_solver(False, n=60, loops=10, seed=9)
    for _ in range(3):
        for e in range(solver.num_edges):
            solver.relax(e, d_max=3)
    R = solver.tree.R[: solver.num_nodes]
    assert np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max() < 1e-12


def _select_reference(len_a, len_b, d_max):
    """The selection in plain Python lists (the numpy version it replaced, restated)."""
    total = len_a + len_b
    if total <= d_max:
        return list(range(total)), list(range(total))
    counts = [min(len_a, d_max), min(len_b, d_max)]
    if len_a and len_b:  # shared in proportion, each chain keeping at least one
        counts[0] = min(len_a, max(1, min(d_max - 1, round(d_max * len_a / total))))
        counts[1] = min(len_b, max(1, d_max - counts[0]))
    kept, start = [], []
    for offset, length, k in ((0, len_a, counts[0]), (len_a, len_b, counts[1])):
        ends = [offset + length - 1 - (i * length) // k for i in reversed(range(k))]
        kept += ends
        start += [offset] + [end + 1 for end in ends[:-1]] if ends else []
    return kept, start


@settings(deadline=None)
@given(len_a=st.integers(0, 2000), len_b=st.integers(1, 2000), d_max=st.integers(1, 300))
def test_compiled_selection_matches_the_numpy_one(len_a, len_b, d_max):
    _check_selection(len_a, len_b, d_max)


@pytest.mark.parametrize(("len_a", "len_b", "d_max"), [(0, 1427, 75), (700, 727, 75),
                                                       (1000, 427, 100), (3, 0, 2)])
def test_compiled_selection_on_long_paths(len_a, len_b, d_max):
    _check_selection(len_a, len_b, d_max)


def _check_selection(len_a, len_b, d_max):
    sel = interpolate.select(len_a, len_b, d_max)
    kept, start = _select_reference(len_a, len_b, d_max)
    assert sel.kept.tolist() == kept
    assert sel.start.tolist() == start


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), planar=st.booleans(), as_tuple=st.booleans())
def test_rotated_stiffness_in_the_coordinates_in_use(seed, planar, as_tuple):
    """``add_rotated_stiffness`` on the coordinates in use equals the full 6×6 ``RᵀSR``
    restricted to them (planar: for rotations about z)."""
    rng = np.random.default_rng(seed)
    dof = geo.PLANAR_DOF if planar else np.arange(6)
    G = rng.normal(size=(6, 6))
    S = G @ G.T
    w = rng.normal(size=3)
    if planar:
        w[:2] = 0.0
    Q = geo.so3_exp(w)
    rot = np.kron(np.eye(2), Q)
    want = (rot.T @ S @ rot)[np.ix_(dof, dof)]
    out = np.eye(len(dof))
    interpolate.add_rotated_stiffness(np.ascontiguousarray(S[np.ix_(dof, dof)]), Q,
                                      tuple(int(q) for q in dof) if as_tuple else dof, out,
                                      np.empty((len(dof), len(dof))))
    np.testing.assert_allclose(out, np.eye(len(dof)) + want, rtol=1e-12, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), length=st.integers(0, 12))
def test_composition_down_a_chain(seed, length):
    rng = np.random.default_rng(seed)
    R = geo.so3_exp(rng.normal(size=(20, 3)))
    t = rng.normal(size=(20, 3))
    nodes = rng.permutation(20)[:length]
    H_R = np.empty((length + 1, 3, 3))
    H_x = np.empty((length + 1, 3))
    H_R[0], H_x[0] = geo.so3_exp(rng.normal(size=3)), rng.normal(size=3)
    jacobians.compose_into(R, t, nodes, H_R, H_x)
    if length:
        want_R, want_t = geo.cumulative_compose(np.concatenate([H_R[:1], R[nodes]]),
                                                np.concatenate([H_x[:1], t[nodes]]))
        np.testing.assert_allclose(H_R, want_R, atol=1e-13)
        np.testing.assert_allclose(H_x, want_t, atol=1e-13)


def test_compliance_is_the_inverse_rotational_diagonal():
    rng = np.random.default_rng(6)
    for p, rot in ((3, [2]), (6, [3, 4, 5])):
        B = rng.uniform(0.5, 2.0, size=(5, p, p))
        B[2] = 0.0
        diag = np.einsum("dii->di", B)[:, rot].sum(axis=1)
        want = 1.0 / (diag + 1e-9 * diag.max())
        np.testing.assert_allclose(interpolate.compliance(B), want, rtol=1e-15)


def test_tree_edges_give_way_only_where_their_contribution_is_their_nodes_alone():
    p = 3
    adjust = np.tile(np.eye(p), (5, 1, 1)) * 5.0  # J_βᵀJ_β of each kept node
    B_c = np.arange(9)[:, None, None] * np.ones((9, p, p))
    domain = np.array([10, 11, 12, 13, 14, 15, 16, 17, 18])
    kept = np.array([1, 3, 5, 7, 8])
    start = np.array([0, 2, 4, 6, 8])
    top = np.zeros(9, dtype=bool)
    top[4] = True  # the third segment holds a subtree top: it keeps B_c
    tree_edge = np.full(20, -1)
    tree_edge[[11, 13, 15, 17, 18]] = [0, 1, 2, 3, 4]
    own_node = np.array([11, 99, 15, 17, 18])  # edge 1's contribution is not node 13's alone
    own_block = np.arange(5)[:, None, None] * np.ones((5, p, p))
    interpolate.give_way(adjust, B_c, domain, kept, start, top, tree_edge, own_node,
                         own_block)
    np.testing.assert_array_equal(adjust[0], 1.0 + 5.0 * np.eye(p))  # B_c − α + β
    np.testing.assert_array_equal(adjust[1], B_c[3])
    np.testing.assert_array_equal(adjust[2], B_c[5])
    np.testing.assert_array_equal(adjust[3], 7.0 + 5.0 * np.eye(p) - 3.0)
    np.testing.assert_array_equal(adjust[4], B_c[8])  # a segment of one node: no merge
