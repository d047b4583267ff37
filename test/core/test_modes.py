"""Offline, online and exact modes over whole graphs."""

from __future__ import annotations

import time

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from graphs import random_graph

from h2o_slam.core.exact import ExactSystem
from h2o_slam.core.graph import EARTH, EdgeKind, chi2, make_graph
from h2o_slam.core.modes import (
    arrivals,
    build_solver,
    solve_exact,
    solve_offline,
    solve_online,
    tree_estimate,
)
from h2o_slam.io.synthetic import grid3d, manhattan


@pytest.fixture(scope="module")
def city():
    return manhattan(150, seed=7).graph


@pytest.fixture(scope="module")
def cube():
    return grid3d(60, seed=3).graph


def _predicted_decrease(graph, R, t):
    """χ² decrease one more Gauss–Newton step would predict: gᵀ H⁻¹ g."""
    solver, _ = build_solver(graph.with_estimate(R, t), init="input")
    H, g, _ = ExactSystem(solver).normal_equations()
    return float(g @ spla.spsolve(H, g))


@pytest.mark.parametrize("name", ["city", "cube"])
def test_exact_mode_reaches_a_stationary_point(name, request):
    graph = request.getfixturevalue(name)
    result = solve_exact(graph, iterations=30)
    assert result.chi2_final < 0.5 * result.chi2_initial
    assert _predicted_decrease(graph, result.R, result.t) < 1e-9 * result.chi2_final
    history = result.chi2_per_pass
    assert all(b <= a * (1 + 1e-12) for a, b in zip(history, history[1:], strict=False))


@pytest.mark.parametrize("name", ["city", "cube"])
def test_offline_passes_approach_the_exact_optimum(name, request):
    graph = request.getfixturevalue(name)
    optimum = solve_exact(graph, iterations=30).chi2_final
    result = solve_offline(graph, passes=10)
    assert result.chi2_per_pass[-1] < result.chi2_initial
    assert result.chi2_per_pass[-1] < 1.5 * optimum


def test_online_mode_times_every_pose_and_ends_near_the_optimum(city):
    optimum = solve_exact(city, iterations=30).chi2_final
    result = solve_online(city, passes=5)
    assert len(result.per_callback_ms) == city.num_nodes
    assert len(result.chi2_per_pass) == 6
    # The thesis' passes settle at a fixed point of their own (here 1.4 times the optimum,
    # above the 1.06 the stream's loop solves left): the run ends on the best map it saw.
    assert result.chi2_final < 4.0 * optimum
    assert chi2(city, result.R, result.t) == pytest.approx(min(result.chi2_per_pass),
                                                           rel=1e-9)


def test_arrivals_group_edges_by_their_newest_pose(city):
    groups = arrivals(city)
    assert sum(len(g) for g in groups) == city.num_edges
    for k, edges in enumerate(groups):
        for e in edges:
            assert max(city.a[e], city.b[e]) == k
        if len(edges) and k > 0:
            first = edges[0]
            assert min(city.a[first], city.b[first]) == k - 1  # odometry first


def test_tree_start_zeroes_every_tree_edge():
    graph = random_graph(1, True, n=12, loops=6)
    solver, start = build_solver(graph, init="tree")
    parent = solver.tree.parent[: solver.num_nodes]
    R, t = tree_estimate(graph, parent)
    assert np.allclose(R, start.R) and np.allclose(t, start.t)
    tree_edges = [e for e in range(graph.num_edges)
                  if parent[graph.b[e]] == graph.a[e] or parent[graph.a[e]] == graph.b[e]]
    zero_child = {}
    for e in tree_edges:
        child = int(graph.b[e]) if parent[graph.b[e]] == graph.a[e] else int(graph.a[e])
        zero = np.allclose(solver.linearize(e).r, 0.0, atol=1e-9)
        zero_child[child] = zero_child.get(child, False) or zero
    # Every non-top node has a tree edge of zero error (a parallel edge may disagree).
    assert len(zero_child) == graph.num_nodes - 1 and all(zero_child.values())


def test_gps_graph_is_anchored_in_the_world_frame():
    synth = manhattan(120, seed=5, gps_every=10, gps_sigma_m=0.5)
    graph = synth.graph
    # Move the whole start 50 m away: only GPS can bring it back.
    shifted = graph.with_estimate(graph.R, graph.t + np.array([50.0, -20.0, 0.0]))
    result = solve_exact(shifted, iterations=30, init="input")
    err = np.linalg.norm(result.t - synth.truth_t, axis=1)
    assert np.median(err) < 2.0
    offline = solve_offline(shifted, passes=10, init="input")
    assert offline.chi2_final < 0.01 * offline.chi2_initial


