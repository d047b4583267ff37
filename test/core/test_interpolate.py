"""Interpolated solving (3.3.6): selection, merged constraints, distribution."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import geometry as geo
from h2o_slam.core import interpolate
from h2o_slam.core.graph import EARTH
from h2o_slam.core.solver import H2OSolver, SolverConfig

UNCAPPED = SolverConfig(max_rotation_step_rad=1e9)


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
