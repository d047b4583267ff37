"""Small random pose graphs for solver tests (independent of h2o_slam.io.synthetic)."""

from __future__ import annotations

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, make_graph


def random_info(rng: np.random.Generator, dim: int) -> np.ndarray:
    G = rng.normal(size=(dim, dim))
    return G @ G.T + dim * np.eye(dim)


def random_pose(rng: np.random.Generator, planar: bool, spread: float = 1.0):
    if planar:
        t = np.zeros(3)
        t[:2] = rng.normal(scale=spread, size=2)
        return geo.yaw_to_matrix(rng.uniform(-np.pi, np.pi)), t
    return geo.so3_exp(rng.normal(size=3)), rng.normal(scale=spread, size=3)


def random_graph(
    seed: int,
    planar: bool,
    n: int = 8,
    loops: int = 4,
    gps: int = 0,
    orientation: int = 0,
    noise: float = 0.1,
) -> PoseGraph:
    """A chain of ``n`` poses with random loop closures and global edges; the estimate is a
    perturbed truth and measurements are noisy, so χ² > 0 at every point."""
    rng = np.random.default_rng(seed)
    R = np.zeros((n, 3, 3))
    t = np.zeros((n, 3))
    for i in range(n):
        R[i], t[i] = random_pose(rng, planar, spread=2.0)
    pairs = [(i, i + 1) for i in range(n - 1)]
    while len(pairs) < n - 1 + loops:
        i, j = sorted(rng.choice(n, size=2, replace=False))
        if j > i + 1:
            pairs.append((int(i), int(j)))
    kind, a, b, mR, mt, info = [], [], [], [], [], []
    dof = geo.PLANAR_DOF if planar else np.arange(6)
    for i, j in pairs:
        Rk, tk = geo.between(R[i], t[i], R[j], t[j])
        dR, dt = random_pose(rng, planar, spread=noise)
        dR = geo.so3_exp(geo.so3_log(dR) * noise)
        Rk, tk = geo.compose(Rk, tk, dR, dt)
        S = np.zeros((6, 6))
        S[np.ix_(dof, dof)] = random_info(rng, len(dof))
        kind.append(EdgeKind.RELATIVE)
        a.append(i)
        b.append(j)
        mR.append(Rk)
        mt.append(tk)
        info.append(S)
    for _ in range(gps):
        j = int(rng.integers(n))
        S = np.zeros((6, 6))
        rows = [0, 1] if planar else [0, 1, 2]
        S[np.ix_(rows, rows)] = random_info(rng, len(rows))
        tk = t[j] + np.where(np.isin(np.arange(3), rows), rng.normal(scale=noise, size=3), 0.0)
        kind.append(EdgeKind.POSITION)
        a.append(EARTH)
        b.append(j)
        mR.append(np.eye(3))
        mt.append(tk)
        info.append(S)
    for _ in range(orientation):
        j = int(rng.integers(n))
        S = np.zeros((6, 6))
        rows = [5] if planar else [3, 4, 5]
        S[np.ix_(rows, rows)] = random_info(rng, len(rows))
        kind.append(EdgeKind.ORIENTATION)
        a.append(EARTH)
        b.append(j)
        mR.append(R[j])
        mt.append(np.zeros(3))
        info.append(S)
    est_R = np.zeros_like(R)
    est_t = t.copy()
    for i in range(n):
        dR, dt = random_pose(rng, planar, spread=0.3)
        est_R[i] = R[i] @ geo.so3_exp(geo.so3_log(dR) * 0.3)
        est_t[i] = t[i] + dt
    return make_graph(
        planar, np.arange(n), est_R, est_t, np.array(kind), np.array(a), np.array(b),
        np.array(mR), np.array(mt), np.array(info),
    )


def loop_graph(seed: int, planar: bool, n: int, reverse: bool,
               closures: tuple[tuple[int, int], ...] = ()) -> PoseGraph:
    """A dead-reckoned chain of ``n`` poses (noisy odometry, its own start) closed by one
    edge from the last pose to the first (``reverse``) or the first to the last, after the
    other ``closures`` ``(a, b)``."""
    rng = np.random.default_rng(seed)
    dof = geo.PLANAR_DOF if planar else np.arange(6)
    truth_R, truth_t = [np.eye(3)], [np.zeros(3)]
    for _ in range(n - 1):
        yaw = rng.normal(0.0, 0.3)
        w = np.array([0.0, 0.0, yaw]) if planar else rng.normal(0.0, 0.1, 3) + [0, 0, yaw]
        step = np.array([1.0, rng.normal(0.0, 0.2), 0.0 if planar else rng.normal(0.0, 0.1)])
        R, t = geo.compose(truth_R[-1], truth_t[-1], geo.so3_exp(w), step)
        truth_R.append(R)
        truth_t.append(t)
    pairs = np.array([(i, i + 1) for i in range(n - 1)] + list(closures)
                     + [(n - 1, 0) if reverse else (0, n - 1)])
    a, b = pairs[:, 0], pairs[:, 1]
    m = len(pairs)
    R_ab, t_ab = geo.between(np.array(truth_R)[a], np.array(truth_t)[a],
                             np.array(truth_R)[b], np.array(truth_t)[b])
    w = rng.normal(0.0, 0.02, (m, 3)) * ([0, 0, 1] if planar else 1)
    noise_t = rng.normal(0.0, 0.05, (m, 3)) * ([1, 1, 0] if planar else 1)
    mR, mt = geo.compose(R_ab, t_ab, geo.so3_exp(w), noise_t)
    info = np.zeros((m, 6, 6))
    info[:, dof, dof] = rng.uniform(50.0, 400.0, (m, len(dof)))
    R0, t0 = geo.cumulative_compose(mR[:n - 1], mt[:n - 1])
    start_R = np.concatenate([np.eye(3)[None], R0])
    start_t = np.concatenate([np.zeros((1, 3)), t0])
    kind = np.full(m, EdgeKind.RELATIVE)
    return make_graph(planar, np.arange(n), start_R, start_t, kind, a,
                      b, mR, mt, info)
