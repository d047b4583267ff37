"""The loop solve condensed: the junctions of a planar loop solved, the chains between them
filled in.

A loop closure's first correction solves every pose newer than its older end
(:class:`~h2o_slam.core.loop_spread.LoopSolve`); on a long loop (kitti_00: 4,450 poses) one
Gauss–Newton iteration of all of them does not fit a callback's budget. Most of those poses
are touched by nothing but their two odometry edges. Such a chain between two *junctions*
(poses with another edge, and the newest pose) is, to first order, one edge: its odometry
measurements composed, with the covariance

    Σ = Σ_i Ad(P_end⁻¹ P_i) Σ_i Ad(P_end⁻¹ P_i)ᵀ

(each increment's right perturbation carried to the chain's end, as in
:mod:`~h2o_slam.core.loop_spread`). Gauss–Newton on the junctions alone, with those edges,
the closures and the held older poses, is the loop solve of a graph of a few hundred poses
(the elimination of a chain's inner poses is exact in the linearized problem). Each chain
is then filled in given its two ends: its increments perturbed by the smallest change,
weighed by their covariances, that joins the ends (the loop spread with a hard
constraint), which is the chain's own least-squares answer.

Planar only: the planar spread's angle arithmetic does the filling in for every chain at
once, and a planar loop closure is the common case on a ground robot.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.exact import MAX_DAMPING, next_damping, settled
from h2o_slam.core.geometry import Array
from h2o_slam.core.loop_spread import dead_reckon
from h2o_slam.core.spd import SPDFactor
from h2o_slam.core.timing import CostModel


def planar_poses(R: Array, t: Array) -> Array:
    """World poses as ``(x, y, yaw)`` rows."""
    return np.column_stack([t[:, 0], t[:, 1], geo.matrix_to_yaw(R)])


def relative_jacobians(pose_a: Array, pose_b: Array, meas: Array
                       ) -> tuple[Array, Array, Array]:
    """The error ``meas⁻¹ (a⁻¹ b)`` of planar relative edges and its Jacobians with respect
    to the ``(x, y, yaw)`` of each end, shapes ``(m, 3)``, ``(m, 3, 3)``, ``(m, 3, 3)``."""
    err = geo.planar_between(meas, geo.planar_between(pose_a, pose_b))
    ca, sa = np.cos(pose_a[:, 2]), np.sin(pose_a[:, 2])
    cm, sm = np.cos(meas[:, 2]), np.sin(meas[:, 2])
    dx, dy = pose_b[:, 0] - pose_a[:, 0], pose_b[:, 1] - pose_a[:, 1]
    # Rmᵀ Raᵀ = R(θa + θm)ᵀ on the translations, Rmᵀ (dRaᵀ/dθ) (t_b − t_a) on θa.
    c, s = np.cos(pose_a[:, 2] + meas[:, 2]), np.sin(pose_a[:, 2] + meas[:, 2])
    rot = np.empty((len(err), 2, 2))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = c, s, -s, c
    d_yaw = np.stack([-sa * dx + ca * dy, -ca * dx - sa * dy], axis=1)
    turn = np.stack([cm * d_yaw[:, 0] + sm * d_yaw[:, 1],
                     -sm * d_yaw[:, 0] + cm * d_yaw[:, 1]], axis=1)
    Jb = np.zeros((len(err), 3, 3))
    Jb[:, :2, :2], Jb[:, 2, 2] = rot, 1.0
    Ja = -Jb
    Ja[:, :2, 2] = turn
    return err, Ja, Jb


def _carried(A: Array, cov: Array, start: np.ndarray) -> tuple[Array, Array]:
    """``A Σ`` per increment and ``Σ A Σ Aᵀ`` per chain (``start``: each chain's first
    increment), ``(3, 3, k)`` layout in, ``(3, 3, S)`` out."""
    A_cov = np.einsum("ijk,jlk->ilk", A, cov)
    return A_cov, np.add.reduceat(np.einsum("ijk,ljk->ilk", A_cov, A), start, axis=2)


@dataclass(frozen=True)
class Chains:
    """The odometry chain after ``lo`` cut at its junctions: chain ``s`` runs from node
    ``first[s]`` to node ``last[s]`` (a junction) over the increments
    ``start[s]:start[s + 1]`` (increment ``i`` leads into node ``lo + 1 + i``).

    Attributes:
        meas: each chain's increments composed, ``(S, 3)``.
        cov: the covariance of that composition, ``(S, 3, 3)``.
        A: each increment's perturbation carried to its chain's end, ``Ad(P_end⁻¹ P_i)``
            at the dead-reckoned poses, ``(3, 3, k)``.
        A_cov: ``A`` times the increment's covariance, ``(3, 3, k)``.
        inc_cov: the increments' covariances, ``(3, 3, k)``.
    """

    lo: int
    first: np.ndarray
    last: np.ndarray
    start: np.ndarray
    meas: Array
    cov: Array
    A: Array
    A_cov: Array
    inc_cov: Array

    @property
    def owner(self) -> np.ndarray:
        """The chain of each increment."""
        return np.repeat(np.arange(len(self.last)), np.diff(self.boundaries))

    @property
    def boundaries(self) -> np.ndarray:
        """``start`` and the end of the last chain's increments."""
        return np.append(self.start, self.last[-1] - self.lo)


