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

Planar only: a chain's angles add up, so condensing and filling in are one pass along it,
and a planar loop closure is the common case on a ground robot. Those passes, the junctions'
normal equations and the χ² of the moved edges are compiled kernels
(:mod:`~h2o_slam.core.compiled`): in numpy, their dozens of calls over thousands of
increments made kitti_00's last loop (4,450 poses) a 23 ms solve; compiled, 9 ms.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.compiled import kernel
from h2o_slam.core.exact import MAX_DAMPING, next_damping, settled
from h2o_slam.core.geometry import Array
from h2o_slam.core.spd import SPDFactor
from h2o_slam.core.timing import CostModel


def planar_poses(R: Array, t: Array) -> Array:
    """World poses as ``(x, y, yaw)`` rows."""
    return np.column_stack([t[:, 0], t[:, 1], geo.matrix_to_yaw(R)])


def relative_jacobians(pose_a: Array, pose_b: Array, meas: Array
                       ) -> tuple[Array, Array, Array]:
    """The error ``meas⁻¹ (a⁻¹ b)`` of planar relative edges and its Jacobians with respect
    to the ``(x, y, yaw)`` of each end, shapes ``(m, 3)``, ``(m, 3, 3)``, ``(m, 3, 3)``.
    Compiled: a condensed solve calls it once per iteration, and numpy's twenty calls on a
    few dozen edges took 0.13-0.22 ms each time."""
    m = len(meas)
    err, Ja, Jb = np.empty((m, 3)), np.zeros((m, 3, 3)), np.zeros((m, 3, 3))
    _relative_jacobians(np.ascontiguousarray(pose_a, dtype=float),
                        np.ascontiguousarray(pose_b, dtype=float),
                        np.ascontiguousarray(meas, dtype=float), err, Ja, Jb)
    return err, Ja, Jb


@kernel
def _relative_jacobians(pose_a: Array, pose_b: Array, meas: Array, err: Array, Ja: Array,
                        Jb: Array) -> None:
    for k in range(len(meas)):
        ca, sa = np.cos(pose_a[k, 2]), np.sin(pose_a[k, 2])
        cm, sm = np.cos(meas[k, 2]), np.sin(meas[k, 2])
        dx, dy = pose_b[k, 0] - pose_a[k, 0], pose_b[k, 1] - pose_a[k, 1]
        rx, ry, ryaw = _between(pose_a[k, 0], pose_a[k, 1], pose_a[k, 2],
                                pose_b[k, 0], pose_b[k, 1], pose_b[k, 2])
        err[k, 0], err[k, 1], err[k, 2] = _between(meas[k, 0], meas[k, 1], meas[k, 2],
                                                   rx, ry, ryaw)
        # Rmᵀ Raᵀ = R(θa + θm)ᵀ on the translations, Rmᵀ (dRaᵀ/dθ) (t_b − t_a) on θa.
        c, s = np.cos(pose_a[k, 2] + meas[k, 2]), np.sin(pose_a[k, 2] + meas[k, 2])
        Jb[k, 0, 0], Jb[k, 0, 1], Jb[k, 1, 0], Jb[k, 1, 1], Jb[k, 2, 2] = c, s, -s, c, 1.0
        for r in range(3):
            for q in range(3):
                Ja[k, r, q] = -Jb[k, r, q]
        yx, yy = -sa * dx + ca * dy, -ca * dx - sa * dy
        Ja[k, 0, 2] = cm * yx + sm * yy
        Ja[k, 1, 2] = -sm * yx + cm * yy


@dataclass(frozen=True)
class Chains:
    """The odometry chain after ``lo`` cut at its junctions: chain ``s`` runs from node
    ``first[s]`` to node ``last[s]`` (a junction) over the increments
    ``start[s]:start[s + 1]`` (increment ``i`` leads into node ``lo + 1 + i``).

    Attributes:
        meas: each chain's increments composed, ``(S, 3)``.
        cov: the covariance of that composition, ``(S, 3, 3)``.
        inc_cov: the increments' covariances, ``(k, 3, 3)``.
    """

    lo: int
    first: np.ndarray
    last: np.ndarray
    start: np.ndarray
    meas: Array
    cov: Array
    inc_cov: Array

    @property
    def boundaries(self) -> np.ndarray:
        """``start`` and the end of the last chain's increments."""
        return np.append(self.start, self.last[-1] - self.lo)


