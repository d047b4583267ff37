"""Exact mode: Gauss–Newton on all edges at once, as the batch of every edge (thesis 3.3.8).

Solved in world coordinates, where ``JᵀJ`` has the sparsity of the graph (the tree's local
coordinates would make every edge's domain a dense clique), then mapped to the tree's local
coordinates by the exact linear change of variables, so that the step is the solver's own.

* :class:`ExactSystem` — linearizes every edge of an :class:`~h2o_slam.core.solver.H2OSolver`
  and solves the (damped) normal equations; it keeps the sparsity pattern and the
  factorization's symbolic analysis while the edges and the free nodes stay
  (:class:`WorldSystem`).
* :func:`converge_exact` — Levenberg-damped Gauss–Newton to convergence: what
  ``h2o-solve --mode exact`` runs and what the anytime back end
  (:mod:`h2o_slam.core.converge`) runs beside the budgeted updates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from h2o_slam.core import geometry as geo
from h2o_slam.core.compiled import kernel
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH
from h2o_slam.core.jacobians import endpoint_jacobians_one
from h2o_slam.core.solver import H2OSolver
from h2o_slam.core.spd import SPDFactor


@dataclass(frozen=True)
class WorldLinearization:
    """All edges linearized at one estimate, in world coordinates (exact mode): the world
    poses, the normal equations' values in ``system``'s pattern, and the χ² there."""

    R: Array
    x: Array
    system: WorldSystem
    data: Array  # H = JᵀJ, undamped
    g: Array  # Jᵀr
    chi2: float


class ExactSystem:
    """The Gauss–Newton system of all of ``solver``'s edges; see the module docstring."""

    def __init__(self, solver: H2OSolver) -> None:
        self.solver = solver
        self._world: WorldSystem | None = None

    def linearize(self, kept: WorldSystem | None = None) -> WorldLinearization:
        """Every edge linearized at the solver's current estimate.

        ``kept``: the system of an earlier linearization, for a caller that knows the edges
        and the tree's structure have not changed since (the iterations of one solve): the
        free nodes are then not derived and compared again.
        """
        R, x = self.solver.world_poses()
        return self.linearize_at(R, x, self.system() if kept is None else kept)

    def linearize_at(self, R: Array, x: Array, system: WorldSystem) -> WorldLinearization:
        """Every edge of ``system`` linearized at the world poses ``(R, x)``, which need not
        be the solver's: a step is scored before the tree takes it."""
        data, g, chi2 = system.normal_equations(self.solver, R, x)
        return WorldLinearization(R, x, system, data, g, chi2)

    def trial(self, lin: WorldLinearization, damping: float = 0.0) -> tuple[Array, Array]:
        """The world poses the damped step from ``lin`` leads to (the tree untouched):
        each pose moved on its own, ``R ← Exp(ω) R``, ``x ← x + δx`` (see :meth:`move`)."""
        return _retracted(lin.R, lin.x, self._world_step(lin, damping))

    def step(self, damping: float = 0.0, lin: WorldLinearization | None = None
             ) -> tuple[Array, np.ndarray]:
        """The Gauss–Newton step of all edges as a local step per node, without applying it:
        the batch of every edge in the tree's coordinates (what :meth:`H2OSolver.relax_batch`
        takes, to first order).

        ``damping`` adds ``damping · diag(H)`` (Levenberg–Marquardt). ``lin``: the
        linearization at the current estimate, when the caller has it.

        Returns:
            ``(x, nodes)``: the local step ``(len(nodes), p)`` for the nodes that move.
        """
        lin = self.linearize() if lin is None else lin
        step = self._world_step(lin, damping)
        free, dof = lin.system.free, self.solver.dof
        return self._world_to_local(lin.R, lin.x, step)[:, dof][free], free

    def move(self, lin: WorldLinearization, damping: float = 0.0) -> None:
        """Take the step from ``lin`` in world coordinates, each pose on its own
        (``R ← Exp(ω) R``, ``x ← x + δx``), and rebuild the tree's local transforms from the
        new poses.

        The same step as :meth:`step` to first order, but applied in the tree's coordinates
        a rotation near the root swings its whole subtree along an arc, not the tangent the
        linearization saw: from a far start (an odometry chain over 10,000 poses) those
        steps were refused, the damping rose and 100 iterations ended 860× above the optimum
        that world-coordinate steps reach in a dozen.
        """
        # set_world_poses renormalizes the local rotations it derives.
        self.solver.tree.set_world_poses(*self.trial(lin, damping))

    def _world_step(self, lin: WorldLinearization, damping: float) -> Array:
        """The damped Gauss–Newton step ``(δx, ω)`` of every node, ``(n, 6)`` (zero where held)."""
        solver, system = self.solver, lin.system
        step = np.zeros((solver.num_nodes, 6))
        step[system.free[:, None], solver.dof] = -system.solve(
            system.damped(lin.data, damping), lin.g).reshape(len(system.free), solver.p)
        return step

    def normal_equations(self) -> tuple[sp.csc_matrix, Array, np.ndarray]:
        """``(H, g, free)`` at the current estimate: the full symmetric ``H = JᵀJ`` and
        ``g = Jᵀr`` over the free nodes' world perturbations (node-major, ``p`` per node),
        and the free nodes."""
        system = self.system()
        data, g, _ = system.normal_equations(self.solver, *self.solver.world_poses())
        return system.matrix(data), g, system.free

    def system(self) -> WorldSystem:
        """The system of the solver's edges and free nodes: the kept one while they stay.

        Edges at robust weight 0 are left out of the pattern (both ends held, as the
        earth): they add nothing to ``H``, but a false loop closure between distant poses
        would still add its block and the fill it causes. On city10000 with 1,000 random
        false closures the factorization was 92 % of a robust solve that did not finish in
        10 minutes."""
        s = self.solver
        out = s.weight <= 0.0
        a, b = np.where(out, EARTH, s.a), np.where(out, EARTH, s.b)
        free = self._free_nodes(s.a[~out], s.b[~out])
        system = self._world
        if system is None or not system.fits(a, b, free, s.num_nodes):
            system = self._world = WorldSystem(a, b, free, s.num_nodes, s.p)
        return system

    def _free_nodes(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        # A subtree top moves only if some edge's root is the earth: a global edge into its
        # subtree, or a relative edge to another subtree. Otherwise it holds the gauge.
        tree, n = self.solver.tree, self.solver.num_nodes
        tops = tree.tops()
        moved = np.zeros(n, dtype=bool)
        glob = a == EARTH
        moved[tops[b[glob]]] = True
        rel = ~glob
        cross = tops[a[rel]] != tops[b[rel]]
        moved[tops[a[rel][cross]]] = True
        moved[tops[b[rel][cross]]] = True
        is_top = tree.parent[:n] == EARTH
        return np.flatnonzero(~is_top | moved)

    def _world_to_local(self, R: Array, x: Array, step: Array) -> Array:
        """Map world perturbations ``(δx, ω)`` of every node to local ``(δt, δθ)``.

        From ``ω_n = ω_p + R_n δθ_n`` and ``δx_n = δx_p − [x_n − x_p]× ω_p + R_p δt_n``.
        """
        parent = self.solver.tree.parent[: self.solver.num_nodes]
        top = parent == EARTH
        p = np.where(top, 0, parent)
        dx_p = np.where(top[:, None], 0.0, step[p, :3])
        w_p = np.where(top[:, None], 0.0, step[p, 3:])
        R_p = np.where(top[:, None, None], np.eye(3), R[p])
        x_p = np.where(top[:, None], 0.0, x[p])
        moved = step[:, :3] - dx_p + np.cross(x - x_p, w_p)
        out = np.empty_like(step)
        out[:, :3] = np.einsum("nji,nj->ni", R_p, moved)
        out[:, 3:] = np.einsum("nji,nj->ni", R, step[:, 3:] - w_p)
        return out


def damped_step(system: ExactSystem, lin: WorldLinearization, damping: float
                ) -> tuple[float | None, WorldLinearization]:
    """Take one exact Gauss–Newton step from the linearization ``lin`` (at the solver's
    estimate), raising the Levenberg damping until χ² does not rise.

    Returns the damping to use next (None when no step helps) and the linearization at the
    new estimate (``lin`` when none): its χ² scores the step, its system gives the next one.
    """
    for _ in range(12):
        new = scored_step(system, lin, damping)
        damping = next_damping(damping, new is not None)
        if new is not None:
            system.solver.tree.set_world_poses(new.R, new.x)
            return damping, new
    return None, lin


def scored_step(system: ExactSystem, lin: WorldLinearization, damping: float
                ) -> WorldLinearization | None:
    """The step from ``lin`` at ``damping`` scored at its poses, the tree untouched: the
    linearization there when χ² did not rise (the tree may take its poses), else ``None``.
    A step moves poses, never the structure: ``lin``'s system serves."""
    R, x = system.trial(lin, damping)
    new = system.linearize_at(R, x, lin.system)
    return new if np.isfinite(new.chi2) and new.chi2 <= lin.chi2 else None


#: Damping beyond which a step that still raises χ² means the estimate is at a minimum
#: (``damped_step`` gives up after 12 tries from 0: 1e-6 · 10¹¹).
MAX_DAMPING = 1e5


def settled(before: float, after: float, tolerance: float) -> bool:
    """A step from χ² ``before`` to ``after`` lowered it by no more than ``tolerance`` of
    it: :func:`converge_exact`'s test of convergence."""
    return before - after <= tolerance * max(before, 1e-300)


def next_damping(damping: float, accepted: bool) -> float:
    """Levenberg's schedule: a tenth after a step that helped (none once it is negligible),
    ten times (at least 1e-6) after one that did not."""
    if accepted:
        return damping / 10.0 if damping > 1e-9 else 0.0
    return max(1e-6, damping * 10.0)


def converge_exact(solver: H2OSolver, iterations: int) -> tuple[list[float], bool]:
    """Damped Gauss–Newton on all of the solver's edges until the relative χ² decrease falls
    to ``config.exact_tolerance`` or no step helps (converged), or ``iterations`` run out.

    Returns the χ² after each iteration (the first entry is the start) and whether it
    converged.
    """
    tol = solver.config.exact_tolerance
    system = ExactSystem(solver)
    lin = system.linearize()
    history = [lin.chi2]
    damping = 0.0
    for _ in range(iterations):
        current = history[-1]
        damping_next, lin = damped_step(system, lin, damping)
        if damping_next is None:
            return history, True
        damping = damping_next
        history.append(lin.chi2)
        if settled(current, lin.chi2, tol):
            return history, True
    return history, False


class WorldSystem:
    """The Gauss–Newton normal equations of all edges in world coordinates, for fixed edges
    and free nodes: ``H = JᵀJ`` (upper triangle, CSC) and ``g = Jᵀr``.

    Built once per set of edges and free nodes and reused by every iteration and damping
    retry: the sparsity pattern, the map that scatters every edge's ``[J_a | J_b]ᵀ[J_a |
    J_b]`` into it (summed by :func:`_normal_equations` as it linearizes each edge), and the
    factorization's symbolic analysis (:class:`~h2o_slam.core.spd.SPDFactor`).

    Args:
        a, b: endpoints of every edge (``a`` is :data:`EARTH` for global edges).
        free: the nodes solved for; the others (and the earth) are held.
        num_nodes: nodes in the graph.
        p: unknowns per node (3 planar, 6 otherwise).
        edges: the solver's edges that ``a`` and ``b`` are the ends of (``None``: all of
            them, in order): a system of part of the graph, such as the poses one loop
            closure moves (:mod:`h2o_slam.core.loop_spread`).
    """

    def __init__(
        self, a: np.ndarray, b: np.ndarray, free: np.ndarray, num_nodes: int, p: int,
        edges: np.ndarray | None = None,
    ) -> None:
        self.a, self.b, self.free = a.copy(), b.copy(), free.copy()
        self.num_nodes, self.p = num_nodes, p
        self.edges = edges
        nf = len(free)
        self.size = size = nf * p
        # Block column of each edge's endpoints, -1 where held (block[-1]: the earth's).
        block = np.full(num_nodes + 1, -1, dtype=np.int64)
        block[free] = np.arange(nf)
        ends = np.stack([block[a], block[b]], axis=1)  # (m, 2)
        # Off-diagonal blocks (upper: row block < column block), sorted column-major; each
        # edge's rank among the blocks of its column. Diagonal blocks: every free node.
        both = np.all(ends >= 0, axis=1)
        lo, hi = ends.min(axis=1), ends.max(axis=1)
        keys, which = np.unique(hi[both] * nf + lo[both], return_inverse=True)
        key_col, key_row = keys // max(nf, 1), keys % max(nf, 1)
        first = np.searchsorted(key_col, np.arange(nf))
        per_col = np.bincount(key_col, minlength=nf)  # off-diagonal blocks per block column
        rank = np.full(len(a), -1, dtype=np.int64)
        rank[both] = which - first[hi[both]]
        # CSC: scalar column (j, v) holds its off-diagonal blocks' p rows each, then the
        # diagonal block's rows u ≤ v.
        u = np.arange(p)
        counts = (per_col[:, None] * p + u + 1).ravel()
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.nnz = nnz = int(self.indptr[-1])
        start = self.indptr[:-1].reshape(nf, p)  # first entry of scalar column (j, v)
        self.indices = np.empty(nnz, dtype=np.int64)
        off = start[key_col][:, None, :] + ((np.arange(len(keys)) - first[key_col]) * p)[
            :, None, None] + u[None, :, None]  # (blocks, u, v)
        self.indices[off.ravel()] = np.broadcast_to(
            (key_row * p)[:, None, None] + u[None, :, None], off.shape).ravel()
        upper_uv = u[:, None] <= u[None, :]
        diag = start[:, None, :] + (per_col * p)[:, None, None] + u[None, :, None]
        rows = np.broadcast_to((np.arange(nf) * p)[:, None, None] + u[None, :, None], diag.shape)
        self.indices[diag[:, upper_uv].ravel()] = rows[:, upper_uv].ravel()
        self._diag = (start + (per_col * p)[:, None] + u).ravel()
        # Where each entry (s, t) of an edge's [J_a | J_b]ᵀ[J_a | J_b] goes (nnz: dropped).
        side = np.repeat([0, 1], p)
        uu = np.tile(u, 2)
        rs = ends[:, side][:, :, None]
        ct = ends[:, side][:, None, :]
        us, vt = uu[None, :, None], uu[None, None, :]
        keep = (rs >= 0) & (ct >= 0) & ((rs < ct) | ((rs == ct) & (us <= vt)))
        blk = np.where(rs == ct, per_col[ct], rank[:, None, None])
        pos = self.indptr[ct * p + vt] + blk * p + us
        self._scatter = np.where(keep, pos, nnz).ravel()
        var = np.where(ends[:, side] >= 0, ends[:, side] * p + uu, size)
        self._gather = var.ravel()
        self.factor = SPDFactor(self.indptr, self.indices)

    @property
    def factor_ready(self) -> bool:
        """The factorization's symbolic analysis is done (a solve ran on this system)."""
        return self.factor.analyzed

    def fits(self, a: np.ndarray, b: np.ndarray, free: np.ndarray, num_nodes: int) -> bool:
        """Whether this system is the one of these edges and free nodes."""
        return (num_nodes == self.num_nodes and np.array_equal(free, self.free)
                and np.array_equal(a, self.a) and np.array_equal(b, self.b))

    def normal_equations(self, solver: H2OSolver, R: Array, x: Array
                         ) -> tuple[Array, Array, float]:
        """Values of ``H = JᵀJ`` in the pattern's order, ``g = Jᵀr`` and ``χ² = rᵀr`` of
        ``solver``'s edges (whitened; those of :attr:`edges` when set) at the world poses
        ``(R, x)``, in one compiled pass."""
        e = self.edges
        if e is None:
            return _normal_equations(solver.kind, solver.a, solver.b, R, x, solver.meas_R,
                                     solver.meas_t, solver.W, solver.dof, self._scatter,
                                     self._gather, self.nnz, self.size)
        return _normal_equations(solver.kind[e], solver.a[e], solver.b[e], R, x,
                                 solver.meas_R[e], solver.meas_t[e], solver.W[e], solver.dof,
                                 self._scatter, self._gather, self.nnz, self.size)

    def damped(self, data: Array, damping: float) -> Array:
        """``data`` of ``H + damping · diag(H)`` (a copy when ``damping > 0``)."""
        if damping <= 0.0:
            return data
        out = data.copy()
        out[self._diag] *= 1.0 + damping
        return out

    def matrix(self, data: Array) -> sp.csc_matrix:
        """The full symmetric matrix with values ``data``."""
        U = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))
        return (U + sp.triu(U, k=1).T).tocsc()

    def solve(self, data: Array, g: Array) -> Array:
        """``H⁻¹ g``; for a singular ``H`` (a direction no edge constrains) the minimum-norm
        least-squares solution."""
        try:
            return self.factor.solve(data, g)
        except np.linalg.LinAlgError:
            H = self.matrix(data)
            import scipy.sparse.linalg as spla  # singular systems only: 0.1 s of import

            return spla.lsqr(H, g, atol=1e-14, btol=1e-14, iter_lim=10 * self.size)[0]