def condense(lo: int, junctions: np.ndarray, inc: Array, cov: Array) -> Chains:
    """The chains of the odometry increments ``inc`` (``(k, 3)``, covariances ``cov``) after
    node ``lo``, cut at ``junctions`` (sorted nodes in ``(lo, lo + k]``, ending at ``lo + k``)."""
    pose = dead_reckon(np.zeros(3), inc)
    last = np.asarray(junctions, dtype=np.int64)
    first = np.concatenate([[lo], last[:-1]])
    start = first - lo
    owner = np.repeat(np.arange(len(last)), np.diff(np.append(start, last[-1] - lo)))
    A = _adjoints_to_end(pose[1:, 0], pose[1:, 1], pose[1:, 2], last - lo - 1, owner)
    inc_cov = np.ascontiguousarray(cov.transpose(1, 2, 0))
    A_cov, carried = _carried(A, inc_cov, start)
    meas = geo.planar_between(pose[start], pose[last - lo])
    return Chains(lo, first, last, start, meas, carried.transpose(2, 0, 1), A, A_cov, inc_cov)


def fill(chains: Chains, pose: Array, inc: Array, moved: Array | None = None,
         steps: int = 4, closed: float = 1e-6) -> Array:
    """The poses of every chain's inner nodes given its ends' ``pose`` rows (world
    ``(x, y, yaw)`` indexed by node; the ends already solved): the increments perturbed
    by ``δᵢ = −Σᵢ Aᵢᵀ S⁻¹ (e − Σ Aᵢ δᵢ)``, ``S = Σ Aᵢ Σᵢ Aᵢᵀ``, the least change that
    joins the ends, each step at the chain's current shape (the rotation's nonlinearity),
    from the perturbations ``moved`` (the map's increments before the correction,
    :func:`perturbations`; ``None``: the odometry's), until every chain's end is within
    ``closed`` (m, rad) or ``steps`` ran. A loop's correction bends a chain (MIT: 1.8 rad
    over 300 poses): from the odometry's shape two steps left χ² a thousand times the
    optimum's and three 1.12 times it; from the map's, most corrections close in two.
    Returns the poses of nodes ``lo + 1 .. last``, ``(k, 3)``."""
    owner = chains.owner
    ends = chains.start + np.diff(chains.boundaries) - 1
    target = geo.planar_between(pose[chains.first], pose[chains.last])
    moved = np.zeros_like(inc) if moved is None else moved
    A, A_cov, S = chains.A, chains.A_cov, chains.cov
    for step in range(steps):
        x, y, yaw = _walk(chains, pose, inc, moved, owner)
        if step or np.any(moved):
            A = _adjoints_to_end(x, y, yaw, ends, owner)
            A_cov, carried = _carried(A, chains.inc_cov, chains.start)
            S = carried.transpose(2, 0, 1)
        end = np.column_stack([x[ends], y[ends], yaw[ends]])
        e = _unturned(geo.planar_between(target, geo.planar_between(pose[chains.first], end)))
        if step and np.max(np.abs(e)) < closed:
            break
        lin = e - np.add.reduceat(np.einsum("ijk,kj->ki", A, moved), chains.start, axis=0)
        lam = np.linalg.solve(S, lin[..., None])[..., 0].T[:, owner]
        moved = -np.einsum("jik,jk->ki", A_cov, lam)
    else:
        x, y, yaw = _walk(chains, pose, inc, moved, owner)
    return np.column_stack([x, y, geo.wrap_angle(yaw)])


