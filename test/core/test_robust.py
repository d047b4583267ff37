"""GNC-TLS robust exact solves: the weight function, weighted whitening, the innovation, and
maps with planted false closures against the outlier-free map."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import geometry as geo
from h2o_slam.core.edges import EdgeTable
from h2o_slam.core.exact import converge_exact
from h2o_slam.core.geometry import PLANAR_DOF
from h2o_slam.core.graph import EdgeKind, PoseGraph, chi2, make_graph
from h2o_slam.core.modes import build_solver, solve_exact
from h2o_slam.core.robust import (
    CLUSTER_SPAN,
    MAX_TRIES,
    TAIL_MIN_CLOSURES,
    EdgeState,
    RobustConfig,
    RobustOutcome,
    _polish,
    closure_noise_scale,
    converge_robust,
    deletion_chi2,
    edge_states,
    edge_thresholds,
    group_chi2,
    initial_mu,
    innovation_chi2,
    lago_restart,
    odometry_edges,
    restarted_if_lower,
    solver_residuals,
    tail_thresholds,
    thresholds,
    tls_weights,
)
from h2o_slam.io.outliers import OUTLIER_KINDS, plant_outliers
from h2o_slam.io.synthetic import manhattan

squares = st.floats(0.0, 1e6, allow_nan=False)
mus = st.floats(1e-4, 1e4, allow_nan=False)


@given(squares, squares, mus)
def test_tls_weights_are_in_unit_interval_and_fall_with_the_residual(r1, r2, mu):
    w = tls_weights(np.array([min(r1, r2), max(r1, r2)]), mu, np.full(2, 10.0))
    assert np.all((w >= 0.0) & (w <= 1.0))
    assert w[0] >= w[1]


@given(mus)
def test_tls_weights_are_continuous_at_both_bounds(mu):
    c2 = 7.0
    lo, hi = mu / (mu + 1.0) * c2, (mu + 1.0) / mu * c2
    r2 = np.array([lo * (1 - 1e-10), lo * (1 + 1e-10), hi * (1 - 1e-10), hi * (1 + 1e-10)])
    w = tls_weights(r2, mu, np.full(4, c2))
    np.testing.assert_allclose(w, [1.0, 1.0, 0.0, 0.0], atol=1e-5)


@given(st.floats(1.0, 1e8, allow_nan=False), st.floats(0.1, 100.0))
def test_initial_mu_keeps_the_largest_residual_weighed(r2_max, c2):
    if r2_max <= c2:
        r2_max = 2.0 * c2
    mu = initial_mu(r2_max, c2)
    assert tls_weights(np.array([r2_max * (1 - 1e-9)]), mu, np.array([c2]))[0] > 0.0


def test_a_weight_scales_the_information_the_whitening_stands_for():
    table = EdgeTable(3)
    info = np.diag([4.0, 9.0, 1.0, 1.0, 1.0, 16.0])
    for _ in range(3):
        table.append(0, 0, 1, np.eye(3), np.zeros(3), info, PLANAR_DOF)
    table.set_weights(np.array([0, 2]), np.array([0.25, 0.0]))
    S = info[np.ix_(PLANAR_DOF, PLANAR_DOF)]
    for e, w in enumerate([0.25, 1.0, 0.0]):
        np.testing.assert_allclose(table.W[e].T @ table.W[e], w * S, atol=1e-12)


def test_thresholds_follow_each_edges_degrees_of_freedom():
    kind = np.array([0, 1])
    planar = thresholds(kind, True, 0.99)
    spatial = thresholds(kind, False, 0.99)
    np.testing.assert_allclose(planar, [11.345, 9.210], rtol=1e-3)
    np.testing.assert_allclose(spatial, [16.812, 11.345], rtol=1e-3)


def test_edge_states_name_each_weight():
    states = edge_states(np.array([1.0, 1.0, 0.5, 0.0]), np.array([True, False, False, False]))
    assert states.tolist() == [EdgeState.TRUSTED, EdgeState.ACCEPTED, EdgeState.DOWNWEIGHTED,
                               EdgeState.DROPPED]


@pytest.fixture(scope="module")
def world():
    """A small planar Manhattan graph (300 poses, ~110 true closures) and its optimum."""
    graph = manhattan(300, seed=4).graph
    return graph, solve_exact(graph)


def test_without_outliers_the_robust_answer_is_the_optimum(world):
    graph, optimum = world
    result = solve_exact(graph, robust=RobustConfig())
    assert result.weights is not None and np.all(result.weights == 1.0)
    np.testing.assert_allclose(result.t, optimum.t, atol=1e-7)
    assert chi2(graph, result.R, result.t) <= chi2(graph, optimum.R, optimum.t) * (1 + 1e-9)


@pytest.mark.parametrize("kind", OUTLIER_KINDS)
def test_each_outlier_kind_leaves_the_outlier_free_map(world, kind):
    graph, optimum = world
    planted = plant_outliers(graph, kind, 10, seed=2)
    result = solve_exact(planted.graph, robust=RobustConfig())
    assert result.weights is not None
    assert np.all(result.weights[planted.outlier] == 0.0)  # every false closure dropped
    assert np.all(result.weights[~planted.outlier] == 1.0)  # no true one turned away
    np.testing.assert_allclose(result.t, optimum.t, atol=1e-6)


def test_least_squares_is_bent_by_the_same_outliers(world):
    """The planted closures are outliers that matter: without the robust solve they move
    the map by metres (the test above could not pass by accident)."""
    graph, optimum = world
    planted = plant_outliers(graph, "random", 10, seed=2)
    plain = solve_exact(planted.graph)
    assert np.max(np.abs(plain.t - optimum.t)) > 0.5


def test_a_group_that_agrees_with_itself_but_not_with_the_rest_is_dropped(world):
    graph, optimum = world
    planted = plant_outliers(graph, "local_grouped", 10, seed=5)  # one group of ten
    meas = planted.graph.meas_t[planted.outlier]
    assert np.all(meas == meas[0])  # one false measurement, mutually consistent
    result = solve_exact(planted.graph, robust=RobustConfig())
    assert result.weights is not None
    assert np.all(result.weights[planted.outlier] == 0.0)
    np.testing.assert_allclose(result.t, optimum.t, atol=1e-6)


def test_a_dropped_true_closure_is_readmitted(world):
    """Started with a true closure already dropped (as a graduation that passed through a
    bent map leaves it), the solve takes it back: decisions are revised."""
    graph, optimum = world
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    closure = int(np.flatnonzero(~trusted)[0])
    solver, _ = build_solver(graph, init="tree", regularizer=False, trusted=trusted)
    weights = np.ones(graph.num_edges)
    weights[closure] = 0.0
    outcome = converge_robust(solver, 100, trusted, RobustConfig(), weights=weights)
    assert outcome.weights[closure] == 1.0
    np.testing.assert_allclose(solver.world_poses()[1], optimum.t, atol=1e-6)


def test_true_closures_dropped_at_many_places_come_back(world):
    """True closures of more places than one round of re-admissions tries start dropped
    (each alone agrees with the map, so they come back together, in one move); the map
    ends at the optimum."""
    graph, optimum = world
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    closures = np.flatnonzero(~trusted)
    dropped, last = [], -CLUSTER_SPAN - 1
    for e in closures[np.argsort(graph.b[closures])]:  # places apart along the way
        if graph.b[e] > last + CLUSTER_SPAN:
            dropped.append(e)
            last = graph.b[e]
    assert len(dropped) > MAX_TRIES
    solver, _ = build_solver(graph, init="tree", regularizer=False, trusted=trusted)
    weights = np.ones(graph.num_edges)
    weights[dropped] = 0.0
    outcome = converge_robust(solver, 100, trusted, RobustConfig(), weights=weights)
    assert np.all(outcome.weights[dropped] == 1.0)
    np.testing.assert_allclose(solver.world_poses()[1], optimum.t, atol=1e-6)


def test_innovation_is_what_adding_the_edge_costs(world):
    """The innovation χ² of an edge left out equals the rise of the optimal χ² when it is
    put back (exactly for a linear problem; to first order here, with small residuals)."""
    graph, _ = world
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    closure = int(np.flatnonzero(~trusted)[3])
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    weights = np.ones(graph.num_edges)
    weights[closure] = 0.0
    solver.set_weights(weights)
    without = converge_exact(solver, 100)[0][-1]
    innovation = float(innovation_chi2(solver, np.array([closure]))[0])
    plain = float(solver_residuals(solver)[closure])
    weights[closure] = 1.0
    solver.set_weights(weights)
    with_edge = converge_exact(solver, 100)[0][-1]
    assert innovation < plain  # the map's own uncertainty widens the test
    np.testing.assert_allclose(with_edge - without, innovation, rtol=0.05)


def test_deletion_is_what_removing_the_edge_saves(world):
    """The deletion χ² of an edge in the map equals the fall of the optimal χ² when it is
    taken out (to first order, with small residuals), and exceeds its own residual: the
    map bent to fit it."""
    graph, _ = world
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    closure = int(np.flatnonzero(~trusted)[3])
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    with_edge = converge_exact(solver, 100)[0][-1]
    deletion = float(deletion_chi2(solver, np.array([closure]))[0])
    plain = float(solver_residuals(solver)[closure])
    weights = np.ones(graph.num_edges)
    weights[closure] = 0.0
    solver.set_weights(weights)
    without = converge_exact(solver, 100)[0][-1]
    assert deletion > plain
    np.testing.assert_allclose(with_edge - without, deletion, rtol=0.05)


def test_joint_deletion_is_what_removing_the_group_saves(world):
    """The joint deletion χ² of two closures equals the fall of the optimal χ² when both
    are taken out (to first order), and a single-edge group is the edge's own."""
    graph, _ = world
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    pair = np.flatnonzero(~trusted)[[3, 4]]
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    with_edges = converge_exact(solver, 100)[0][-1]
    joint, alone = group_chi2(solver, [pair, pair[:1]], sign=-1.0)
    np.testing.assert_allclose(alone, deletion_chi2(solver, pair[:1])[0], rtol=1e-9)
    weights = np.ones(graph.num_edges)
    weights[pair] = 0.0
    solver.set_weights(weights)
    without = converge_exact(solver, 100)[0][-1]
    np.testing.assert_allclose(with_edges - without, joint, rtol=0.05)


