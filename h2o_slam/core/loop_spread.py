"""The first correction of a long loop: the closure's error spread along its odometry chain.

When a loop closes, H₂O's single-edge update solves for the nodes on the tree path between
the closure's ends; with a balanced tree that path is short, so the correction lands on a
few nodes and bends the map there (measured on kitti_00: χ² right after the first closure
of a loop 10³–10⁴ times the optimum). The least-squares answer for a loop that nothing else
ties is known in closed form: with the odometry increments ``D_i`` of the chain ``lo → hi``
perturbed on the right by ``δ_i`` (information ``Ω_i``) and the closure's error ``e``
(information ``Ω_c``) changed by ``C Σ_i A_i δ_i``, where ``A_i = Ad(T_hi⁻¹ T_i)`` carries an
increment's perturbation to the loop's end,

    minimize  Σ_i δ_iᵀ Ω_i δ_i + (e + C Σ_i A_i δ_i)ᵀ Ω_c (e + C Σ_i A_i δ_i)
    ⇒  δ_i = −Ω_i⁻¹ (C A_i)ᵀ S⁻¹ e,   S = Ω_c⁻¹ + Σ_i (C A_i) Ω_i⁻¹ (C A_i)ᵀ,

the covariance-weighted spread of error along a loop that Olson, Leonard & Teller ("Fast
iterative alignment of pose graphs with poor initial estimates", ICRA 2006) and Grisetti et
al.'s TORO distribute iteratively. It is one Gauss–Newton step of the loop alone, in time
linear in its length (batched numpy: a 1500-pose loop takes well under a millisecond);
:func:`spread_loop` iterates it a few times for the rotation's nonlinearity. Nodes newer
than the loop follow its end rigidly. Other edges on the chain are not in the system: the
caller keeps the spread only if the χ² of every edge it moves falls.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.compiled import kernel
from h2o_slam.core.condensed import _between, _inverse3, _solve3, _walk_chain, _yaw_trig
from h2o_slam.core.exact import (
    MAX_DAMPING,
    ExactSystem,
    WorldSystem,
    next_damping,
    scored_step,
    settled,
)
from h2o_slam.core.geometry import Array
from h2o_slam.core.solver import H2OSolver
from h2o_slam.core.timing import CostModel


def adjoint(R: Array, t: Array) -> Array:
    """``Ad(T)`` for perturbations ordered ``[translation; rotation]`` (the order of
    :func:`~h2o_slam.core.geometry.relative_error`), shape ``(..., 6, 6)``."""
    out = np.zeros((*R.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = geo.hat(t) @ R
    return out


def closure_moved(C_R: Array, C_t: Array, meas_R: Array, meas_t: Array, info: Array,
                  forward: bool) -> tuple[Array, Array, Array]:
    """A closure between poses ``lo`` and ``hi`` rewritten as one between pose ``k`` and
    ``hi``, for ``T_lo`` and ``T_k`` held with ``T_lo⁻¹ T_k = C``: its measurement and
    information such that its χ² is the original's at every ``T_hi``. ``forward``: the
    closure is ``lo → hi`` (its error unchanged); else ``hi → lo`` and the result ``hi → k``,
    whose error is the original's conjugated by ``C`` (``Ad(C⁻¹) e`` to first order: the
    rotation's part exactly, the translation's up to ``(R_E − I − [ω]ₓ) C_t``)."""
    if forward:
        # (C⁻¹ Z)⁻¹ T_k⁻¹ T_hi = Z⁻¹ T_lo⁻¹ T_hi: the same error.
        C_inv_R, C_inv_t = geo.inverse(C_R, C_t)
        R, t = geo.compose(C_inv_R, C_inv_t, meas_R, meas_t)
        return R, t, info
    # (Z C)⁻¹ T_hi⁻¹ T_k = C⁻¹ (Z⁻¹ T_hi⁻¹ T_lo) C: the error Ad(C⁻¹) e.
    R, t = geo.compose(meas_R, meas_t, C_R, C_t)
    Ad = adjoint(C_R, C_t)
    return R, t, Ad.T @ info @ Ad


def closure_error(R: Array, t: Array, a: int, b: int, meas_R: Array, meas_t: Array) -> Array:
    """The closure's error ``[t_E; Log R_E]`` of ``Z⁻¹ T_a⁻¹ T_b`` at world poses ``(R, t)``."""
    return geo.relative_error(R[a], t[a], R[b], t[b], meas_R, meas_t)