def perturbations(pose: Array, lo: int, inc: Array) -> Array:
    """The right perturbations ``δ`` that turn the increments ``inc`` into the increments of
    ``pose`` (rows by node) after ``lo``: ``inc ⊕ δ = pose[i−1]⁻¹ pose[i]``."""
    return geo.planar_between(inc, geo.planar_between(pose[lo:-1], pose[lo + 1:]))


def _unturned(e: Array) -> Array:
    """``J⁻¹ e`` for the error ``e = E`` of a chain's end, ``J`` the derivative of ``E·Exp(x)``
    by ``x`` (``R(e_yaw)`` on the translation): the error a change of the chain's
    increments must undo, in the frame their perturbation ``A δ`` acts in. Without it a
    chain that ends a third of a radian off (MIT) needs several more steps to close."""
    c, s = np.cos(e[:, 2]), np.sin(e[:, 2])
    return np.column_stack([c * e[:, 0] + s * e[:, 1], -s * e[:, 0] + c * e[:, 1], e[:, 2]])


def _walk(chains: Chains, pose: Array, inc: Array, moved: Array, owner: np.ndarray
          ) -> tuple[Array, Array, Array]:
    """Each chain dead-reckoned from its first node's ``pose`` along the increments ``inc``
    perturbed by ``moved`` (``inc ⊕ moved``): ``x``, ``y`` and unwrapped yaw of every node
    after ``lo``, by segmented cumulative sums (every chain at once, component arrays:
    this runs a few times per loop solve on thousands of poses)."""
    c, s = np.cos(inc[:, 2]), np.sin(inc[:, 2])
    dx = inc[:, 0] + c * moved[:, 0] - s * moved[:, 1]
    dy = inc[:, 1] + s * moved[:, 0] + c * moved[:, 1]
    dyaw = inc[:, 2] + moved[:, 2]
    before = chains.start[owner]
    first = pose[chains.first[owner]]
    yaw_sum = np.cumsum(dyaw)
    yaw = first[:, 2] + yaw_sum - np.concatenate([[0.0], yaw_sum])[before]
    heading = yaw - dyaw
    c, s = np.cos(heading), np.sin(heading)
    x_sum, y_sum = np.cumsum(c * dx - s * dy), np.cumsum(s * dx + c * dy)
    x = first[:, 0] + x_sum - np.concatenate([[0.0], x_sum])[before]
    y = first[:, 1] + y_sum - np.concatenate([[0.0], y_sum])[before]
    return x, y, yaw


