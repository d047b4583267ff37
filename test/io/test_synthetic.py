"""Synthetic graphs: determinism, structure, noise statistics, and the command line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EdgeKind, chi2, odometry_chain
from h2o_slam.io import synthetic
from h2o_slam.io.g2o import read_g2o
from h2o_slam.io.synthetic import SyntheticGraph, grid3d, manhattan

GENERATORS = [manhattan, grid3d]


def constrained_dims(syn: SyntheticGraph) -> int:
    g = syn.graph
    rel = int(np.sum(g.kind == EdgeKind.RELATIVE))
    return rel * (3 if g.planar else 6) + syn.num_gps * (2 if g.planar else 3)


@pytest.mark.parametrize("make", GENERATORS)
def test_deterministic_from_seed(make) -> None:
    a, b, c = make(150, 7, gps_every=10), make(150, 7, gps_every=10), make(150, 8, gps_every=10)
    for name in ("kind", "a", "b", "meas_R", "meas_t", "info", "R", "t"):
        np.testing.assert_array_equal(getattr(a.graph, name), getattr(b.graph, name))
    np.testing.assert_array_equal(a.truth_t, b.truth_t)
    assert not np.array_equal(a.graph.meas_t[:50], c.graph.meas_t[:50])


@pytest.mark.parametrize("make", GENERATORS)
def test_structure(make) -> None:
    syn = make(200, 3)
    g = syn.graph
    assert g.num_nodes == 200
    assert syn.num_loop_closures > 20
    assert syn.num_gps == 0
    odo = (g.kind == EdgeKind.RELATIVE) & (g.b == g.a + 1)
    assert np.sum(odo) == 199
    # Loop closures point back in time, never to the previous pose.
    loops = (g.kind == EdgeKind.RELATIVE) & ~odo
    assert np.all(g.a[loops] < g.b[loops] - 1)
    # Loop closures join poses within the loop radius.
    dist = np.linalg.norm(syn.truth_t[g.a[loops]] - syn.truth_t[g.b[loops]], axis=1)
    assert np.all(dist <= (0.5 if g.planar else 1.0) + 1e-9)
    # Correlated noise: information matrices are full, not diagonal.
    S = g.info[0][np.ix_(g.dof, g.dof)]
    assert np.count_nonzero(S - np.diag(np.diag(S))) >= 2
    assert np.linalg.eigvalsh(S)[0] > 0
    assert len(g.clamped_edges) == 0
    # The truth starts at the origin like the odometry chain.
    np.testing.assert_allclose(syn.truth_R[0], np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(syn.truth_t[0], 0.0)


def test_manhattan_is_planar_on_a_grid() -> None:
    syn = manhattan(300, 5)
    g = syn.graph
    assert g.planar
    np.testing.assert_array_equal(syn.truth_t[:, 2], 0.0)
    np.testing.assert_array_equal(syn.truth_t[:, :2], np.round(syn.truth_t[:, :2]))
    steps = np.linalg.norm(np.diff(syn.truth_t, axis=0), axis=1)
    np.testing.assert_allclose(steps, 1.0)
    yaw = geo.matrix_to_yaw(syn.truth_R) / (np.pi / 2)
    np.testing.assert_allclose(yaw, np.round(yaw), atol=1e-12)
    assert len(np.unique(np.round(yaw) % 4)) == 4  # it turns
    np.testing.assert_array_equal(g.t[:, 2], 0.0)


def test_grid3d_walks_a_lattice_with_random_orientations() -> None:
    syn = grid3d(125, 0)
    assert not syn.graph.planar
    np.testing.assert_array_equal(syn.truth_t, np.round(syn.truth_t))
    steps = np.abs(np.diff(syn.truth_t, axis=0)).sum(axis=1)
    np.testing.assert_array_equal(steps, 1.0)
    assert syn.truth_t.min() == 0 and syn.truth_t.max() == 4  # a 5×5×5 cube
    angles = np.linalg.norm(geo.so3_log(syn.truth_R[1:]), axis=1)
    assert angles.mean() > 1.0


@pytest.mark.parametrize("make", GENERATORS)
@pytest.mark.parametrize("gps_every", [0, 4])
def test_chi2_at_truth_matches_degrees_of_freedom(make, gps_every: int) -> None:
    syn = make(400, 11, gps_every=gps_every)
    dof = constrained_dims(syn)
    c = chi2(syn.graph, syn.truth_R, syn.truth_t)
    # χ²(dof) has mean dof and standard deviation √(2 dof); 5σ never fails by chance.
    assert abs(c - dof) < 5 * np.sqrt(2 * dof)
    assert chi2(syn.graph) > c


@pytest.mark.parametrize("make", GENERATORS)
def test_gps_edges_when_asked(make) -> None:
    syn = make(101, 2, gps_every=10, gps_sigma_m=0.5)
    g = syn.graph
    gps = np.flatnonzero(g.kind == EdgeKind.POSITION)
    np.testing.assert_array_equal(g.b[gps], np.arange(0, 101, 10))
    axes = 2 if g.planar else 3
    np.testing.assert_allclose(g.info[gps[0]][:axes, :axes], np.eye(axes) / 0.25)
    err = g.meas_t[gps, :axes] - syn.truth_t[g.b[gps], :axes]
    assert 0.1 < np.std(err) < 1.5


@pytest.mark.parametrize("make", GENERATORS)
def test_estimate_is_the_odometry_chain(make) -> None:
    syn = make(300, 9)
    R, t = odometry_chain(syn.graph)
    np.testing.assert_allclose(syn.graph.R, R, atol=1e-13)
    np.testing.assert_array_equal(syn.graph.t, t)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(num_poses=1), "num_poses must be at least 2"),
        (dict(loop_probability=1.5), "loop_probability"),
        (dict(loop_radius_m=-1.0), "loop_radius_m"),
        (dict(gps_every=-2), "gps_every"),
        (dict(gps_sigma_m=0.0), "standard deviations must be positive"),
    ],
)
@pytest.mark.parametrize("make", GENERATORS)
def test_bad_arguments(make, kwargs: dict, match: str) -> None:
    args = dict(num_poses=10, seed=0) | kwargs
    with pytest.raises(InputError, match=match):
        make(**args)


def test_cli_writes_graph_and_truth(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "demo.g2o"
    assert synthetic.main([str(out), "--poses", "60", "--seed", "3", "--gps-every", "5"]) == 0
    assert "wrote" in capsys.readouterr().err
    g = read_g2o(out)
    truth = read_g2o(tmp_path / "demo.truth.g2o")
    syn = manhattan(60, 3, gps_every=5)
    np.testing.assert_array_equal(g.t, syn.graph.t)
    np.testing.assert_array_equal(g.meas_t, syn.graph.meas_t)
    np.testing.assert_array_equal(truth.t, syn.truth_t)
    assert chi2(truth) == pytest.approx(chi2(syn.graph, syn.truth_R, syn.truth_t), rel=1e-12)


def test_cli_3d_and_explicit_truth_path(tmp_path: Path) -> None:
    out, truth = tmp_path / "g3", tmp_path / "t.g2o"
    assert synthetic.main([str(out), "--3d", "--poses", "30", "--truth", str(truth)]) == 0
    g = read_g2o(out)
    assert not g.planar and g.num_nodes == 30
    assert read_g2o(truth).num_edges == g.num_edges


def test_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_info:
        synthetic.main([str(tmp_path / "x.g2o"), "--poses", "1"])
    assert exit_info.value.code == 2
    assert "num_poses must be at least 2" in capsys.readouterr().err
    assert synthetic.main([str(tmp_path / "missing" / "x.g2o")]) == 1
    assert "error:" in capsys.readouterr().err


def test_truth_path() -> None:
    assert synthetic.truth_path(Path("a/demo.g2o")) == Path("a/demo.truth.g2o")
    assert synthetic.truth_path(Path("graph")) == Path("graph.truth.g2o")
