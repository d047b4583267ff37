"""Errors and Jacobians of the edge kinds (thesis appendices A and B).

Two layers:

* :func:`endpoint_jacobians` — the error of each edge and its derivative with respect to a
  *global* perturbation of each endpoint, ``(δx, ω)`` with ``x ← x + δx`` and
  ``R ← Exp(ω) R`` in the frame the poses are expressed in (the edge root's frame).
* :func:`chain_jacobians` — the chain rule down the pose tree: the derivative of an endpoint's
  global pose with respect to the *local* perturbation ``(δt, δθ)`` of each ancestor on the
  path (``t ← t + δt``, ``R ← R Exp(δθ)``), appendix A's (A.11), (A.24) and (A.37) written in
  the tangent space. Their product is the block of the edge Jacobian for that path node.

Shapes: errors ``(..., 6)``, Jacobians ``(..., 6, 6)`` with rows ``(e_t, e_θ)`` and columns
``(δx, ω)`` or ``(δt, δθ)``.
"""

from __future__ import annotations

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.compiled import kernel
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EdgeKind

_RELATIVE = int(EdgeKind.RELATIVE)
_POSITION = int(EdgeKind.POSITION)

#: The tangent coordinates in use, as indices into ``(δt, δθ)``. Kernels of the per-node
#: hot paths take them as a tuple: its length and entries are then known when numba
#: compiles, which unrolls the ``p × p`` loops and drops the coordinates that do not mix
#: (about twice as fast as an index array, which they accept too).
Dof = tuple[int, ...] | np.ndarray

#: All six coordinates (3-D).
ALL_DOF = (0, 1, 2, 3, 4, 5)


def endpoint_jacobians(
    kind: np.ndarray,
    Ra: Array, xa: Array, Rb: Array, xb: Array,
    Rk: Array, tk: Array,
) -> tuple[Array, Array, Array]:
    """Errors and endpoint Jacobians of edges, batched over the leading axis.

    For a relative edge, ``e = [R_Kᵀ(R_aᵀ(x_b − x_a) − t_K); Log(R_Kᵀ R_aᵀ R_b)]``. A position
    edge measures ``x_b`` (``e_t = x_b − t_K``); an orientation edge measures ``R_b``
    (``e_θ = Log(R_Kᵀ R_b)``). Global edges ignore ``(Ra, xa)`` and get a zero ``J_a``.

    Returns:
        ``(e, J_a, J_b)`` with shapes ``(M, 6)``, ``(M, 6, 6)``, ``(M, 6, 6)``.
    """
    def c(a: Array) -> Array:
        return np.ascontiguousarray(a, dtype=float)

    e, Ja, Jb = _endpoint_jacobians_many(
        np.ascontiguousarray(kind, dtype=np.int64), c(Ra), c(xa), c(Rb), c(xb), c(Rk), c(tk))
    return e, Ja, Jb


@kernel
def _endpoint_jacobians_many(
    kind: np.ndarray, Ra: Array, xa: Array, Rb: Array, xb: Array, Rk: Array, tk: Array
) -> tuple[Array, Array, Array]:
    m = len(kind)
    e = np.empty((m, 6))
    Ja = np.empty((m, 6, 6))
    Jb = np.empty((m, 6, 6))
    for i in range(m):
        ei, Jai, Jbi = endpoint_jacobians_one(kind[i], Ra[i], xa[i], Rb[i], xb[i], Rk[i], tk[i])
        e[i] = ei
        Ja[i] = Jai
        Jb[i] = Jbi
    return e, Ja, Jb