def _near_singular(graph):
    info = graph.info.copy()
    # CSAIL-like: x and y almost perfectly correlated, and one slightly indefinite matrix.
    info[::3, 0, 1] = info[::3, 1, 0] = 0.9999999 * np.sqrt(info[::3, 0, 0] * info[::3, 1, 1])
    info[1, 0, 1] = info[1, 1, 0] = 1.000001 * np.sqrt(info[1, 0, 0] * info[1, 1, 1])
    return make_graph(graph.planar, graph.ids, graph.R, graph.t, graph.kind, graph.a, graph.b,
                      graph.meas_R, graph.meas_t, info)


@pytest.mark.parametrize("solve", [solve_exact, solve_offline, solve_online])
def test_near_singular_information_never_gives_nan(city, solve):
    graph = _near_singular(city)
    assert len(graph.clamped_edges) >= 1
    result = solve(graph)
    assert np.all(np.isfinite(result.R)) and np.all(np.isfinite(result.t))
    assert np.isfinite(result.chi2_final)
    assert result.chi2_final <= result.chi2_initial


def test_disconnected_components_each_keep_their_gauge():
    graph = random_graph(6, True, n=10, loops=0)
    keep = ~((graph.a == 4) & (graph.b == 5))
    split = make_graph(True, graph.ids, graph.R, graph.t, graph.kind[keep], graph.a[keep],
                       graph.b[keep], graph.meas_R[keep], graph.meas_t[keep], graph.info[keep])
    solver, _ = build_solver(split)
    assert np.sum(solver.tree.parent[: solver.num_nodes] == EARTH) == 2
    result = solve_exact(split)
    assert result.chi2_final < 1e-12 * max(result.chi2_initial, 1.0) + 1e-9
    assert chi2(split, result.R, result.t) == pytest.approx(result.chi2_final)
    assert np.all(split.kind == EdgeKind.RELATIVE)


def test_paced_arrivals_run_idle_steps_between_and_take_the_stream_time():
    graph = manhattan(40, seed=3).graph
    period_s, budget_s = 0.004, 0.001
    start = time.perf_counter()
    result = solve_online(graph, budget_s=budget_s, period_s=period_s)
    took = time.perf_counter() - start
    assert len(result.per_callback_ms) == graph.num_nodes
    # Pose k arrives k periods after the first: the stream cannot end sooner.
    assert took >= (graph.num_nodes - 1) * period_s
    # A gap of four budgets holds an idle step even after a callback that used its budget.
    assert result.idle_steps_between >= (graph.num_nodes - 1) // 2
    assert solve_online(graph, budget_s=budget_s).idle_steps_between == 0


@pytest.mark.parametrize("mode", ["online", "offline"])
def test_passes_that_make_the_map_worse_are_not_kept(mode: str,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The thesis' passes can settle at a fixed point worse than the map they were given
    (an online run at the optimum, 7.7 times it after 10 passes on a KITTI graph): the run
    ends on the best map it saw. Here every pass shakes the map, so the answer is the map
    before the passes."""
    from h2o_slam.core import modes

    graph = manhattan(120, seed=3).graph
    rng = np.random.default_rng(0)
    real_pass = modes.offline_pass
    shakes = iter(range(1, 100))

    def shaking_pass(solver, order, d_max=None):  # type: ignore[no-untyped-def]
        real_pass(solver, order, d_max)
        R, t = solver.world_poses()  # each pass shakes harder: the last is the worst
        solver.tree.set_world_poses(R, t + rng.normal(0.0, 0.5 * next(shakes), t.shape))

    before = (modes.solve_online(graph, passes=0) if mode == "online"
              else modes.solve_offline(graph, passes=1))
    monkeypatch.setattr(modes, "offline_pass", shaking_pass)
    after = (modes.solve_online(graph, passes=5) if mode == "online"
             else modes.solve_offline(graph, passes=5))
    assert min(after.chi2_per_pass[1:]) > chi2(graph, before.R, before.t)
    assert chi2(graph, after.R, after.t) <= min(after.chi2_per_pass) * (1 + 1e-9)