def _adjoints_to_end(x: Array, y: Array, yaw: Array, ends: np.ndarray, owner: np.ndarray
                     ) -> Array:
    """``Ad(P_end⁻¹ P_i)`` of every node ``i`` (``x``, ``y``, ``yaw`` by increment) and its
    chain's end (``ends``: each chain's last increment), on right perturbations
    ``(δx, δy, δθ)``, laid out ``(3, 3, k)``: the chains' products are over thousands of
    3×3 blocks, and numpy's einsum over the last axis is several times faster than its
    batched matmul over the first."""
    end = ends[owner]
    c, s = np.cos(yaw[end]), np.sin(yaw[end])
    dx, dy = x - x[end], y - y[end]
    rel = np.empty((3, len(x)))
    rel[0], rel[1], rel[2] = c * dx + s * dy, -s * dx + c * dy, yaw - yaw[end]
    turn_c, turn_s = np.cos(rel[2]), np.sin(rel[2])
    out = np.zeros((3, 3, len(x)))
    out[0, 0], out[0, 1], out[0, 2] = turn_c, -turn_s, rel[1]
    out[1, 0], out[1, 1], out[1, 2] = turn_s, turn_c, -rel[0]
    out[2, 2] = 1.0
    return out


@dataclass(frozen=True)
class Reduced:
    """Planar relative edges between nodes, those in ``free`` solved for, the rest held."""

    a: np.ndarray
    b: np.ndarray
    meas: Array
    info: Array
    free: np.ndarray

    def chi2(self, pose: Array) -> float:
        """χ² of the edges at ``pose`` (rows by node)."""
        err = geo.planar_between(self.meas, geo.planar_between(pose[self.a], pose[self.b]))
        return float(np.einsum("mi,mij,mj->", err, self.info, err))

    def step(self, pose: Array, damping: float) -> Array:
        """The Gauss–Newton (Levenberg ``damping``) step's poses."""
        err, Ja, Jb = relative_jacobians(pose[self.a], pose[self.b], self.meas)
        return self._moved(pose, np.arange(3), self._solve(Ja, Jb, self.info, err, damping))

    def rotations_first(self, pose: Array) -> Array:
        """LAGO's two linear solves (Carlone et al., "A fast and accurate approximation for
        planar pose graph optimization", IJRR 2014) from ``pose``: the yaws from the edges'
        yaw errors alone (weighed by their yaw variance; the wrap fixed at ``pose``), then
        the positions at those yaws. A start for Gauss–Newton where a closure's yaw error
        is too large for the chains' linearization (:data:`ROTATION_FIRST_RAD`)."""
        yaw_info = np.asarray(1.0 / np.linalg.inv(self.info)[:, 2, 2], dtype=float)
        err = geo.wrap_angle(pose[self.b, 2] - pose[self.a, 2] - self.meas[:, 2])
        one = np.ones((len(err), 1, 1))
        dyaw = self._solve(-one, one, yaw_info[:, None, None], err[:, None], 0.0)
        turned = self._moved(pose, np.array([2]), dyaw)
        err, Ja, Jb = relative_jacobians(turned[self.a], turned[self.b], self.meas)
        dxy = self._solve(Ja[:, :2, :2], Jb[:, :2, :2], self.info[:, :2, :2], err[:, :2], 0.0)
        return self._moved(turned, np.arange(2), dxy)

    def _moved(self, pose: Array, dof: np.ndarray, step: Array) -> Array:
        out = pose.copy()
        out[np.ix_(self.free, dof)] += step.reshape(len(self.free), len(dof))
        out[self.free, 2] = geo.wrap_angle(out[self.free, 2])
        return out

    def _solve(self, Ja: Array, Jb: Array, info: Array, err: Array, damping: float
               ) -> Array:
        """``(JᵀΩJ + damping · diag) δ = −JᵀΩe`` over the free nodes' columns of ``J``."""
        c = Ja.shape[2]
        pattern = self._patterns.get(c)
        if pattern is None:
            pattern = self._patterns[c] = _Pattern(self.a, self.b, self.free, c)
        return pattern.solve(Ja, Jb, info, err, damping)

    def __post_init__(self) -> None:
        # The systems' sparsity, by unknowns per node: built once, refactored each step.
        object.__setattr__(self, "_patterns", {})

    _patterns: dict[int, _Pattern] = field(init=False, repr=False, compare=False)


