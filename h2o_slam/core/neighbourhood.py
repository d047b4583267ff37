"""Upper bounds on a group of edges' deletion χ² from the edges around it.

The deletion χ² of a group of edges ``g`` (how much the optimal χ² of the linearized map
falls without them) is ``rᵀ (I − J Σ Jᵀ)⁻¹ r`` in whitened terms, ``Σ = H⁻¹`` the map's
covariance: it needs blocks of the inverse of the whole graph's Gauss–Newton matrix. The
edges near the group give a bound instead. Leaving edges out of ``H`` can only raise the
covariance of what the rest still determine: with ``H_s`` the Gauss–Newton matrix of the
group's neighbourhood alone, ``H ⪰ H_s`` and so ``J H⁻¹ Jᵀ ⪯ J H_s⁺ Jᵀ`` for the relative
edges ``J`` of the group (their rows lie in ``H_s``'s range: a connected neighbourhood
leaves only the gauge free, and a relative edge does not see the gauge). Where
``I − J H_s⁺ Jᵀ`` is positive definite, its inverse bounds ``(I − J H⁻¹ Jᵀ)⁻¹`` from
above, and so its quadratic form bounds the deletion χ²; where it is not (the
neighbourhood holds the group's ends by the group alone), there is no bound.

On a 2,200-pose sphere the poses one edge away from a closure's ends bound every strained
closure's deletion χ² within a few per cent (median 1.04 times), each from a dense system
of 13 poses, where the graph's covariance at those closures cost a factorization and a
selected inverse of 3 million entries (0.35 s).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind
from h2o_slam.core.jacobians import endpoint_jacobians
from h2o_slam.core.solver import H2OSolver


def whitened_terms(solver: H2OSolver, edges: np.ndarray, weighted: bool = False,
                   poses: tuple[Array, Array] | None = None) -> tuple[Array, Array]:
    """Whitened residuals (``e × p``) and Jacobians on both ends (``e × p × 2p``, the first
    end's ``p`` columns first) of ``edges`` at the solver's map (its world ``poses``, when
    the caller has them); ``weighted``: scaled by the square root of each edge's robust
    weight, as the Gauss–Newton matrix holds them."""
    dof = solver.dof
    R, x = solver.world_poses() if poses is None else poses
    a, b = solver.a[edges], solver.b[edges]
    glob = a == EARTH
    ia = np.where(glob, 0, a)
    err, Ja, Jb = endpoint_jacobians(
        solver.kind[edges], np.where(glob[:, None, None], np.eye(3), R[ia]),
        np.where(glob[:, None], 0.0, x[ia]), R[b], x[b], solver.meas_R[edges],
        solver.meas_t[edges])
    table = solver._edges
    W = (table.W if weighted else table.W_unit)[edges]
    r = np.einsum("eij,ej->ei", W, err[:, dof])
    J = np.concatenate([Ja[:, dof][:, :, dof], Jb[:, dof][:, :, dof]], axis=2)
    return r, np.einsum("eij,ejk->eik", W, J)


def deletion_bounds(solver: H2OSolver, groups: list[np.ndarray], hops: int = 1) -> Array:
    """An upper bound on each group's deletion χ² (:func:`h2o_slam.core.robust.group_chi2`
    with ``sign`` −1) from the relative edges of weight above zero among the poses at most
    ``hops`` edges from the group's ends (module docstring); ``inf`` where there is none: a
    group with an edge to the earth, or whose neighbourhood holds its ends only through it.
    Each group's edges must be in the map (weight 1)."""
    m = solver.num_edges
    a, b = solver.a[:m], solver.b[:m]
    used = np.flatnonzero((solver.kind[:m] == EdgeKind.RELATIVE) & (a != EARTH)
                          & (solver.weight[:m] > 0.0))
    near = _Incidence(solver.num_nodes, a[used], b[used])
    poses = solver.world_poses()
    out = np.full(len(groups), np.inf)
    for i, group in enumerate(groups):
        group = np.asarray(group, dtype=np.int64)
        if np.any(a[group] == EARTH):
            continue
        nodes = near.around(np.unique(np.concatenate([a[group], b[group]])), hops)
        local = used[near.edges_within(nodes)]
        out[i] = _bound(solver, poses, group, nodes, local)
    return out