def test_groups_scored_at_one_state_are_scored_once(world, monkeypatch):
    """A group scored again at the same map, edges and weights is not recomputed; after a
    change of weights or of the map it is, and equals a fresh scoring."""
    from h2o_slam.core import robust

    graph, _ = world
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    pair = np.flatnonzero(~trusted)[[3, 4]]
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    converge_exact(solver, 100)
    calls = []
    scored = robust._group_chi2
    monkeypatch.setattr(robust, "_group_chi2", lambda groups, *a: calls.append(len(groups))
                        or scored(groups, *a))
    first = group_chi2(solver, [pair, pair[:1]], sign=-1.0)
    again = group_chi2(solver, [pair[::-1], pair[1:], pair[:1]], sign=-1.0)
    assert calls == [2, 1]  # only the new single
    np.testing.assert_array_equal(again[[0, 2]], first)
    weights = np.ones(graph.num_edges)
    weights[pair[1]] = 0.0
    solver.set_weights(weights)
    after = group_chi2(solver, [pair[:1]], sign=-1.0)
    assert calls == [2, 1, 1]
    np.testing.assert_allclose(after, scored([pair[:1]], solver, 128, -1.0), rtol=1e-12)
    assert not np.isclose(after[0], first[1])
    solver.tree.t[5] += 0.1
    group_chi2(solver, [pair[:1]], sign=-1.0)
    assert calls == [2, 1, 1, 1]