def spread_step(R: Array, t: Array, a: int, b: int, meas_R: Array, meas_t: Array,
                cov_closure: Array, cov: Array, dof: np.ndarray, moved: Array) -> Array:
    """One Gauss–Newton step of the loop alone (module docstring): the increments' new
    perturbation ``δ``, ``(hi - lo, 6)``, from the one that placed the poses ``(R, t)``.

    ``R, t``: every node's world pose (the chain's increments at ``moved``);
    ``cov_closure``, ``cov[i]``: covariances (over ``dof``) of the closure and of the
    increment into node ``min(a, b) + 1 + i`` (:func:`_covariances`). The perturbation is
    weighed from where the spread began, so repeated steps converge to the loop's optimum
    instead of pulling ever closer to the closure."""
    lo, hi = min(a, b), max(a, b)
    e = closure_error(R, t, a, b, meas_R, meas_t)[dof]
    # Ad(T_hi⁻¹ T_i) for the increments' end nodes i = lo+1 .. hi.
    R_y, t_y = geo.between(R[hi], t[hi], R[lo + 1: hi + 1], t[lo + 1: hi + 1])
    A = adjoint(R_y, t_y)
    if a > b:  # the closure measures T_hi⁻¹ T_lo: a chain change η moves it by −Ad(T_lo⁻¹T_hi) η
        R_p, t_p = geo.between(R[lo], t[lo], R[hi], t[hi])
        A = -adjoint(R_p, t_p) @ A
    M = A[:, dof[:, None], dof[None, :]]
    MC = M @ cov
    S = cov_closure + np.einsum("kij,klj->il", MC, M)
    lam = np.linalg.solve(S, e - np.einsum("kij,kj->i", M, moved[:, dof]))
    out = np.zeros_like(moved)
    out[:, dof] = -np.einsum("kji,j->ki", MC, lam)
    return out


def perturbed(R: Array, t: Array, lo: int, hi: int, D_R: Array, D_t: Array, delta: Array
              ) -> tuple[Array, Array]:
    """World poses with the chain's increments set to ``D · (Exp ω, δt)`` (``delta`` rows
    ``[δt; ω]``) and recomposed from ``lo``; nodes after ``hi`` keep their pose relative to
    ``hi``."""
    P_R, P_t = geo.cumulative_compose(geo.renormalize(D_R @ geo.so3_exp(delta[:, 3:])),
                                      D_t + np.einsum("kij,kj->ki", D_R, delta[:, :3]))
    R_new, t_new = R.copy(), t.copy()
    R_new[lo + 1: hi + 1], t_new[lo + 1: hi + 1] = geo.compose(R[lo], t[lo], P_R, P_t)
    _follow_end(R, t, R_new, t_new, hi)
    return R_new, t_new


def _follow_end(R: Array, t: Array, R_new: Array, t_new: Array, hi: int) -> None:
    """Move the nodes after ``hi`` in ``(R_new, t_new)`` rigidly with ``hi``: each keeps its
    pose relative to ``hi`` in ``(R, t)``."""
    if hi + 1 < len(R):
        rel_R, rel_t = geo.between(R[hi], t[hi], R[hi + 1:], t[hi + 1:])
        R_new[hi + 1:], t_new[hi + 1:] = geo.compose(R_new[hi], t_new[hi], rel_R, rel_t)


def _covariances(info: Array, chain_info: Array, dof: np.ndarray) -> tuple[Array, Array]:
    """The closure's and the chain increments' covariances over ``dof``, inverted once per
    spread (every step reuses them)."""
    cov_closure = np.asarray(np.linalg.inv(info[np.ix_(dof, dof)]), dtype=float)
    cov = np.asarray(np.linalg.inv(chain_info[:, dof[:, None], dof[None, :]]), dtype=float)
    return cov_closure, cov


