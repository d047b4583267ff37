"""Global-optimality certificate of a pose-graph solution: SE-Sync's Lagrangian-duality test.

The problem certified is SE-Sync's (D. M. Rosen, L. Carlone, A. S. Bandeira and
J. J. Leonard, "SE-Sync: A certifiably correct algorithm for synchronization over the
special Euclidean group", IJRR 2019; the duality test of L. Carlone, D. M. Rosen,
G. Calafiore, J. J. Leonard and F. Dellaert, "Lagrangian duality in 3D SLAM: verification
techniques and optimal solutions", IROS 2015): over rotations ``R_i ∈ SO(d)`` and
translations ``t_i ∈ Rᵈ`` (``d = 2`` for planar graphs, 3 otherwise), minimize the chordal
cost

    F(R, t) = Σ_e κ_e ‖R_j − R_i R̃_e‖²_F + τ_e ‖t_j − t_i − R_i t̃_e‖²

with one rotation weight ``κ_e`` and one translation weight ``τ_e`` per edge ``e = (i, j)``
measuring ``(R̃_e, t̃_e)``. The weights come from the edge's information matrix ``Ω`` by
SE-Sync's rule for 3-D graphs (its g2o reader), used here for planar graphs too:
``τ = d / tr(Ω_tt⁻¹)`` and ``κ = p / (2 tr(Ω_rr⁻¹))`` with ``Ω_tt`` the ``d × d``
translation block, ``Ω_rr`` the ``p × p`` rotation block (``p`` = 1 planar, 3 in 3-D): the
harmonic means of each block's eigenvalues (exactly SE-Sync's planar ``τ``; its planar
reader takes ``κ = Ω_θθ``, twice ours). The ½ makes ``F`` equal the g2o χ² to second order
in the errors when ``Ω = diag(τ I_d, 2κ I_p)`` (``‖R − R Exp(φ)‖²_F ≈ 2‖φ‖²``): a graph
whose information is isotropic per block is exactly SE-Sync's problem with these weights;
off-diagonal information (correlations between axes, anisotropy) is left out of ``F``.

GPS and compass edges (``POSITION`` / ``ORIENTATION``, :mod:`h2o_slam.core.graph`) are
relative edges to one extra node, the earth frame, whose pose is the identity in the
solution: a GPS fix is an edge with ``κ = 0`` and ``t̃`` the fix, a compass edge one with
``τ = 0`` and ``R̃`` the measured rotation. ``F`` and the certificate below are invariant
under one rigid motion of every node, the earth included, so the earth-fixed solution is
certified as it stands.

The certificate (SE-Sync §4): with ``X = [R_1 … R_n]`` (``d × dn``) the translations are
eliminated in closed form, ``min_t F = tr(Q XᵀX)`` with

    Q = L(G̃^ρ) + Σ̃ − Ṽᵀ L(W^τ)† Ṽ        (dn × dn)

(``L(G̃^ρ)`` the rotation connection Laplacian, ``L(W^τ)`` the translation-weighted graph
Laplacian, ``Σ̃`` and ``Ṽ`` the translation data; :class:`ReducedProblem` builds them).
``Q`` is never formed: :class:`ReducedProblem` applies it with one sparse factorization of
``L(W^τ)`` with a node of each connected component held at zero. At a critical point
``X̂``, ``Λ = SymBlockDiag(Q X̂ᵀ X̂)`` and ``S = Q − Λ``. For any ``X`` in ``SO(d)ⁿ``,
``tr(Q XᵀX) = tr(S XᵀX) + tr(Λ) ≥ λ_min(S)·dn + tr(Λ)`` and ``tr(Λ) = F(X̂)``, so

    F(X̂) − F* ≤ max(0, −λ_min(S)) · d · n        (the suboptimality bound)

and ``S ⪰ 0`` makes ``X̂`` a global minimizer (of ``F`` and of its semidefinite
relaxation). ``X̂`` is *certified* when ``λ_min(S) ≥ −η``, ``η`` = :data:`EIG_TOLERANCE` ×
the largest diagonal entry of ``L(G̃^ρ) + Σ̃`` (see :func:`tolerance`).

What is certified, and what is not:

* h2o's solution minimizes the g2o χ² (geodesic errors, full information), not ``F``; it
  is not a critical point of ``F``, so it is first refined on ``F`` by Levenberg–Marquardt
  on ``SO(d)ⁿ × Rᵈⁿ`` started from it (:func:`refine`), and the *refined* point is the one
  certified: certified means it is the global minimum of ``F`` to within ``η·d·n``.
* The report says how far the refined point lies from h2o's (largest rotation angle and
  translation, each node's first-node or earth gauge kept) and the g2o χ² of both. A
  certified refined point close to h2o's, with nearly equal χ², is evidence that h2o found
  the basin of the global optimum of the χ² too, not a proof: the χ² is not ``F``.
* A point that is not certified may still be globally optimal (the relaxation is not
  always exact; SE-Sync's Riemannian staircase would climb to a higher rank, which is not
  done here); ``λ_min`` and the suboptimality bound still bound how far its ``F`` can be
  above the optimum.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from h2o_slam.core import geometry as geo
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EdgeKind, PoseGraph, edge_chi2
from h2o_slam.core.spd import SPDFactor, symmetric_lu, upper

#: ``η`` relative to the largest diagonal entry of ``L(G̃^ρ) + Σ̃`` (an upper bound of
#: ``‖S‖`` up to a factor of the largest degree). SE-Sync's own defaults are absolute,
#: 1e-4 (C++) and 1e-3 (MATLAB), for its benchmark graphs, whose diagonals are ~10²–10⁴;
#: 1e-6 of the diagonal gives that range there and scales with the information. The
#: refinement's residual gradient and rounding put ``λ_min`` of a certified point within
#: 1e-15 of the diagonal (|λ_min| ≤ 2e-12 on the public graphs intel, manhattan,
#: city10000, sphere2500, smallGrid3D and parking-garage), far inside it, while a planted
#: local minimum's is -0.1 of it or lower (test/core/test_certificate.py).
EIG_TOLERANCE = 1e-6

#: Most Levenberg–Marquardt iterations of the refinement on ``F``.
REFINE_ITERATIONS = 50

#: The refinement stops when no coordinate of a step exceeds this (rad, or m per m of the
#: graph's largest measured translation).
REFINE_STEP = 1e-11


@dataclass(frozen=True)
class SyncProblem:
    """SE-Sync's problem data (module docstring).

    Attributes:
        d: dimension of the poses (2 planar, 3 otherwise).
        n: nodes, the earth frame included as the last node when ``earth``.
        i, j: endpoints of each edge, shape ``(m,)``; the edge measures ``X_i⁻¹ X_j``.
        R, t: measurement of each edge, shapes ``(m, d, d)`` and ``(m, d)`` (m).
        kappa: rotation weight of each edge, shape ``(m,)`` (1/rad², ≥ 0).
        tau: translation weight of each edge, shape ``(m,)`` (1/m², ≥ 0).
        earth: the last node is the earth frame (the graph has GPS or compass edges).
    """

    d: int
    n: int
    i: np.ndarray
    j: np.ndarray
    R: Array
    t: Array
    kappa: Array
    tau: Array
    earth: bool

    @property
    def p(self) -> int:
        """Rotation degrees of freedom per node (1 planar, 3 otherwise)."""
        return 1 if self.d == 2 else 3


def sync_problem(graph: PoseGraph, keep: np.ndarray | None = None) -> SyncProblem:
    """SE-Sync's problem for the edges ``keep`` (a boolean mask; default: every edge) of
    ``graph``, weights from each edge's information (module docstring)."""
    edges = np.arange(graph.num_edges) if keep is None else np.flatnonzero(keep)
    d = 2 if graph.planar else 3
    p = 1 if graph.planar else 3
    kind = graph.kind[edges]
    absolute = kind != EdgeKind.RELATIVE
    earth = bool(np.any(absolute))
    n = graph.num_nodes + int(earth)
    i = np.where(absolute, n - 1, graph.a[edges])
    j = graph.b[edges].copy()
    R = graph.meas_R[edges][:, :d, :d].copy()
    t = graph.meas_t[edges][:, :d].copy()
    R[kind == EdgeKind.POSITION] = np.eye(d)  # a GPS fix measures no rotation
    t[kind == EdgeKind.ORIENTATION] = 0.0  # a compass no translation
    info = graph.info[edges]
    trans = np.arange(d)
    rot = np.array([5]) if graph.planar else np.arange(3, 6)
    tau = np.zeros(len(edges))
    kappa = np.zeros(len(edges))
    has_t = kind != EdgeKind.ORIENTATION
    has_r = kind != EdgeKind.POSITION
    if np.any(has_t):
        cov = np.linalg.inv(info[np.ix_(np.flatnonzero(has_t), trans, trans)])
        tau[has_t] = d / np.trace(cov, axis1=1, axis2=2)
    if np.any(has_r):
        cov = np.linalg.inv(info[np.ix_(np.flatnonzero(has_r), rot, rot)])
        kappa[has_r] = p / (2.0 * np.trace(cov, axis1=1, axis2=2))
    return SyncProblem(d, n, i, j, R, t, kappa, tau, earth)


