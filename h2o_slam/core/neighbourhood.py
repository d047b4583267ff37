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
of 13 poses (0.1 ms), where the graph's covariance at those closures cost a factorization
and a selected inverse of 3 million entries (0.35 s). A sparse graph bounds less well: one
edge around bounds half the closures of a 1,000-pose 3-D lattice walk below the bar a drop
must pass, three edges 89 % (intel: 84 % and 99 %).
"""

from __future__ import annotations

import numpy as np

from h2o_slam.core.compiled import kernel
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind
from h2o_slam.core.jacobians import endpoint_jacobians
from h2o_slam.core.solver import H2OSolver


def whitened_terms(solver: H2OSolver, edges: np.ndarray, weighted: bool = False
                   ) -> tuple[Array, Array]:
    """Whitened residuals (``e × p``) and Jacobians on both ends (``e × p × 2p``, the first
    end's ``p`` columns first) of ``edges`` at the solver's map; ``weighted``: scaled by the
    square root of each edge's robust weight, as the Gauss–Newton matrix holds them."""
    dof = solver.dof
    R, x = solver.world_poses()
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
    group with an edge to the earth, one whose neighbourhood holds its ends only through it,
    or one whose neighbourhood has more than :data:`MAX_UNKNOWNS` unknowns. Each group's
    edges must be in the map (weight 1)."""
    return Neighbourhoods(solver).bounds(groups, hops)


class Neighbourhoods:
    """The solver's map as :func:`deletion_bounds` reads it, built once for bounds at
    several reaches: the edges in it, which edges each node has, and every edge's whitened
    Jacobians and residual (on a 2,200-pose sphere the Jacobians alone are 3 ms)."""

    def __init__(self, solver: H2OSolver) -> None:
        m = solver.num_edges
        a, b = solver.a[:m], solver.b[:m]
        used = np.flatnonzero((solver.kind[:m] == EdgeKind.RELATIVE) & (a != EARTH)
                              & (solver.weight[:m] > 0.0))
        self._position = np.full(m, -1, dtype=np.int64)
        self._position[used] = np.arange(len(used))
        self._r, self._J = whitened_terms(solver, used, weighted=True)
        ends = np.concatenate([a[used], b[used]])
        self._incident = (np.argsort(ends, kind="stable") % max(len(used), 1)).astype(np.int64)
        self._ptr = np.concatenate([[0], np.cumsum(np.bincount(ends, minlength=solver.num_nodes))
                                    ]).astype(np.int64)
        self._a = np.ascontiguousarray(a[used], dtype=np.int64)
        self._b = np.ascontiguousarray(b[used], dtype=np.int64)

    def bounds(self, groups: list[np.ndarray], hops: int) -> Array:
        """:func:`deletion_bounds` of ``groups`` at ``hops`` edges around."""
        out = np.full(len(groups), np.inf)
        members = [self._position[np.asarray(g, dtype=np.int64)] for g in groups]
        bounded = [i for i, g in enumerate(members) if len(g) and np.all(g >= 0)]
        if not bounded:
            return out
        sizes = [len(members[i]) for i in bounded]
        found = np.full(len(bounded), np.inf)
        _bounds(self._ptr, self._incident, self._a, self._b, self._J, self._r,
                np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
                np.concatenate([members[i] for i in bounded]), hops, MAX_UNKNOWNS, found)
        out[bounded] = found
        return out


#: Most unknowns of a neighbourhood's dense system (beyond: no bound, the group is scored
#: on the whole graph): a factorization of about a thousand rows, 25 ms. A 12-closure
#: candidate of a 2,200-pose sphere takes 600-900 one edge around.
MAX_UNKNOWNS = 900


@kernel
def _bounds(ptr: np.ndarray, incident: np.ndarray, ea: np.ndarray, eb: np.ndarray,
            J: Array, r: Array, group_ptr: np.ndarray, group_edges: np.ndarray, hops: int,
            max_unknowns: int, out: Array) -> None:
    """:func:`deletion_bounds` of each group (``group_edges[group_ptr[g]:group_ptr[g+1]]``,
    positions among the edges ``ea``–``eb`` with whitened Jacobians ``J`` and residuals
    ``r``; ``incident[ptr[v]:ptr[v+1]]``: the edges at node ``v``) into ``out``."""
    n = len(ptr) - 1
    p = r.shape[1]
    stamp = np.full(n, -1, dtype=np.int64)
    where = np.zeros(n, dtype=np.int64)
    nodes = np.empty(n, dtype=np.int64)
    for g in range(len(group_ptr) - 1):
        edges = group_edges[group_ptr[g]:group_ptr[g + 1]]
        count = 0
        for e in edges:
            for v in (ea[e], eb[e]):
                if stamp[v] != g:
                    stamp[v] = g
                    nodes[count] = v
                    count += 1
        count = _grow(ptr, incident, ea, eb, nodes, count, stamp, g, hops,
                      max_unknowns // p + 1)
        if count * p > max_unknowns + p:
            continue
        for i in range(count):
            where[nodes[i]] = i
        local = _edges_within(ptr, incident, ea, eb, nodes[:count], stamp, g)
        slot = _unknown_slots(local, ea, eb, where, count)
        out[g] = _bound(J, r, edges, local, ea, eb, where, slot, p)


@kernel
def _grow(ptr: np.ndarray, incident: np.ndarray, ea: np.ndarray, eb: np.ndarray,
          nodes: np.ndarray, count: int, stamp: np.ndarray, g: int, hops: int,
          most: int) -> int:
    """``nodes[:count]`` and every node at most ``hops`` edges away, marked ``g`` in
    ``stamp``; stops past ``most`` nodes. Returns the count."""
    begin = 0
    for _ in range(hops):
        end = count
        for i in range(begin, end):
            v = nodes[i]
            for k in range(ptr[v], ptr[v + 1]):
                e = incident[k]
                w = eb[e] if ea[e] == v else ea[e]
                if stamp[w] != g:
                    stamp[w] = g
                    nodes[count] = w
                    count += 1
                    if count > most:
                        return count
        begin = end
    return count


@kernel
def _edges_within(ptr: np.ndarray, incident: np.ndarray, ea: np.ndarray, eb: np.ndarray,
                  nodes: np.ndarray, stamp: np.ndarray, g: int) -> np.ndarray:
    """The edges with both ends among ``nodes`` (those marked ``g``), each once."""
    total = 0
    for v in nodes:
        total += ptr[v + 1] - ptr[v]
    found = np.empty(total, dtype=np.int64)
    count = 0
    for v in nodes:
        for k in range(ptr[v], ptr[v + 1]):
            e = incident[k]
            if ea[e] == v and eb[e] != v and stamp[eb[e]] == g:
                found[count] = e
                count += 1
    return found[:count]


@kernel
def _unknown_slots(local: np.ndarray, ea: np.ndarray, eb: np.ndarray, where: np.ndarray,
                   count: int) -> np.ndarray:
    """Each of the ``count`` nodes' block among the unknowns, -1 for the first node of each
    connected piece of the ``local`` edges (held: its gauge)."""
    root = np.arange(count)
    for e in local:
        i, j = _find(root, where[ea[e]]), _find(root, where[eb[e]])
        if i != j:
            root[max(i, j)] = min(i, j)
    slot = np.full(count, -1, dtype=np.int64)
    free = 0
    for i in range(count):
        if _find(root, i) != i:
            slot[i] = free
            free += 1
    return slot


@kernel
def _find(root: np.ndarray, i: int) -> int:
    while root[i] != i:
        root[i] = root[root[i]]
        i = root[i]
    return i


@kernel
def _bound(J: Array, r: Array, group: np.ndarray, local: np.ndarray, ea: np.ndarray,
           eb: np.ndarray, where: np.ndarray, slot: np.ndarray, p: int) -> float:
    """The group's bound from the dense Gauss–Newton matrix ``H`` of the ``local`` edges
    over the unknowns ``slot`` (module docstring); ``inf`` where a factor fails. One
    Cholesky factorization of ``[[H, B], [Bᵀ, I]]`` (``B = J_gᵀ``): its last block is the
    factor of the Schur complement ``I − J_g H⁻¹ J_gᵀ``."""
    size = (slot.max() + 1) * p
    rows = len(group) * p
    M = np.zeros((size + rows, size + rows))
    for e in local:
        _add_normal(M, J[e], slot[where[ea[e]]], slot[where[eb[e]]], p)
    for q in range(len(group)):
        e = group[q]
        for side in range(2):
            s = slot[where[ea[e] if side == 0 else eb[e]]]
            if s < 0:
                continue
            for i in range(p):
                for c in range(p):
                    M[size + q * p + i, s * p + c] += J[e, i, side * p + c]
    for i in range(rows):
        M[size + i, size + i] = 1.0
    try:  # the factorization reads the lower triangle only: J_g's block is written there
        L = np.linalg.cholesky(M)
    except Exception:  # noqa: BLE001 - numba raises no narrower one: no bound
        return np.inf
    y = np.empty(rows)
    for i in range(rows):
        total = r[group[i // p], i % p]
        for k in range(i):
            total -= L[size + i, size + k] * y[k]
        y[i] = total / L[size + i, size + i]
    return float(np.sum(y * y))


@kernel
def _add_normal(H: Array, J: Array, sa: int, sb: int, p: int) -> None:
    """``JᵀJ`` of one edge (``p × 2p``, ends at unknown blocks ``sa``, ``sb``; -1: held)."""
    for side_i, si in ((0, sa), (1, sb)):
        if si < 0:
            continue
        for side_j, sj in ((0, sa), (1, sb)):
            if sj < 0:
                continue
            for i in range(p):
                for j in range(p):
                    total = 0.0
                    for k in range(p):
                        total += J[k, side_i * p + i] * J[k, side_j * p + j]
                    H[si * p + i, sj * p + j] += total