@pytest.fixture(scope="module")
def solved_world(world):
    """The small world's solver at its optimum, and its loop closures."""
    graph, _ = world
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    converge_exact(solver, 100)
    return solver, np.flatnonzero(~odometry_edges(graph.kind, graph.a, graph.b))


@given(picks=st.lists(st.lists(st.integers(0, 39), min_size=1, max_size=4), min_size=1,
                      max_size=12),
       chunk=st.integers(1, 9), sign=st.sampled_from([1.0, -1.0]))
def test_groups_scored_together_equal_each_scored_alone(solved_world, picks, chunk, sign):
    """Groups that share closures are solved from their closures' shared columns of H⁻¹,
    packed into batches of ``chunk`` edges: each group's χ² is the one it has alone."""
    from h2o_slam.core import robust

    solver, closures = solved_world
    groups = [closures[np.unique(p)] for p in picks]
    together = robust._group_chi2(groups, solver, chunk, sign)
    alone = [robust._group_chi2([g], solver, 128, sign)[0] for g in groups]
    np.testing.assert_allclose(together, alone, rtol=1e-9, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(picks=st.lists(st.lists(st.integers(0, 39), min_size=1, max_size=6), min_size=1,
                      max_size=8),
       sign=st.sampled_from([1.0, -1.0]))
def test_the_three_ways_of_scoring_a_group_agree(solved_world, picks, sign):
    """A group's χ² from columns of H⁻¹, from the selected inverse at its ends' pairs, and
    by one solve with the group left out (put in, for the innovation) are one number."""
    from h2o_slam.core import robust

    solver, closures = solved_world
    groups = [closures[np.unique(p)] for p in picks]
    edges, member = np.unique(np.concatenate(groups), return_inverse=True)
    members = np.split(member.ravel(), np.cumsum([len(g) for g in groups])[:-1])
    r, J, var, H = robust._whitened(solver, edges)
    columns = robust._columns_chi2(r, J, var, members, H, 128, sign)
    selected = robust._selected_chi2(r, J, var, members, H, sign)
    left_out = robust._left_out_chi2(H, r, J, var, members, sign)
    np.testing.assert_allclose(selected, columns, rtol=1e-7)
    np.testing.assert_allclose(left_out, columns, rtol=1e-7)


def test_many_closures_are_scored_from_the_selected_inverse(solved_world, monkeypatch):
    """Many closures are scored from the selected inverse, a few from columns of H⁻¹, and
    from columns where the selected inverse is not affordable (tried once per graph)."""
    from h2o_slam.core import robust, selinv

    solver, closures = solved_world
    paths = []

    def spy(name):
        scored = getattr(robust, name)
        return lambda *a: paths.append(name) or scored(*a)

    for name in ("_selected_chi2", "_columns_chi2"):
        monkeypatch.setattr(robust, name, spy(name))
    many = [closures[[i]] for i in range(robust.SELECTED_FROM * 4)]
    first = robust._group_chi2(many, solver, 128, -1.0)
    robust._group_chi2(many[:2], solver, 128, -1.0)
    assert paths == ["_selected_chi2", "_columns_chi2"]
    monkeypatch.setattr(selinv, "MAX_WORK", 0)
    paths.clear()
    np.testing.assert_allclose(robust._group_chi2(many, solver, 128, -1.0), first, rtol=1e-7)
    robust._group_chi2(many, solver, 128, -1.0)  # known unaffordable: not tried again
    assert paths == ["_selected_chi2", "_columns_chi2", "_columns_chi2"]


@given(ends=st.lists(st.tuples(st.integers(0, 80), st.integers(0, 80), st.floats(0, 1)),
                     max_size=60))
def test_places_are_the_components_of_closures_near_at_both_ends(ends):
    """The clusters found along the closures' order are the connected components of every
    pair whose ends are both within ``CLUSTER_SPAN``, in the same order."""
    from scipy.sparse.csgraph import connected_components

    from h2o_slam.core import robust

    a, b, ratio = (np.array([e[i] for e in ends]) for i in range(3))
    a, b = a.astype(np.int64), b.astype(np.int64)
    near = (np.abs(a[:, None] - a[None, :]) <= CLUSTER_SPAN) & (
        np.abs(b[:, None] - b[None, :]) <= CLUSTER_SPAN)
    _, label = connected_components(near.astype(float), directed=False)
    want = [np.flatnonzero(label == g) for g in range(label.max(initial=-1) + 1)]
    want.sort(key=lambda g: float(np.min(ratio[g])))
    got = robust._clusters(a, b, ratio)
    assert [g.tolist() for g in got] == [g.tolist() for g in want]


def test_false_closures_that_hold_a_stretch_together_are_dropped_together():
    """Two consistent false closures accepted together on a weakly tied walk (few closures,
    noisy odometry): each one's deletion χ² is small (the other holds the bent stretch), so
    only the place's joint drop finds the lower cost."""
    graph = manhattan(400, seed=4, loop_probability=0.05, sigma_xy_m=0.2,
                      sigma_yaw_rad=0.05).graph
    optimum = solve_exact(graph)
    planted = plant_outliers(graph, "random_grouped", 2, seed=1, group_size=2, span_m=3.0)
    trusted = odometry_edges(planted.graph.kind, planted.graph.a, planted.graph.b)
    solver, _ = build_solver(planted.graph, init="tree", regularizer=False)
    converge_exact(solver, 100)  # least squares over every edge: bent to fit the pair
    weights = np.ones(planted.graph.num_edges)
    outcome = converge_robust(solver, 100, trusted, RobustConfig(), weights=weights)
    assert np.all(outcome.weights[planted.outlier] == 0.0)
    assert np.all(outcome.weights[~planted.outlier] == 1.0)
    np.testing.assert_allclose(solver.world_poses()[1], optimum.t, atol=1e-4)


def test_a_consistent_group_the_map_bends_to_fit_is_refused_as_incompatible():
    """Groups of 10 consistent false closures on a weakly tied walk: accepting some costs
    the TLS objective less than leaving them out, so only the joint compatibility test
    (the place's joint innovation beyond its χ² quantile) turns them away."""
    graph = manhattan(300, seed=4, loop_probability=0.05, sigma_xy_m=0.2,
                      sigma_yaw_rad=0.02).graph
    optimum = solve_exact(graph)
    planted = plant_outliers(graph, "local_grouped", 20, seed=1, group_size=10, span_m=1.0)
    result = solve_exact(planted.graph, robust=RobustConfig())
    assert result.weights is not None
    assert not np.any(result.weights[planted.outlier] > 0.5)
    assert np.all(result.weights[~planted.outlier] == 1.0)
    np.testing.assert_allclose(result.t, optimum.t, atol=1e-4)


def _with_false_group(graph: PoseGraph, optimum, closure: int, offset_m: float = 1.0
                      ) -> PoseGraph:
    """``graph`` and ten false closures at the place of ``closure`` (ends 5 poses either
    side of its ends), each the true relative pose of its ends moved ``offset_m`` along x:
    mutually consistent, so they hold a bent stretch together."""
    a = np.arange(graph.a[closure] - 5, graph.a[closure] + 5)
    b = np.arange(graph.b[closure] - 5, graph.b[closure] + 5)
    meas_R, meas_t = geo.between(optimum.R[a], optimum.t[a], optimum.R[b], optimum.t[b])
    meas_t = meas_t + np.array([offset_m, 0.0, 0.0])
    info = np.repeat(graph.info[closure:closure + 1], len(a), axis=0)
    return graph.with_edges(EdgeKind.RELATIVE, a, b, meas_R, meas_t, info)


def test_true_closures_of_a_dropped_place_that_fit_the_map_come_back():
    """A consistent false group accepted beside true closures of the same revisit: the
    joint compatibility test drops the whole place, and the true closures, which fit the
    map built without it, come back (they stayed out before: 1-8 true closures out, the map
    4-10 cm off the optimum)."""
    graph = manhattan(300, seed=4, loop_probability=0.3).graph
    optimum = solve_exact(graph)
    closures = np.flatnonzero(~odometry_edges(graph.kind, graph.a, graph.b))
    for closure in closures[5::15]:
        if not 5 <= graph.a[closure] < graph.b[closure] < graph.num_nodes - 5:
            continue
        planted = _with_false_group(graph, optimum, int(closure))
        trusted = odometry_edges(planted.kind, planted.a, planted.b)
        solver, _ = build_solver(planted, init="tree", regularizer=False, trusted=trusted)
        # Carried decisions that took every closure in: the place is accepted whole.
        outcome = converge_robust(solver, 100, trusted, RobustConfig(),
                                  weights=np.ones(planted.num_edges))
        assert np.all(outcome.weights[graph.num_edges:] == 0.0)
        assert np.all(outcome.weights[:graph.num_edges] == 1.0), closure
        np.testing.assert_allclose(solver.world_poses()[1], optimum.t, atol=1e-6)


def test_a_3d_map_caught_in_a_local_minimum_restarts_from_the_chordal_start():
    """A noisy 3-D grid with 100 false closures against ~100 true: from the odometry the
    graduation ends with true closures dropped on a wrongly folded map; re-admissions from
    the chordal initialization of the decisions (the 3-D sibling of LAGO) reach the
    outlier-free map."""
    from h2o_slam.io.synthetic import grid3d

    graph = grid3d(125, seed=4, sigma_rot_rad=0.1, sigma_xyz_m=0.1).graph
    optimum = solve_exact(graph)
    planted = plant_outliers(graph, "random", 100, seed=1)
    result = solve_exact(planted.graph, robust=RobustConfig())
    assert result.weights is not None
    assert not np.any(result.weights[planted.outlier] > 0.5)
    assert np.all(result.weights[~planted.outlier] == 1.0)
    np.testing.assert_allclose(result.t, optimum.t, atol=1e-4)


def _with_information(graph: PoseGraph, info: np.ndarray) -> PoseGraph:
    return make_graph(graph.planar, graph.ids, graph.R, graph.t, graph.kind, graph.a, graph.b,
                      graph.meas_R, graph.meas_t, info)


def _tight_walk(seed: int = 0, gps_every: int = 0, poses: int = 400) -> PoseGraph:
    """A walk whose measurements are 100 times more precise (σ) than ``_loose``'s."""
    return manhattan(poses, seed=seed, sigma_xy_m=0.01, sigma_yaw_rad=0.002,
                     gps_every=gps_every).graph


@given(st.integers(0, 2**32 - 1), st.integers(TAIL_MIN_CLOSURES, 2000),
       st.floats(1e-6, 1e6), st.floats(1.0, 100.0))
def test_the_tail_cap_only_tightens_loop_closures_to_the_factor_times_their_quantile(
        seed, accepted, scale, factor):
    rng = np.random.default_rng(seed)
    m = accepted + 40
    closures = np.ones(m, dtype=bool)
    closures[-20:] = False  # GPS fixes, say
    taken = closures.copy()
    taken[accepted:-20] = False  # closures that were dropped
    r2 = scale * rng.chisquare(3, m)
    r2[accepted:-20] *= 1e6  # dropped for a reason: they do not set the cap
    c2 = scale * rng.uniform(1.0, 50.0, m)
    tight = tail_thresholds(r2, closures, taken, c2, factor)
    cap = factor * np.quantile(r2[taken], 0.99)
    np.testing.assert_allclose(tight[closures], np.minimum(c2[closures], cap), rtol=1e-12)
    np.testing.assert_array_equal(tight[~closures], c2[~closures])
    assert np.all(tight <= c2)


def test_the_tail_cap_needs_enough_accepted_closures_and_ignores_infinity():
    rng = np.random.default_rng(0)
    r2, c2 = rng.chisquare(3, 600), np.full(600, 1e3)
    closures = np.ones(600, dtype=bool)
    few = np.arange(600) < TAIL_MIN_CLOSURES - 1
    np.testing.assert_array_equal(tail_thresholds(r2, closures, few, c2, 30.0), c2)
    np.testing.assert_array_equal(tail_thresholds(r2, closures, closures, c2, np.inf), c2)
    assert np.all(tail_thresholds(r2, closures, closures, c2, 30.0) < c2)


def _loose(graph: PoseGraph) -> PoseGraph:
    """The walk with every edge's information the identity (σ 1 m and 1 rad), as
    parking-garage states it while its edges fit to centimetres."""
    return _with_information(graph, np.broadcast_to(np.eye(6), graph.info.shape).copy())


@pytest.mark.parametrize("factor", [1e-4, 0.5, 30.0])
def test_the_closure_noise_scale_follows_the_closures_stated_information(factor):
    graph = _tight_walk()
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    info = graph.info.copy()
    info[~trusted] *= factor
    scaled = closure_noise_scale(_with_information(graph, info), trusted)
    assert scaled == pytest.approx(factor * closure_noise_scale(graph, trusted), rel=1e-9)


def test_the_closure_noise_scale_tells_stated_noise_from_loose_noise():
    """Information that matches the noise gives a scale of order 1 (above it: the dead
    reckoning between a pair's ends adds its own noise); the identity on centimetre
    measurements, of order 1e-4."""
    graph = _tight_walk()
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    assert 0.5 < closure_noise_scale(graph, trusted) < 10.0
    assert closure_noise_scale(_loose(graph), trusted) < 1e-3


def test_only_loop_closure_thresholds_tighten_and_never_loosen():
    graph = _loose(_tight_walk(gps_every=10))
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    config = RobustConfig()
    plain = thresholds(graph.kind, graph.planar, config.inlier_probability)
    c2 = edge_thresholds(graph, trusted, config)
    closures = graph.kind == EdgeKind.RELATIVE
    scale = config.noise_margin * closure_noise_scale(graph, trusted)
    np.testing.assert_allclose(c2[closures], scale * plain[closures])
    np.testing.assert_array_equal(c2[~closures], plain[~closures])
    assert np.any(~closures)
    matched = _tight_walk()
    np.testing.assert_array_equal(
        edge_thresholds(matched, odometry_edges(matched.kind, matched.a, matched.b), config),
        thresholds(matched.kind, matched.planar, config.inlier_probability))


@pytest.mark.parametrize("kind", ["random", "local", "random_grouped"])
def test_loose_information_does_not_let_false_closures_bend_the_map(kind):
    """With σ 1 m stated on centimetre edges, bending the map onto a false closure costs
    less than the unscaled ``c̄²`` (the control: 9-10 of 10 accepted); with the thresholds
    scaled by the closures' noise every false closure is out and every true one in."""
    graph = _loose(_tight_walk())
    optimum = solve_exact(graph)
    planted = plant_outliers(graph, kind, 10, seed=0)
    unscaled = solve_exact(planted.graph,
                           robust=RobustConfig(noise_margin=1e12, tail_factor=np.inf))
    assert unscaled.weights is not None
    assert np.count_nonzero(unscaled.weights[planted.outlier] > 0.5) >= 5
    _assert_outlier_free(solve_exact(planted.graph, robust=RobustConfig()), planted, optimum)


def test_the_closures_tail_turns_away_false_closures_the_median_scale_lets_in():
    """Local grouped false closures on a loosely stated walk: by the median-scaled thresholds
    alone (the control) some stay in, since the margin those leave for heavy-tailed real
    noise is a hundred times the variance; the accepted closures' tail (565 of them, all
    light-tailed) caps the thresholds and turns every false one away."""
    graph = _loose(_tight_walk(poses=1500))
    optimum = solve_exact(graph)
    planted = plant_outliers(graph, "local_grouped", 50, seed=0)
    median_only = solve_exact(planted.graph, robust=RobustConfig(tail_factor=np.inf))
    assert median_only.weights is not None
    assert np.any(median_only.weights[planted.outlier] > 0.5)
    _assert_outlier_free(solve_exact(planted.graph, robust=RobustConfig()), planted, optimum)


def _assert_outlier_free(result, planted, optimum) -> None:
    assert result.weights is not None
    assert not np.any(result.weights[planted.outlier] > 0.5)
    assert np.all(result.weights[~planted.outlier] == 1.0)
    np.testing.assert_allclose(result.t, optimum.t, atol=1e-6)


def _bent(solver, seed: int = 0) -> float:
    """Moves the solver's poses metres off; returns its χ² there."""
    R, t = solver.world_poses()
    solver.tree.set_world_poses(R, t + np.random.default_rng(seed).normal(0.0, 3.0, t.shape))
    return float(converge_exact(solver, 0)[0][0])


def test_an_unconverged_robust_solve_is_solved_again_from_its_start():
    graph = manhattan(200, seed=1).graph
    optimum = solve_exact(graph)
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    start = (solver.tree.R.copy(), solver.tree.t.copy())
    outcome = RobustOutcome(np.ones(graph.num_edges), [_bent(solver)], 0, False)
    _polish(solver, outcome, start, 100)
    assert outcome.converged and len(outcome.history) > 1
    np.testing.assert_allclose(solver.world_poses()[1], optimum.t, atol=1e-6)


def test_a_polish_that_ends_higher_leaves_the_map_as_it_was():
    graph = manhattan(200, seed=1).graph
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    history, _ = converge_exact(solver, 100)
    there = solver.world_poses()[1].copy()
    worse = solver.tree.R.copy(), solver.tree.t.copy()
    _bent(solver)
    start = (solver.tree.R.copy(), solver.tree.t.copy())
    solver.tree.R[:], solver.tree.t[:] = worse
    outcome = RobustOutcome(np.ones(graph.num_edges), history[-1:], 0, False)
    _polish(solver, outcome, start, 1)  # one iteration from metres off: higher
    assert not outcome.converged and outcome.history == history[-1:]
    np.testing.assert_array_equal(solver.world_poses()[1], there)


def _local_minimum(graph: PoseGraph, seed: int = 0) -> tuple[object, float]:
    """A solver converged by Gauss–Newton from headings drawn at random: a local minimum
    thousands of times the optimum's χ²; returns it and that χ²."""
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    R, t = solver.world_poses()
    rng = np.random.default_rng(seed)
    turn = geo.yaw_to_matrix(rng.uniform(-np.pi, np.pi, len(R)))
    solver.tree.set_world_poses(turn @ R, t + rng.normal(0.0, 5.0, t.shape))
    history, converged = converge_exact(solver, 200)
    assert converged
    return solver, history[-1]


def test_a_converged_answer_in_a_worse_basin_is_solved_again_from_lago():
    graph = manhattan(200, seed=1).graph
    optimum = solve_exact(graph)
    best = chi2(graph, optimum.R, optimum.t)
    solver, stuck = _local_minimum(graph)
    assert stuck > 100 * best
    outcome = RobustOutcome(np.ones(graph.num_edges), [stuck], 0, True)
    restarted_if_lower(solver, outcome, lago_restart(graph), 100)
    assert outcome.converged and outcome.history[-1] <= best * (1 + 1e-9)
    np.testing.assert_allclose(solver.world_poses()[1], optimum.t, atol=1e-6)


def test_a_restart_that_ends_higher_leaves_the_map_as_it_was():
    graph = manhattan(200, seed=1).graph
    solver, _ = build_solver(graph, init="tree", regularizer=False)
    history, _ = converge_exact(solver, 100)
    there = solver.world_poses()[1].copy()
    stuck, _ = _local_minimum(graph)
    far = stuck.world_poses()

    def restart(weights):
        return far

    outcome = RobustOutcome(np.ones(graph.num_edges), history[-1:], 0, True)
    restarted_if_lower(solver, outcome, restart, 100)
    assert outcome.history == history[-1:]
    np.testing.assert_array_equal(solver.world_poses()[1], there)


def test_the_closure_noise_scale_ignores_closures_whose_error_overflows():
    """Closures at 1e200 m with correlated x-y information: their χ² is inf - inf (NaN),
    which would make the median NaN."""
    graph = _tight_walk()
    trusted = odometry_edges(graph.kind, graph.a, graph.b)
    info = graph.info.copy()
    info[:, 0, 1] = info[:, 1, 0] = 0.5 * np.sqrt(info[:, 0, 0] * info[:, 1, 1])
    meas_t = graph.meas_t.copy()
    meas_t[np.flatnonzero(~trusted)[::7]] = [1e200, -1e200, 0.0]
    extreme = make_graph(graph.planar, graph.ids, graph.R, graph.t, graph.kind, graph.a,
                         graph.b, graph.meas_R, meas_t, info)
    with np.errstate(over="ignore", invalid="ignore"):
        scale = closure_noise_scale(extreme, trusted)
    assert np.isfinite(scale) and 0.5 < scale < 10.0


def _graduations(monkeypatch) -> list[int]:
    """Counts the graduations afresh that the robust solve runs."""
    import h2o_slam.core.robust as robust

    calls: list[int] = []
    graduate = robust._graduate

    def counted(*args, **kwargs):
        calls.append(1)
        return graduate(*args, **kwargs)

    monkeypatch.setattr(robust, "_graduate", counted)
    return calls


@pytest.mark.parametrize("regraduate", [False, True])
def test_an_explicit_solve_also_graduates_afresh_and_keeps_the_lower_cost(
        world, monkeypatch, regraduate):
    """Carried decisions that raise no doubt are kept as they are, unless the solve is asked
    to graduate afresh too (an explicit exact solve): then it graduates and ends on the
    answer of lowest TLS cost, here the outlier-free map either way."""
    graph, optimum = world
    planted = plant_outliers(graph, "random", 10, seed=2)
    g = planted.graph
    trusted = odometry_edges(g.kind, g.a, g.b)
    solver, _ = build_solver(g, init="tree", regularizer=False, trusted=trusted)
    weights = np.where(planted.outlier, 0.0, 1.0)  # the right decisions, carried on
    calls = _graduations(monkeypatch)
    outcome = converge_robust(solver, 100, trusted, RobustConfig(), weights=weights,
                              regraduate=regraduate)
    assert (len(calls) > 0) == regraduate
    assert np.all(outcome.weights[planted.outlier] == 0.0)
    assert np.all(outcome.weights[~planted.outlier] == 1.0)
    np.testing.assert_allclose(solver.world_poses()[1], optimum.t, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(side=st.integers(1, 120), rank_cut=st.integers(0, 3), seed=st.integers(0, 2**31),
       count=st.integers(1, 3))
def test_quadratic_forms_equal_the_pseudo_inverse(side, rank_cut, seed, count):
    """``rᵀ S⁺ r`` by Cholesky equals the pseudo-inverse's, and a singular ``S`` (an edge
    the map cannot do without), alone or in a stack, falls back to the pseudo-inverse."""
    from h2o_slam.core.robust import _quadratic_forms

    rng = np.random.default_rng(seed)
    rank = max(side - rank_cut, 1)
    A = rng.standard_normal((count, side, rank))
    S = A @ A.transpose(0, 2, 1) / side
    r = np.einsum("kij,kj->ki", A, rng.standard_normal((count, rank)))  # in S's range
    want = np.einsum("ki,kij,kj->k", r, np.linalg.pinv(S, hermitian=True), r)
    np.testing.assert_allclose(_quadratic_forms(S, r), want, rtol=1e-6)


def test_a_large_place_is_scored_as_the_pseudo_inverse_scores_it(solved_world, monkeypatch):
    """A place of many closures is scored by Cholesky, as the pseudo-inverse scores it."""
    from h2o_slam.core import robust

    solver, closures = solved_world
    place = closures[: 64 // solver.p + 2]
    pinv, used = np.linalg.pinv, []
    monkeypatch.setattr(np.linalg, "pinv", lambda S, **kw: used.append(S.shape) or pinv(S, **kw))
    fast = robust._group_chi2([place], solver, 128, -1.0)
    assert not used  # factored by Cholesky
    monkeypatch.undo()

    def no_factor(S):
        raise np.linalg.LinAlgError("forced: the pseudo-inverse scores it")

    monkeypatch.setattr(np.linalg, "cholesky", no_factor)
    slow = robust._group_chi2([place], solver, 128, -1.0)
    np.testing.assert_allclose(fast, slow, rtol=1e-8)


@pytest.mark.parametrize("false_closures", [0, 1])
def test_drop_candidates_their_neighbourhood_clears_are_not_scored(world, monkeypatch,
                                                                   false_closures):
    """Of the drop candidates, those whose neighbourhood bounds their deletion χ² below the
    bar are not scored on the whole graph, and the candidates kept are those scoring every
    one keeps: none without outliers, the false closure among them with one."""
    from h2o_slam.core import robust

    graph, _ = world
    planted = plant_outliers(graph, "random", false_closures, seed=2)
    trusted = odometry_edges(planted.graph.kind, planted.graph.a, planted.graph.b)
    solver, _ = build_solver(planted.graph, init="tree", regularizer=False, trusted=trusted)
    converge_exact(solver, 100)  # least squares: a false closure is in, bending the map
    inside = np.flatnonzero(~trusted)
    c2 = edge_thresholds(planted.graph, trusted, RobustConfig())
    order = np.argsort(-solver_residuals(solver)[inside] / c2[inside])
    candidates = [order[[i]] for i in range(12)] + [order[[3, 7]]]
    scored = []
    real = robust.group_chi2
    monkeypatch.setattr(robust, "group_chi2", lambda s, groups, **kw: scored.extend(
        groups) or real(s, groups, **kw))
    kept = [g.tolist() for g in robust._significant_drops(solver, inside, c2, candidates)]
    bar = robust.SIGNIFICANT * np.array([c2[inside[g]].sum() for g in candidates])
    every = real(solver, [inside[g] for g in candidates], sign=-1.0) > bar
    assert kept == [g.tolist() for g, k in zip(candidates, every, strict=True) if k]
    if false_closures:
        assert [int(np.flatnonzero(inside == np.flatnonzero(planted.outlier)[0])[0])] in kept
    else:
        assert not kept and len(scored) < len(candidates)