@kernel
def endpoint_jacobians_one(
    kind: int, Ra: Array, xa: Array, Rb: Array, xb: Array, Rk: Array, tk: Array
) -> tuple[Array, Array, Array]:
    """:func:`endpoint_jacobians` of a single edge: ``(e, J_a, J_b)`` with shapes ``(6,)``,
    ``(6, 6)``, ``(6, 6)``."""
    # Written out in scalars: this runs once per edge update and per exact-mode edge, where
    # a temporary per 3×3 product cost more than the arithmetic.
    e = np.zeros(6)
    Ja = np.zeros((6, 6))
    Jb = np.zeros((6, 6))
    if kind == _POSITION:
        for i in range(3):
            e[i] = xb[i] - tk[i]
            Jb[i, i] = 1.0
        return e, Ja, Jb
    E = np.empty((3, 3))  # the error's rotation
    if kind == _RELATIVE:
        d0, d1, d2 = xb[0] - xa[0], xb[1] - xa[1], xb[2] - xa[2]
        for i in range(3):  # R_Kᵀ R_aᵀ, which is also J_b's translation block
            for j in range(3):
                Jb[i, j] = Rk[0, i] * Ra[j, 0] + Rk[1, i] * Ra[j, 1] + Rk[2, i] * Ra[j, 2]
        for i in range(3):
            for j in range(3):
                E[i, j] = Jb[i, 0] * Rb[0, j] + Jb[i, 1] * Rb[1, j] + Jb[i, 2] * Rb[2, j]
            e[i] = (Jb[i, 0] * d0 + Jb[i, 1] * d1 + Jb[i, 2] * d2
                    - (Rk[0, i] * tk[0] + Rk[1, i] * tk[1] + Rk[2, i] * tk[2]))
            # Rotating A about its origin swings B's offset as seen from A: d/dω of R_aᵀ d
            # is R_aᵀ[d]×, row by row a cross product with d.
            m0, m1, m2 = Jb[i, 0], Jb[i, 1], Jb[i, 2]
            Ja[i, 3] = m1 * d2 - m2 * d1
            Ja[i, 4] = m2 * d0 - m0 * d2
            Ja[i, 5] = m0 * d1 - m1 * d0
            for j in range(3):
                Ja[i, j] = -Jb[i, j]
    else:
        for i in range(3):
            for j in range(3):
                E[i, j] = Rk[0, i] * Rb[0, j] + Rk[1, i] * Rb[1, j] + Rk[2, i] * Rb[2, j]
    rot = geo.so3_log_one(E)
    jr = geo.so3_right_jacobian_inv_one(rot)
    for i in range(3):
        e[3 + i] = rot[i]
        for j in range(3):  # J_r⁻¹(rot) R_bᵀ
            v = jr[i, 0] * Rb[j, 0] + jr[i, 1] * Rb[j, 1] + jr[i, 2] * Rb[j, 2]
            Jb[3 + i, 3 + j] = v
            if kind == _RELATIVE:
                Ja[3 + i, 3 + j] = -v
    return e, Ja, Jb


def chain_jacobians(
    R_parent: Array, R_node: Array, x_node: Array, x_end: Array
) -> Array:
    """Derivative of an end pose's global perturbation w.r.t. local perturbations of its
    ancestors.

    Args:
        R_parent: global rotation of each ancestor's parent, ``(d, 3, 3)``.
        R_node: global rotation of each ancestor, ``(d, 3, 3)``.
        x_node: global position of each ancestor, ``(d, 3)``.
        x_end: global position of the end node (``a`` or ``b``), ``(3,)``.

    Returns:
        ``(d, 6, 6)`` maps ``(δt_i, δθ_i) ↦ (δx_end, ω_end)``: a local translation moves the end
        by ``R_parent δt``; a local rotation turns the end about the ancestor's origin by
        ``ω = R_node δθ``, moving it by ``ω × (x_end − x_node)``.
    """
    def c(a: Array) -> Array:
        return np.ascontiguousarray(a, dtype=float)

    return _chain_jacobians_many(c(R_parent), c(R_node), c(x_node), c(x_end))


@kernel
def _chain_jacobians_many(R_parent: Array, R_node: Array, x_node: Array, x_end: Array) -> Array:
    out = np.empty((len(R_node), 6, 6))
    for i in range(len(R_node)):
        out[i] = chain_jacobian_one(R_parent[i], R_node[i], x_node[i], x_end)
    return out


@kernel
def chain_jacobian_into(
    R_parent: Array, R_node: Array, x_node: Array, x_end: Array, M: Array
) -> None:
    """One block of :func:`chain_jacobians` into ``M`` ``(6, 6)``, whose lower-left block
    must already be zero."""
    v0 = x_end[0] - x_node[0]
    v1 = x_end[1] - x_node[1]
    v2 = x_end[2] - x_node[2]
    for j in range(3):
        # Column j of −[x_end − x_node]× R_node: R_node[:, j] × (x_end − x_node).
        a0, a1, a2 = R_node[0, j], R_node[1, j], R_node[2, j]
        M[0, 3 + j] = a1 * v2 - a2 * v1
        M[1, 3 + j] = a2 * v0 - a0 * v2
        M[2, 3 + j] = a0 * v1 - a1 * v0
        for i in range(3):
            M[i, j] = R_parent[i, j]
            M[3 + i, 3 + j] = R_node[i, j]


@kernel
def chain_jacobian_one(R_parent: Array, R_node: Array, x_node: Array, x_end: Array) -> Array:
    """One block of :func:`chain_jacobians`, ``(6, 6)``."""
    M = np.zeros((6, 6))
    chain_jacobian_into(R_parent, R_node, x_node, x_end, M)
    return M


@kernel
def compose_into(R: Array, t: Array, nodes: np.ndarray, H_R: Array, H_x: Array) -> None:
    """Poses down a chain: ``(H_R, H_x)[i + 1] = (H_R, H_x)[i] · (R, t)[nodes[i]]``.

    ``H_R[0], H_x[0]`` (set by the caller) is the frame the chain hangs from; ``R, t`` are
    local transforms, ``(N, 3, 3)`` and ``(N, 3)``; ``H_R, H_x`` hold ``len(nodes) + 1``.
    """
    for i in range(len(nodes)):
        n = nodes[i]
        for a in range(3):  # on scalars: a view of a row per node costs as much
            H_x[i + 1, a] = H_x[i, a] + (H_R[i, a, 0] * t[n, 0] + H_R[i, a, 1] * t[n, 1]
                                         + H_R[i, a, 2] * t[n, 2])
            for b in range(3):
                H_R[i + 1, a, b] = (H_R[i, a, 0] * R[n, 0, b] + H_R[i, a, 1] * R[n, 1, b]
                                    + H_R[i, a, 2] * R[n, 2, b])


