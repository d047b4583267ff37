"""The loop's closed-form spread against an exact solve of the loop, and its adjoint against
finite differences."""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest
from graphs import loop_graph, random_graph
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import geometry as geo
from h2o_slam.core.condensed import planar_chi2, planar_poses
from h2o_slam.core.graph import chi2, edge_chi2
from h2o_slam.core.loop_spread import (
    LoopSolve,
    _covariances,
    adjoint,
    closure_error,
    closure_moved,
    perturbed,
    spread_loop,
    spread_step,
)
from h2o_slam.core.modes import build_solver, solve_exact


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


def _pose(v: list[float]) -> tuple[np.ndarray, np.ndarray]:
    return geo.so3_exp(np.array(v[3:])), np.array(v[:3])


def _closure_chi2(Ra, ta, Rb, tb, Z_R, Z_t, info) -> float:
    e = geo.relative_error(Ra, ta, Rb, tb, Z_R, Z_t)
    return float(e @ info @ e)


_POSE = st.lists(st.floats(-2.0, 2.0), min_size=6, max_size=6)


@settings(max_examples=40, deadline=None)
@given(_POSE, _POSE, _POSE, _POSE, st.lists(st.floats(-1e-4, 1e-4), min_size=6, max_size=6),
       st.integers(0, 2**32 - 1))
