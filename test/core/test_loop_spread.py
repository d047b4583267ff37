"""The loop's closed-form spread against an exact solve of the loop, and its adjoint against
finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from graphs import loop_graph, random_graph
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import chi2, edge_chi2
from h2o_slam.core.loop_spread import adjoint, closure_error, planar_edge_chi2, spread_loop
from h2o_slam.core.modes import solve_exact


@pytest.mark.parametrize("planar", [True, False])
@pytest.mark.parametrize("reverse", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_a_lone_loop_spread_reaches_its_least_squares_optimum(
        planar: bool, reverse: bool, seed: int) -> None:
    g = loop_graph(seed, planar, 60, reverse)
    dof = geo.PLANAR_DOF if planar else np.arange(6)
    optimum = solve_exact(g).chi2_final
    start = chi2(g)
    R, t = spread_loop(g.R, g.t, int(g.a[-1]), int(g.b[-1]), g.meas_R[-1], g.meas_t[-1],
                       g.info[-1], g.info[:-1], dof, steps=8)
    assert start > 5.0 * optimum  # dead reckoning leaves the loop open
    assert chi2(g, R, t) <= 1.001 * optimum
    # Node 0 stays where it was: the loop is spread towards the newer end.
    np.testing.assert_allclose(R[0], g.R[0])
    np.testing.assert_allclose(t[0], g.t[0])


def test_one_step_is_one_gauss_newton_step_of_the_loop() -> None:
    """From dead reckoning, a single step leaves the closure at the fraction of its error
    the covariances say: far below where it started, not at zero."""
    g = loop_graph(7, True, 40, False)
    dof = geo.PLANAR_DOF
    before = closure_error(g.R, g.t, 0, 39, g.meas_R[-1], g.meas_t[-1])
    R, t = spread_loop(g.R, g.t, 0, 39, g.meas_R[-1], g.meas_t[-1], g.info[-1], g.info[:-1],
                       dof, steps=1)
    after = closure_error(R, t, 0, 39, g.meas_R[-1], g.meas_t[-1])
    assert 0.0 < np.linalg.norm(after[dof]) < 0.2 * np.linalg.norm(before[dof])


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-2.0, 2.0), min_size=6, max_size=6),
       st.lists(st.floats(-1e-3, 1e-3), min_size=6, max_size=6))
def test_adjoint_carries_a_right_perturbation_across_a_pose(pose: list[float],
                                                            xi: list[float]) -> None:
    """``T · (Exp ω, δt) = (Ad(T) applied to (δt, ω)) · T`` to first order, in the error's
    ``[translation; rotation]`` order."""
    R, t = geo.so3_exp(np.array(pose[3:])), np.array(pose[:3])
    d = np.array(xi)
    lhs_R, lhs_t = geo.compose(R, t, geo.so3_exp(d[3:]), d[:3])
    moved = adjoint(R, t) @ d
    rhs_R, rhs_t = geo.compose(geo.so3_exp(moved[3:]), moved[:3], R, t)
    np.testing.assert_allclose(lhs_R, rhs_R, atol=1e-5)
    np.testing.assert_allclose(lhs_t, rhs_t, atol=1e-5)


@pytest.mark.parametrize("seed", range(3))
def test_planar_edge_chi2_is_edge_chi2(seed: int) -> None:
    g = random_graph(seed, True, n=12, loops=6, noise=0.3)
    edges = np.arange(g.num_edges)
    np.testing.assert_allclose(planar_edge_chi2(g, edges, g.R, g.t), edge_chi2(g), rtol=1e-9)