class _Incidence:
    """Which nodes the edges join (``a``, ``b``: the edges' ends) and which edges each node
    has, for neighbourhoods."""

    def __init__(self, n: int, a: np.ndarray, b: np.ndarray) -> None:
        m = len(a)
        ones = np.ones(2 * m)
        ends = np.concatenate([a, b])
        self.node_edge = sp.csr_matrix((ones, (ends, np.tile(np.arange(m), 2))), shape=(n, m))
        self.a, self.b, self.n = a, b, n

    def around(self, nodes: np.ndarray, hops: int) -> np.ndarray:
        """``nodes`` and every node at most ``hops`` edges from one, sorted."""
        inside = np.zeros(self.n, dtype=bool)
        inside[nodes] = True
        for _ in range(hops):
            edges = np.unique(self.node_edge[np.flatnonzero(inside)].indices)
            inside[self.a[edges]] = inside[self.b[edges]] = True
        return np.flatnonzero(inside)

    def edges_within(self, nodes: np.ndarray) -> np.ndarray:
        """The edges (positions in ``a``, ``b``) with both ends among ``nodes``."""
        inside = np.zeros(self.n, dtype=bool)
        inside[nodes] = True
        edges = np.unique(self.node_edge[nodes].indices)
        return edges[inside[self.a[edges]] & inside[self.b[edges]]]


def _bound(solver: H2OSolver, poses: tuple[Array, Array], group: np.ndarray,
           nodes: np.ndarray, local: np.ndarray) -> float:
    """The group's deletion χ² bound from the Gauss–Newton matrix of the ``local`` edges
    over ``nodes``, the first node of each of their connected pieces held (its gauge: a
    place's closures on a ring may each have a piece of their own)."""
    from scipy.sparse.csgraph import connected_components  # on use: a module of 0.1 s

    p = solver.p
    slot = np.full(solver.num_nodes, -1, dtype=np.int64)
    slot[nodes] = np.arange(len(nodes))
    ends = sp.coo_matrix((np.ones(len(local)), (slot[solver.a[local]], slot[solver.b[local]])),
                         shape=(len(nodes), len(nodes)))
    _, piece = connected_components(ends, directed=False)
    free = np.ones(len(nodes), dtype=bool)
    free[np.unique(piece, return_index=True)[1]] = False
    slot[nodes] = np.where(free, np.cumsum(free) - 1, -1)
    size = int(free.sum()) * p

    def unknowns(edges: np.ndarray) -> np.ndarray:  # e × 2p, -1 where the end is held
        ends = np.stack([slot[solver.a[edges]], slot[solver.b[edges]]], axis=1)
        var = np.where(ends[:, :, None] >= 0, ends[:, :, None] * p + np.arange(p), -1)
        return var.reshape(len(edges), 2 * p)

    _, J = whitened_terms(solver, local, weighted=True, poses=poses)
    H = np.zeros((size + 1, size + 1))  # the last row and column gather the held ends'
    var = unknowns(local)
    np.add.at(H, (var[:, :, None], var[:, None, :]), np.einsum("eki,ekj->eij", J, J))
    r, Jg = whitened_terms(solver, group, poses=poses)
    rows = len(group) * p
    B = np.zeros((size + 1, rows))
    cols = np.arange(rows).reshape(len(group), p)
    np.add.at(B, (unknowns(group)[:, None, :], cols[:, :, None]), Jg)
    try:
        Y = np.linalg.solve(np.linalg.cholesky(H[:size, :size]), B[:size])
        S = np.linalg.cholesky(np.eye(rows) - Y.T @ Y)
    except np.linalg.LinAlgError:  # no bound: the group alone holds its ends here
        return np.inf
    y = np.linalg.solve(S, r.ravel())
    return float(y @ y)
