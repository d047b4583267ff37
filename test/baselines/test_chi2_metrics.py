"""χ² as GTSAM and g2o compute it (h2o_slam.baselines.chi2_metrics): hand-derived single edges, and
GTSAM's own factors where the bench requirements (the gtsam wheel) are installed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from h2o_slam.baselines.chi2_metrics import METRICS, all_chi2, chi2_as
from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import EdgeKind, PoseGraph, chi2, make_graph
from h2o_slam.io.synthetic import grid3d, manhattan


def one_edge(planar: bool, t_b: np.ndarray, R_b: np.ndarray, info: np.ndarray,
             kind: int = EdgeKind.RELATIVE) -> PoseGraph:
    """Pose 0 at the origin, pose 1 at ``(R_b, t_b)``, one edge 0 → 1 measuring identity."""
    R = np.stack([np.eye(3), R_b])
    t = np.stack([np.zeros(3), t_b])
    a = np.array([0 if kind == EdgeKind.RELATIVE else -1])
    return make_graph(planar, np.arange(2), R, t, np.array([kind]), a, np.array([1]),
                      np.eye(3)[None], np.zeros((1, 3)), info[None])


def rot_z(angle: float) -> np.ndarray:
    return geo.yaw_to_matrix(np.array([angle]))[0]


def test_se3_rotation_about_z_by_hand() -> None:
    """E = (Rz(φ), t): h2o weighs φ, g2o sin(φ/2), GTSAM φ and V(φ)⁻¹ t."""
    phi, t = 0.8, np.array([1.0, 2.0, 0.5])
    g = one_edge(False, t, rot_z(phi), np.eye(6))
    assert chi2_as("h2o", g) == pytest.approx(t @ t + phi**2, rel=1e-12)
    assert chi2_as("g2o", g) == pytest.approx(t @ t + math.sin(phi / 2) ** 2, rel=1e-12)
    # Pose2/Pose3 Logmap about z: v = V(φ)⁻¹ t in the plane, with
    # V(φ) = [[sin φ, −(1 − cos φ)], [1 − cos φ, sin φ]] / φ; z passes through.
    V = np.array([[math.sin(phi), -(1 - math.cos(phi))], [1 - math.cos(phi), math.sin(phi)]])
    v = np.linalg.solve(V / phi, t[:2])
    assert chi2_as("gtsam", g) == pytest.approx(v @ v + t[2] ** 2 + phi**2, rel=1e-12)


def test_se2_g2o_is_h2o_and_gtsam_uses_the_pose2_logmap() -> None:
    phi, t = -2.5, np.array([0.3, -1.2, 0.0])
    info = np.diag([4.0, 9.0, 1.0, 1.0, 1.0, 16.0])
    g = one_edge(True, t, rot_z(phi), info)
    assert chi2_as("g2o", g) == chi2_as("h2o", g) == pytest.approx(
        4 * t[0] ** 2 + 9 * t[1] ** 2 + 16 * phi**2, rel=1e-12)
    V = np.array([[math.sin(phi), -(1 - math.cos(phi))], [1 - math.cos(phi), math.sin(phi)]])
    v = np.linalg.solve(V / phi, t[:2])
    assert chi2_as("gtsam", g) == pytest.approx(4 * v[0] ** 2 + 9 * v[1] ** 2 + 16 * phi**2,
                                                rel=1e-12)


def test_orientation_and_position_priors() -> None:
    phi = 0.6
    info = np.zeros((6, 6))
    info[3:, 3:] = np.eye(3)
    ori = one_edge(False, np.array([5.0, 0, 0]), rot_z(phi), info, EdgeKind.ORIENTATION)
    assert chi2_as("h2o", ori) == chi2_as("gtsam", ori) == pytest.approx(phi**2)
    assert chi2_as("g2o", ori) == pytest.approx(math.sin(phi / 2) ** 2)
    info = np.zeros((6, 6))
    info[:3, :3] = np.eye(3)
    pos = one_edge(False, np.array([1.0, 2.0, 2.0]), rot_z(phi), info, EdgeKind.POSITION)
    assert all_chi2(pos) == {m: pytest.approx(9.0) for m in METRICS}


def test_h2o_is_the_package_chi2_and_unknown_metrics_are_refused() -> None:
    g = grid3d(20, seed=3).graph
    values = all_chi2(g)
    assert values["h2o"] == chi2(g)
    assert list(values) == list(METRICS)
    with pytest.raises(ValueError, match="unknown metric"):
        chi2_as("ceres", g)


@pytest.mark.parametrize("planar", [True, False])
def test_gtsam_metric_is_twice_gtsams_graph_error(planar: bool) -> None:
    gtsam = pytest.importorskip("gtsam")
    g = manhattan(80, seed=5).graph if planar else grid3d(30, seed=6).graph
    rng = np.random.default_rng(7)
    # Move the estimate well off the measurements so the conventions differ.
    R = g.R @ geo.so3_exp(rng.normal(0, 0.2, (g.num_nodes, 3)) * (
        np.array([0, 0, 1.0]) if planar else 1.0))
    t = g.t + rng.normal(0, 0.5, g.t.shape) * (np.array([1, 1, 0.0]) if planar else 1.0)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for i in range(g.num_nodes):
        if planar:
            values.insert(i, gtsam.Pose2(t[i, 0], t[i, 1], float(geo.matrix_to_yaw(R[i]))))
        else:
            values.insert(i, gtsam.Pose3(gtsam.Rot3(R[i]), t[i]))
    for e in np.flatnonzero(g.kind == EdgeKind.RELATIVE):
        a, b = int(g.a[e]), int(g.b[e])
        if planar:
            K = gtsam.Pose2(g.meas_t[e, 0], g.meas_t[e, 1], float(geo.matrix_to_yaw(g.meas_R[e])))
            info = g.info[e][np.ix_(geo.PLANAR_DOF, geo.PLANAR_DOF)]
            noise = gtsam.noiseModel.Gaussian.Information(info)
            graph.add(gtsam.BetweenFactorPose2(a, b, K, noise))
        else:
            K = gtsam.Pose3(gtsam.Rot3(g.meas_R[e]), g.meas_t[e])
            order = [3, 4, 5, 0, 1, 2]  # GTSAM's Pose3 tangent: rotation first
            noise = gtsam.noiseModel.Gaussian.Information(g.info[e][np.ix_(order, order)])
            graph.add(gtsam.BetweenFactorPose3(a, b, K, noise))
    assert chi2_as("gtsam", g, R, t) == pytest.approx(2.0 * graph.error(values), rel=1e-9)
    assert abs(chi2_as("h2o", g, R, t) / chi2_as("gtsam", g, R, t) - 1.0) > 1e-4
