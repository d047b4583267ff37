"""Seeded synthetic pose graphs with known ground truth, for tests, benchmarks and the demo.

Three generators, deterministic from their seed (``numpy.random.Generator``):

* :func:`manhattan` — a planar random walk on a 1 m grid with ±90° turns, in the manner of
  Olson's Manhattan world (M3500).
* :func:`grid3d` — a random walk on a 3-D lattice with a random orientation at every pose,
  in the manner of smallGrid3D.
* :func:`sphere` — rings of poses on a sphere, in the manner of g2o's ``create_sphere`` and
  the sphere graphs of Carlone, Tron, Daniilidis & Dellaert, "Initialization techniques for
  3D SLAM: a survey on rotation estimation and its use in pose graph optimization" (ICRA
  2015): odometry along the rings, loop closures to the neighbouring ring.

All add odometry edges ``(i, i+1)`` and loop closures to earlier poses nearby; the first two
optionally GPS position edges. For large noise (rotation σ of 0.05–0.3 rad, where a start
from dead reckoning is far from the optimum) :func:`matched_translation_sigma` gives the
translation σ that matches a rotation σ. Every measurement is made from the truth with
noise drawn from the covariance its information matrix states, such that the edge's error
at the truth *is* that noise sample: χ² at the truth follows a χ² distribution with as many
degrees of freedom as the edges constrain (3 per planar relative edge, 6 per 3-D one, 2 or
3 per GPS edge). The graph's estimate is the noisy odometry chain (dead reckoning, as a
file's vertices would be).

Command line (used by the demo)::

    python -m h2o_slam.io.synthetic OUT.g2o [--poses N] [--seed S] [--3d]
                                 [--gps-every K] [--gps-sigma S] [--truth PATH]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, make_graph, odometry_chain
from h2o_slam.io.g2o import write_g2o

#: Probability that the Manhattan walk turns (left or right, evenly) at a pose.
TURN_PROBABILITY = 0.3

# Correlations of the relative-pose noise, so that information matrices are not diagonal
# (the case LAGO's structured-covariance handling and the solvers must get right).
_PLANAR_CORR = np.array([[1.0, 0.2, 0.0], [0.2, 1.0, 0.3], [0.0, 0.3, 1.0]])  # x, y, yaw
_SPATIAL_CORR = np.eye(6)
_SPATIAL_CORR[0, 1] = _SPATIAL_CORR[1, 0] = 0.2  # x - y
_SPATIAL_CORR[1, 5] = _SPATIAL_CORR[5, 1] = 0.3  # y - rot z
_SPATIAL_CORR[2, 3] = _SPATIAL_CORR[3, 2] = -0.1  # z - rot x

_STEPS_2D = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])  # heading k·90°
_STEPS_3D = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])

#: The rotation noise levels (σ per axis, rad) of the large-noise 3-D benchmarks.
LARGE_NOISE_SIGMAS_RAD = (0.05, 0.1, 0.2, 0.3)


@dataclass(frozen=True)
class SyntheticGraph:
    """A synthetic graph and the truth it was made from.

    Attributes:
        graph: the graph; its estimate is the noisy odometry chain.
        truth_R: true world rotations, shape ``(N, 3, 3)``.
        truth_t: true world positions in m, shape ``(N, 3)``.
    """

    graph: PoseGraph
    truth_R: Array
    truth_t: Array

    @property
    def num_loop_closures(self) -> int:
        """Relative edges that are not odometry ``(i, i+1)``."""
        g = self.graph
        return int(np.sum((g.kind == EdgeKind.RELATIVE) & (g.b != g.a + 1)))

    @property
    def num_gps(self) -> int:
        """GPS (position) edges."""
        return int(np.sum(self.graph.kind == EdgeKind.POSITION))


def manhattan(
    num_poses: int,
    seed: int,
    *,
    loop_probability: float = 0.5,
    loop_radius_m: float = 0.5,
    sigma_xy_m: float = 0.05,
    sigma_yaw_rad: float = 0.01,
    gps_every: int = 0,
    gps_sigma_m: float = 1.0,
) -> SyntheticGraph:
    """Planar Manhattan-world graph: a walk of 1 m steps on a grid, turning ±90° at random.

    The walk stays in a square of about ``√num_poses / 2`` m a side so that it keeps
    revisiting places. At each pose, with probability ``loop_probability``, one loop
    closure is added to a random earlier pose (not the previous one) within
    ``loop_radius_m`` (the default 0.5 m means the same grid point).

    Args:
        num_poses: number of poses (≥ 2).
        seed: seed of the random generator.
        loop_probability: chance of a loop closure at a pose that has candidates.
        loop_radius_m: largest distance between the poses of a loop closure.
        sigma_xy_m: standard deviation of the translational noise of relative edges.
        sigma_yaw_rad: standard deviation of their yaw noise (x–y and y–yaw correlated).
        gps_every: a GPS edge at poses ``0, K, 2K, …`` (0: none).
        gps_sigma_m: standard deviation of GPS noise per axis.
    """
    _check_args(num_poses, loop_probability, loop_radius_m, gps_every,
                (sigma_xy_m, sigma_yaw_rad, gps_sigma_m))
    rng = np.random.default_rng(seed)
    half = max(2, round(np.sqrt(num_poses) / 4))
    cells = np.zeros((num_poses, 2), dtype=np.int64)
    heading = np.zeros(num_poses, dtype=np.int64)
    for k in range(1, num_poses):
        cells[k] = cells[k - 1] + _STEPS_2D[heading[k - 1]]
        turn = rng.choice([0, 1, -1], p=[1 - TURN_PROBABILITY, *[TURN_PROBABILITY / 2] * 2])
        others = rng.permutation([d for d in (0, 1, -1) if d != turn])
        # Leaving the square is not an option; a U-turn (always possible) is the last resort.
        for d in (turn, *others, 2):
            nxt = cells[k] + _STEPS_2D[(heading[k - 1] + d) % 4]
            if np.all(np.abs(nxt) <= half):
                heading[k] = (heading[k - 1] + d) % 4
                break
    truth_t = np.zeros((num_poses, 3))
    truth_t[:, :2] = cells
    truth_yaw = geo.wrap_angle(heading.astype(float) * (np.pi / 2))
    truth_R = geo.yaw_to_matrix(truth_yaw)

    sigma = np.array([sigma_xy_m, sigma_xy_m, sigma_yaw_rad])
    cov = sigma[:, None] * _PLANAR_CORR * sigma[None, :]
    pairs = _edge_plan(rng, truth_t, loop_probability, loop_radius_m, gps_every)
    return _assemble(rng, True, truth_R, truth_t, pairs, cov, gps_sigma_m)


def grid3d(
    num_poses: int,
    seed: int,
    *,
    loop_probability: float = 0.5,
    loop_radius_m: float = 1.0,
    sigma_xyz_m: float = 0.05,
    sigma_rot_rad: float = 0.01,
    gps_every: int = 0,
    gps_sigma_m: float = 1.0,
) -> SyntheticGraph:
    """3-D lattice graph: a walk of 1 m steps along the axes with random orientations.

    The walk stays in a cube of ``⌈num_poses^(1/3)⌉`` lattice points a side; pose 0 is the
    identity, every other pose has a uniformly random orientation. Loop closures as in
    :func:`manhattan` (default radius 1 m: the same or a neighbouring lattice point).

    Args:
        num_poses: number of poses (≥ 2).
        seed: seed of the random generator.
        loop_probability: chance of a loop closure at a pose that has candidates.
        loop_radius_m: largest distance between the poses of a loop closure.
        sigma_xyz_m: standard deviation of the translational noise of relative edges.
        sigma_rot_rad: standard deviation of their rotation noise per axis (some axes
            correlated).
        gps_every: a GPS edge at poses ``0, K, 2K, …`` (0: none).
        gps_sigma_m: standard deviation of GPS noise per axis.
    """
    _check_args(num_poses, loop_probability, loop_radius_m, gps_every,
                (sigma_xyz_m, sigma_rot_rad, gps_sigma_m))
    rng = np.random.default_rng(seed)
    side = max(2, int(np.ceil(num_poses ** (1.0 / 3.0) - 1e-9)))
    cells = np.zeros((num_poses, 3), dtype=np.int64)
    for k in range(1, num_poses):
        for d in rng.permutation(len(_STEPS_3D)):
            nxt = cells[k - 1] + _STEPS_3D[d]
            if np.all((nxt >= 0) & (nxt < side)):
                cells[k] = nxt
                break
    truth_t = cells.astype(float)
    quats = rng.standard_normal((num_poses, 4))
    quats[0] = [0.0, 0.0, 0.0, 1.0]
    truth_R = geo.quat_to_matrix(quats)

    sigma = np.array([sigma_xyz_m] * 3 + [sigma_rot_rad] * 3)
    cov = sigma[:, None] * _SPATIAL_CORR * sigma[None, :]
    pairs = _edge_plan(rng, truth_t, loop_probability, loop_radius_m, gps_every)
    return _assemble(rng, False, truth_R, truth_t, pairs, cov, gps_sigma_m)


def sphere(
    rings: int,
    per_ring: int,
    seed: int,
    *,
    radius_m: float = 100.0,
    sigma_rot_rad: float = 0.05,
    sigma_xyz_m: float | None = None,
) -> SyntheticGraph:
    """Sphere graph: ``rings × per_ring`` poses on a sphere, as g2o's ``create_sphere`` lays
    them out (the standard sphere benchmarks; 44 × 50 is the size of the 2,200-pose
    large-noise sphere).

    Pose ``k = f·per_ring + i`` (ring ``f``, place ``i``) is ``Rz(−π + 2πi / per_ring) ·
    Ry(−π/2 + (k + 1)·π / (rings·per_ring))`` with its x axis pointing out of the sphere
    (position ``R · (radius_m, 0, 0)``), so the poses spiral from the south pole to the north
    pole; the truth is expressed in pose 0's frame (pose 0 is the identity). Odometry joins
    ``k`` and ``k + 1`` (along a ring, and from each ring's last pose to the next ring's
    first); loop closures join ``k`` to ``k + per_ring − 1``, ``k + per_ring`` and
    ``k + per_ring + 1`` (the neighbouring ring), as in ``create_sphere``.

    Noise: independent, ``sigma_rot_rad`` per rotation axis and ``sigma_xyz_m`` per
    translation axis (default :func:`matched_translation_sigma` of the mean odometry step);
    information = the inverse of that diagonal covariance.

    Args:
        rings: number of rings (≥ 2).
        per_ring: poses per ring (≥ 3).
        seed: seed of the random generator.
        radius_m: radius of the sphere in m.
        sigma_rot_rad: standard deviation of the rotation noise per axis in rad.
        sigma_xyz_m: standard deviation of the translation noise per axis in m (None: matched
            to ``sigma_rot_rad``).

    Raises:
        InputError: a size below its minimum, or a radius or σ that is not positive.
    """
    if rings < 2 or per_ring < 3:
        raise InputError(f"a sphere needs at least 2 rings of 3 poses, got {rings} × {per_ring}")
    if not (np.isfinite(radius_m) and radius_m > 0.0):
        raise InputError(f"radius_m must be positive, got {radius_m}")
    n = rings * per_ring
    k = np.arange(n)
    yaw = -np.pi + 2.0 * np.pi * (k % per_ring) / per_ring
    pitch = -0.5 * np.pi + (k + 1) * np.pi / n
    zero = np.zeros(n)
    world_R = geo.so3_exp(np.column_stack([zero, zero, yaw])) @ geo.so3_exp(
        np.column_stack([zero, pitch, zero]))
    world_t = world_R[:, :, 0] * radius_m
    # In pose 0's frame, as the odometry chain starts there.
    truth_R, truth_t = geo.between(world_R[:1], world_t[:1], world_R, world_t)
    truth_R = geo.orthonormalize(truth_R)
    truth_t[0] = 0.0
    truth_R[0] = np.eye(3)
    if sigma_xyz_m is None:
        step_m = float(np.mean(np.linalg.norm(np.diff(truth_t, axis=0), axis=1)))
        sigma_xyz_m = matched_translation_sigma(sigma_rot_rad, step_m)
    _check_args(n, 0.0, 0.0, 0, (sigma_xyz_m, sigma_rot_rad))
    rng = np.random.default_rng(seed)
    plan: list[tuple[int, int]] = []
    for b in range(1, n):
        plan.append((b - 1, b))
        for gap in (per_ring + 1, per_ring, per_ring - 1):
            a = b - gap
            # create_sphere closes from every pose of a ring but the last ring's.
            if 0 <= a < (rings - 1) * per_ring:
                plan.append((a, b))
    cov = np.diag(np.array([sigma_xyz_m] * 3 + [sigma_rot_rad] * 3) ** 2)
    return _assemble(rng, False, truth_R, truth_t, plan, cov, 1.0)


def matched_translation_sigma(sigma_rot_rad: float, step_m: float) -> float:
    """The translation σ (m) that matches a rotation σ (rad) on steps of ``step_m`` m: a
    heading error of ``sigma_rot_rad`` displaces the end of a step by about
    ``sigma_rot_rad · step_m``, so translation and rotation noise weigh alike in χ² (on
    the 1 m steps of :func:`grid3d`, σ_t in m equals σ_R in rad)."""
    return sigma_rot_rad * step_m


def _check_args(
    num_poses: int, loop_probability: float, loop_radius_m: float, gps_every: int,
    sigmas: tuple[float, ...],
) -> None:
    if num_poses < 2:
        raise InputError(f"num_poses must be at least 2, got {num_poses}")
    if not 0.0 <= loop_probability <= 1.0:
        raise InputError(f"loop_probability must be in [0, 1], got {loop_probability}")
    if not loop_radius_m >= 0.0:
        raise InputError(f"loop_radius_m must be non-negative, got {loop_radius_m}")
    if gps_every < 0:
        raise InputError(f"gps_every must be non-negative, got {gps_every}")
    if not all(np.isfinite(s) and s > 0.0 for s in sigmas):
        raise InputError(f"noise standard deviations must be positive, got {sigmas}")


def _edge_plan(
    rng: np.random.Generator, truth_t: Array, loop_probability: float, loop_radius_m: float,
    gps_every: int,
) -> list[tuple[int, int]]:
    """Edges ``(a, b)`` in arrival order; ``a`` is :data:`EARTH` for GPS edges."""
    plan: list[tuple[int, int]] = []
    for k in range(len(truth_t)):
        if k > 0:
            plan.append((k - 1, k))
        if k >= 2 and rng.random() < loop_probability:
            # A small tolerance so that lattice neighbours at exactly the radius count.
            dist = np.linalg.norm(truth_t[: k - 1] - truth_t[k], axis=1)
            near = np.flatnonzero(dist <= loop_radius_m + 1e-9)
            if len(near):
                plan.append((int(rng.choice(near)), k))
        if gps_every and k % gps_every == 0:
            plan.append((EARTH, k))
    return plan


def _assemble(
    rng: np.random.Generator, planar: bool, truth_R: Array, truth_t: Array,
    plan: list[tuple[int, int]], cov: Array, gps_sigma_m: float,
) -> SyntheticGraph:
    n, m = len(truth_t), len(plan)
    a = np.array([p[0] for p in plan], dtype=np.int64)
    b = np.array([p[1] for p in plan], dtype=np.int64)
    kind = np.where(a == EARTH, EdgeKind.POSITION, EdgeKind.RELATIVE).astype(np.int8)
    meas_R = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    meas_t = np.zeros((m, 3))
    info = np.zeros((m, 6, 6))

    rel = np.flatnonzero(kind == EdgeKind.RELATIVE)
    rows = geo.PLANAR_DOF if planar else np.arange(6)
    noise = rng.standard_normal((len(rel), len(rows))) @ np.linalg.cholesky(cov).T
    ra, rb = a[rel], b[rel]
    true_R, true_t = geo.between(truth_R[ra], truth_t[ra], truth_R[rb], truth_t[rb])
    # K = T · E⁻¹ with E = (Exp(δθ), δt) makes the error of K at the truth, the
    # [t; Log R] of K⁻¹ T = E, equal to the noise sample δ itself.
    if planar:
        # Built from an angle so that the measurement is an exact yaw matrix, which the
        # g2o writer reproduces bit for bit.
        mR = geo.yaw_to_matrix(geo.wrap_angle(geo.matrix_to_yaw(true_R) - noise[:, 2]))
        dt = np.column_stack([noise[:, :2], np.zeros(len(rel))])
    else:
        mR = true_R @ np.swapaxes(geo.so3_exp(noise[:, 3:]), -1, -2)
        dt = noise[:, :3]
    meas_R[rel] = mR
    meas_t[rel] = true_t - np.einsum("mij,mj->mi", mR, dt)
    info[np.ix_(rel, rows, rows)] = np.linalg.inv(cov)

    gps = np.flatnonzero(kind == EdgeKind.POSITION)
    axes = np.arange(2 if planar else 3)
    meas_t[np.ix_(gps, axes)] = truth_t[np.ix_(b[gps], axes)] + gps_sigma_m * rng.standard_normal(
        (len(gps), len(axes))
    )
    info[np.ix_(gps, axes, axes)] = np.eye(len(axes)) / gps_sigma_m**2

    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    graph = make_graph(planar, np.arange(n), eye, np.zeros((n, 3)), kind, a, b,
                       meas_R, meas_t, info)
    R, t = odometry_chain(graph)
    # The chain drifts off orthonormality by ~√n ulps; snap it back (an ulp-level change)
    # so that g2o files round-trip: bitwise for exact yaw matrices, ~1e-15 via quaternions.
    R = geo.yaw_to_matrix(geo.matrix_to_yaw(R)) if planar else geo.orthonormalize(R)
    graph.R, graph.t = R, t
    return SyntheticGraph(graph, truth_R, truth_t)


def add_gps(
    graph: PoseGraph, truth_t: Array, every: int, sigma_m: float, seed: int = 0
) -> PoseGraph:
    """A copy of ``graph`` with a GPS position edge at poses ``0, every, 2·every, …``.

    Each fix is ``truth_t`` of its pose plus Gaussian noise of ``sigma_m`` per axis (x, y for
    planar graphs), with the matching information matrix. Used to run experiments like the
    thesis' GPS-augmented Paris graphs on any graph, taking its optimum as the truth.

    Raises:
        InputError: ``every`` is not positive or ``sigma_m`` is not positive and finite.
    """
    if every < 1:
        raise InputError(f"--gps-every must be at least 1, got {every}")
    if not (np.isfinite(sigma_m) and sigma_m > 0.0):
        raise InputError(f"--gps-sigma must be positive, got {sigma_m}")
    rng = np.random.default_rng(seed)
    nodes = np.arange(0, graph.num_nodes, every)
    axes = np.arange(2 if graph.planar else 3)
    meas_t = np.zeros((len(nodes), 3))
    meas_t[:, axes] = truth_t[np.ix_(nodes, axes)] + sigma_m * rng.standard_normal(
        (len(nodes), len(axes)))
    info = np.zeros((len(nodes), 6, 6))
    info[np.ix_(np.arange(len(nodes)), axes, axes)] = np.eye(len(axes)) / sigma_m**2
    return graph.with_edges(EdgeKind.POSITION, np.full(len(nodes), EARTH), nodes,
                            np.broadcast_to(np.eye(3), (len(nodes), 3, 3)), meas_t, info)


def truth_path(out: Path) -> Path:
    """Where the command line writes the ground truth for the graph file ``out``."""
    if out.suffix == ".g2o":
        return out.with_suffix(".truth.g2o")
    return out.with_name(out.name + ".truth.g2o")


def main(argv: list[str] | None = None) -> int:
    """Command line: write a synthetic graph and its ground truth as g2o files."""
    parser = argparse.ArgumentParser(
        prog="python -m h2o_slam.io.synthetic",
        description="Write a seeded synthetic pose graph (noisy odometry start) to OUT, and "
        "the same graph with its vertices at the ground truth to OUT with .g2o replaced by "
        ".truth.g2o (e.g. demo.g2o -> demo.truth.g2o), or to --truth.",
    )
    parser.add_argument("out", type=Path, metavar="OUT.g2o", help="graph file to write")
    parser.add_argument("--poses", type=int, default=500, help="number of poses (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--3d", dest="three_d", action="store_true",
                        help="3-D lattice walk (grid3d) instead of the planar Manhattan world")
    parser.add_argument("--gps-every", type=int, default=0, metavar="K",
                        help="a GPS position edge every K poses (default 0: none)")
    parser.add_argument("--gps-sigma", type=float, default=1.0, metavar="S",
                        help="GPS standard deviation per axis in m (default 1.0)")
    parser.add_argument("--truth", type=Path, default=None, metavar="PATH",
                        help="ground-truth file (default: OUT with .truth.g2o)")
    args = parser.parse_args(argv)
    make = grid3d if args.three_d else manhattan
    try:
        syn = make(args.poses, args.seed, gps_every=args.gps_every, gps_sigma_m=args.gps_sigma)
    except InputError as err:
        parser.error(str(err))
    truth = args.truth if args.truth is not None else truth_path(args.out)
    try:
        write_g2o(args.out, syn.graph)
        write_g2o(truth, syn.graph, syn.truth_R, syn.truth_t)
    except OSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    g = syn.graph
    print(f"wrote {args.out}: {g.num_nodes} poses, {g.num_edges} edges "
          f"({syn.num_loop_closures} loop closures, {syn.num_gps} GPS); truth in {truth}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