@kernel
def chain_block_into(
    A: Array, R_parent: Array, R_node: Array, v: Array, dof: Dof, out: Array
) -> None:
    """``out = (A M)[:, dof]`` for ``M`` the chain block of :func:`chain_jacobian_into`,
    without forming ``M``: the edge Jacobian block of one path node.

    Args:
        A: the endpoint Jacobian, whitened and restricted to the rows in use, ``(m, 6)``.
        R_parent, R_node: global rotations of the node's parent and of the node.
        v: ``x_end − x_node``, the end's offset from the node, ``(3,)``.
        dof: the tangent coordinates in use (``p`` of them).
        out: ``(m, p)``.

    A translation column ``c`` is ``A_t R_parent[:, c]``; a rotation column ``j`` is
    ``A_t (R_node[:, j] × v) + A_r R_node[:, j] = R_node[:, j] · (A_r + v × A_t)`` (row by
    row), so a row costs one cross product and ``p`` dot products of three.
    """
    for a in range(A.shape[0]):
        at0, at1, at2 = A[a, 0], A[a, 1], A[a, 2]
        g0 = A[a, 3] + v[1] * at2 - v[2] * at1
        g1 = A[a, 4] + v[2] * at0 - v[0] * at2
        g2 = A[a, 5] + v[0] * at1 - v[1] * at0
        for q in range(len(dof)):
            c = dof[q]
            if c < 3:
                out[a, q] = at0 * R_parent[0, c] + at1 * R_parent[1, c] + at2 * R_parent[2, c]
            else:
                c -= 3
                out[a, q] = R_node[0, c] * g0 + R_node[1, c] * g1 + R_node[2, c] * g2


@kernel
def whitened_rows_into(W: Array, Je: Array, dof: Dof, out: Array) -> None:
    """``out = W Je[dof, :]`` (``(p, 6)``): an endpoint Jacobian whitened, in the
    coordinates in use."""
    p = len(dof)
    for a in range(p):
        for k in range(6):
            acc = 0.0
            for q in range(p):
                acc += W[a, q] * Je[dof[q], k]
            out[a, k] = acc


@kernel
def path_linearization(
    tree_R: Array, tree_t: Array, a_chain: np.ndarray, b_chain: np.ndarray, kind: int,
    Rk: Array, tk: Array, W: Array, dof: Dof,
) -> tuple[Array, Array]:
    """Whitened Jacobian blocks and residual of one edge over its tree path.

    Args:
        tree_R, tree_t: local transforms of the pose tree, ``(N, 3, 3)`` and ``(N, 3)``.
        a_chain, b_chain: the path's chains, from just below the root down to each endpoint.
        kind, Rk, tk: the edge's kind and measurement.
        W: the edge's whitening in the coordinates ``dof`` (``(p, p)``).

    Returns:
        ``J`` ``(d, p, p)`` (a-chain blocks first) and ``r`` ``(p,)``: ``r + Σᵢ Jᵢ xᵢ`` is the
        whitened error to first order in local perturbations ``xᵢ`` of the domain nodes.
    """
    la = len(a_chain)
    lb = len(b_chain)
    p = len(dof)
    # Poses in the root's frame, each chain after an identity: node i of the a-chain at
    # i + 1, its parent at i; the b-chain likewise from la + 1.
    H_R = np.empty((la + lb + 2, 3, 3))
    H_x = np.empty((la + lb + 2, 3))
    for first in (0, la + 1):
        H_R[first] = np.eye(3)
        H_x[first] = 0.0
    compose_into(tree_R, tree_t, a_chain, H_R, H_x)
    compose_into(tree_R, tree_t, b_chain, H_R[la + 1:], H_x[la + 1:])
    end = (la, la + lb + 1)
    e, Ja, Jb = endpoint_jacobians_one(kind, H_R[end[0]], H_x[end[0]], H_R[end[1]],
                                       H_x[end[1]], Rk, tk)
    # The whitening folded into each end's Jacobian once, not into every block.
    A = np.empty((2, p, 6))
    whitened_rows_into(W, Ja, dof, A[0])
    whitened_rows_into(W, Jb, dof, A[1])
    J = np.empty((la + lb, p, p))
    v = np.empty(3)
    for i in range(la + lb):
        c = 0 if i < la else 1
        h = i + 1 + c  # the node's row in H_R, H_x
        for k in range(3):
            v[k] = H_x[end[c], k] - H_x[h, k]
        chain_block_into(A[c], H_R[h - 1], H_R[h], v, dof, J[i])
    r = np.empty(p)
    for a in range(p):
        r[a] = e[dof[a]]
    return J, W @ r
