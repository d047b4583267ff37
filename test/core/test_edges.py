"""The edge table's planar copies: the same edges as the full arrays, however they arrive."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import geometry as geo
from h2o_slam.core.edges import EdgeTable
from h2o_slam.core.graph import EdgeKind


def _edges(rng: np.random.Generator, k: int):
    yaw = rng.uniform(-np.pi, np.pi, k)
    meas_R = geo.yaw_to_matrix(yaw)
    meas_t = np.column_stack([rng.normal(size=(k, 2)), np.zeros(k)])
    info = np.zeros((k, 6, 6))
    for i in range(k):
        L = rng.normal(size=(3, 3))
        info[i][np.ix_(geo.PLANAR_DOF, geo.PLANAR_DOF)] = L @ L.T + 0.1 * np.eye(3)
    return yaw, meas_R, meas_t, info


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 150))
def test_planar_copies_match_the_edges_through_appends_extends_and_growth(seed, k):
    rng = np.random.default_rng(seed)
    yaw, meas_R, meas_t, info = _edges(rng, k)
    table = EdgeTable(3, capacity=4)
    half = k // 2
    for e in range(half):
        table.append(EdgeKind.RELATIVE, e, e + 1, meas_R[e], meas_t[e], info[e],
                     geo.PLANAR_DOF)
    rest = np.arange(half, k)
    table.extend(np.full(len(rest), EdgeKind.RELATIVE, np.int8), rest, rest + 1,
                 meas_R[rest], meas_t[rest], info[rest], geo.PLANAR_DOF)
    S = info[:, geo.PLANAR_DOF[:, None], geo.PLANAR_DOF[None, :]]
    m = table.m
    assert m == k
    np.testing.assert_allclose(table.planar_meas[:m, :2], meas_t[:, :2])
    np.testing.assert_allclose(geo.wrap_angle(table.planar_meas[:m, 2] - yaw), 0.0,
                               atol=1e-12)
    np.testing.assert_array_equal(table.planar_info[:m], S)
    np.testing.assert_allclose(table.planar_cov[:m] @ S, np.broadcast_to(np.eye(3), S.shape),
                               atol=1e-8)


def test_a_gps_fix_without_yaw_information_gets_a_pseudo_inverse():
    table = EdgeTable(3)
    info = np.zeros((6, 6))
    info[0, 0] = info[1, 1] = 4.0
    table.append(EdgeKind.POSITION, -1, 0, np.eye(3), np.array([1.0, 2.0, 0.0]), info,
                 geo.PLANAR_DOF)
    np.testing.assert_allclose(table.planar_cov[0], np.diag([0.25, 0.25, 0.0]))


def test_a_3d_table_keeps_no_planar_copies():
    assert not EdgeTable(6).planar