def sync_poses(graph: PoseGraph, problem: SyncProblem, R: Array, t: Array
               ) -> tuple[Array, Array]:
    """The graph's poses ``(R, t)`` (shapes ``(N, 3, 3)``, ``(N, 3)``) as the problem's,
    shapes ``(n, d, d)`` and ``(n, d)``, the earth frame (identity) appended when present."""
    d = problem.d
    Rs, ts = np.asarray(R, float)[:, :d, :d], np.asarray(t, float)[:, :d]
    if problem.earth:
        Rs = np.concatenate([Rs, np.eye(d)[None]])
        ts = np.concatenate([ts, np.zeros((1, d))])
    return Rs, ts


def graph_poses(graph: PoseGraph, problem: SyncProblem, R: Array, t: Array
                ) -> tuple[Array, Array]:
    """The inverse of :func:`sync_poses`: the problem's poses as the graph's, shapes
    ``(N, 3, 3)`` and ``(N, 3)`` (planar ones about z at z = 0)."""
    N, d = graph.num_nodes, problem.d
    R3 = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
    t3 = np.zeros((N, 3))
    R3[:, :d, :d] = R[:N]
    t3[:, :d] = t[:N]
    return R3, t3


def sesync_cost(problem: SyncProblem, R: Array, t: Array) -> float:
    """``F(R, t)`` (module docstring) at poses of shapes ``(n, d, d)`` and ``(n, d)``."""
    rot, trans = _residuals(problem, R, t)
    return float(np.sum(rot**2) + np.sum(trans**2))


