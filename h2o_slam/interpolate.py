"""Interpolated solving (thesis 3.3.6): solve for at most ``d_max`` nodes of a domain.

An edge's domain is two chains of the pose tree, each running from just below the edge root
down to an endpoint. Interpolation keeps a subset of each chain, evenly spaced and always
including the endpoint, and treats each kept node ``s`` as the end of a *segment*: the nodes
after the previous kept node (or after the root) down to ``s``. Three pieces live here:

* :func:`select` — which domain positions are kept, and their segments;
* :func:`merge_segments` — the merged constraint β of each segment (3.37–3.38): the product of
  the tree edges' desired transforms, and the sum of their stiffnesses rotated into the
  frame of ``s``;
* :func:`distribute` — the TORO-style spread of each kept node's solved change over its whole
  segment, weighted by the compliance ``1 / diag(B)`` so that stiff nodes move less, keeping
  the path continuous.

The per-node work is compiled (:mod:`h2o_slam.compiled`): one pass of 3×3 products along
each segment, O(d) in the domain with a small constant, so that the interpolated update
costs the O(``d_max``) solve plus cheap compositions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h2o_slam import geometry as geo
from h2o_slam.compiled import kernel
from h2o_slam.geometry import Array
from h2o_slam.jacobians import chain_jacobian_one, endpoint_jacobians_one


@dataclass(frozen=True)
class Selection:
    """Kept domain positions and their segments (positions index the domain array, which is
    the a-chain followed by the b-chain, each ordered from the root down).

    Attributes:
        kept: kept positions, ascending, shape ``(k,)``.
        start: first position of each kept node's segment, shape ``(k,)``; the segment is
            ``start[j] … kept[j]``.
    """

    kept: np.ndarray
    start: np.ndarray

    @property
    def lengths(self) -> np.ndarray:
        """Segment lengths (1 where the kept node's parent is kept or is the root)."""
        return self.kept - self.start + 1


def select(len_a: int, len_b: int, d_max: int) -> Selection:
    """Keep at most ``d_max`` nodes (at least one per non-empty chain), evenly along each chain.

    Nodes are shared between the chains in proportion to their lengths; each chain keeps its
    endpoint, where the edge acts.
    """
    total = len_a + len_b
    if total <= d_max:
        kept = np.arange(total)
        return Selection(kept, kept.copy())
    if len_a and len_b:
        k_a = min(len_a, max(1, min(d_max - 1, round(d_max * len_a / total))))
        k_b = min(len_b, max(1, d_max - k_a))
    else:
        k_a, k_b = min(len_a, d_max), min(len_b, d_max)
    kept_a, start_a = _even(len_a, k_a, 0)
    kept_b, start_b = _even(len_b, k_b, len_a)
    return Selection(np.concatenate([kept_a, kept_b]), np.concatenate([start_a, start_b]))


def _even(length: int, k: int, offset: int) -> tuple[np.ndarray, np.ndarray]:
    if k == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    # Count back from the endpoint in equal strides; the top segment takes the remainder.
    kept = (length - 1 - (np.arange(k)[::-1] * length) // k).astype(np.int64)
    start = np.concatenate([[0], kept[:-1] + 1])
    return kept + offset, start + offset


def merge_segments(
    sel: Selection, k_R: Array, k_t: Array, S: Array
) -> tuple[Array, Array, Array]:
    """Merged constraint β of each segment (eq. 3.37–3.38).

    Args:
        sel: the selection.
        k_R, k_t: desired transform of each domain node's tree edge, oriented parent → node,
            shapes ``(d, 3, 3)`` and ``(d, 3)``.
        S: stiffness of each tree edge in the error coordinates of its node, ``(d, 6, 6)``.

    Returns:
        ``(R_β, t_β, S_β)`` per segment: ``k_β = ∏ kᵢ`` from the segment's parent down to its
        kept node, and ``S_β = Σᵢ Rᵢₛᵀ Sᵢ Rᵢₛ`` with ``Rᵢₛ`` the desired rotation from node
        ``i`` to the kept node ``s``, applied to the translation and rotation blocks alike.
    """
    def c(a: Array) -> Array:
        return np.ascontiguousarray(a, dtype=float)

    return _merge_segments(sel.kept, sel.start, c(k_R), c(k_t), c(S))


@kernel
def _merge_segments(
    kept: np.ndarray, start: np.ndarray, k_R: Array, k_t: Array, S: Array
) -> tuple[Array, Array, Array]:
    k = len(kept)
    R_beta = np.empty((k, 3, 3))
    t_beta = np.empty((k, 3))
    S_beta = np.zeros((k, 6, 6))
    for j in range(k):
        length = kept[j] - start[j] + 1
        P_R = np.empty((length, 3, 3))
        R = np.eye(3)
        t = np.zeros(3)
        for i in range(length):
            pos = start[j] + i
            t = t + geo.mulv3(R, k_t[pos])
            R = geo.mul3(R, k_R[pos])
            P_R[i] = R
        R_beta[j] = R
        t_beta[j] = t
        for i in range(length):
            Q = geo.mul3t(P_R[i], R)
            Si = S[start[j] + i]
            for a in range(2):
                for b in range(2):
                    block = geo.mul3t(Q, geo.mul3(np.ascontiguousarray(
                        Si[3 * a:3 * a + 3, 3 * b:3 * b + 3]), Q))
                    S_beta[j, 3 * a:3 * a + 3, 3 * b:3 * b + 3] += block
    return R_beta, t_beta, S_beta


@kernel
def tree_edge_constraints(
    domain: np.ndarray, tree_edge: np.ndarray, forward: np.ndarray, meas_R: Array,
    meas_t: Array, info: Array,
) -> tuple[Array, Array, Array, np.ndarray]:
    """Desired transform (parent → node) and stiffness (in the node's error coordinates) of
    each domain node's tree edge, and whether the node is a subtree top (no tree edge:
    identity, zero stiffness).

    A tree edge measured node → parent is inverted, and its stiffness, which lives in the
    parent's frame, turned into the node's.
    """
    d = len(domain)
    k_R = np.empty((d, 3, 3))
    k_t = np.empty((d, 3))
    S = np.zeros((d, 6, 6))
    top = np.zeros(d, dtype=np.bool_)
    for i in range(d):
        e = tree_edge[domain[i]]
        if e < 0:
            top[i] = True
            k_R[i] = np.eye(3)
            k_t[i] = 0.0
            continue
        if forward[domain[i]]:
            k_R[i] = meas_R[e]
            k_t[i] = meas_t[e]
            S[i] = info[e]
            continue
        Rinv = np.ascontiguousarray(meas_R[e].T)
        k_R[i] = Rinv
        k_t[i] = -geo.mulv3(Rinv, meas_t[e])
        for a in range(2):
            for b in range(2):
                S[i, 3 * a:3 * a + 3, 3 * b:3 * b + 3] = geo.mul3t(meas_R[e], geo.mul3(
                    np.ascontiguousarray(info[e, 3 * a:3 * a + 3, 3 * b:3 * b + 3]),
                    meas_R[e]))
    return k_R, k_t, S, top


@kernel
def merged_stiffness(
    tree_R: Array, tree_t: Array, domain: np.ndarray, kept: np.ndarray, start: np.ndarray,
    R_beta: Array, t_beta: Array, S_beta: Array, dof: np.ndarray,
) -> Array:
    """``J_βᵀ J_β`` at each kept node: the diagonal block the merged constraint β of its
    segment contributes to ``B`` (eq. 3.36), for a perturbation of the kept node's local
    transform.

    Args:
        tree_R, tree_t: local transforms of the pose tree.
        domain: the edge's domain; ``kept``/``start`` index it.
        kept, start: the segments (see :class:`Selection`).
        R_beta, t_beta: merged measurements, ``(k, 3, 3)`` and ``(k, 3)``.
        S_beta: merged stiffness in error coordinates, ``(k, 6, 6)``.
        dof: the tangent coordinates in use.

    Returns:
        ``(k, p, p)`` blocks ``J_rawᵀ S_β J_raw`` (= ``J_βᵀ J_β`` with ``J_β = W_β J_raw``,
        ``W_βᵀ W_β = S_β``: no whitening factor is needed).
    """
    k = len(kept)
    p = len(dof)
    out = np.empty((k, p, p))
    Sd = np.empty((p, p))
    raw = np.empty((p, p))
    for j in range(k):
        R = np.eye(3)
        x = np.zeros(3)
        R_par = np.eye(3)
        for pos in range(start[j], kept[j] + 1):
            n = domain[pos]
            R_par = R
            x = x + geo.mulv3(R, tree_t[n])
            R = geo.mul3(R, tree_R[n])
        _, _, Jb = endpoint_jacobians_one(0, np.eye(3), np.zeros(3), R, x, R_beta[j], t_beta[j])
        M = chain_jacobian_one(R_par, R, x, x)
        for a in range(p):
            for b in range(p):
                acc = 0.0
                for c in range(6):
                    acc += Jb[dof[a], c] * M[c, dof[b]]
                raw[a, b] = acc
                Sd[a, b] = S_beta[j, dof[a], dof[b]]
        out[j] = raw.T @ Sd @ raw
    return out


def distribute(
    sel: Selection, R_loc: Array, t_loc: Array, step: Array, compliance: Array
) -> tuple[Array, Array]:
    """Spread each kept node's local step over its segment (TORO-style, 3.3.6.2).

    Args:
        sel: the selection.
        R_loc, t_loc: local transforms of the domain nodes, ``(d, 3, 3)`` and ``(d, 3)``.
        step: local step ``(δt, δθ)`` of each kept node, ``(k, 6)``, already scaled.
        compliance: distribution weight of each domain node, ``(d,)`` (``1 / diag(B)``).

    Returns:
        New local transforms of the domain nodes (see :func:`distribute_into`).
    """
    out_R = np.array(R_loc, dtype=float)
    out_t = np.array(t_loc, dtype=float)
    distribute_into(out_R, out_t, np.arange(len(out_R)), sel.kept, sel.start,
                    np.ascontiguousarray(step, dtype=float),
                    np.ascontiguousarray(compliance, dtype=float))
    return out_R, out_t


@kernel
def distribute_into(
    tree_R: Array, tree_t: Array, domain: np.ndarray, kept: np.ndarray, start: np.ndarray,
    step: Array, compliance: Array,
) -> None:
    """:func:`distribute` in place on the pose tree's local transforms (``domain`` maps the
    selection's positions to nodes).

    Each kept node ends exactly where its step puts it relative to the segment's parent; the
    nodes in between take a share of the rotation and translation in proportion to their
    cumulative compliance, keeping the path continuous.
    """
    for j in range(len(kept)):
        s0 = start[j]
        length = kept[j] - s0 + 1
        H_R = np.empty((length, 3, 3))
        H_x = np.empty((length, 3))
        R = np.eye(3)
        x = np.zeros(3)
        total = 0.0
        for i in range(length):
            n = domain[s0 + i]
            x = x + geo.mulv3(R, tree_t[n])
            R = geo.mul3(R, tree_R[n])
            H_R[i] = R
            H_x[i] = x
            total += compliance[s0 + i]
        # Target of the kept node in its segment's frame: its parent's pose times its local
        # transform with the step applied.
        last = domain[kept[j]]
        if length > 1:
            par_R = H_R[length - 2]
            par_x = H_x[length - 2]
        else:
            par_R = np.eye(3)
            par_x = np.zeros(3)
        target_R = geo.mul3(par_R, geo.mul3(tree_R[last], geo.so3_exp_one(step[j, 3:])))
        target_x = par_x + geo.mulv3(par_R, tree_t[last] + step[j, :3])
        omega = geo.so3_log_one(geo.mul3(target_R, np.ascontiguousarray(H_R[length - 1].T)))
        # Turn the segment: node i's pose rotates by its share of ω.
        frac = np.empty(length)
        R_new = np.empty((length, 3, 3))
        local_R = np.empty((length, 3, 3))
        x_rot = np.empty((length, 3))
        R_prev = np.eye(3)
        acc_R = np.eye(3)
        acc_x = np.zeros(3)
        cum = 0.0
        for i in range(length):
            cum += compliance[s0 + i]
            frac[i] = cum / total
            R_new[i] = geo.mul3(geo.so3_exp_one(frac[i] * omega), H_R[i])
            local_R[i] = geo.mul3t(R_prev, R_new[i])
            R_prev = R_new[i]
            acc_x = acc_x + geo.mulv3(acc_R, tree_t[domain[s0 + i]])
            acc_R = geo.mul3(acc_R, local_R[i])
            x_rot[i] = acc_x
        # Then shift it: node i's position moves by its share of the kept node's miss.
        miss = target_x - x_rot[length - 1]
        x_prev = np.zeros(3)
        for i in range(length):
            x_new = x_rot[i] + frac[i] * miss
            n = domain[s0 + i]
            tree_t[n] = x_new - x_prev if i == 0 else geo.mulv3t(R_new[i - 1], x_new - x_prev)
            tree_R[n] = geo.renormalize_one(local_R[i])
            x_prev = x_new