class _Pattern:
    """The upper triangle of ``JᵀΩJ``'s sparsity for edges ``(a, b)`` with ``c`` unknowns
    per free node, and where each block entry lands in it: a Gauss–Newton step then only
    sums values into it and refactors (the symbolic analysis is the factor's, once). Built
    by scipy per step, the system took 1.2 ms of kitti_00's 405 reduced edges; this, a
    quarter."""

    def __init__(self, a: np.ndarray, b: np.ndarray, free: np.ndarray, c: int) -> None:
        var = np.full(int(max(a.max(), b.max(), free.max())) + 1, -1, dtype=np.int64)
        var[free] = np.arange(len(free))
        self.c, self.n = c, c * len(free)
        self.var_a, self.var_b = var[a], var[b]
        cells = np.arange(c)
        rows, cols, self.blocks = [], [], []
        for p, q in ((0, 0), (0, 1), (1, 0), (1, 1)):
            vp, vq = (self.var_a, self.var_b)[p], (self.var_a, self.var_b)[q]
            both = (vp >= 0) & (vq >= 0)
            r = (c * vp[both])[:, None, None] + cells[None, :, None]
            k = (c * vq[both])[:, None, None] + cells[None, None, :]
            r, k = np.broadcast_to(r, (len(r), c, c)).ravel(), np.broadcast_to(
                k, (len(k), c, c)).ravel()
            upper_half = r <= k
            self.blocks.append((p, q, both, upper_half))
            rows.append(r[upper_half])
            cols.append(k[upper_half])
        diag = np.arange(self.n)
        key = np.concatenate(cols + [diag]) * self.n + np.concatenate(rows + [diag])
        unique, where = np.unique(key, return_inverse=True)
        self.where = where
        self.diag = where[-self.n:]
        indices = unique % self.n
        indptr = np.concatenate([[0], np.cumsum(np.bincount(unique // self.n,
                                                            minlength=self.n))])
        self.nnz = len(unique)
        self.factor = SPDFactor(indptr, indices)

    def solve(self, Ja: Array, Jb: Array, info: Array, err: Array, damping: float) -> Array:
        """The damped Gauss–Newton step of the free nodes."""
        J = (Ja, Jb)
        JtW = [j.transpose(0, 2, 1) @ info for j in J]
        var = (self.var_a, self.var_b)
        values = []
        g = np.zeros(self.n)
        for end in (0, 1):
            keep = var[end] >= 0
            idx = self.c * var[end][keep][:, None] + np.arange(self.c)
            np.add.at(g, idx, np.einsum("mij,mj->mi", JtW[end][keep], err[keep]))
        for p, q, both, upper_half in self.blocks:
            values.append((JtW[p][both] @ J[q][both]).ravel()[upper_half])
        values.append(np.zeros(self.n))
        data = np.asarray(np.bincount(self.where, weights=np.concatenate(values),
                                      minlength=self.nnz), dtype=float)
        data[self.diag] += damping * data[self.diag] + 1e-12
        return self.factor.solve(data, -g)


#: A yaw error beyond which :func:`solve_loop` starts from :meth:`Reduced.rotations_first`:
#: a chain's linearization holds for a few degrees of bending; MIT's closure of 303 poses,
#: 1.8 rad off, led Gauss–Newton from the map to a minimum 700 times the optimum's χ².
ROTATION_FIRST_RAD = 0.1


