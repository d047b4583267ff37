"""Chordal initialization of 3-D graphs: exact without noise, against a brute-force small
problem, and a start that needs no guess."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from h2o_slam.core import chordal as chordal_module
from h2o_slam.core import geometry as geo
from h2o_slam.core.chordal import _nearest_rotations, chordal
from h2o_slam.core.errors import GraphError
from h2o_slam.core.graph import EdgeKind, chi2, make_graph
from h2o_slam.core.modes import solve_exact
from h2o_slam.io.synthetic import grid3d


def _graph(R: np.ndarray, t: np.ndarray, a: np.ndarray, b: np.ndarray,
           noise: float = 0.0, seed: int = 0):
    """Relative edges measured between the given world poses, rotations perturbed by
    ``noise`` radians."""
    rng = np.random.default_rng(seed)
    mR, mt = geo.between(R[a], t[a], R[b], t[b])
    if noise:
        mR = mR @ Rotation.from_rotvec(rng.normal(0, noise, (len(a), 3))).as_matrix()
    info = np.broadcast_to(np.eye(6), (len(a), 6, 6)).copy()
    start_R = np.broadcast_to(np.eye(3), R.shape).copy()
    return make_graph(False, np.arange(len(R)), start_R, np.zeros_like(t),
                      np.full(len(a), EdgeKind.RELATIVE, np.int8), a, b, mR, mt, info)


def _world(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    R[0] = np.eye(3)
    t = rng.normal(0, 3.0, (n, 3))
    t[0] = 0.0
    return R, t


def test_without_noise_the_poses_are_recovered_exactly() -> None:
    R, t = _world(12, seed=1)
    a = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 0, 3, 5])
    b = np.array([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 6, 9, 11])
    got_R, got_t = chordal(_graph(R, t, a, b))
    np.testing.assert_allclose(got_R, R, atol=1e-9)
    np.testing.assert_allclose(got_t, t, atol=1e-9)


def test_rotations_match_a_brute_force_solve_of_the_relaxation() -> None:
    """Four poses, six noisy edges: the linear solve's unprojected matrices equal a generic
    minimizer's of Σ ‖R_b − R_a R_ab‖²_F with R_0 = I (then both project alike)."""
    R, t = _world(4, seed=2)
    a = np.array([0, 1, 2, 0, 1, 0])
    b = np.array([1, 2, 3, 2, 3, 3])
    graph = _graph(R, t, a, b, noise=0.2, seed=3)

    def cost(x: np.ndarray) -> float:
        M = np.concatenate([np.eye(3)[None], x.reshape(3, 3, 3)])
        return float(np.sum((M[b] - M[a] @ graph.meas_R) ** 2))

    best = minimize(cost, np.tile(np.eye(3).ravel(), 3), method="BFGS",
                    options={"gtol": 1e-12, "maxiter": 10000})
    expected = _nearest_rotations(np.concatenate([np.eye(3)[None], best.x.reshape(3, 3, 3)]))
    got_R, _ = chordal(graph)
    np.testing.assert_allclose(got_R, expected, atol=1e-5)


def test_a_noisy_grid_starts_near_the_optimum_with_no_guess() -> None:
    graph = grid3d(5, seed=4).graph
    R, t = chordal(graph)
    optimum = solve_exact(graph)
    assert chi2(graph, R, t) < 3.0 * chi2(graph, optimum.R, optimum.t)


def test_edges_that_leave_a_node_unconnected_are_an_error() -> None:
    R, t = _world(4, seed=5)
    graph = _graph(R, t, np.array([0, 1]), np.array([1, 2]))
    with pytest.raises(GraphError):
        chordal(graph)


@pytest.mark.parametrize("dense_max", [0, 10_000])
def test_the_dense_and_sparse_solves_agree(monkeypatch, dense_max) -> None:
    """The small graphs' dense solve and the sparse one give the same start, weighted edges
    and edges into the held node 0 included; both refuse a node no edge reaches."""
    graph = grid3d(40, seed=6, sigma_rot_rad=0.1).graph
    weights = np.random.default_rng(7).uniform(0.3, 2.0, graph.num_edges)
    closures = np.flatnonzero(graph.b != graph.a + 1)
    weights[closures[::2]] = 0.0  # left out, as the robust weights leave outliers out
    expected = chordal(graph, weights)  # 117 rotation unknowns, 39 translation: both paths
    monkeypatch.setattr(chordal_module, "DENSE_MAX", dense_max)
    got = chordal(graph, weights)
    np.testing.assert_allclose(got[0], expected[0], atol=1e-9)
    np.testing.assert_allclose(got[1], expected[1], atol=1e-9)
    R, t = _world(4, seed=5)
    with pytest.raises(GraphError):
        chordal(_graph(R, t, np.array([0, 1]), np.array([1, 2])))