def test_a_closure_moved_to_a_held_pose_has_the_same_chi2(
        lo: list[float], c: list[float], z: list[float], far: list[float], near: list[float],
        seed: int) -> None:
    """Rewritten between pose ``k`` and ``hi`` (``T_lo`` and ``T_k`` held), a closure
    ``lo → hi`` has its χ² at any ``T_hi``; one ``hi → lo`` near its fit, where the spread
    linearizes it, to first order."""
    R_lo, t_lo = _pose(lo)
    C_R, C_t = _pose(c)
    R_k, t_k = geo.compose(R_lo, t_lo, C_R, C_t)
    Z_R, Z_t = _pose(z)
    A = np.random.default_rng(seed).standard_normal((6, 6))
    info = A @ A.T + 0.1 * np.eye(6)
    R_hi, t_hi = _pose(far)
    M_R, M_t, M_info = closure_moved(C_R, C_t, Z_R, Z_t, info, forward=True)
    assert _closure_chi2(R_k, t_k, R_hi, t_hi, M_R, M_t, M_info) == pytest.approx(
        _closure_chi2(R_lo, t_lo, R_hi, t_hi, Z_R, Z_t, info), rel=1e-9, abs=1e-12)
    # hi → lo near its fit: T_hi = T_lo Z⁻¹ Exp(δ).
    R_hi, t_hi = geo.compose(*geo.compose(R_lo, t_lo, *geo.inverse(Z_R, Z_t)), *_pose(near))
    M_R, M_t, M_info = closure_moved(C_R, C_t, Z_R, Z_t, info, forward=False)
    want = _closure_chi2(R_hi, t_hi, R_lo, t_lo, Z_R, Z_t, info)
    got = _closure_chi2(R_hi, t_hi, R_k, t_k, M_R, M_t, M_info)
    assert got == pytest.approx(want, rel=1e-3, abs=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_planar_edge_chi2_is_edge_chi2(seed: int) -> None:
    """Each edge's χ² from the solver's planar copies (what the spread's and the condensed
    solve's checks read) is :func:`edge_chi2`'s."""
    g = random_graph(seed, True, n=12, loops=6, noise=0.3)
    solver, _ = build_solver(g, init="input")
    pose = planar_poses(g.R, g.t)
    planar = [planar_chi2(solver.a[[e]], solver.b[[e]], solver.planar_meas[[e]],
                          solver.planar_info[[e]], np.ones(1), pose)
              for e in range(g.num_edges)]
    np.testing.assert_allclose(planar, edge_chi2(g), rtol=1e-9)


@pytest.mark.parametrize("planar", [True, False])
def test_the_loop_solve_is_gauss_newton_on_the_newer_poses(planar: bool) -> None:
    """With the closure's older end at node 0 every other pose is newer: the loop solve is
    then the whole graph's exact solve (node 0 holds the gauge in both)."""
    g = loop_graph(5, planar, 120, reverse=True, closures=((80, 10), (110, 50)))
    solver, _ = build_solver(g, init="input", regularizer=False)
    loop = LoopSolve()
    free, edges = loop.problem(solver, 0)
    np.testing.assert_array_equal(free, np.arange(1, g.num_nodes))
    assert len(edges) == g.num_edges
    kept, converged = loop.run(solver, free, edges, math.inf, time.perf_counter, 1.0)
    assert kept
    for _ in range(5):  # LOOP_ITERATIONS at a time
        if converged:
            break
        _, converged = loop.run(solver, free, edges, math.inf, time.perf_counter, 1.0)
    assert converged
    assert solver.chi2(g) <= 1.0001 * solve_exact(g).chi2_final


def test_a_loop_solve_cut_short_goes_on_from_the_poses_it_reached() -> None:
    """Out of time after two iterations, the map keeps what they gained (χ² fell); the next
    calls go on from there to the optimum. Poses older than the closure's end stay."""
    g = loop_graph(5, True, 120, reverse=True, closures=((80, 10), (110, 50)))
    solver, _ = build_solver(g, init="input", regularizer=False)
    loop = LoopSolve()
    free, edges = loop.problem(solver, 10)
    ticks = itertools.count()

    def clock() -> float:  # each reading a millisecond later
        return 1e-3 * next(ticks)

    start = solver.chi2(g)
    old = solver.world_poses()[1][:11].copy()
    kept, converged = loop.run(solver, free, edges, clock() + 4e-3, clock, 1.0)
    assert kept and not converged
    assert solver.chi2(g) < start
    for _ in range(20):
        if converged:
            break
        kept, converged = loop.run(solver, free, edges, clock() + 1.0, clock, 1.0)
    assert converged
    np.testing.assert_allclose(solver.world_poses()[1][:11], old, atol=1e-9)
    # The optimum with nodes 0-10 held where dead reckoning put them.
    assert solver.chi2(g) < 0.01 * start


@pytest.mark.parametrize("reverse", [False, True])
@pytest.mark.parametrize("steps", [1, 3])
def test_the_compiled_planar_spread_is_the_general_spread_on_planar_poses(
        reverse: bool, steps: int) -> None:
    """The planar kernel in (x, y, yaw) and the general steps in SE(3) (``spread_step`` and
    ``perturbed`` over the planar degrees of freedom) give the same poses."""
    g = loop_graph(5, True, 50, reverse)
    dof = geo.PLANAR_DOF
    a, b = int(g.a[-1]), int(g.b[-1])
    R, t = spread_loop(g.R, g.t, a, b, g.meas_R[-1], g.meas_t[-1], g.info[-1], g.info[:-1],
                       dof, steps=steps)
    lo, hi = min(a, b), max(a, b)
    D_R, D_t = geo.between(g.R[lo:hi], g.t[lo:hi], g.R[lo + 1: hi + 1], g.t[lo + 1: hi + 1])
    cov_closure, cov = _covariances(g.info[-1], g.info[:-1], dof)
    moved = np.zeros((hi - lo, 6))
    R_gen, t_gen = g.R, g.t
    for _ in range(steps):
        moved = spread_step(R_gen, t_gen, a, b, g.meas_R[-1], g.meas_t[-1], cov_closure, cov,
                            dof, moved)
        R_gen, t_gen = perturbed(g.R, g.t, lo, hi, D_R, D_t, moved)
    assert not np.allclose(t, g.t)
    np.testing.assert_allclose(R, R_gen, atol=1e-9)
    np.testing.assert_allclose(t, t_gen, atol=1e-9)
