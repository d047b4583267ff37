"""Planted false loop closures: Sünderhauf's four kinds, seeded."""

from __future__ import annotations

import numpy as np
import pytest

from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EdgeKind
from h2o_slam.core.robust import odometry_edges
from h2o_slam.io.outliers import OUTLIER_KINDS, plant_outliers
from h2o_slam.io.synthetic import manhattan


@pytest.fixture(scope="module")
def graph():
    return manhattan(200, seed=1).graph


@pytest.mark.parametrize("kind", OUTLIER_KINDS)
def test_planted_closures_are_appended_relative_edges_between_distinct_poses(graph, kind):
    planted = plant_outliers(graph, kind, 30, seed=3)
    out = planted.graph
    assert planted.num_outliers == 30
    assert out.num_edges == graph.num_edges + 30
    first = graph.num_edges
    assert np.all(planted.outlier[first:]) and not planted.outlier[:first].any()
    new = slice(graph.num_edges, None)
    assert np.all(out.kind[new] == EdgeKind.RELATIVE)
    assert not odometry_edges(out.kind[new], out.a[new], out.b[new]).any()
    assert np.all((out.a[new] >= 0) & (out.b[new] < graph.num_nodes) & (out.a[new] < out.b[new]))
    np.testing.assert_array_equal(out.meas_t[: graph.num_edges], graph.meas_t)


def test_local_closures_stay_within_the_window(graph):
    planted = plant_outliers(graph, "local", 50, seed=4, local_window=20)
    span = planted.graph.b[planted.outlier] - planted.graph.a[planted.outlier]
    assert np.all((span >= 2) & (span <= 20))


def test_grouped_closures_share_one_measurement_between_consecutive_poses(graph):
    planted = plant_outliers(graph, "random_grouped", 20, seed=5, group_size=10)
    g = planted.graph
    a, b, t = g.a[planted.outlier], g.b[planted.outlier], g.meas_t[planted.outlier]
    for group in (slice(0, 10), slice(10, 20)):
        np.testing.assert_array_equal(np.diff(a[group]), 1)
        np.testing.assert_array_equal(np.diff(b[group]), 1)
        assert np.all(t[group] == t[group][0])
    assert not np.array_equal(t[0], t[10])


def test_the_same_seed_plants_the_same_closures(graph):
    one = plant_outliers(graph, "random", 10, seed=9).graph
    two = plant_outliers(graph, "random", 10, seed=9).graph
    other = plant_outliers(graph, "random", 10, seed=10).graph
    np.testing.assert_array_equal(one.meas_t, two.meas_t)
    assert not np.array_equal(one.meas_t, other.meas_t)


def test_bad_requests_are_refused(graph):
    with pytest.raises(InputError, match="unknown outlier kind 'near'"):
        plant_outliers(graph, "near", 10)
    with pytest.raises(InputError, match="count must be >= 0"):
        plant_outliers(graph, "random", -1)
    with pytest.raises(InputError, match="cannot hold groups of 10"):
        plant_outliers(manhattan(12, seed=1).graph, "local_grouped", 10)