def spread_loop(R: Array, t: Array, a: int, b: int, meas_R: Array, meas_t: Array,
                info: Array, chain_info: Array, dof: np.ndarray, steps: int = 3
                ) -> tuple[Array, Array]:
    """:func:`spread_step` ``steps`` times from the current increments (the rotation's
    nonlinearity: a closure a few degrees off needs two or three)."""
    lo, hi = min(a, b), max(a, b)
    if len(dof) == 3:
        return _spread_planar(R, t, a, b, meas_R, meas_t, info, chain_info, dof, steps)
    D_R, D_t = geo.between(R[lo: hi], t[lo: hi], R[lo + 1: hi + 1], t[lo + 1: hi + 1])
    cov_closure, cov = _covariances(info, chain_info, dof)
    moved = np.zeros((hi - lo, 6))
    R_now, t_now = R, t
    for _ in range(steps):
        moved = spread_step(R_now, t_now, a, b, meas_R, meas_t, cov_closure, cov, dof, moved)
        R_now, t_now = perturbed(R, t, lo, hi, D_R, D_t, moved)
    return R_now, t_now


def _spread_planar(R: Array, t: Array, a: int, b: int, meas_R: Array, meas_t: Array,
                   info: Array, chain_info: Array, dof: np.ndarray, steps: int
                   ) -> tuple[Array, Array]:
    """:func:`spread_loop` for a planar graph in ``(x, y, yaw)``: the same steps on 3×3
    blocks built from angles, compiled (:func:`_spread_planar_chain`: a 2,000-pose loop
    took 4-6 ms in batched numpy, inside a callback's budget)."""
    lo, hi = min(a, b), max(a, b)
    yaw = np.arctan2(R[lo: hi + 1, 1, 0], R[lo: hi + 1, 0, 0])
    xy = t[lo: hi + 1, :2]
    d = geo.planar_between(np.column_stack([xy[:-1], yaw[:-1]]),
                           np.column_stack([xy[1:], yaw[1:]]))
    meas = np.array([meas_t[0], meas_t[1], np.arctan2(meas_R[1, 0], meas_R[0, 0])])
    cov_closure = np.linalg.inv(info[np.ix_(dof, dof)])
    first = np.array([xy[0, 0], xy[0, 1], yaw[0]])
    pose = _spread_planar_chain(first, d, meas, chain_info[:, dof[:, None], dof[None, :]],
                                cov_closure, a > b, steps)
    R_new, t_new = R.copy(), t.copy()
    R_new[lo + 1: hi + 1] = geo.yaw_to_matrix(pose[1:, 2])
    t_new[lo + 1: hi + 1, :2] = pose[1:, :2]
    _follow_end(R, t, R_new, t_new, hi)
    return R_new, t_new


def dead_reckon(start: Array, inc: Array) -> Array:
    """Poses ``(k + 1, 3)`` as ``(x, y, yaw)`` from ``start`` along the planar increments
    ``inc`` ``(k, 3)`` (yaw unwrapped)."""
    yaw = start[2] + np.concatenate([[0.0], np.cumsum(inc[:, 2])])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    step = np.column_stack([c * inc[:, 0] - s * inc[:, 1], s * inc[:, 0] + c * inc[:, 1]])
    xy = start[:2] + np.concatenate([np.zeros((1, 2)), np.cumsum(step, axis=0)])
    return np.column_stack([xy, yaw])


@kernel
def _spread_planar_chain(first: Array, d: Array, meas: Array, info: Array,
                         cov_closure: Array, reverse: bool, steps: int) -> Array:
    """The chain's poses ``(k + 1, 3)`` from ``first`` along the increments ``d ⊕ δ`` after
    ``steps`` of :func:`_planar_step` from ``δ = 0``; ``info``: the increments' information
    (inverted here: numpy's batched inverse took 0.9 ms on a 2,000-pose loop)."""
    k = d.shape[0]
    cov = np.empty((k, 3, 3))
    for i in range(k):
        _inverse3(info[i], cov[i])
    moved = np.zeros((k, 3))
    pose = np.empty((k + 1, 3))
    pose[0] = first
    A = np.empty((k, 3, 3))
    MC = np.empty((k, 3, 3))
    d_trig, trig = _yaw_trig(d), np.empty((k, 2))
    for _ in range(steps):
        _walk_chain(first, d, d_trig, moved, 0, k, pose[1:], trig)
        _planar_step(pose, reverse, meas, cov, cov_closure, moved, A, MC)
    _walk_chain(first, d, d_trig, moved, 0, k, pose[1:], trig)
    return pose


