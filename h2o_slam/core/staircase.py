"""SE-Sync's Riemannian staircase: a start in the global optimum's basin when the certificate
fails.

D. M. Rosen, L. Carlone, A. S. Bandeira and J. J. Leonard, "SE-Sync: A certifiably correct
algorithm for synchronization over the special Euclidean group" (IJRR 2019), the Riemannian
staircase and its rounding procedure. With ``Q`` the reduced data matrix of
:mod:`h2o_slam.core.certificate` (translations eliminated), the rank-``r`` relaxation is

    minimize tr(Mᵀ Q M)  over  M = [M_1; …; M_n],  M_i ∈ R^{d×r},  M_i M_iᵀ = I_d

(SE-Sync's ``Y_i = M_iᵀ`` on the Stiefel manifold ``St(d, r)``; at ``r = d`` the rotations,
``M_i = R_iᵀ``, up to their determinant). On this product of Stiefel manifolds:

* the tangent vectors at ``M`` are the ``V`` with ``sym(V_i M_iᵀ) = 0``; the projection is
  ``Proj_M(V)_i = V_i − sym(V_i M_iᵀ) M_i``;
* the Riemannian gradient is ``Proj_M(2QM) = 2(QM − ΛM)`` with ``Λ_i = sym((QM)_i M_iᵀ)``,
  and the Riemannian Hessian ``Hess f(M)[V] = Proj_M(2(QV − ΛV))``;
* a step is retracted block by block to the polar factor of ``M_i + V_i``.

Each rank is solved by a Riemannian trust-region method with truncated conjugate gradients
(Absil, Baker & Gallivan, "Trust-region methods on Riemannian manifolds", FoCM 2007),
preconditioned as SE-Sync is by solves with ``Q``'s sparse part ``L(G̃^ρ) + Σ̃`` (one
sparse factorization, SuperLU's symmetric mode, kept for the climb). At a critical point
``S = Q − Λ ⪰ 0`` proves it optimal for the semidefinite relaxation; otherwise the
eigenvector ``v`` of ``S``'s smallest eigenvalue ``λ < 0`` is a direction of negative
curvature at ``[M, 0]`` one rank up (``f`` falls by ``α²λ`` along ``[0, αv]``), from which
the next rank starts. The last rank's ``M`` is rounded
to rotations: its ``d`` leading singular vectors, the sign that gives most blocks a positive
determinant, each block projected to ``SO(d)``.

When the relaxation is exact the rounded rotations are the global optimum of SE-Sync's cost;
at large noise it is not (the staircase ends above rank ``d``), but the rounded point still
starts the χ²'s own descent in a lower basin than a local method found: on a 1,000-pose 3-D
grid with 0.3 rad of rotation noise, χ² 2,480 against 2,545 from the chordal start.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from h2o_slam.core.certificate import (
    ReducedProblem,
    graph_poses,
    min_eigenvalue,
    sym_blocks,
    sync_poses,
    sync_problem,
    tolerance,
)
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import PoseGraph, chi2
from h2o_slam.core.modes import (
    EXACT_ITERATIONS,
    SolveResult,
    lowest_result,
    solve_exact,
)
from h2o_slam.core.robust import RobustConfig
from h2o_slam.core.solver import SolverConfig
from h2o_slam.core.spd import symmetric_lu

#: Highest rank the staircase climbs to before it rounds what it has.
MAX_RANK = 10

#: Trust-region iterations per rank at most.
MAX_ITERATIONS = 300

#: A rank is solved when the Riemannian gradient's norm falls below this fraction of its
#: norm at the rank's start, or the cost's relative decrease in an iteration below
#: :data:`COST_TOLERANCE`.
GRADIENT_TOLERANCE = 1e-6
COST_TOLERANCE = 1e-10


@dataclass(frozen=True)
class Climb:
    """Outcome of :func:`climb`.

    Attributes:
        R: the rounded rotations, shape ``(n, d, d)``.
        rank: the rank the staircase ended at.
        cost: ``tr(Mᵀ Q M)`` at the last rank's point (a lower bound of SE-Sync's optimum
            when ``relaxation_solved``).
        lambda_min: the smallest eigenvalue of ``S`` at the last rank's point.
        relaxation_solved: ``λ_min ≥ −η`` there: the semidefinite relaxation is solved.
        iterations: trust-region iterations over all ranks.
        seconds: wall time.
    """

    R: Array
    rank: int
    cost: float
    lambda_min: float
    relaxation_solved: bool
    iterations: int
    seconds: float


class RankProblem:
    """``f(M) = tr(Mᵀ Q M)`` on the product of Stiefel manifolds (module docstring), for a
    reduced problem ``reduced`` (:class:`~h2o_slam.core.certificate.ReducedProblem`)."""

    def __init__(self, reduced: ReducedProblem) -> None:
        self.reduced = reduced
        self.d, self.n = reduced.problem.d, reduced.problem.n
        A = reduced.A
        # Q's sparse part, lifted a little: L(G̃^ρ) is singular along the global rotation.
        # Factored once, solved with at every inner iteration.
        lift = 1e-6 * float(np.max(A.diagonal(), initial=1.0))
        self._pre = symmetric_lu(A + lift * sp.identity(A.shape[0], format="csr"))

    def q(self, M: Array) -> Array:
        """``Q M`` for ``M`` of shape ``(n, d, r)``."""
        d, n = self.d, self.n
        return self.reduced.apply_q(M.reshape(n * d, -1)).reshape(n, d, -1)

    def cost(self, M: Array, QM: Array | None = None) -> float:
        """``f(M) = tr(Mᵀ Q M)`` (``QM``: ``Q M`` when the caller has it)."""
        return float(np.sum(M * (self.q(M) if QM is None else QM)))

    @staticmethod
    def lam(M: Array, QM: Array) -> Array:
        """``Λ`` blocks ``sym((QM)_i M_iᵀ)``, shape ``(n, d, d)``."""
        return sym_blocks(QM, M)

    @staticmethod
    def project(M: Array, V: Array) -> Array:
        """``Proj_M(V)``: the tangent part of ``V`` at ``M``."""
        B = V @ np.swapaxes(M, 1, 2)
        return V - 0.5 * (B + np.swapaxes(B, 1, 2)) @ M

    def gradient(self, M: Array, QM: Array, Lam: Array) -> Array:
        """The Riemannian gradient ``2(QM − ΛM)``."""
        return 2.0 * (QM - Lam @ M)

    def hessian(self, M: Array, Lam: Array, V: Array) -> Array:
        """The Riemannian Hessian applied to the tangent vector ``V``."""
        return self.project(M, 2.0 * (self.q(V) - Lam @ V))

    def precondition(self, M: Array, V: Array) -> Array:
        """``Proj_M(A⁻¹ V)`` with ``A`` Q's sparse part (SE-Sync's preconditioner)."""
        d, n = self.d, self.n
        return self.project(M, self._pre.solve(V.reshape(n * d, -1)).reshape(V.shape))

    @staticmethod
    def retract(M: Array, V: Array) -> Array:
        """Each block moved to the polar factor of ``M_i + V_i`` (orthonormal rows)."""
        U, _, Wt = np.linalg.svd(M + V, full_matrices=False)
        return U @ Wt


def _inner(a: Array, b: Array) -> float:
    # Not np.vdot: BLAS's threads contend on a busy machine (4 of 9 s of a climb).
    return float(np.einsum("ijk,ijk->", a, b))


def solve_rank(problem: RankProblem, M: Array, max_iterations: int = MAX_ITERATIONS
               ) -> tuple[Array, int]:
    """A critical point of ``f`` on this rank from ``M`` by the Riemannian trust-region
    method; returns it and the iterations run."""
    QM = problem.q(M)
    f = problem.cost(M, QM)
    Lam = problem.lam(M, QM)
    grad = problem.gradient(M, QM, Lam)
    grad0 = np.sqrt(_inner(grad, grad))
    radius = 0.1 * np.sqrt(problem.n)  # a tenth of a rotation per block on average
    for it in range(max_iterations):
        gnorm = np.sqrt(_inner(grad, grad))
        if gnorm <= GRADIENT_TOLERANCE * max(grad0, 1e-300):
            return M, it
        step, Hstep, boundary = truncated_cg(problem, M, Lam, grad, radius)
        model = _inner(grad, step) + 0.5 * _inner(step, Hstep)
        M_new = problem.retract(M, step)
        QM_new = problem.q(M_new)
        f_new = problem.cost(M_new, QM_new)
        rho = (f - f_new) / -model if model < 0.0 else -1.0
        if rho < 0.25:
            radius *= 0.25
        elif rho > 0.75 and boundary:
            radius *= 2.0
        if rho > 0.1:
            settled = f - f_new <= COST_TOLERANCE * max(abs(f), 1e-300)
            M, QM, f = M_new, QM_new, f_new
            Lam = problem.lam(M, QM)
            grad = problem.gradient(M, QM, Lam)
            if settled:
                return M, it + 1
        elif radius < 1e-12:
            return M, it + 1
    return M, max_iterations


def truncated_cg(problem: RankProblem, M: Array, Lam: Array, grad: Array, radius: float,
                 max_inner: int = 200) -> tuple[Array, Array, bool]:
    """Steihaug–Toint truncated conjugate gradients on the trust-region model at ``M``,
    preconditioned, the region measured in the preconditioner's norm (as Manopt's ``tCG``);
    returns the step, the Hessian applied to it, and whether it reached the boundary."""
    step = np.zeros_like(M)
    Hstep = np.zeros_like(M)
    r = grad
    z = problem.precondition(M, r)
    z_r = _inner(z, r)
    r0 = np.sqrt(_inner(r, r))
    delta = -z
    e_Pe, e_Pd, d_Pd = 0.0, 0.0, z_r
    for _ in range(max_inner):
        Hd = problem.hessian(M, Lam, delta)
        d_Hd = _inner(delta, Hd)
        alpha = z_r / d_Hd if d_Hd != 0.0 else np.inf
        e_Pe_new = e_Pe + 2.0 * alpha * e_Pd + alpha * alpha * d_Pd
        if d_Hd <= 0.0 or e_Pe_new >= radius * radius:
            tau = (-e_Pd + np.sqrt(e_Pd * e_Pd + d_Pd * (radius * radius - e_Pe))) / d_Pd
            return step + tau * delta, Hstep + tau * Hd, True
        e_Pe = e_Pe_new
        step = step + alpha * delta
        Hstep = Hstep + alpha * Hd
        r = r + alpha * Hd
        rnorm = np.sqrt(_inner(r, r))
        if rnorm <= r0 * min(r0, 0.1):  # superlinear: κ = 0.1, θ = 1
            break
        z = problem.precondition(M, r)
        z_r_old, z_r = z_r, _inner(z, r)
        beta = z_r / z_r_old
        delta = -z + beta * delta
        e_Pd = beta * (e_Pd + alpha * d_Pd)
        d_Pd = z_r + beta * beta * d_Pd
    return step, Hstep, False


def escape(problem: RankProblem, M: Array, v: Array) -> Array | None:
    """From the critical point ``M`` of rank ``r`` along ``[0, αv]`` one rank up (``v`` the
    eigenvector ``(n·d,)`` of ``S``'s negative eigenvalue): the first ``α``, halving from
    ``√n`` (``v`` scaled to unit norm: about a unit per block), whose retracted point lowers
    ``f``; None when none of 40 does."""
    n, d, r = M.shape
    f = problem.cost(M)
    lifted = np.concatenate([M, np.zeros((n, d, 1))], axis=2)
    direction = np.zeros_like(lifted)
    direction[:, :, r] = v.reshape(n, d) / np.linalg.norm(v)
    alpha = np.sqrt(n)
    for _ in range(40):
        trial = problem.retract(lifted, alpha * direction)
        if problem.cost(trial) < f:
            return trial
        alpha *= 0.5
    return None


def round_rotations(M: Array) -> Array:
    """SE-Sync's rounding: the ``d`` leading singular vectors of ``M`` (``(n, d, r)``), the
    sign giving most blocks a positive determinant, each block projected to ``SO(d)``;
    returns the rotations ``R_i`` (``M_i ≈ R_iᵀ``), shape ``(n, d, d)``."""
    n, d, r = M.shape
    U, S, _ = np.linalg.svd(M.reshape(n * d, r), full_matrices=False)
    blocks = (U[:, :d] * S[:d]).reshape(n, d, d)  # M_i in the top singular directions
    if np.sum(np.linalg.det(blocks) > 0.0) < n / 2:
        blocks[:, :, -1] *= -1.0
    R = np.swapaxes(blocks, 1, 2)
    Ur, _, Vt = np.linalg.svd(R)
    flip = np.sign(np.linalg.det(Ur @ Vt))
    Ur[:, :, -1] *= flip[:, None]
    return Ur @ Vt


def climb(reduced: ReducedProblem, R: Array, eta: float, max_rank: int = MAX_RANK) -> Climb:
    """The Riemannian staircase from rotations ``R`` ``(n, d, d)`` at rank ``d``: solve each
    rank, test ``S``'s smallest eigenvalue against ``−eta``, escape one rank up while it is
    below, and round the last rank's point (module docstring)."""
    start = time.perf_counter()
    problem = RankProblem(reduced)
    M = np.swapaxes(np.asarray(R, float), 1, 2).copy()
    iterations = 0
    while True:
        M, its = solve_rank(problem, M)
        iterations += its
        QM = problem.q(M)
        spectrum = min_eigenvalue(problem.reduced, problem.lam(M, QM), eta, vector=True)
        lam, v = spectrum.lambda_min, spectrum.vector
        solved = spectrum.psd and lam >= -eta
        if solved or v is None or M.shape[2] >= max_rank:
            break
        lifted = escape(problem, M, v)
        if lifted is None:
            break
        M = lifted
    return Climb(R=round_rotations(M), rank=M.shape[2], cost=problem.cost(M),
                 lambda_min=lam, relaxation_solved=solved, iterations=iterations,
                 seconds=time.perf_counter() - start)


def staircase_start(graph: PoseGraph, R: Array, t: Array, keep: np.ndarray | None = None
                    ) -> tuple[Array, Array, Climb]:
    """A start for the χ² from the staircase climbed from the solution ``(R, t)`` of
    ``graph`` over the edges ``keep`` (default every edge): the rounded rotations and the
    translations that minimize SE-Sync's cost for them, in the solution's gauge (its first
    pose, or the earth frame's when the graph has GPS or compass edges), shapes
    ``(N, 3, 3)`` and ``(N, 3)``."""
    problem = sync_problem(graph, keep)
    reduced = ReducedProblem(problem)
    Rs, _ = sync_poses(graph, problem, R, t)
    out = climb(reduced, Rs, tolerance(reduced))
    Rr, tr = out.R, reduced.optimal_translations(out.R)
    if problem.earth:  # the earth frame (last) back at the identity
        G, o = Rr[-1].T, tr[-1]
        Rr, tr = G[None] @ Rr, (tr - o) @ G.T
    R3, t3 = graph_poses(graph, problem, Rr, tr)
    if not problem.earth:  # the first pose where the solution has it
        G = np.asarray(R, float)[0] @ R3[0].T
        R3, t3 = G[None] @ R3, (t3 - t3[0]) @ G.T + np.asarray(t, float)[0]
    return R3, t3, out


#: Relative χ² change below which the staircase's answer is the solve's own basin again
#: (both stop at the exact solver's tolerance): the solve's answer is kept.
STAIRCASE_GAIN = 1e-4


def staircase_solve(
    graph: PoseGraph, result: SolveResult, iterations: int = EXACT_ITERATIONS,
    config: SolverConfig | None = None, robust: RobustConfig | None = None,
) -> tuple[SolveResult, Climb, bool]:
    """Exact mode again from SE-Sync's Riemannian staircase climbed from the exact solve
    ``result`` over the edges it kept (:func:`staircase_start`), for a solution the
    certificate could not certify: where the relaxation is not exact the rounded point may
    still start the descent in a lower basin. The robust decisions are taken again from
    there.

    Returns the answer that ends lower (``solve_exact``'s comparison of starts, and χ² over
    every edge changed by more than :data:`STAIRCASE_GAIN` of it; the second's
    ``chi2_per_pass`` follows the first's), the climb, and whether the staircase's answer is
    the one returned.
    """
    keep = None if result.weights is None else result.weights > 0.5
    R, t, climb = staircase_start(graph, result.R, result.t, keep)
    again = solve_exact(graph.with_estimate(R, t), iterations, config, init="input",
                        robust=robust)
    before, after = chi2(graph, result.R, result.t), chi2(graph, again.R, again.t)
    if (lowest_result(graph, robust, [result, again]) == 0
            or abs(before - after) <= STAIRCASE_GAIN * max(before, 1e-300)):
        return result, climb, False
    again.chi2_initial, again.start, again.init = result.chi2_initial, result.start, result.init
    again.chi2_per_pass = result.chi2_per_pass + again.chi2_per_pass
    return again, climb, True