def _generators(d: int) -> Array:
    """Infinitesimal rotations: ``(1, 2, 2)`` about z for planar, ``(3, 3, 3)`` otherwise."""
    if d == 2:
        return np.array([[[0.0, -1.0], [1.0, 0.0]]])
    return geo.hat(np.eye(3))


def _retract(R: Array, phi: Array) -> Array:
    """``R Exp(φ)`` for rotations ``(n, d, d)`` and steps ``(n, p)`` (rad)."""
    if R.shape[-1] == 2:
        c, s = np.cos(phi[:, 0]), np.sin(phi[:, 0])
        step = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        return R @ step
    return R @ geo.so3_exp(phi)


def _anchors(n: int, i: np.ndarray, j: np.ndarray, prefer_last: bool) -> np.ndarray:
    """One node of each connected component of the graph on ``n`` nodes with edges
    ``(i, j)``: the last node (the earth) in its own component when ``prefer_last``, else
    the first."""
    adjacency = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    _, labels = connected_components(adjacency, directed=False)
    order = np.r_[n - 1, np.arange(n - 1)] if prefer_last else np.arange(n)
    _, first = np.unique(labels[order], return_index=True)
    return np.sort(order[first])


@dataclass(frozen=True)
class Refined:
    """Outcome of :func:`refine`.

    Attributes:
        R, t: refined poses, shapes ``(n, d, d)`` and ``(n, d)``.
        cost: ``F`` at them.
        iterations: Levenberg–Marquardt steps accepted.
        converged: the last step was below :data:`REFINE_STEP` (or no step lowered ``F``
            at the start: already a minimum to working precision).
    """

    R: Array
    t: Array
    cost: float
    iterations: int
    converged: bool


