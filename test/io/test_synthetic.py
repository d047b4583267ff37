"""Synthetic graphs: determinism, structure, noise statistics, and the command line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EdgeKind, chi2, odometry_chain
from h2o_slam.io import synthetic
from h2o_slam.io.g2o import read_g2o, write_g2o
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


# --- the large-noise sphere and the matched translation σ ---------------------------------------


def _residuals_at_truth(syn: SyntheticGraph) -> tuple[np.ndarray, np.ndarray]:
    """Each relative edge's error at the truth, ``(m, 3)`` translation (m) and ``(m, 3)``
    rotation (rad): the noise sample the generator drew."""
    g = syn.graph
    R, t = geo.between(syn.truth_R[g.a], syn.truth_t[g.a], syn.truth_R[g.b], syn.truth_t[g.b])
    dR, dt = geo.between(g.meas_R, g.meas_t, R, t)  # K⁻¹ T
    return dt, geo.so3_log(dR)


def test_sphere_is_deterministic_from_seed() -> None:
    a, b, c = synthetic.sphere(6, 10, 4), synthetic.sphere(6, 10, 4), synthetic.sphere(6, 10, 5)
    for name in ("kind", "a", "b", "meas_R", "meas_t", "info", "R", "t"):
        np.testing.assert_array_equal(getattr(a.graph, name), getattr(b.graph, name))
    np.testing.assert_array_equal(a.truth_R, b.truth_R)
    np.testing.assert_array_equal(a.truth_t, c.truth_t)  # same layout, other noise
    assert not np.array_equal(a.graph.meas_t, c.graph.meas_t)


def test_sphere_layout_like_create_sphere() -> None:
    rings, per_ring, radius = 8, 12, 10.0
    syn = synthetic.sphere(rings, per_ring, 0, radius_m=radius)
    g = syn.graph
    n = rings * per_ring
    assert not g.planar and g.num_nodes == n
    # Odometry along the rings; three closures to the previous ring from every pose but the
    # last ring's and the very last of the others: 3 (rings − 1) per_ring − 1.
    assert g.num_edges == (n - 1) + 3 * (rings - 1) * per_ring - 1
    assert syn.num_loop_closures == 3 * (rings - 1) * per_ring - 1
    np.testing.assert_array_equal(np.unique(g.b - g.a), [1, per_ring - 1, per_ring, per_ring + 1])
    assert np.all(g.kind == EdgeKind.RELATIVE)
    # Every pose on one sphere: the centre is pose 0's (radius, 0, 0) back along its x axis.
    centre = -radius * syn.truth_R[0][:, 0]
    np.testing.assert_allclose(np.linalg.norm(syn.truth_t - centre, axis=1), radius, rtol=1e-12)
    # Each pose's x axis points out of the sphere.
    out = (syn.truth_t - centre) / radius
    np.testing.assert_allclose(np.einsum("nij,ni->nj", syn.truth_R, out)[:, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(syn.truth_R[0], np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(syn.truth_t[0], 0.0)
    # Rotations are rotations; the start is the dead reckoning of the noisy odometry.
    np.testing.assert_allclose(np.linalg.det(syn.truth_R), 1.0, atol=1e-12)
    R, t = odometry_chain(g)
    np.testing.assert_allclose(g.R, R, atol=1e-13)
    np.testing.assert_array_equal(g.t, t)


def test_the_standard_large_noise_sphere_size() -> None:
    g = synthetic.sphere(44, 50, 0).graph
    assert (g.num_nodes, g.num_edges) == (2200, 8648)


@pytest.mark.parametrize("sigma", synthetic.LARGE_NOISE_SIGMAS_RAD)
def test_sphere_noise_has_the_stated_sigma(sigma: float) -> None:
    syn = synthetic.sphere(30, 40, 1, sigma_rot_rad=sigma)
    g = syn.graph
    step = np.mean(np.linalg.norm(np.diff(syn.truth_t, axis=0), axis=1))
    sigma_t = synthetic.matched_translation_sigma(sigma, float(step))
    dt, dtheta = _residuals_at_truth(syn)
    # 3 × 3500 samples per block: the sample σ is within 2 % of the true one (≈ 8 σ of its
    # own spread), zero-mean, and the axes are independent as the information says.
    np.testing.assert_allclose(np.std(dtheta, axis=0), sigma, rtol=0.03)
    np.testing.assert_allclose(np.std(dt, axis=0), sigma_t, rtol=0.03)
    assert np.all(np.abs(np.mean(dtheta, axis=0)) < 0.1 * sigma)
    corr = np.corrcoef(np.column_stack([dt, dtheta]).T)
    assert np.max(np.abs(corr - np.eye(6))) < 0.08
    # Information = the inverse of that covariance, on every edge.
    expect = np.diag(1.0 / np.array([sigma_t] * 3 + [sigma] * 3) ** 2)
    np.testing.assert_allclose(g.info, np.broadcast_to(expect, g.info.shape), rtol=1e-12)
    # χ² at the truth is χ²(6 m) distributed: the information matches the noise.
    dof = 6 * g.num_edges
    assert abs(chi2(g, syn.truth_R, syn.truth_t) - dof) < 5 * np.sqrt(2 * dof)


@pytest.mark.parametrize("sigma", [0.05, 0.3])
def test_grid3d_large_noise_has_the_stated_sigma(sigma: float) -> None:
    syn = grid3d(1500, 2, sigma_rot_rad=sigma,
                 sigma_xyz_m=synthetic.matched_translation_sigma(sigma, 1.0))
    dt, dtheta = _residuals_at_truth(syn)
    np.testing.assert_allclose(np.std(dtheta, axis=0), sigma, rtol=0.05)
    np.testing.assert_allclose(np.std(dt, axis=0), sigma, rtol=0.05)


def test_matched_translation_sigma() -> None:
    assert synthetic.matched_translation_sigma(0.2, 1.0) == pytest.approx(0.2)
    assert synthetic.matched_translation_sigma(0.1, 8.0) == pytest.approx(0.8)
    syn = synthetic.sphere(5, 8, 0, sigma_rot_rad=0.1, sigma_xyz_m=0.5)
    np.testing.assert_allclose(syn.graph.info[0].diagonal(), [4, 4, 4, 100, 100, 100])


def test_large_noise_start_is_far_from_the_truth() -> None:
    """At σ_R = 0.3 rad dead reckoning is far off: what the chordal start is for."""
    syn = synthetic.sphere(10, 20, 0, sigma_rot_rad=0.3)
    assert chi2(syn.graph) > 20 * chi2(syn.graph, syn.truth_R, syn.truth_t)


def test_sphere_written_g2o_reads_back(tmp_path: Path) -> None:
    syn = synthetic.sphere(6, 10, 3, sigma_rot_rad=0.2)
    path = tmp_path / "sphere.g2o"
    write_g2o(path, syn.graph)
    back = read_g2o(path)
    g = syn.graph
    for name in ("kind", "a", "b"):
        np.testing.assert_array_equal(getattr(back, name), getattr(g, name))
    np.testing.assert_allclose(back.meas_t, g.meas_t, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(back.meas_R, g.meas_R, atol=1e-12)
    np.testing.assert_allclose(back.t, g.t, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(back.R, g.R, atol=1e-12)
    np.testing.assert_allclose(back.info, g.info, rtol=1e-9)
    assert chi2(back) == pytest.approx(chi2(g), rel=1e-8)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(rings=1), "at least 2 rings of 3 poses"),
        (dict(per_ring=2), "at least 2 rings of 3 poses"),
        (dict(radius_m=0.0), "radius_m must be positive"),
        (dict(sigma_rot_rad=-0.1), "standard deviations must be positive"),
        (dict(sigma_xyz_m=float("nan")), "standard deviations must be positive"),
    ],
)
def test_sphere_bad_arguments(kwargs: dict, match: str) -> None:
    args = dict(rings=4, per_ring=5, seed=0) | kwargs
    with pytest.raises(InputError, match=match):
        synthetic.sphere(**args)