def condense(lo: int, junctions: np.ndarray, inc: Array, cov: Array) -> Chains:
    """The chains of the odometry increments ``inc`` (``(k, 3)``, covariances ``cov``) after
    node ``lo``, cut at ``junctions`` (sorted nodes in ``(lo, lo + k]``, ending at ``lo + k``)."""
    last = np.asarray(junctions, dtype=np.int64)
    first = np.concatenate([[lo], last[:-1]])
    start = first - lo
    inc = np.ascontiguousarray(inc, dtype=float)
    inc_cov = np.ascontiguousarray(cov, dtype=float)
    meas, chain_cov = np.empty((len(last), 3)), np.empty((len(last), 3, 3))
    _condense(np.append(start, last[-1] - lo), inc, inc_cov, meas, chain_cov)
    return Chains(lo, first, last, start, meas, chain_cov, inc_cov)


@kernel
def _condense(bounds: np.ndarray, inc: Array, cov: Array, meas: Array, chain_cov: Array
              ) -> None:
    """Each chain's increments composed (``meas``) and the covariance of that composition
    (``chain_cov``), every increment's carried to the chain's end."""
    walk, still = np.empty_like(inc), np.zeros_like(inc)
    inc_trig, trig = _yaw_trig(inc), np.empty((len(inc), 2))
    zero, lin = np.zeros(3), np.zeros(3)
    carried = np.empty((len(inc), 3, 3))
    for s in range(len(bounds) - 1):
        lo, hi = bounds[s], bounds[s + 1]
        _walk_chain(zero, inc, inc_trig, still, lo, hi, walk, trig)
        chain_cov[s] = _carry(walk, trig, cov, still, lo, hi, carried, lin)
        meas[s, 0], meas[s, 1] = walk[hi - 1, 0], walk[hi - 1, 1]
        meas[s, 2] = _wrapped(walk[hi - 1, 2])


def fill(chains: Chains, pose: Array, inc: Array, moved: Array | None = None,
         steps: int = 4, closed: float = 1e-6) -> Array:
    """The poses of every chain's inner nodes given its ends' ``pose`` rows (world
    ``(x, y, yaw)`` indexed by node; the ends already solved): the increments perturbed
    by ``δᵢ = −Σᵢ Aᵢᵀ S⁻¹ (e − Σ Aᵢ δᵢ)``, ``S = Σ Aᵢ Σᵢ Aᵢᵀ``, the least change that
    joins the ends, each step at the chain's current shape (the rotation's nonlinearity),
    from the perturbations ``moved`` (the map's increments before the correction,
    :func:`perturbations`; ``None``: the odometry's), until the chain's end is within
    ``closed`` (m, rad) or ``steps`` ran. A loop's correction bends a chain (MIT: 1.8 rad
    over 300 poses): from the odometry's shape two steps left χ² a thousand times the
    optimum's and three 1.12 times it; from the map's, most corrections close in two.
    Returns the poses of nodes ``lo + 1 .. last``, ``(k, 3)``.

    One compiled pass per chain and step (:func:`_fill_chains`): vectorized, the steps'
    dozens of numpy calls over thousands of increments took 6 of the 16 ms of kitti_00's
    last loop's condensed solve."""
    moved = np.zeros_like(inc) if moved is None else np.array(moved, dtype=float)
    out = np.empty_like(inc, dtype=float)
    _fill_chains(np.ascontiguousarray(pose[chains.first], dtype=float),
                 np.ascontiguousarray(pose[chains.last], dtype=float),
                 chains.boundaries.astype(np.int64), np.ascontiguousarray(inc, dtype=float),
                 chains.inc_cov, moved,
                 int(steps), float(closed), out)
    out[:, 2] = geo.wrap_angle(out[:, 2])
    return out