def refine(problem: SyncProblem, R: Array, t: Array,
           iterations: int = REFINE_ITERATIONS) -> Refined:
    """Minimize ``F`` locally from ``(R, t)`` (shapes ``(n, d, d)``, ``(n, d)``): Newton's
    method with Levenberg–Marquardt damping on ``SO(d)ⁿ × Rᵈⁿ``, steps
    ``R_i ← R_i Exp(φ_i)``, ``t_i ← t_i + δ_i``.

    One node per connected component (the earth frame in its own) is held where it is, so
    the result keeps the start's gauge. The Hessian is Gauss–Newton's ``JᵀJ`` plus the
    curvature of ``Exp`` weighed by the residuals (:func:`_newton_system`): Gauss–Newton
    alone converges only linearly here (ratio ~0.7 per step on intel and sphere2500, whose
    residuals are not small), Newton quadratically.
    """
    d, p = problem.d, problem.p
    k = d + p
    anchors = _anchors(problem.n, problem.i, problem.j, problem.earth)
    free = np.ones(problem.n * k, dtype=bool)
    free[(anchors[:, None] * k + np.arange(k)).ravel()] = False
    scale = 1.0 + float(np.max(np.abs(problem.t), initial=0.0))
    R, t = np.array(R, dtype=float), np.array(t, dtype=float)
    cost = sesync_cost(problem, R, t)
    mu = 1e-10
    accepted, converged = 0, False
    factor: SPDFactor | None = None
    for _ in range(iterations):
        H, g = _newton_system(problem, R, t)
        H = H[free][:, free]
        g = g[free]
        U = upper(H + sp.identity(H.shape[0]))  # the whole diagonal in the pattern
        on_diag = np.repeat(np.arange(U.shape[1]), np.diff(U.indptr)) == U.indices
        U.data[on_diag] -= 1.0
        # One symbolic analysis while the pattern holds (an entry that cancels to zero
        # leaves it, so it is compared, not assumed).
        if factor is None or not (np.array_equal(factor.indptr, U.indptr)
                                  and np.array_equal(factor.indices, U.indices)):
            factor = SPDFactor(U.indptr, U.indices)
        diag = np.abs(H.diagonal())
        floor = 1e-12 * max(float(diag.max(initial=0.0)), 1.0)
        step_ok = False
        while mu < 1e12:
            data = U.data.copy()
            data[on_diag] += mu * (diag + floor)
            try:
                delta = -factor.solve(data, g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            flat = np.zeros(problem.n * k)
            flat[free] = delta
            full = flat.reshape(problem.n, k)
            R_new = _retract(R, full[:, d:])
            t_new = t + full[:, :d]
            new_cost = sesync_cost(problem, R_new, t_new)
            if new_cost <= cost:
                step_ok = True
                break
            mu *= 10.0
        if not step_ok:
            # No step lowers F: a minimum to working precision when the gradient vanishes.
            converged = accepted == 0 or converged
            break
        R, t, cost = R_new, t_new, new_cost
        accepted += 1
        mu = max(mu / 10.0, 1e-12)
        size = max(float(np.max(np.abs(full[:, d:]), initial=0.0)),
                   float(np.max(np.abs(full[:, :d]), initial=0.0)) / scale)
        if size <= REFINE_STEP:
            converged = True
            break
    return Refined(R, t, cost, accepted, converged)


def _residuals(problem: SyncProblem, R: Array, t: Array) -> tuple[Array, Array]:
    """``F``'s whitened residuals: rotation ``√κ (R_j − R_i R̃)`` ``(m, d, d)`` and
    translation ``√τ (t_j − t_i − R_i t̃)`` ``(m, d)``; ``F`` is the sum of their squares."""
    Ri = R[problem.i]
    rot = np.sqrt(problem.kappa)[:, None, None] * (R[problem.j] - Ri @ problem.R)
    trans = np.sqrt(problem.tau)[:, None] * (
        t[problem.j] - t[problem.i] - np.einsum("mab,mb->ma", Ri, problem.t))
    return rot, trans


def _jacobian(problem: SyncProblem, R: Array, t: Array) -> tuple[sp.csr_matrix, Array]:
    """Jacobian (sparse, ``(m (d² + d), n (d + p))``) and value of the residuals of
    :func:`_residuals`, stacked per edge, in the coordinates ``[δt_i; φ_i]`` of each node."""
    d, p, m = problem.d, problem.p, len(problem.i)
    k, q = d + p, d * d + d
    G = _generators(d)
    Ri, Rj = R[problem.i], R[problem.j]
    sk = np.sqrt(problem.kappa)[:, None, None]
    st = np.sqrt(problem.tau)[:, None, None]
    rot, trans = _residuals(problem, R, t)
    res = np.concatenate([rot.reshape(m, d * d), trans], axis=1)
    RiG = np.einsum("mab,cbe->mcae", Ri, G)  # (m, p, d, d): R_i G_c
    RjG = np.einsum("mab,cbe->mcae", Rj, G)
    block = np.zeros((m, q, 2 * k))
    # rotation rows: ∂/∂φ_i = −R_i G_c R̃, ∂/∂φ_j = R_j G_c
    block[:, :d * d, d:k] = -np.swapaxes(
        (RiG @ problem.R[:, None]).reshape(m, p, d * d), 1, 2) * sk
    block[:, :d * d, k + d:] = np.swapaxes(RjG.reshape(m, p, d * d), 1, 2) * sk
    # translation rows: ∂/∂t_i = −I, ∂/∂t_j = I, ∂/∂φ_i = −R_i G_c t̃
    eye = np.eye(d)[None] * st
    block[:, d * d:, :d] = -eye
    block[:, d * d:, k:k + d] = eye
    block[:, d * d:, d:k] = -np.einsum("mcab,mb->mac", RiG, problem.t) * st
    rows = np.broadcast_to((np.arange(m)[:, None] * q + np.arange(q))[:, :, None],
                           (m, q, 2 * k))
    cols_i = problem.i[:, None] * k + np.arange(k)
    cols_j = problem.j[:, None] * k + np.arange(k)
    cols = np.broadcast_to(np.concatenate([cols_i, cols_j], axis=1)[:, None, :],
                           (m, q, 2 * k))
    J = sp.csr_matrix((block.ravel(), (rows.ravel(), cols.ravel())),
                      shape=(m * q, problem.n * k))
    return J, res.ravel()


def _newton_system(problem: SyncProblem, R: Array, t: Array) -> tuple[sp.csr_matrix, Array]:
    """Half of ``F``'s Hessian and gradient in the coordinates of :func:`_jacobian`, at
    ``φ = 0``: ``JᵀJ + C`` and ``Jᵀr``.

    ``C`` is block diagonal over the rotation coordinates: with
    ``Exp(φ) = I + [φ]× + ½[φ]×² + O(φ³)`` and ``[φ]×² = φφᵀ − ‖φ‖² I``, a residual term
    ``R_i Exp(φ) M`` weighed by the residual ``c`` contributes ``φᵀ(sym W − tr(W) I)φ`` with
    ``W = R_iᵀ c Mᵀ`` (planar: ``G² = −I`` gives ``−tr(W) φ²``).
    """
    d, p, n = problem.d, problem.p, problem.n
    k = d + p
    J, r = _jacobian(problem, R, t)
    rot, trans = _residuals(problem, R, t)
    sk = np.sqrt(problem.kappa)[:, None, None]
    st = np.sqrt(problem.tau)[:, None, None]
    Rit = np.swapaxes(R[problem.i], 1, 2)
    W = np.zeros((n, d, d))
    # rotation residual √κ (R_j − R_i R̃): M = I at j, −R̃ at i; translation −√τ R_i t̃
    np.add.at(W, problem.j, sk * np.swapaxes(R[problem.j], 1, 2) @ rot)
    np.add.at(W, problem.i, -sk * Rit @ rot @ np.swapaxes(problem.R, 1, 2)
              - st * Rit @ np.einsum("ma,mb->mab", trans, problem.t))
    trace = np.trace(W, axis1=1, axis2=2)
    if d == 2:
        C = -trace[:, None, None]
    else:
        C = 0.5 * (W + np.swapaxes(W, 1, 2)) - trace[:, None, None] * np.eye(3)
    rows = (np.arange(n)[:, None] * k + d + np.arange(p))
    Csp = sp.csr_matrix((C.ravel(), (np.repeat(rows, p, axis=1).ravel(),
                                     np.tile(rows, (1, p)).ravel())),
                        shape=(n * k, n * k))
    return (J.T @ J + Csp).tocsr(), J.T @ r


def _block_entries(d: int, nodes_a: np.ndarray, nodes_b: np.ndarray, blocks: Array
                   ) -> tuple[np.ndarray, np.ndarray, Array]:
    """COO triplets of ``d × d`` blocks ``blocks[e]`` at block position
    ``(nodes_a[e], nodes_b[e])``."""
    r = nodes_a[:, None, None] * d + np.arange(d)[None, :, None]
    c = nodes_b[:, None, None] * d + np.arange(d)[None, None, :]
    shape = blocks.shape
    return (np.broadcast_to(r, shape).ravel(), np.broadcast_to(c, shape).ravel(),
            blocks.ravel())


class ReducedProblem:
    """``Q`` of :class:`SyncProblem` (module docstring), applied without forming it.

    Holds ``A = L(G̃^ρ) + Σ̃`` (sparse, ``dn × dn``), ``Ṽ`` (sparse, ``n × dn``) and one
    sparse LU factorization of ``L(W^τ)`` with a node of each of its connected
    components removed (its ``L†`` acts on ``Ṽ v``, which sums to zero on every component,
    as that solve does up to a constant per component, which ``Ṽᵀ`` maps to zero).
    """

    def __init__(self, problem: SyncProblem) -> None:
        self.problem = problem
        d, n = problem.d, problem.n
        i, j, kappa, tau = problem.i, problem.j, problem.kappa, problem.tau
        eye = np.broadcast_to(np.eye(d), (len(i), d, d))
        parts = [
            _block_entries(d, i, i, kappa[:, None, None] * eye),
            _block_entries(d, j, j, kappa[:, None, None] * eye),
            _block_entries(d, i, j, -kappa[:, None, None] * problem.R),
            _block_entries(d, j, i, -kappa[:, None, None] * np.swapaxes(problem.R, 1, 2)),
            _block_entries(d, i, i, tau[:, None, None]
                           * np.einsum("ma,mb->mab", problem.t, problem.t)),
        ]
        rows, cols, vals = (np.concatenate(x) for x in zip(*parts, strict=True))
        self.A = sp.csr_matrix((vals, (rows, cols)), shape=(d * n, d * n))
        # Ṽ = Σ_e τ_e (e_j − e_i)(e_i ⊗ t̃_e)ᵀ
        vr = np.concatenate([np.repeat(j, d), np.repeat(i, d)])
        vc = np.tile((i[:, None] * d + np.arange(d)).ravel(), 2)
        vt = (tau[:, None] * problem.t).ravel()
        self.V = sp.csr_matrix((np.concatenate([vt, -vt]), (vr, vc)), shape=(n, d * n))
        weighted = tau > 0.0
        L = sp.coo_matrix((np.concatenate([tau, tau, -tau, -tau]),
                           (np.concatenate([i, j, i, j]), np.concatenate([i, j, j, i]))),
                          shape=(n, n)).tocsr()
        self.L = L
        held = _anchors(n, i[weighted], j[weighted], False)
        self.free = np.setdiff1d(np.arange(n), held)
        self._lu = symmetric_lu(L[self.free][:, self.free])

    def solve_laplacian(self, y: Array) -> Array:
        """``z`` with ``L(W^τ) z = y`` and ``z = 0`` at the held nodes, for ``y`` of shape
        ``(n,)`` or ``(n, k)`` summing to zero over each component."""
        z = np.zeros_like(y, dtype=float)
        if len(self.free):
            z[self.free] = self._lu.solve(np.ascontiguousarray(y[self.free], dtype=float))
        return z

    def apply_q(self, v: Array) -> Array:
        """``Q v`` for ``v`` of shape ``(dn,)`` or ``(dn, k)``."""
        return self.A @ v - self.V.T @ self.solve_laplacian(self.V @ v)

    def lambda_blocks(self, R: Array) -> Array:
        """``Λ = SymBlockDiag(Q XᵀX)`` at rotations ``R`` ``(n, d, d)``, as ``(n, d, d)``."""
        d, n = self.problem.d, self.problem.n
        Mt = np.swapaxes(R, 1, 2)  # Xᵀ: block i is R_iᵀ
        return sym_blocks(self.apply_q(Mt.reshape(n * d, d)).reshape(n, d, d), Mt)

    def optimal_translations(self, R: Array) -> Array:
        """The translations minimizing ``F`` at rotations ``R``, shape ``(n, d)``, zero at
        the held node of each component: ``T L = X Ṽᵀ``."""
        d, n = self.problem.d, self.problem.n
        Xt = np.swapaxes(R, 1, 2).reshape(n * d, d)
        return self.solve_laplacian(self.V @ Xt)


def sym_blocks(QM: Array, M: Array) -> Array:
    """``SymBlockDiag(Q MᵀM)``'s blocks ``sym((QM)_i M_iᵀ)``, shape ``(n, d, d)``, from the
    block rows ``(n, d, r)`` of ``Q M`` and of ``M`` (at rank ``d`` and ``M_i = R_iᵀ``, the
    certificate's ``Λ``; at higher ranks the staircase's)."""
    B = QM @ np.swapaxes(M, 1, 2)
    return 0.5 * (B + np.swapaxes(B, 1, 2))


def tolerance(reduced: ReducedProblem) -> float:
    """``η``: :data:`EIG_TOLERANCE` × the largest diagonal entry of ``L(G̃^ρ) + Σ̃``."""
    return EIG_TOLERANCE * float(np.max(reduced.A.diagonal(), initial=0.0))


@dataclass(frozen=True)
class Spectrum:
    """``λ_min(S)`` and the test ``S + ηI ≻ 0`` (:func:`min_eigenvalue`).

    Attributes:
        lambda_min: the smallest eigenvalue of ``S`` (1/m² scale of the weights).
        psd: ``S + ηI`` is positive definite (its factorization has no negative pivot).
        converged: the eigensolver converged (else ``lambda_min`` is its best Ritz value,
            an upper bound of ``λ_min``).
        vector: the eigenvector of ``lambda_min``, shape ``(n·d,)``, when asked for and
            ``S + ηI`` is not positive definite (a direction of negative curvature).
    """

    lambda_min: float
    psd: bool
    converged: bool
    vector: Array | None = None


def min_eigenvalue(reduced: ReducedProblem, Lam: Array, eta: float, vector: bool = False
                   ) -> Spectrum:
    """``λ_min(S)``, ``S = Q − Λ`` with ``Λ`` blocks ``(n, d, d)``, and whether ``S + ηI ≻ 0``;
    ``vector``: with its eigenvector when ``S + ηI`` is not positive definite.

    ``S + ηI`` is the Schur complement of the sparse matrix
    ``K = [[L_r, −Ṽ_r], [−Ṽ_rᵀ, A − Λ + ηI]]`` (``L_r``, ``Ṽ_r``: the held nodes' rows
    removed, ``L_r ≻ 0``), so by Sylvester's law of inertia ``S + ηI ≻ 0`` exactly when
    ``K``'s ``LDLᵀ`` has no negative pivot (the test of SE-Sync's later versions, a
    factorization of the shifted certificate matrix). Then ``λ_min`` is found by Lanczos
    (ARPACK's ``eigsh``) on ``(S + ηI)⁻¹`` applied by solves with ``K``'s factors: its
    largest eigenvalue ``1/(λ_min + η)`` stands well apart from the rest, so it converges
    in a few dozen steps even when the small eigenvalues of ``S`` cluster. Otherwise on
    ``cI − S`` with ``c`` a Gershgorin bound of ``A − Λ`` (≥ ``λ_max(S)``, since
    ``Ṽᵀ L† Ṽ ⪰ 0``): a negative ``λ_min`` stands apart from the cluster at zero.
    """
    p = reduced.problem
    d, n = p.d, p.n
    nd = n * d
    rows, cols, vals = _block_entries(d, np.arange(n), np.arange(n), Lam)
    Lam_sp = sp.csr_matrix((vals, (rows, cols)), shape=(nd, nd))
    B = (reduced.A - Lam_sp).tocsr()
    free = reduced.free
    Lr = reduced.L[free][:, free]
    Vr = reduced.V[free]
    nf = len(free)
    rng = np.random.default_rng(0)  # a fixed start vector: the same answer every run
    v0 = rng.standard_normal(nd)
    K = sp.bmat([[Lr, -Vr], [-Vr.T, B + eta * sp.identity(nd)]], format="csc")
    psd = False
    lu: spla.SuperLU | None = None
    try:
        lu = symmetric_lu(K)
        symmetric = np.array_equal(lu.perm_r, lu.perm_c)
        psd = symmetric and bool(np.all(lu.U.diagonal() > 0.0))
    except RuntimeError:  # an exactly singular pivot: S + ηI is not positive definite
        lu = None
    if psd and lu is not None:
        solver = lu

        def inverse(v: Array) -> Array:
            rhs = np.zeros(nf + nd)
            rhs[nf:] = v
            return solver.solve(rhs)[nf:]

        op = spla.LinearOperator((nd, nd), matvec=inverse, dtype=float)
        try:
            mu = spla.eigsh(op, k=1, which="LA", v0=v0, tol=1e-10,
                            return_eigenvectors=False)[0]
            return Spectrum(float(1.0 / mu - eta), True, True)
        except spla.ArpackNoConvergence as err:
            values = err.eigenvalues
            mu = float(values[0]) if len(values) else 1.0 / eta
            return Spectrum(float(1.0 / mu - eta), True, False)
    c = float(np.max(np.abs(B).sum(axis=1)))

    def shifted(v: Array) -> Array:
        return c * v - (reduced.apply_q(v) - Lam_sp @ v)

    op = spla.LinearOperator((nd, nd), matvec=shifted, dtype=float)
    try:
        found = spla.eigsh(op, k=1, which="LA", v0=v0, tol=1e-8, ncv=min(nd, 64),
                           maxiter=max(1000, nd), return_eigenvectors=vector)
        tops, vectors = found if vector else (found, None)
        return Spectrum(float(c - tops[0]), False, True,
                        vectors[:, 0] if vectors is not None else None)
    except spla.ArpackNoConvergence as err:
        values = err.eigenvalues
        if not len(values):
            return Spectrum(0.0, False, False)
        best = int(np.argmax(values))
        return Spectrum(float(c - values[best]), False, False,
                        err.eigenvectors[:, best] if vector else None)


@dataclass(frozen=True)
class Certificate:
    """Outcome of :func:`certify` (module docstring says what is certified).

    Attributes:
        certified: the refined point is certified globally optimal for ``F``.
        message: one line saying so, or why not.
        lambda_min: ``λ_min(S)`` at the refined point (``None``: not computed).
        tolerance: ``η``.
        sesync_cost: ``F`` at the refined point (= ``tr(Λ)``).
        suboptimality_bound: ``max(0, −λ_min)·d·n``: ``F`` of the refined point is at most
            this above ``F``'s global minimum.
        cost_at_solution: ``F`` at h2o's solution.
        chi2_solution, chi2_refined: g2o χ² (:func:`~h2o_slam.core.graph.chi2`) of the
            certified edges at h2o's solution and at the refined point.
        max_rotation_moved_rad, max_translation_moved_m: largest change of a node's rotation
            (angle) and position from h2o's solution to the refined point.
        refine_iterations: Levenberg–Marquardt steps of the refinement.
        refine_converged: the refinement converged (:class:`Refined`).
        eig_converged: the eigensolver converged.
        chi2_returned: g2o χ² where Gauss–Newton on the g2o problem, started from the refined
            point, ends (the round trip of :func:`certify`; ``None`` when not run).
        edges: edges in the certified problem; nodes: its nodes (the earth frame included).
        seconds: wall time of the refinement and the certificate.
    """

    certified: bool
    message: str
    lambda_min: float | None = None
    tolerance: float | None = None
    sesync_cost: float | None = None
    suboptimality_bound: float | None = None
    cost_at_solution: float | None = None
    chi2_solution: float | None = None
    chi2_refined: float | None = None
    max_rotation_moved_rad: float | None = None
    max_translation_moved_m: float | None = None
    refine_iterations: int = 0
    refine_converged: bool | None = None
    eig_converged: bool | None = None
    chi2_returned: float | None = None
    edges: int = 0
    nodes: int = 0
    seconds: float = 0.0


def certify(graph: PoseGraph, R: Array, t: Array, keep: np.ndarray | None = None
            ) -> Certificate:
    """Refine the solution ``(R, t)`` (shapes ``(N, 3, 3)``, ``(N, 3)``) of ``graph`` on
    SE-Sync's cost over the edges ``keep`` (boolean mask; default every edge), and test the
    refined point's global optimality (module docstring)."""
    start = time.perf_counter()
    problem = sync_problem(graph, keep)
    if len(problem.i) == 0:
        return Certificate(False, "could not certify: the graph has no edges")
    Rs, ts = sync_poses(graph, problem, R, t)
    cost0 = sesync_cost(problem, Rs, ts)
    refined = refine(problem, Rs, ts)
    reduced = ReducedProblem(problem)
    Lam = reduced.lambda_blocks(refined.R)
    eta = tolerance(reduced)
    spectrum = min_eigenvalue(reduced, Lam, eta)
    lam = spectrum.lambda_min
    certified = spectrum.psd and lam >= -eta
    mask = np.ones(graph.num_edges, bool) if keep is None else np.asarray(keep, bool)
    R3, t3 = graph_poses(graph, problem, refined.R, refined.t)
    moved = geo.so3_log(np.swapaxes(np.asarray(R, float), 1, 2) @ R3)
    chi2_solution = float(np.sum(edge_chi2(graph, R, t)[mask]))
    returned = _round_trip(graph, mask, R3, t3) if certified else None
    if certified and returned is not None and not _same(returned, chi2_solution):
        certified = False
        message = (f"could not certify: Gauss–Newton from the certified optimum of SE-Sync's "
                   f"cost ends at χ² {returned:.6g}, not this solution's {chi2_solution:.6g}")
    elif certified:
        message = (f"certified globally optimal (λ_min = {lam:.3g} ≥ -{eta:.3g}; SE-Sync's "
                   f"certified optimum leads back to this solution)")
    elif spectrum.psd:  # inertia says S + ηI ≻ 0 but the eigensolver disagrees: say so
        message = f"could not certify: λ_min = {lam:.3g} < -{eta:.3g} (eigensolver)"
    else:
        message = f"could not certify: λ_min = {lam:.3g} < -{eta:.3g}"
    if not refined.converged:
        message += " (refinement did not converge)"
    return Certificate(
        certified=certified, message=message, lambda_min=lam, tolerance=eta,
        sesync_cost=refined.cost,
        suboptimality_bound=max(0.0, -lam) * problem.d * problem.n,
        cost_at_solution=cost0,
        chi2_solution=chi2_solution,
        chi2_refined=float(np.sum(edge_chi2(graph, R3, t3)[mask])),
        chi2_returned=returned,
        max_rotation_moved_rad=float(np.max(np.linalg.norm(moved, axis=1), initial=0.0)),
        max_translation_moved_m=float(np.max(np.linalg.norm(t3 - np.asarray(t, float),
                                                            axis=1), initial=0.0)),
        refine_iterations=refined.iterations, refine_converged=refined.converged,
        eig_converged=spectrum.converged, edges=len(problem.i), nodes=problem.n,
        seconds=time.perf_counter() - start,
    )



#: Relative χ² difference within which the round trip counts as back at the solution (the
#: exact solver stops at a relative decrease of 1e-6 per iteration; a few such steps).
ROUND_TRIP_TOLERANCE = 1e-4


def _round_trip(graph: PoseGraph, keep: np.ndarray, R: Array, t: Array) -> float:
    """g2o χ² over the edges ``keep`` where the exact solver (damped Gauss–Newton on the
    file's problem) ends when started from ``(R, t)``: the certified optimum of ``F`` is the
    χ²'s global optimum only approximately (``F`` drops the information's correlations), so
    the solution counts as certified when the χ²'s own descent from there returns to it."""
    from h2o_slam.core.exact import converge_exact
    from h2o_slam.core.modes import EXACT_ITERATIONS, build_solver

    solver, _ = build_solver(graph.with_estimate(R, t), init="input", regularizer=False)
    solver.set_weights(keep.astype(float))
    converge_exact(solver, EXACT_ITERATIONS)
    R_b, t_b = solver.world_poses()
    return float(np.sum(edge_chi2(graph, R_b, t_b)[keep]))


def _same(chi2_a: float, chi2_b: float) -> bool:
    """Two χ² values equal to within :data:`ROUND_TRIP_TOLERANCE` (relative)."""
    return abs(chi2_a - chi2_b) <= ROUND_TRIP_TOLERANCE * max(abs(chi2_b), 1e-12)