@kernel
def _normal_equations(kind: np.ndarray, a: np.ndarray, b: np.ndarray, R: Array, x: Array,
                      meas_R: Array, meas_t: Array, W: Array, dof: np.ndarray,
                      scatter: np.ndarray, gather: np.ndarray, nnz: int, size: int
                      ) -> tuple[Array, Array, float]:
    """Every edge's whitened ``J = W [J_a | J_b]`` (``p × 2p``, world perturbations of its
    endpoints) and ``r = W e``, summed into ``H``'s values through ``scatter`` and into
    ``g`` through ``gather`` (index ``nnz`` / ``size``: a held node's entry, dropped)."""
    p = len(dof)
    q = 2 * p
    data = np.zeros(nnz + 1)
    g = np.zeros(size + 1)
    chi2 = 0.0
    eye, zero = np.eye(3), np.zeros(3)
    J = np.empty((p, q))
    r = np.empty(p)
    for e in range(len(kind)):
        glob = a[e] == EARTH
        err, Ja, Jb = endpoint_jacobians_one(
            kind[e], eye if glob else R[a[e]], zero if glob else x[a[e]], R[b[e]], x[b[e]],
            meas_R[e], meas_t[e])
        We = W[e]
        for i in range(p):
            acc = 0.0
            for k in range(p):
                acc += We[i, k] * err[dof[k]]
            r[i] = acc
            chi2 += acc * acc
            for j in range(p):
                sa = 0.0
                sb = 0.0
                for k in range(p):
                    sa += We[i, k] * Ja[dof[k], dof[j]]
                    sb += We[i, k] * Jb[dof[k], dof[j]]
                J[i, j] = sa
                J[i, p + j] = sb
        base = e * q * q
        for u in range(q):
            grad = 0.0
            for i in range(p):
                grad += J[i, u] * r[i]
            g[gather[e * q + u]] += grad
            for v in range(q):
                acc = 0.0
                for i in range(p):
                    acc += J[i, u] * J[i, v]
                data[scatter[base + u * q + v]] += acc
    return data[:nnz], g[:size], chi2


@kernel
def _retracted(R: Array, x: Array, step: Array) -> tuple[Array, Array]:
    """World poses moved by ``step`` ``(δx, ω)`` each: ``R ← Exp(ω) R``, ``x ← x + δx``."""
    R_new = np.empty_like(R)
    x_new = np.empty_like(x)
    for i in range(len(R)):
        geo.mul3_into(geo.so3_exp_one(step[i, 3:]), R[i], R_new[i])
        x_new[i] = x[i] + step[i, :3]
    return R_new, x_new