@kernel
def _fill_chains(first: Array, last: Array, bounds: np.ndarray, inc: Array, cov: Array,
                 moved: Array, steps: int, closed: float, out: Array) -> None:
    """:func:`fill` of every chain ``s`` (increments ``bounds[s]:bounds[s + 1]``, from the
    world pose ``first[s]`` to join ``last[s]``): ``moved`` updated in place, the poses in
    ``out`` (yaw unwrapped)."""
    carried = np.empty((len(inc), 3, 3))
    inc_trig, trig = _yaw_trig(inc), np.empty((len(inc), 2))
    lin = np.empty(3)
    for s in range(len(bounds) - 1):
        lo, hi = bounds[s], bounds[s + 1]
        # The end as the chain must reach it, in its first node's frame.
        c0, s0 = np.cos(first[s, 2]), np.sin(first[s, 2])
        dx, dy = last[s, 0] - first[s, 0], last[s, 1] - first[s, 1]
        tx, ty = c0 * dx + s0 * dy, -s0 * dx + c0 * dy
        tyaw = last[s, 2] - first[s, 2]
        ct, st = np.cos(tyaw), np.sin(tyaw)
        for step in range(steps + 1):
            _walk_chain(first[s], inc, inc_trig, moved, lo, hi, out, trig)
            if step == steps:
                break
            # e = J⁻¹ (target⁻¹ (first⁻¹ end)): the end's error in the increments' frame.
            ex, ey = out[hi - 1, 0] - first[s, 0], out[hi - 1, 1] - first[s, 1]
            rx, ry = c0 * ex + s0 * ey - tx, -s0 * ex + c0 * ey - ty
            e2 = _wrapped(out[hi - 1, 2] - first[s, 2] - tyaw)
            e0, e1 = ct * rx + st * ry, -st * rx + ct * ry
            ce, se = np.cos(e2), np.sin(e2)
            lin[0], lin[1], lin[2] = ce * e0 + se * e1, -se * e0 + ce * e1, e2
            if step and max(abs(lin[0]), abs(lin[1]), abs(lin[2])) < closed:
                break
            S = _carry(out, trig, cov, moved, lo, hi, carried, lin)
            lam = _solve3(S, lin)
            for i in range(lo, hi):
                ac = carried[i]
                for c in range(3):
                    moved[i, c] = -(ac[0, c] * lam[0] + ac[1, c] * lam[1] + ac[2, c] * lam[2])