@kernel
def _planar_step(pose: Array, reverse: bool, meas: Array, cov: Array, cov_closure: Array,
                 moved: Array, A: Array, MC: Array) -> None:
    """:func:`spread_step` in ``(x, y, yaw)`` on the chain's poses ``pose`` (first = lo):
    ``moved`` becomes the new perturbation (``A``, ``MC``: scratch of ``(k, 3, 3)``)."""
    k = moved.shape[0]
    ex, ey, eyaw = pose[k, 0], pose[k, 1], pose[k, 2]
    if reverse:
        rel = _between(ex, ey, eyaw, pose[0, 0], pose[0, 1], pose[0, 2])
    else:
        rel = _between(pose[0, 0], pose[0, 1], pose[0, 2], ex, ey, eyaw)
    e0, e1, e2 = _between(meas[0], meas[1], meas[2], rel[0], rel[1], rel[2])
    # The closure measures T_hi⁻¹ T_lo when reversed: −Ad(T_lo⁻¹ T_hi) first.
    flip = np.eye(3)
    if reverse:
        p = _between(pose[0, 0], pose[0, 1], pose[0, 2], ex, ey, eyaw)
        cp, sp = np.cos(p[2]), np.sin(p[2])
        flip[0, 0], flip[0, 1], flip[0, 2] = -cp, sp, -p[1]
        flip[1, 0], flip[1, 1], flip[1, 2] = -sp, -cp, p[0]
        flip[2, 2] = -1.0
    S = cov_closure.copy()
    rhs = np.empty(3)
    rhs[0], rhs[1], rhs[2] = e0, e1, e2
    c, s = np.cos(eyaw), np.sin(eyaw)
    ad = np.zeros((3, 3))
    ad[2, 2] = 1.0
    for i in range(k):
        # Ad(T_hi⁻¹ T_i) on (δx, δy, δθ) for the increment into node lo + 1 + i.
        dx, dy = pose[i + 1, 0] - ex, pose[i + 1, 1] - ey
        ang = pose[i + 1, 2] - eyaw
        ca, sa = np.cos(ang), np.sin(ang)
        ad[0, 0], ad[0, 1], ad[0, 2] = ca, -sa, -s * dx + c * dy
        ad[1, 0], ad[1, 1], ad[1, 2] = sa, ca, -(c * dx + s * dy)
        for r in range(3):
            for q in range(3):
                A[i, r, q] = (flip[r, 0] * ad[0, q] + flip[r, 1] * ad[1, q]
                              + flip[r, 2] * ad[2, q])
        for r in range(3):
            for q in range(3):
                MC[i, r, q] = (A[i, r, 0] * cov[i, 0, q] + A[i, r, 1] * cov[i, 1, q]
                               + A[i, r, 2] * cov[i, 2, q])
        for r in range(3):
            for q in range(3):
                S[r, q] += MC[i, r, 0] * A[i, q, 0] + MC[i, r, 1] * A[i, q, 1] \
                    + MC[i, r, 2] * A[i, q, 2]
            rhs[r] -= A[i, r, 0] * moved[i, 0] + A[i, r, 1] * moved[i, 1] \
                + A[i, r, 2] * moved[i, 2]
    lam = _solve3(S, rhs)
    for i in range(k):
        for q in range(3):
            moved[i, q] = -(MC[i, 0, q] * lam[0] + MC[i, 1, q] * lam[1] + MC[i, 2, q] * lam[2])


# --- the loop solved: Gauss–Newton on the poses a closure moves -----------------------------


