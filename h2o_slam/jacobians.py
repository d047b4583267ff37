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

from h2o_slam import geometry as geo
from h2o_slam.geometry import Array
from h2o_slam.graph import EdgeKind


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
    m = len(kind)
    e = np.zeros((m, 6))
    Ja = np.zeros((m, 6, 6))
    Jb = np.zeros((m, 6, 6))
    rel = kind == EdgeKind.RELATIVE
    if np.any(rel):
        e[rel], Ja[rel], Jb[rel] = _relative(Ra[rel], xa[rel], Rb[rel], xb[rel], Rk[rel], tk[rel])
    pos = kind == EdgeKind.POSITION
    if np.any(pos):
        e[pos, :3] = xb[pos] - tk[pos]
        Jb[pos, :3, :3] = np.eye(3)
    ori = kind == EdgeKind.ORIENTATION
    if np.any(ori):
        rot = geo.so3_log(np.swapaxes(Rk[ori], -1, -2) @ Rb[ori])
        e[ori, 3:] = rot
        Jb[ori, 3:, 3:] = geo.so3_right_jacobian_inv(rot) @ np.swapaxes(Rb[ori], -1, -2)
    return e, Ja, Jb


def endpoint_jacobians_one(
    kind: int, Ra: Array, xa: Array, Rb: Array, xb: Array, Rk: Array, tk: Array
) -> tuple[Array, Array, Array]:
    """:func:`endpoint_jacobians` of a single edge (the per-edge hot path, without batching
    overhead): ``(e, J_a, J_b)`` with shapes ``(6,)``, ``(6, 6)``, ``(6, 6)``."""
    e = np.zeros(6)
    Ja = np.zeros((6, 6))
    Jb = np.zeros((6, 6))
    if kind == EdgeKind.RELATIVE:
        d = xb - xa
        RkRa = Rk.T @ Ra.T
        rot = geo.so3_log_one(RkRa @ Rb)
        e[:3] = RkRa @ d - Rk.T @ tk
        e[3:] = rot
        jr_rbT = geo.so3_right_jacobian_inv_one(rot) @ Rb.T
        Jb[:3, :3] = RkRa
        Jb[3:, 3:] = jr_rbT
        Ja[:3, :3] = -RkRa
        Ja[:3, 3:] = RkRa @ np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
        Ja[3:, 3:] = -jr_rbT
    elif kind == EdgeKind.POSITION:
        e[:3] = xb - tk
        Jb[:3, :3] = np.eye(3)
    else:
        rot = geo.so3_log_one(Rk.T @ Rb)
        e[3:] = rot
        Jb[3:, 3:] = geo.so3_right_jacobian_inv_one(rot) @ Rb.T
    return e, Ja, Jb


def _relative(
    Ra: Array, xa: Array, Rb: Array, xb: Array, Rk: Array, tk: Array
) -> tuple[Array, Array, Array]:
    RaT = np.swapaxes(Ra, -1, -2)
    RkT = np.swapaxes(Rk, -1, -2)
    d = xb - xa
    tab = np.einsum("mij,mj->mi", RaT, d)
    RkRa = RkT @ RaT
    rot = geo.so3_log(RkRa @ Rb)
    e = np.concatenate([np.einsum("mij,mj->mi", RkT, tab - tk), rot], axis=-1)
    jr_rbT = geo.so3_right_jacobian_inv(rot) @ np.swapaxes(Rb, -1, -2)
    m = len(Ra)
    Ja = np.zeros((m, 6, 6))
    Jb = np.zeros((m, 6, 6))
    Jb[:, :3, :3] = RkRa
    Jb[:, 3:, 3:] = jr_rbT
    Ja[:, :3, :3] = -RkRa
    # Rotating A about its origin swings B's offset as seen from A: d/dω of R_aᵀ d is R_aᵀ[d]×.
    Ja[:, :3, 3:] = RkRa @ geo.hat(d)
    Ja[:, 3:, 3:] = -jr_rbT
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
    d = len(R_node)
    M = np.zeros((d, 6, 6))
    M[:, :3, :3] = R_parent
    M[:, :3, 3:] = -geo.hat(x_end - x_node) @ R_node
    M[:, 3:, 3:] = R_node
    return M