@kernel
def _wrapped(angle: float) -> float:
    """``angle`` in ``[-π, π)``, as :func:`~h2o_slam.core.geometry.wrap_angle` for one."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


@kernel
def _between(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float
             ) -> tuple[float, float, float]:
    """``a⁻¹ b`` for one pair of planar poses, as
    :func:`~h2o_slam.core.geometry.planar_between`: the compiled loops' one composition
    (an edge's error is ``_between(*meas, *_between(*a, *b))``)."""
    c, s = np.cos(a2), np.sin(a2)
    dx, dy = b0 - a0, b1 - a1
    return c * dx + s * dy, -s * dx + c * dy, _wrapped(b2 - a2)


@kernel
def _inverse3(S: Array, out: Array) -> None:
    """``out = S⁻¹`` for a 3×3 ``S`` by its adjugate (no allocation; LAPACK's call per
    chain cost more)."""
    out[0, 0] = S[1, 1] * S[2, 2] - S[1, 2] * S[2, 1]
    out[1, 0] = S[1, 2] * S[2, 0] - S[1, 0] * S[2, 2]
    out[2, 0] = S[1, 0] * S[2, 1] - S[1, 1] * S[2, 0]
    out[0, 1] = S[0, 2] * S[2, 1] - S[0, 1] * S[2, 2]
    out[1, 1] = S[0, 0] * S[2, 2] - S[0, 2] * S[2, 0]
    out[2, 1] = S[0, 1] * S[2, 0] - S[0, 0] * S[2, 1]
    out[0, 2] = S[0, 1] * S[1, 2] - S[0, 2] * S[1, 1]
    out[1, 2] = S[0, 2] * S[1, 0] - S[0, 0] * S[1, 2]
    out[2, 2] = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    det = S[0, 0] * out[0, 0] + S[0, 1] * out[1, 0] + S[0, 2] * out[2, 0]
    for r in range(3):
        for q in range(3):
            out[r, q] /= det


@kernel
def _solve3(S: Array, v: Array) -> Array:
    """``S⁻¹ v`` for a 3×3 ``S``."""
    inv = np.empty((3, 3))
    _inverse3(S, inv)
    out = np.empty(3)
    for r in range(3):
        out[r] = inv[r, 0] * v[0] + inv[r, 1] * v[1] + inv[r, 2] * v[2]
    return out


@kernel
def _yaw_trig(inc: Array) -> Array:
    """Cosine and sine of each row's yaw, ``(k, 2)``."""
    out = np.empty((len(inc), 2))
    for i in range(len(inc)):
        out[i, 0], out[i, 1] = np.cos(inc[i, 2]), np.sin(inc[i, 2])
    return out


@kernel
def _walk_chain(start: Array, inc: Array, inc_trig: Array, moved: Array, lo: int, hi: int,
                out: Array, trig: Array) -> None:
    """Dead reckoning from ``start`` along ``inc ⊕ moved`` over increments ``lo:hi``: the
    world ``(x, y, yaw)`` of each (yaw unwrapped) in ``out`` and its yaw's cosine and sine
    in ``trig``; ``inc_trig``: :func:`_yaw_trig` of ``inc`` (the walks of one chain's steps
    share it, and :func:`_carry` takes each pose's from ``trig``: the sines and cosines were
    most of a fill's time)."""
    x, y, yaw = start[0], start[1], start[2]
    ch, sh = np.cos(yaw), np.sin(yaw)
    for i in range(lo, hi):
        c, s = inc_trig[i, 0], inc_trig[i, 1]
        dx = inc[i, 0] + c * moved[i, 0] - s * moved[i, 1]
        dy = inc[i, 1] + s * moved[i, 0] + c * moved[i, 1]
        x += ch * dx - sh * dy
        y += sh * dx + ch * dy
        yaw += inc[i, 2] + moved[i, 2]
        ch, sh = np.cos(yaw), np.sin(yaw)
        out[i, 0], out[i, 1], out[i, 2] = x, y, yaw
        trig[i, 0], trig[i, 1] = ch, sh


@kernel
def _carry(pose: Array, trig: Array, cov: Array, moved: Array, lo: int, hi: int,
           carried: Array, lin: Array) -> Array:
    """``S = Σ Aᵢ Σᵢ Aᵢᵀ`` over increments ``lo:hi`` at the walked ``pose`` (its yaws' cosines
    and sines ``trig``), ``Aᵢ = Ad(P_end⁻¹ Pᵢ)``: ``Aᵢ Σᵢ`` into ``carried[i]`` and
    ``Σ Aᵢ δᵢ`` (``moved``) taken from ``lin``; a step of :func:`fill` then moves the
    increments by ``δᵢ = −(Aᵢ Σᵢ)ᵀ S⁻¹ lin``. The 3×3 products by hand: a BLAS call per
    block costs more than the block."""
    end = hi - 1
    ce, se = trig[end, 0], trig[end, 1]
    S = np.zeros((3, 3))
    a = np.zeros((3, 3))
    a[2, 2] = 1.0
    for i in range(lo, hi):
        dx, dy = pose[i, 0] - pose[end, 0], pose[i, 1] - pose[end, 1]
        # cos and sin of the turn pose[i, 2] - pose[end, 2]
        ct = trig[i, 0] * ce + trig[i, 1] * se
        st = trig[i, 1] * ce - trig[i, 0] * se
        a[0, 0], a[0, 1], a[0, 2] = ct, -st, -se * dx + ce * dy
        a[1, 0], a[1, 1], a[1, 2] = st, ct, -(ce * dx + se * dy)
        ac = carried[i]
        for r in range(3):
            lin[r] -= a[r, 0] * moved[i, 0] + a[r, 1] * moved[i, 1] + a[r, 2] * moved[i, 2]
            for c in range(3):
                ac[r, c] = a[r, 0] * cov[i, 0, c] + a[r, 1] * cov[i, 1, c] + a[r, 2] * cov[i, 2, c]
        for r in range(3):
            for c in range(3):
                S[r, c] += ac[r, 0] * a[c, 0] + ac[r, 1] * a[c, 1] + ac[r, 2] * a[c, 2]
    return S


def perturbations(pose: Array, lo: int, inc: Array) -> Array:
    """The right perturbations ``δ`` that turn the increments ``inc`` into the increments of
    ``pose`` (rows by node) after ``lo``: ``inc ⊕ δ = pose[i−1]⁻¹ pose[i]``."""
    out = np.empty((len(inc), 3))
    _perturbations(np.ascontiguousarray(pose, dtype=float), int(lo),
                   np.ascontiguousarray(inc, dtype=float), out)
    return out


@kernel
def _perturbations(pose: Array, lo: int, inc: Array, out: Array) -> None:
    # Compiled: numpy's two between-compositions of kitti_00's last loop took 0.5 ms of a
    # condensed solve that has to fit a callback.
    for i in range(len(inc)):
        p, q = pose[lo + i], pose[lo + i + 1]
        rx, ry, ryaw = _between(p[0], p[1], p[2], q[0], q[1], q[2])
        out[i, 0], out[i, 1], out[i, 2] = _between(inc[i, 0], inc[i, 1], inc[i, 2],
                                                   rx, ry, ryaw)


def planar_chi2(a: np.ndarray, b: np.ndarray, meas: Array, info: Array, weight: Array,
                pose: Array, rows: np.ndarray | None = None) -> float:
    """``Σ wᵢ eᵢᵀ Ωᵢ eᵢ`` of planar relative edges ``a → b`` at world ``(x, y, yaw)`` rows
    ``pose``, ``e = meas⁻¹ (pose_a⁻¹ pose_b)``: a loop closure's correction scores thousands
    of edges several times inside a callback (numpy: 1 ms on kitti_00's last loop).
    ``rows``: the edges (rows of the arrays) summed; ``None``: all of them (the arrays'
    rows gathered per call cost more than the sum on kitti_00's last loop)."""
    rows = np.arange(len(a)) if rows is None else np.asarray(rows, dtype=np.int64)
    return float(_planar_chi2(rows, np.asarray(a, dtype=np.int64),
                              np.asarray(b, dtype=np.int64),
                              np.ascontiguousarray(meas, dtype=float),
                              np.ascontiguousarray(info, dtype=float),
                              np.ascontiguousarray(weight, dtype=float),
                              np.ascontiguousarray(pose, dtype=float)))


@kernel
def _planar_chi2(rows: np.ndarray, a: np.ndarray, b: np.ndarray, meas: Array, info: Array,
                 weight: Array, pose: Array) -> float:
    total = 0.0
    e = np.empty(3)
    for m in rows:
        i, j = a[m], b[m]
        rx, ry, ryaw = _between(pose[i, 0], pose[i, 1], pose[i, 2],
                                pose[j, 0], pose[j, 1], pose[j, 2])
        e[0], e[1], e[2] = _between(meas[m, 0], meas[m, 1], meas[m, 2], rx, ry, ryaw)
        quad = 0.0
        for r in range(3):
            for c in range(3):
                quad += e[r] * info[m, r, c] * e[c]
        total += weight[m] * quad
    return total


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
        return planar_chi2(self.a, self.b, self.meas, self.info, np.ones(len(self.a)), pose)

    def step(self, pose: Array, damping: float) -> Array:
        """The Gauss–Newton (Levenberg ``damping``) step's poses."""
        err, Ja, Jb = relative_jacobians(pose[self.a], pose[self.b], self.meas)
        return self._moved(pose, self._solve(Ja, Jb, self.info, err, damping))

    def rotations_first(self, pose: Array) -> Array:
        """LAGO's two linear solves (Carlone et al., "A fast and accurate approximation for
        planar pose graph optimization", IJRR 2014) from ``pose``: the yaws from the edges'
        yaw errors alone (weighed by their yaw variance; the wrap fixed at ``pose``), then
        the positions at those yaws. A start for Gauss–Newton where a closure's yaw error
        is too large for the chains' linearization (:data:`ROTATION_FIRST_RAD`).

        Both are solved in the Gauss–Newton step's system with the other unknowns held:
        a system of their own each cost more to build (0.5 ms on MIT's closure of 180
        poses) than its smaller factorization saves."""
        m = len(self.a)
        yaw_info = np.zeros((m, 3, 3))
        yaw_info[:, 2, 2] = 1.0 / np.linalg.inv(self.info)[:, 2, 2]
        turn = np.zeros((m, 3, 3))
        turn[:, 2, 2] = 1.0
        err = np.zeros((m, 3))
        err[:, 2] = geo.wrap_angle(pose[self.b, 2] - pose[self.a, 2] - self.meas[:, 2])
        turned = self._moved(pose, self._solve(-turn, turn, yaw_info, err, 0.0, held=_XY))
        err, Ja, Jb = relative_jacobians(turned[self.a], turned[self.b], self.meas)
        Ja[:, :, 2] = Jb[:, :, 2] = err[:, 2] = 0.0
        xy_info = self.info.copy()
        xy_info[:, 2, :] = xy_info[:, :, 2] = 0.0
        return self._moved(turned, self._solve(Ja, Jb, xy_info, err, 0.0, held=_YAW))

    def _moved(self, pose: Array, step: Array) -> Array:
        out = pose.copy()
        out[self.free] += step.reshape(len(self.free), 3)
        out[self.free, 2] = geo.wrap_angle(out[self.free, 2])
        return out

    def _solve(self, Ja: Array, Jb: Array, info: Array, err: Array, damping: float,
               held: tuple[int, ...] = ()) -> Array:
        """``(JᵀΩJ + damping · diag) δ = −JᵀΩe`` over the free nodes' columns of ``J``,
        the ``held`` unknowns of every node at zero (their columns of ``J`` must be zero)."""
        if self._pattern is None:
            # The system's sparsity: built once, refactored each step.
            object.__setattr__(self, "_pattern", _Pattern(self.a, self.b, self.free, 3))
        assert self._pattern is not None
        return self._pattern.solve(Ja, Jb, info, err, damping, held)

    _pattern: _Pattern | None = field(default=None, init=False, repr=False, compare=False)


#: Unknowns a rotations-first solve holds: a node's position, then its yaw.
_XY, _YAW = (0, 1), (2,)


class _Pattern:
    """The upper triangle of ``JᵀΩJ``'s sparsity for edges ``(a, b)`` with ``c`` unknowns
    per free node, and where each block entry lands in it: a Gauss–Newton step then only
    sums values into it and refactors (the symbolic analysis is the factor's, once). Built
    by scipy per step, the system took 1.2 ms of kitti_00's 405 reduced edges; in numpy
    with this pattern, a quarter; summed by one compiled pass, a tenth of that."""

    def __init__(self, a: np.ndarray, b: np.ndarray, free: np.ndarray, c: int) -> None:
        var = np.full(int(max(a.max(), b.max(), free.max())) + 1, -1, dtype=np.int64)
        var[free] = np.arange(len(free))
        self.c, self.n = c, c * len(free)
        self.var_a, self.var_b = var[a], var[b]
        # Each edge's block entry's place in the factor's values (-1: a held end, or below
        # the diagonal), so that a step sums its blocks in one compiled pass.
        self.slots = np.full((len(a), 2, 2, c, c), -1, dtype=np.int64)
        self.diag = np.empty(self.n, dtype=np.int64)
        indptr, indices = _pattern(self.var_a, self.var_b, len(free), self.slots, self.diag)
        self.nnz = len(indices)
        self.factor = SPDFactor(indptr, indices)

    def solve(self, Ja: Array, Jb: Array, info: Array, err: Array, damping: float,
              held: tuple[int, ...] = ()) -> Array:
        """The damped Gauss–Newton step of the free nodes, with the ``held`` unknowns of
        each (whose columns of ``J`` are zero) at zero."""
        data, g = np.zeros(self.nnz), np.zeros(self.n)
        _assemble(np.ascontiguousarray(Ja, dtype=float), np.ascontiguousarray(Jb, dtype=float),
                  np.ascontiguousarray(info, dtype=float), np.ascontiguousarray(err, dtype=float),
                  self.var_a, self.var_b, self.slots, data, g)
        data[self.diag] += damping * data[self.diag] + 1e-12
        if held:
            data[self.diag.reshape(-1, self.c)[:, held]] = 1.0
        return self.factor.solve(data, -g)


@kernel
def _pattern(var_a: np.ndarray, var_b: np.ndarray, free: int, slots: np.ndarray,
             diag: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The upper triangle of ``JᵀΩJ`` (every edge's blocks between free ends, and the whole
    diagonal) in CSC, ``(indptr, indices)``, and each edge's block entries' place in it
    (``slots``, left at -1 where an end is held or the entry is below the diagonal) and each
    diagonal entry's (``diag``). Built block by block: with ``c`` unknowns a node, scalar
    column ``c·v + j`` holds ``c`` rows of each block above the diagonal in block column
    ``v``, then rows ``0 … j`` of the diagonal block. Compiled: numpy's twenty calls took
    0.6-0.9 ms of a condensed solve that has to fit a callback."""
    c = slots.shape[3]
    blocks = np.empty(len(var_a) + free, dtype=np.int64)
    count = 0
    for e in range(len(var_a)):
        u, v = min(var_a[e], var_b[e]), max(var_a[e], var_b[e])
        if u >= 0 and u != v:
            blocks[count] = v * free + u
            count += 1
    for v in range(free):
        blocks[count] = v * free + v
        count += 1
    blocks = np.unique(blocks[:count])  # block column-major: CSC order
    first = np.zeros(free + 1, dtype=np.int64)  # each block column's first block
    for key in blocks:
        first[key // free + 1] += 1
    for v in range(free):
        first[v + 1] += first[v]
    indptr = np.zeros(c * free + 1, dtype=np.int64)
    for v in range(free):
        above = first[v + 1] - first[v] - 1
        for j in range(c):
            indptr[c * v + j + 1] = indptr[c * v + j] + c * above + j + 1
    indices = np.empty(indptr[-1], dtype=np.int64)
    for v in range(free):
        for j in range(c):
            at = indptr[c * v + j]
            for key in blocks[first[v]:first[v + 1]]:
                u = key % free
                for i in range(c if u != v else j + 1):
                    indices[at] = c * u + i
                    at += 1
            diag[c * v + j] = at - 1
    for e in range(len(var_a)):
        for p in range(2):
            vp = var_a[e] if p == 0 else var_b[e]
            for q in range(2):
                vq = var_a[e] if q == 0 else var_b[e]
                if vp < 0 or vq < 0 or vp > vq:
                    continue
                place = np.searchsorted(blocks, vq * free + vp) - first[vq]
                for j in range(c):
                    for i in range(c if vp != vq else j + 1):
                        slots[e, p, q, i, j] = indptr[c * vq + j] + c * place + i
    return indptr, indices


@kernel
def _assemble(Ja: Array, Jb: Array, info: Array, err: Array, var_a: np.ndarray,
              var_b: np.ndarray, slots: np.ndarray, data: Array, g: Array) -> None:
    """``JᵀΩJ`` summed into ``data`` at each edge's ``slots`` and ``JᵀΩe`` into ``g``."""
    d, c = Ja.shape[1], Ja.shape[2]
    jtw = np.empty((2, c, d))
    for e in range(len(err)):
        for p in range(2):
            J = Ja[e] if p == 0 else Jb[e]
            for i in range(c):
                for k in range(d):
                    total = 0.0
                    for j in range(d):
                        total += J[j, i] * info[e, j, k]
                    jtw[p, i, k] = total
            v = var_a[e] if p == 0 else var_b[e]
            if v < 0:
                continue
            for i in range(c):
                total = 0.0
                for k in range(d):
                    total += jtw[p, i, k] * err[e, k]
                g[c * v + i] += total
        for p in range(2):
            for q in range(2):
                J = Ja[e] if q == 0 else Jb[e]
                for i in range(c):
                    for j in range(c):
                        slot = slots[e, p, q, i, j]
                        if slot < 0:
                            continue
                        total = 0.0
                        for k in range(d):
                            total += jtw[p, i, k] * J[k, j]
                        data[slot] += total


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