def solve_loop(pose: Array, lo: int, inc: Array, cov: Array, cross: Reduced,
               iterations: int, tolerance: float, out_of_time: Callable[[], bool]
               ) -> tuple[Array, bool]:
    """The poses after ``lo`` solved, every older pose held (module docstring).

    ``pose``: world ``(x, y, yaw)`` of every node, the newest last; ``inc``, ``cov``: the
    odometry measurements into nodes ``lo + 1 ..`` and their covariances; ``cross``: every
    other edge with an end after ``lo`` (its ``free`` unused). Damped Gauss–Newton on the
    junctions until the relative χ² decrease is within ``tolerance``, ``iterations`` run
    out, or ``out_of_time()`` after the first. Returns the poses and whether it converged.
    """
    n = len(pose)
    ends = np.concatenate([cross.a, cross.b])
    junctions = np.unique(np.append(ends[ends > lo], n - 1))
    chains = condense(lo, junctions, inc, cov)
    reduced = Reduced(np.concatenate([chains.first, cross.a]),
                      np.concatenate([chains.last, cross.b]),
                      np.concatenate([chains.meas, cross.meas]),
                      np.concatenate([np.linalg.inv(chains.cov), cross.info]), junctions)
    now = pose.copy()
    chi2 = reduced.chi2(now)
    turn = geo.wrap_angle(now[reduced.b, 2] - now[reduced.a, 2] - reduced.meas[:, 2])
    if np.max(np.abs(turn), initial=0.0) > ROTATION_FIRST_RAD:
        # Gauss–Newton from the map would start beyond the chains' linearization.
        start = reduced.rotations_first(now)
        if reduced.chi2(start) < chi2:
            now, chi2 = start, reduced.chi2(start)
    damping, converged = 0.0, False
    for i in range(iterations):
        if i and out_of_time():
            break
        trial = reduced.step(now, damping)
        after = reduced.chi2(trial)
        accepted = bool(np.isfinite(after) and after <= chi2)
        damping = next_damping(damping, accepted)
        if accepted:
            converged = settled(chi2, after, tolerance)
            now, chi2 = trial, after
        else:
            converged = damping > MAX_DAMPING
        if converged:
            break
    now[lo + 1:] = fill(chains, now, inc, perturbations(pose, lo, inc))
    return now, converged


#: Gauss–Newton iterations a condensed loop solve runs at most.
CONDENSED_ITERATIONS = 10


class CondensedLoop:
    """:func:`solve_loop` inside a callback's budget: a cost model by the chain's increments
    (condensing and filling in, vectorized) and the reduced edges times the iterations run
    (each a sparse factorization of the junctions' system)."""

    def __init__(self) -> None:
        # Priors from kitti_00's last loop (4,450 increments, 90 other edges, 270 reduced
        # nodes and edges): 0.5 ms to condense, 1.1-1.5 ms to fill in, 0.5 ms an iteration.
        self.cost = CostModel((2e-4, 4e-7, 1.7e-6), (4000.0, 300.0))

    def fits(self, increments: int, reduced: int, deadline: float, clock: Callable[[], float],
             safety: float) -> bool:
        """Two iterations on ``reduced`` nodes and edges, and the rest, fit before
        ``deadline``."""
        predicted = self.cost.predict(increments, 2 * reduced) * self.cost.margin(safety)
        return clock() + predicted <= deadline

    def run(self, pose: Array, lo: int, inc: Array, cov: Array, cross: Reduced,
            deadline: float, clock: Callable[[], float], safety: float, tolerance: float
            ) -> tuple[Array, bool]:
        """:func:`solve_loop` iterating while one more iteration and the filling in fit."""
        begin = clock()
        k, r = len(inc), len(cross.a) + len(np.unique(np.concatenate([cross.a, cross.b])))
        margin = self.cost.margin(safety)
        rest = (self.cost.predict(k, 2 * r) - self.cost.predict(k, r) + self.cost.predict(k, 0))
        runs = [0]

        def out_of_time() -> bool:
            runs[0] += 1
            return clock() + rest * margin > deadline

        poses, converged = solve_loop(pose, lo, inc, cov, cross, CONDENSED_ITERATIONS,
                                      tolerance, out_of_time)
        self.cost.update(clock() - begin, k, r * (runs[0] + 1))
        return poses, converged