#: Gauss–Newton iterations a loop solve runs at most (measured on MIT's closures, from a map
#: at the optimum before each: r ≤ 1.14 after 2-5, none moving after 6).
LOOP_ITERATIONS = 8
#: Iterations a loop solve must be predicted to fit before it starts; else the spread.
LOOP_MIN_ITERATIONS = 2


class LoopSolve:
    """Damped Gauss–Newton on the poses after a loop closure's older end, everything older
    held: the closure, every edge among those poses and every edge from them into the past
    (closures of earlier loops that cross this one), at the map's weights.

    The spread solves the loop as if nothing else tied it; where earlier closures do (on
    MIT, a closure of 303 poses with 7 older closures inside it, and closures across the
    loop's start), its answer bends them: χ² right after the closure's callback was 11 to
    7·10⁴ times the optimum. Solving the newer poses exactly, warm-started from the map,
    gave 1.00-1.08 times it after 2-5 iterations of 0.3-0.7 ms each. It costs the newer
    poses and their edges, so it runs where a few iterations fit the callback's budget
    and the spread serves the rest (kitti_00's loops of thousands of poses).
    """

    def __init__(self) -> None:
        # Seconds by poses plus edges: building the system with the first linearization
        # and the first iteration (which also analyses the pattern), and each later
        # iteration (solve, score). Priors from MIT's closures: 0.9 ms for 620, 0.35 ms.
        self.setup_cost = CostModel((4e-4, 8e-7), (1000.0,))
        self.iteration_cost = CostModel((1e-4, 4e-7), (1000.0,))

    def problem(self, solver: H2OSolver, lo: int) -> tuple[np.ndarray, np.ndarray]:
        """The free poses (after ``lo`` in ``lo``'s subtree) and the edges at weight above 0
        with an end among them."""
        n, m = solver.num_nodes, solver.num_edges
        tops = solver.tree.tops()
        newer = np.zeros(n + 1, dtype=bool)  # [-1]: the earth
        newer[lo + 1: n] = tops[lo + 1: n] == tops[lo]
        a, b = solver.a[:m], solver.b[:m]
        edges = np.flatnonzero((solver.weight[:m] > 0.0) & (newer[a] | newer[b]))
        return np.flatnonzero(newer[:n]), edges

    def fits(self, work: int, deadline: float, clock: Any, safety: float) -> bool:
        """The setup and :data:`LOOP_MIN_ITERATIONS` iterations in all fit before
        ``deadline``."""
        predicted = (self.setup_cost.predict(work) * self.setup_cost.margin(safety)
                     + (LOOP_MIN_ITERATIONS - 1) * self.iteration_cost.predict(work)
                     * self.iteration_cost.margin(safety))
        return clock() + predicted <= deadline

    def run(self, solver: H2OSolver, free: np.ndarray, edges: np.ndarray, deadline: float,
            clock: Any, safety: float) -> tuple[bool, bool]:
        """Iterate while iterations fit and χ² falls; the map takes the last poses. Returns
        whether χ² fell (it never rises: a step that would raise it is damped and tried
        again, as in :func:`~h2o_slam.core.exact.converge_exact`) and whether the solve
        converged (else the time ran out: a later call goes on from the poses reached)."""
        work = len(free) + len(edges)
        begin = clock()
        es = ExactSystem(solver)
        system = WorldSystem(solver.a[edges], solver.b[edges], free, solver.num_nodes,
                             solver.p, edges)
        first = lin = es.linearize_at(*solver.world_poses(), system)
        damping, converged = 0.0, False
        tol = solver.config.exact_tolerance
        for i in range(LOOP_ITERATIONS):
            if i and not self.iteration_cost.fits(deadline - clock(), safety, work):
                break
            new = scored_step(es, lin, damping)
            damping = next_damping(damping, new is not None)
            now = clock()
            (self.iteration_cost if i else self.setup_cost).update(now - begin, work)
            begin = now
            if new is None:
                converged = damping > MAX_DAMPING  # no step helps: at the minimum
            else:
                converged = settled(lin.chi2, new.chi2, tol)
                lin = new
            if converged:
                break
        if lin.chi2 >= first.chi2:
            return False, converged
        solver.tree.set_world_poses(lin.R, lin.x)
        return True, converged

