"""TORO baseline (h2o_slam.baselines.toro), planar and 3-D: monotone χ² on a small loop at its own
learning rate, near the exact optimum on synthetic graphs, its tree parameterization and its
error paths."""

from __future__ import annotations

import numpy as np
import pytest

from h2o_slam.baselines.toro import ToroProblem, ToroProblem3, solve_toro
from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EARTH, PoseGraph, chi2, make_graph
from h2o_slam.core.modes import build_solver, solve_exact
from h2o_slam.io.synthetic import grid3d, manhattan


def small_loop(n: int = 24, seed: int = 0, sigma_xy_m: float = 0.05,
               sigma_yaw_rad: float = 0.02, planar: bool = True) -> PoseGraph:
    """Poses on a circle of radius 4 m, odometry ``(i, i+1)`` and one closure ``(n-1, 0)``,
    measurements noisy, information the inverse of the noise covariance."""
    rng = np.random.default_rng(seed)
    yaw = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    R = geo.yaw_to_matrix(yaw + np.pi / 2)
    t = np.zeros((n, 3))
    t[:, 0], t[:, 1] = 4 * np.cos(yaw), 4 * np.sin(yaw)
    pairs = [(i, i + 1) for i in range(n - 1)] + [(n - 1, 0)]
    info = np.zeros((len(pairs), 6, 6))
    info[:, 0, 0] = info[:, 1, 1] = 1 / sigma_xy_m**2
    info[:, 5, 5] = 1 / sigma_yaw_rad**2
    info[:, 2, 2] = info[:, 3, 3] = info[:, 4, 4] = 1.0
    mR, mt = [], []
    for i, j in pairs:
        Rk, tk = geo.between(R[i], t[i], R[j], t[j])
        tk = tk + np.array([*rng.normal(scale=sigma_xy_m, size=2), 0.0])
        Rk = Rk @ geo.yaw_to_matrix(rng.normal(scale=sigma_yaw_rad))
        mR.append(Rk)
        mt.append(tk)
    a, b = np.array(pairs).T
    return make_graph(planar, np.arange(n), R, t, np.zeros(len(pairs), np.int8), a, b,
                      np.array(mR), np.array(mt), info)


@pytest.mark.parametrize("planar", [True, False])
@pytest.mark.parametrize("seed", range(4))
def test_small_loop_chi2_falls_monotonically(seed: int, planar: bool) -> None:
    """At TORO's own learning rate (1/γi, steps clipped to the residual) χ² falls every
    iteration. TORO's fixed point is not the least-squares optimum (it decouples rotation
    from translation), so once there χ² may creep up by a few 1e-4 of itself (seed 2: 2e-4
    after 37 iterations); a rise of 1e-3 fails. Measured: a constant rate 1/γ rises by
    1.4e-3 to 1e-2 on these seeds, a flipped distribution sign diverges. The 3-D variant
    (the same loop as a 3-D graph) falls strictly on seeds 0–5."""
    graph = small_loop(seed=seed, planar=planar)
    _, history = solve_toro(graph, iterations=40)
    c = np.array(history.chi2)
    assert history.iterations == 40
    assert np.all(np.diff(c) <= 1e-3 * c[:-1]), c
    assert np.all(np.diff(c[:20]) < 0.0), c
    assert c[-1] < 0.1 * c[0]  # it does descend, not merely stand still
    assert np.all(np.diff(history.seconds) >= 0.0)


@pytest.mark.parametrize(("planar", "iterations", "ratio", "drop"),
                         [(True, 200, 1.25, 0.1), (False, 100, 1.3, 0.2)])
def test_synthetic_result_is_near_the_exact_optimum(planar: bool, iterations: int,
                                                    ratio: float, drop: float) -> None:
    """TORO ignores the coupling of rotation and translation (its known weakness), so it
    stops short of the optimum; poses within 0.15 m and 0.05 rad of the optimum's on a 1 m
    grid. Measured over seeds 0–2: planar (synthetic Manhattan, 200 iterations) 1.17–1.20×
    the optimal χ² and 6–10 cm; 3-D (lattice walk, 100 iterations) 1.19–1.22× and 6–9 cm."""
    graph = manhattan(200, seed=0).graph if planar else grid3d(100, seed=0).graph
    out, history = solve_toro(graph, iterations=iterations)
    best = solve_exact(graph)
    assert history.chi2[-1] == pytest.approx(chi2(out))
    assert best.chi2_final <= history.chi2[-1] < ratio * best.chi2_final
    assert history.chi2[-1] < drop * history.chi2[0]
    assert np.max(np.linalg.norm(out.t - best.t, axis=1)) < 0.15
    rot_gap = geo.so3_log(np.swapaxes(best.R, 1, 2) @ out.R)
    assert np.max(np.linalg.norm(rot_gap, axis=1)) < 0.05


def test_3d_start_and_parameters() -> None:
    """Local transforms compose to the tree start; edges by level of their top."""
    graph = grid3d(40, seed=2).graph
    problem = ToroProblem3.from_graph(graph)
    _, start = build_solver(graph)
    R, t = problem.estimate()
    np.testing.assert_allclose(t, start.t, atol=1e-9)
    np.testing.assert_allclose(R, start.R, atol=1e-9)
    assert np.all(np.diff(problem.level[problem.top[problem.order]]) >= 0)


def test_tree_start_is_h2o_tree_start() -> None:
    """The parameters sum to the tree initialization H₂O starts from (same tree, same start),
    and each node's parameter is its pose minus its parent's."""
    graph = manhattan(60, seed=3).graph
    problem = ToroProblem.from_graph(graph)
    _, start = build_solver(graph)
    R, t = problem.estimate()
    np.testing.assert_allclose(t, start.t, atol=1e-9)
    np.testing.assert_allclose(R, start.R, atol=1e-9)
    p = problem.poses()
    inner = problem.parent != EARTH
    np.testing.assert_allclose(problem.x[inner], p[inner] - p[problem.parent[inner]])
    # edges by increasing level of their top, tops being common ancestors of both ends
    levels = problem.level[problem.top[problem.order]]
    assert np.all(np.diff(levels) >= 0)
    for e in range(graph.num_edges):
        for end in (problem.a[e], problem.b[e]):
            n = end
            while n != problem.top[e]:
                n = problem.parent[n]
                assert n != EARTH


def test_input_start_keeps_the_graph_estimate() -> None:
    graph = manhattan(40, seed=1).graph
    out, history = solve_toro(graph, iterations=0, init="input")
    assert history.chi2 == [pytest.approx(chi2(graph))]
    np.testing.assert_allclose(out.t, graph.t, atol=1e-9)


def test_refuses_what_it_cannot_solve() -> None:
    flat = small_loop(seed=0)
    flat.planar = False  # its information has no z, roll or pitch rows
    with pytest.raises(InputError, match="positive information"):
        solve_toro(flat, 1)
    with pytest.raises(InputError, match="global edges"):
        solve_toro(grid3d(30, seed=0, gps_every=10).graph, 1)
    with pytest.raises(InputError, match="global edges"):
        solve_toro(manhattan(30, seed=0, gps_every=10).graph, 1)
    with pytest.raises(ValueError, match="unknown init"):
        solve_toro(manhattan(30, seed=0).graph, 1, init="lago")
