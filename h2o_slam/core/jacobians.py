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
    e = np.zeros(6)
    Ja = np.zeros((6, 6))
    Jb = np.zeros((6, 6))
    if kind == _RELATIVE:
        d = xb - xa
        RkRa = geo.mul3t(Rk, Ra.T.copy())
        rot = geo.so3_log_one(geo.mul3(RkRa, Rb))
        e[:3] = geo.mulv3(RkRa, d) - geo.mulv3t(Rk, tk)
        e[3:] = rot
        jr_rbT = geo.mul3(geo.so3_right_jacobian_inv_one(rot), Rb.T.copy())
        # Rotating A about its origin swings B's offset as seen from A: d/dω of R_aᵀ d is
        # R_aᵀ[d]×.
        swing = geo.mul3(RkRa, geo.hat_one(d))
        for i in range(3):
            for j in range(3):
                Jb[i, j] = RkRa[i, j]
                Jb[3 + i, 3 + j] = jr_rbT[i, j]
                Ja[i, j] = -RkRa[i, j]
                Ja[i, 3 + j] = swing[i, j]
                Ja[3 + i, 3 + j] = -jr_rbT[i, j]
    elif kind == _POSITION:
        for i in range(3):
            e[i] = xb[i] - tk[i]
            Jb[i, i] = 1.0
    else:
        rot = geo.so3_log_one(geo.mul3t(Rk, Rb))
        e[3:] = rot
        Jb[3:, 3:] = geo.mul3(geo.so3_right_jacobian_inv_one(rot), Rb.T.copy())
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
def dof_product_into(Je: Array, M: Array, dof: np.ndarray, out: Array) -> None:
    """``out = (Je M)[dof, dof]``: a node's raw Jacobian block in the coordinates in use."""
    p = len(dof)
    for a in range(p):
        for b in range(p):
            acc = 0.0
            for k in range(6):
                acc += Je[dof[a], k] * M[k, dof[b]]
            out[a, b] = acc


@kernel
def path_linearization(
    tree_R: Array, tree_t: Array, a_chain: np.ndarray, b_chain: np.ndarray, kind: int,
    Rk: Array, tk: Array, W: Array, dof: np.ndarray,
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
    # Poses in the root's frame: R_all[i], x_all[i] of node i, R_all[i - 1] its parent's.
    R_all = np.empty((la + lb + 2, 3, 3))
    x_all = np.empty((la + lb, 3))
    ends_R = np.empty((2, 3, 3))
    ends_x = np.zeros((2, 3))
    for c in range(2):
        chain = a_chain if c == 0 else b_chain
        off = 0 if c == 0 else la
        R = ends_R[c]
        R[:] = np.eye(3)
        x = ends_x[c]
        for i in range(len(chain)):
            n = chain[i]
            geo.add_mulv3(R, tree_t[n], x)
            x_all[off + i] = x
            geo.mul3_into(R, tree_R[n], R_all[off + i])
            R = R_all[off + i]
        ends_R[c] = R
    e, Ja, Jb = endpoint_jacobians_one(kind, ends_R[0], ends_x[0], ends_R[1], ends_x[1], Rk, tk)
    J = np.empty((la + lb, p, p))
    raw = np.empty((p, p))
    M = np.zeros((6, 6))
    eye = np.eye(3)
    for i in range(la + lb):
        end = 0 if i < la else 1
        R_par = eye if i == 0 or i == la else R_all[i - 1]
        chain_jacobian_into(R_par, R_all[i], x_all[i], ends_x[end], M)
        dof_product_into(Ja if end == 0 else Jb, M, dof, raw)
        for a in range(p):
            for b in range(p):
                acc = 0.0
                for k in range(p):
                    acc += W[a, k] * raw[k, b]
                J[i, a, b] = acc
    r = np.empty(p)
    for a in range(p):
        r[a] = e[dof[a]]
    return J, W @ r
