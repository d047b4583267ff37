"""The pose-graph model: χ² by hand, wrapping, eigen-clamping, validation, odometry chain."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import GraphError, InputError
from h2o_slam.core.graph import (
    EARTH,
    INFO_EIG_FLOOR,
    EdgeKind,
    PoseGraph,
    chi2,
    chi2_as_written,
    edge_chi2,
    edge_errors,
    make_graph,
    odometry_chain,
)

PLANAR = [0, 1, 5]


def planar_pose(x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    return geo.yaw_to_matrix(yaw), np.array([x, y, 0.0])


def planar_info(S3: np.ndarray) -> np.ndarray:
    S = np.zeros((6, 6))
    S[np.ix_(PLANAR, PLANAR)] = S3
    return S


def build(
    planar: bool,
    poses: list[tuple[np.ndarray, np.ndarray]],
    edges: list[tuple[EdgeKind, int, int, np.ndarray, np.ndarray, np.ndarray]],
) -> PoseGraph:
    """A graph from ``(R, t)`` poses and ``(kind, a, b, meas_R, meas_t, info6)`` edges."""
    return make_graph(
        planar,
        np.arange(len(poses)),
        np.array([p[0] for p in poses]),
        np.array([p[1] for p in poses]),
        np.array([e[0] for e in edges]),
        np.array([e[1] for e in edges]),
        np.array([e[2] for e in edges]),
        np.array([e[3] for e in edges]),
        np.array([e[4] for e in edges]),
        np.array([e[5] for e in edges]),
    )


def planar_triangle() -> PoseGraph:
    # x0 = (0, 0, 0), x1 = (1, 0, 0), x2 = (1, 1, 90°).
    poses = [planar_pose(0, 0, 0), planar_pose(1, 0, 0), planar_pose(1, 1, np.pi / 2)]
    S_loop = np.array([[1.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]])
    edges = [
        # Truth 0→1 is (1, 0, 0): K⁻¹ T = (-0.1, 0, 0), χ² = 0.01.
        (EdgeKind.RELATIVE, 0, 1, *planar_pose(1.1, 0, 0), planar_info(np.eye(3))),
        # Truth 1→2 is (0, 1, 90°): yaw error 0.2 rad, weight 4, χ² = 0.16.
        (EdgeKind.RELATIVE, 1, 2, *planar_pose(0, 1, np.pi / 2 - 0.2),
         planar_info(np.diag([2.0, 3.0, 4.0]))),
        # Truth 2→0 is (-1, 1, -90°); K = (-1.2, 1.5, -90°): error Rz(90°)(0.2, -0.5) =
        # (0.5, 0.2), χ² = 0.25 + 2·0.5·0.5·0.2 + 0.04 = 0.39.
        (EdgeKind.RELATIVE, 2, 0, *planar_pose(-1.2, 1.5, -np.pi / 2), planar_info(S_loop)),
    ]
    return build(True, poses, edges)


def test_planar_chi2_by_hand() -> None:
    g = planar_triangle()
    e = edge_errors(g)
    np.testing.assert_allclose(e[0], [-0.1, 0, 0, 0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(e[1], [0, 0, 0, 0, 0, 0.2], atol=1e-15)
    np.testing.assert_allclose(e[2], [0.5, 0.2, 0, 0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(edge_chi2(g), [0.01, 0.16, 0.39], atol=1e-14)
    assert chi2(g) == pytest.approx(0.56, abs=1e-14)


def test_3d_chi2_by_hand() -> None:
    Rz90 = geo.yaw_to_matrix(np.pi / 2)
    poses = [(np.eye(3), np.zeros(3)), (Rz90, np.array([1.0, 2.0, 3.0]))]
    gps_info = np.zeros((6, 6))
    gps_info[:3, :3] = 10 * np.eye(3)
    ori_info = np.zeros((6, 6))
    ori_info[3:, 3:] = 7 * np.eye(3)
    edges = [
        # K⁻¹ T = (Rz(90°), (0, 0, -0.5)): e = (0, 0, -0.5, 0, 0, π/2).
        (EdgeKind.RELATIVE, 0, 1, np.eye(3), np.array([1.0, 2.0, 3.5]),
         np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])),
        # GPS at (1, 2, 2): e = (0, 0, 1).
        (EdgeKind.POSITION, EARTH, 1, np.eye(3), np.array([1.0, 2.0, 2.0]), gps_info),
        # Compass Rz(0.5): e = (0, 0, π/2 - 0.5).
        (EdgeKind.ORIENTATION, EARTH, 1, geo.yaw_to_matrix(0.5), np.zeros(3), ori_info),
    ]
    g = build(False, poses, edges)
    np.testing.assert_allclose(edge_errors(g)[0], [0, 0, -0.5, 0, 0, np.pi / 2], atol=1e-15)
    expected = [3 * 0.25 + 6 * (np.pi / 2) ** 2, 10.0, 7 * (np.pi / 2 - 0.5) ** 2]
    np.testing.assert_allclose(edge_chi2(g), expected, rtol=1e-14)
    assert chi2(g) == pytest.approx(sum(expected), rel=1e-14)


@pytest.mark.parametrize("planar", [True, False])
def test_chi2_is_zero_at_noiseless_truth(planar: bool) -> None:
    rng = np.random.default_rng(3)
    n = 12
    if planar:
        poses = [planar_pose(*rng.normal(size=2), rng.uniform(-np.pi, np.pi)) for _ in range(n)]
        dof = PLANAR
    else:
        poses = [(geo.so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(n)]
        dof = list(range(6))
    pairs = [(i, i + 1) for i in range(n - 1)] + [(0, 5), (3, 11), (10, 2)]
    info = np.zeros((6, 6))
    info[np.ix_(dof, dof)] = np.eye(len(dof)) * 3
    gps_info = np.zeros((6, 6))
    gps_info[:2, :2] = np.eye(2)
    edges = [(EdgeKind.RELATIVE, i, j, *geo.between(*poses[i], *poses[j]), info)
             for i, j in pairs]
    edges.append((EdgeKind.POSITION, EARTH, 4, np.eye(3), poses[4][1], gps_info))
    g = build(planar, poses, edges)
    assert chi2(g) < 1e-20
    # Moving one pose makes it positive.
    t = g.t.copy()
    t[7, 0] += 0.1
    assert chi2(g, g.R, t) > 1e-3


def test_planar_yaw_error_wraps() -> None:
    poses = [planar_pose(0, 0, 0), planar_pose(0, 0, np.deg2rad(-179.0))]
    edges = [(EdgeKind.RELATIVE, 0, 1, *planar_pose(0, 0, np.deg2rad(179.0)),
              planar_info(np.eye(3)))]
    g = build(True, poses, edges)
    e = edge_errors(g)[0]
    np.testing.assert_allclose(e[5], np.deg2rad(2.0), atol=1e-12)
    assert chi2(g) == pytest.approx(np.deg2rad(2.0) ** 2, rel=1e-9)


def test_eigen_clamping_of_indefinite_information(caplog: pytest.LogCaptureFixture) -> None:
    # Like CSAIL's: a 2×2 block [[1, 1], [1, 1 - 1e-12]] with a tiny negative eigenvalue.
    bad = np.array([[1.0, 1.0, 0.0], [1.0, 1.0 - 1e-12, 0.0], [0.0, 0.0, 5.0]])
    assert np.linalg.eigvalsh(bad)[0] < 0
    good = np.diag([2.0, 3.0, 4.0])
    poses = [planar_pose(0, 0, 0), planar_pose(1, 0, 0), planar_pose(2, -1, 0)]
    edges = [
        (EdgeKind.RELATIVE, 0, 1, *planar_pose(1, 0, 0), planar_info(good)),
        (EdgeKind.RELATIVE, 1, 2, *planar_pose(0, 0, 0), planar_info(bad)),
    ]
    with caplog.at_level(logging.INFO, logger="h2o_slam.core.graph"):
        g = build(True, poses, edges)
    assert "eigen-clamped 1" in caplog.text
    np.testing.assert_array_equal(g.clamped_edges, [1])
    lam = np.linalg.eigvalsh(g.info[1][np.ix_(PLANAR, PLANAR)])
    assert lam[0] >= INFO_EIG_FLOOR * lam[-1] * (1 - 1e-9)
    # The error (1, -1, 0) lies along the negative direction: unclamped, χ² would be < 0.
    e = edge_errors(g)[1, PLANAR]
    np.testing.assert_allclose(e, [1.0, -1.0, 0.0], atol=1e-15)
    assert e @ bad @ e < 0.0
    c = edge_chi2(g)
    assert np.all(np.isfinite(c)) and np.all(c >= 0.0)
    assert c[1] > 0.0
    # An information matrix that needs no clamping is kept exactly as given.
    np.testing.assert_array_equal(g.info[0], planar_info(good))


def test_clamped_information_is_kept_as_given_for_chi2_as_written() -> None:
    # x and y perfectly correlated: singular, clamped; the error (1, -1) lies in its null
    # space, so as written that edge costs nothing along it, conditioned a little.
    singular = np.array([[4.0, 4.0, 0.0], [4.0, 4.0, 0.0], [0.0, 0.0, 9.0]])
    good = np.diag([2.0, 3.0, 4.0])
    poses = [planar_pose(0, 0, 0), planar_pose(1, 0, 0), planar_pose(2, -1, 0.1)]
    edges = [
        (EdgeKind.RELATIVE, 0, 1, *planar_pose(1, 0, 0), planar_info(good)),
        (EdgeKind.RELATIVE, 1, 2, *planar_pose(0, 0, 0), planar_info(singular)),
    ]
    g = build(True, poses, edges)
    np.testing.assert_array_equal(g.clamped_edges, [1])
    np.testing.assert_array_equal(g.clamped_info, [planar_info(singular)])
    e = edge_errors(g)[1, PLANAR]
    by_hand = edge_chi2(g)[0] + e @ singular @ e
    assert chi2_as_written(g) == pytest.approx(by_hand, rel=1e-12)
    assert chi2(g) - chi2_as_written(g) == pytest.approx(
        e @ (g.info[1][np.ix_(PLANAR, PLANAR)] - singular) @ e, rel=1e-6)
    assert chi2(g) > chi2_as_written(g)
    # Copies carry it; a graph without clamped edges has the same χ² either way.
    np.testing.assert_array_equal(g.copy().clamped_info, g.clamped_info)
    assert chi2_as_written(planar_triangle()) == chi2(planar_triangle())


def test_information_is_symmetrized() -> None:
    S = np.array([[2.0, 0.4, 0.0], [0.2, 2.0, 0.0], [0.0, 0.0, 1.0]])
    g = build(True, [planar_pose(0, 0, 0), planar_pose(1, 0, 0)],
              [(EdgeKind.RELATIVE, 0, 1, *planar_pose(1, 0, 0), planar_info(S))])
    np.testing.assert_allclose(g.info[0][0, 1], 0.3)
    np.testing.assert_allclose(g.info[0], g.info[0].T)


def _two_node_args(**override: object) -> dict:
    args: dict = dict(
        planar=True,
        ids=np.arange(2),
        R=np.broadcast_to(np.eye(3), (2, 3, 3)).copy(),
        t=np.zeros((2, 3)),
        kind=np.array([EdgeKind.RELATIVE]),
        a=np.array([0]),
        b=np.array([1]),
        meas_R=np.eye(3)[None],
        meas_t=np.array([[1.0, 0.0, 0.0]]),
        info=planar_info(np.eye(3))[None],
    )
    args.update(override)
    return args


@pytest.mark.parametrize(
    ("override", "error", "match"),
    [
        (dict(b=np.array([2])), GraphError, "endpoint b refers to an unknown node"),
        (dict(a=np.array([-3])), GraphError, "endpoint a refers to an unknown node"),
        (dict(b=np.array([0])), GraphError, "from a node to itself"),
        (dict(kind=np.array([EdgeKind.POSITION])), GraphError,
         "global edges must have the earth"),
        (dict(t=np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]])), InputError,
         "non-finite estimate"),
        (dict(meas_t=np.array([[np.inf, 0.0, 0.0]])), InputError, "non-finite measurement"),
        (dict(info=np.full((1, 6, 6), np.nan)), InputError, "non-finite information"),
        (dict(info=-planar_info(np.eye(3))[None]), InputError, "no positive eigenvalue"),
        (dict(info=np.zeros((1, 6, 6))), InputError, "no positive eigenvalue"),
    ],
)
def test_make_graph_rejects(override: dict, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        make_graph(**_two_node_args(**override))


def test_make_graph_accepts_the_valid_case() -> None:
    g = make_graph(**_two_node_args())
    assert (g.num_nodes, g.num_edges) == (2, 1)
    assert len(g.clamped_edges) == 0


def test_odometry_chain_with_backwards_edges() -> None:
    rng = np.random.default_rng(5)
    n = 6
    poses = [(geo.so3_exp(rng.normal(size=3)), rng.normal(size=3)) for _ in range(n)]
    poses[0] = (np.eye(3), np.zeros(3))
    info = np.eye(6)
    # 0→1 forward, 2→1 backward, 2→3 forward, 4→3 backward, 5→4 backward, and a loop.
    pairs = [(0, 1), (2, 1), (2, 3), (4, 3), (5, 4), (0, 5)]
    edges = [(EdgeKind.RELATIVE, i, j, *geo.between(*poses[i], *poses[j]), info)
             for i, j in pairs]
    g = build(False, poses, edges)
    R, t = odometry_chain(g)
    np.testing.assert_allclose(R, [p[0] for p in poses], atol=1e-12)
    np.testing.assert_allclose(t, [p[1] for p in poses], atol=1e-12)


def test_odometry_chain_unreachable_node_keeps_previous_pose() -> None:
    poses = [planar_pose(0, 0, 0), planar_pose(1, 0, 0), planar_pose(5, 5, 1.0)]
    edges = [(EdgeKind.RELATIVE, 0, 1, *planar_pose(1, 0, 0), planar_info(np.eye(3))),
             (EdgeKind.RELATIVE, 0, 2, *planar_pose(5, 5, 1.0), planar_info(np.eye(3)))]
    R, t = odometry_chain(build(True, poses, edges))
    np.testing.assert_allclose(t[2], t[1])
    np.testing.assert_allclose(R[2], R[1])


def test_with_estimate_copies() -> None:
    g = planar_triangle()
    h = g.with_estimate(g.R * 1.0, g.t + 1.0)
    np.testing.assert_allclose(h.t, g.t + 1.0)
    h.meas_t[0, 0] = 99.0
    assert g.meas_t[0, 0] != 99.0
