"""Deletion χ² bounds from a group's neighbourhood against the whole graph's deletion χ²."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core.exact import converge_exact
from h2o_slam.core.graph import EdgeKind
from h2o_slam.core.modes import build_solver
from h2o_slam.core.neighbourhood import deletion_bounds
from h2o_slam.core.robust import group_chi2, odometry_edges
from h2o_slam.io.synthetic import grid3d, manhattan, sphere


def _solved(graph, init):
    solver, _ = build_solver(graph, init=init, regularizer=False)
    converge_exact(solver, 100)
    m = solver.num_edges
    trusted = odometry_edges(solver.kind[:m], solver.a, solver.b)
    closures = np.flatnonzero(~trusted & (solver.kind[:m] == EdgeKind.RELATIVE)
                              & (solver.a[:m] >= 0))
    return solver, closures


@pytest.fixture(scope="module", params=["planar", "3-D grid", "sphere"])
def solved(request):
    """A solver at its optimum (a planar walk, a 3-D lattice walk, a noisy sphere) and its
    loop closures."""
    if request.param == "planar":
        return _solved(manhattan(200, seed=3).graph, "tree")
    if request.param == "3-D grid":
        return _solved(grid3d(150, seed=2, sigma_rot_rad=0.1).graph, "chordal")
    return _solved(sphere(8, 12, seed=1, sigma_rot_rad=0.2).graph, "chordal")


@settings(max_examples=30, deadline=None)
@given(picks=st.lists(st.lists(st.integers(0, 10**6), min_size=1, max_size=5), min_size=1,
                      max_size=6),
       hops=st.integers(0, 3))
def test_the_bound_is_never_below_the_deletion_chi2(solved, picks, hops):
    """Whatever the group and the neighbourhood, the bound is at least the whole graph's
    deletion χ² (a neighbourhood's covariance is never smaller than the graph's)."""
    solver, closures = solved
    groups = [np.unique(closures[np.array(p) % len(closures)]) for p in picks]
    exact = group_chi2(solver, groups, sign=-1.0)
    bound = deletion_bounds(solver, groups, hops)
    assert np.all(bound >= exact * (1 - 1e-7) - 1e-9)


def test_a_neighbourhood_of_the_whole_graph_bounds_it_exactly(solved, monkeypatch):
    """Reaching every pose, the neighbourhood is the graph: the bound is the deletion χ²."""
    from h2o_slam.core import neighbourhood

    solver, closures = solved
    monkeypatch.setattr(neighbourhood, "MAX_UNKNOWNS", solver.num_nodes * solver.p)
    groups = [closures[[i]] for i in range(0, len(closures), 7)] + [closures[:3]]
    exact = group_chi2(solver, groups, sign=-1.0)
    np.testing.assert_allclose(deletion_bounds(solver, groups, solver.num_nodes), exact,
                               rtol=1e-6)


def test_one_edge_around_bounds_a_closure_of_a_sphere_closely(solved):
    """Where the graph is a mesh, the poses one edge away already hold a closure's ends
    nearly as the whole graph does (measured on a 2,200-pose sphere: 1.04 times)."""
    solver, closures = solved
    groups = [closures[[i]] for i in range(len(closures))]
    ratio = deletion_bounds(solver, groups, 1) / group_chi2(solver, groups, sign=-1.0)
    assert np.all(ratio >= 1 - 1e-7)
    assert np.median(ratio[np.isfinite(ratio)]) < 2.0


def test_no_bound_where_the_group_alone_holds_its_ends(monkeypatch):
    """A closure with no other way between its ends in the neighbourhood (none of its
    neighbours taken) has no bound; a GPS fix neither, nor a neighbourhood too large."""
    from h2o_slam.core import neighbourhood

    graph = manhattan(200, seed=3, gps_every=10).graph
    solver, closures = _solved(graph, "tree")
    assert np.all(np.isinf(deletion_bounds(solver, [closures[[0]]], 0)))
    fixes = np.flatnonzero(solver.kind[:solver.num_edges] == EdgeKind.POSITION)
    assert np.isinf(deletion_bounds(solver, [fixes[:1], fixes[:1]], 2)).all()
    groups = [closures[[i]] for i in range(len(closures))]
    bounded = groups[int(np.argmax(np.isfinite(deletion_bounds(solver, groups, 2))))]
    assert np.isfinite(deletion_bounds(solver, [bounded], 2)[0])
    monkeypatch.setattr(neighbourhood, "MAX_UNKNOWNS", 3 * solver.p)
    assert np.isinf(deletion_bounds(solver, [bounded], 2)[0])


@pytest.mark.parametrize("weight", [0.0, 0.05])
def test_edges_out_of_the_map_are_not_in_the_bound(weight):
    """A neighbour the robust weights drop holds nothing, one they lower holds less: either
    raises the bound and keeps it above the deletion χ² of that map."""
    solver, closures = _solved(manhattan(200, seed=3).graph, "tree")
    group = closures[[5]]
    before = deletion_bounds(solver, [group], 2)[0]
    ends = np.concatenate([solver.a[group], solver.b[group]])
    m = solver.num_edges
    near = np.flatnonzero(np.isin(solver.a[:m], ends) | np.isin(solver.b[:m], ends))
    others = np.setdiff1d(np.intersect1d(near, closures), group)
    weights = np.ones(m)
    weights[others] = weight
    solver.set_weights(weights)
    converge_exact(solver, 100)
    after = deletion_bounds(solver, [group], 2)[0]
    assert after >= group_chi2(solver, [group], sign=-1.0)[0] * (1 - 1e-7)
    assert len(others) and after > before
