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

The per-node work is compiled (:mod:`h2o_slam.core.compiled`): one pass of 3×3 products along
each segment, O(d) in the domain with a small constant, so that the interpolated update
costs the O(``d_max``) solve plus cheap compositions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.compiled import kernel
from h2o_slam.core.geometry import Array
from h2o_slam.core.jacobians import (
    ALL_DOF,
    Dof,
    chain_block_into,
    compose_into,
    endpoint_jacobians_one,
)


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
    return Selection(*_select(len_a, len_b, d_max))


@kernel
def _select(len_a: int, len_b: int, d_max: int) -> tuple[np.ndarray, np.ndarray]:
    # Compiled: in numpy the few small arrays cost 16 µs a call.
    total = len_a + len_b
    if total <= d_max:
        kept = np.arange(total)
        return kept, kept.copy()
    if len_a and len_b:
        k_a = min(len_a, max(1, min(d_max - 1, round(d_max * len_a / total))))
        k_b = min(len_b, max(1, d_max - k_a))
    else:
        k_a, k_b = min(len_a, d_max), min(len_b, d_max)
    kept = np.empty(k_a + k_b, dtype=np.int64)
    start = np.empty(k_a + k_b, dtype=np.int64)
    _even_into(len_a, 0, kept[:k_a], start[:k_a])
    _even_into(len_b, len_a, kept[k_a:], start[k_a:])
    return kept, start


@kernel
def _even_into(length: int, offset: int, kept: np.ndarray, start: np.ndarray) -> None:
    # Count back from the endpoint in equal strides; the top segment takes the remainder.
    k = len(kept)
    for j in range(k):
        kept[j] = offset + length - 1 - ((k - 1 - j) * length) // k
        start[j] = offset if j == 0 else kept[j - 1] + 1


def merge_segments(
    sel: Selection, k_R: Array, k_t: Array, S: Array, dof: Dof = ALL_DOF
) -> tuple[Array, Array, Array]:
    """Merged constraint β of each segment (eq. 3.37–3.38).

    Args:
        sel: the selection.
        k_R, k_t: desired transform of each domain node's tree edge, oriented parent → node,
            shapes ``(d, 3, 3)`` and ``(d, 3)``.
        S: stiffness of each tree edge in the error coordinates of its node, ``(d, p, p)``
            in the coordinates ``dof`` (default all six).
        dof: the coordinates in use (see :data:`h2o_slam.core.jacobians.Dof`).

    Returns:
        ``(R_β, t_β, S_β)`` per segment: ``k_β = ∏ kᵢ`` from the segment's parent down to its
        kept node, and ``S_β = Σᵢ Rᵢₛᵀ Sᵢ Rᵢₛ`` with ``Rᵢₛ`` the desired rotation from node
        ``i`` to the kept node ``s``, applied to the translation and rotation blocks alike.
    """
    def c(a: Array) -> Array:
        return np.ascontiguousarray(a, dtype=float)

    return _merge_segments(sel.kept, sel.start, c(k_R), c(k_t), c(S), dof)


@kernel
def add_rotated_stiffness(S: Array, Q: Array, dof: Dof, out: Array, work: Array) -> None:
    """``out += Rᵀ S R`` with ``R = diag(Q, Q)``: a stiffness whose error is turned by the
    rotation ``Q`` (translation and rotation blocks alike), in the coordinates ``dof``.

    ``S``, ``out`` and the scratch ``work`` are ``(p, p)``. Restricting to ``dof``
    before turning is exact when ``Q`` maps the coordinates in use onto themselves: any
    rotation for all six, rotations about z for the planar ``(x, y, yaw)`` (``p = 3``, taken
    to be those coordinates).
    """
    p = len(dof)
    if p == 6:  # all six: Qᵀ S_ab Q for each 3×3 block (216 products, not 432)
        for a in range(2):
            for b in range(2):
                for i in range(3):
                    for j in range(3):
                        work[i, j] = (S[3 * a + i, 3 * b] * Q[0, j]
                                      + S[3 * a + i, 3 * b + 1] * Q[1, j]
                                      + S[3 * a + i, 3 * b + 2] * Q[2, j])
                for i in range(3):
                    for j in range(3):
                        out[3 * a + i, 3 * b + j] += (Q[0, i] * work[0, j]
                                                      + Q[1, i] * work[1, j]
                                                      + Q[2, i] * work[2, j])
        return
    if p != 3:
        raise ValueError("dof must be all six coordinates or the planar three")
    # Planar (x, y, yaw): Q turns (x, y) and leaves yaw.
    c00, c01, c10, c11 = Q[0, 0], Q[0, 1], Q[1, 0], Q[1, 1]
    for i in range(3):  # S R
        work[i, 0] = S[i, 0] * c00 + S[i, 1] * c10
        work[i, 1] = S[i, 0] * c01 + S[i, 1] * c11
        work[i, 2] = S[i, 2]
    for j in range(3):  # Rᵀ (S R)
        out[0, j] += c00 * work[0, j] + c10 * work[1, j]
        out[1, j] += c01 * work[0, j] + c11 * work[1, j]
        out[2, j] += work[2, j]


@kernel
def restrict_into(M: Array, dof: Dof, out: Array) -> None:
    """``out = M[dof][:, dof]`` for a 6×6 ``M``."""
    if len(dof) == 6:  # (a tuple index that the compiler cannot unroll is slow)
        out[:] = M
        return
    for a in range(len(dof)):
        for b in range(len(dof)):
            out[a, b] = M[dof[a], dof[b]]


@kernel
def _merge_segments(
    kept: np.ndarray, start: np.ndarray, k_R: Array, k_t: Array, S: Array, dof: Dof
) -> tuple[Array, Array, Array]:
    k = len(kept)
    p = len(dof)
    R_beta = np.empty((k, 3, 3))
    t_beta = np.empty((k, 3))
    S_beta = np.empty((k, p, p))
    positions = np.arange(len(k_R))
    longest = int((kept - start).max()) + 1 if k else 1
    P_R = np.empty((longest + 1, 3, 3))
    P_t = np.empty((longest + 1, 3))
    P_R[0] = np.eye(3)
    P_t[0] = 0.0
    S_acc = np.empty((p, p))
    S_next = np.empty((p, p))
    work = np.empty((p, p))
    for j in range(k):
        # k_β: the product of the segment's transforms.
        length = kept[j] - start[j] + 1
        compose_into(k_R, k_t, positions[start[j]:kept[j] + 1], P_R, P_t)
        R_beta[j] = P_R[length]
        t_beta[j] = P_t[length]
        # S_β by Horner's rule: the stiffness gathered so far is turned into the next node's
        # frame, then that node's own is added.
        S_acc[:] = S[start[j]]
        for pos in range(start[j] + 1, kept[j] + 1):
            for a in range(p):
                for b in range(p):
                    S_next[a, b] = S[pos, a, b]
            add_rotated_stiffness(S_acc, k_R[pos], dof, S_next, work)
            S_acc, S_next = S_next, S_acc
        S_beta[j] = S_acc
    return R_beta, t_beta, S_beta


@kernel
def tree_edge_constraints(
    domain: np.ndarray, tree_edge: np.ndarray, forward: np.ndarray, meas_R: Array,
    meas_t: Array, info: Array, dof: Dof | None = None,
) -> tuple[Array, Array, Array, np.ndarray]:
    """Desired transform (parent → node) and stiffness (in the node's error coordinates,
    restricted to ``dof``, default all six) of each domain node's tree edge, and whether the
    node is a subtree top (no tree edge: identity, zero stiffness).

    A tree edge measured node → parent is inverted, and its stiffness, which lives in the
    parent's frame, turned into the node's.
    """
    if dof is None:
        return _tree_edge_constraints(domain, tree_edge, forward, meas_R, meas_t, info, ALL_DOF)
    return _tree_edge_constraints(domain, tree_edge, forward, meas_R, meas_t, info, dof)


@kernel
def _tree_edge_constraints(
    domain: np.ndarray, tree_edge: np.ndarray, forward: np.ndarray, meas_R: Array,
    meas_t: Array, info: Array, dof: Dof,
) -> tuple[Array, Array, Array, np.ndarray]:
    d = len(domain)
    p = len(dof)
    k_R = np.empty((d, 3, 3))
    k_t = np.empty((d, 3))
    S = np.zeros((d, p, p))
    top = np.zeros(d, dtype=np.bool_)
    S_e = np.empty((p, p))
    work = np.empty((p, p))
    for i in range(d):
        e = tree_edge[domain[i]]
        if e < 0:
            top[i] = True
            for a in range(3):
                k_t[i, a] = 0.0
                for b in range(3):
                    k_R[i, a, b] = 1.0 if a == b else 0.0
        elif forward[domain[i]]:
            for a in range(3):
                k_t[i, a] = meas_t[e, a]
                for b in range(3):
                    k_R[i, a, b] = meas_R[e, a, b]
            restrict_into(info[e], dof, S[i])
        else:
            for a in range(3):
                k_t[i, a] = 0.0
                for b in range(3):
                    k_R[i, a, b] = meas_R[e, b, a]
                    k_t[i, a] -= meas_R[e, b, a] * meas_t[e, b]
            restrict_into(info[e], dof, S_e)
            add_rotated_stiffness(S_e, meas_R[e], dof, S[i], work)
    return k_R, k_t, S, top


@kernel
def merged_stiffness(
    tree_R: Array, tree_t: Array, domain: np.ndarray, kept: np.ndarray, start: np.ndarray,
    R_beta: Array, t_beta: Array, S_beta: Array, dof: Dof,
) -> Array:
    """``J_βᵀ J_β`` at each kept node: the diagonal block the merged constraint β of its
    segment contributes to ``B`` (eq. 3.36), for a perturbation of the kept node's local
    transform.

    Args:
        tree_R, tree_t: local transforms of the pose tree.
        domain: the edge's domain; ``kept``/``start`` index it.
        kept, start: the segments (see :class:`Selection`).
        R_beta, t_beta: merged measurements, ``(k, 3, 3)`` and ``(k, 3)``.
        S_beta: merged stiffness in error coordinates, ``(k, 6, 6)``, or already restricted
            to ``dof``, ``(k, p, p)``.
        dof: the tangent coordinates in use.

    Returns:
        ``(k, p, p)`` blocks ``J_rawᵀ S_β J_raw`` (= ``J_βᵀ J_β`` with ``J_β = W_β J_raw``,
        ``W_βᵀ W_β = S_β``: no whitening factor is needed).
    """
    k = len(kept)
    p = len(dof)
    restricted = S_beta.shape[1] == p
    out = np.empty((k, p, p))
    Sd = np.empty((p, p))
    raw = np.empty((p, p))
    tmp = np.empty((p, p))
    A = np.empty((p, 6))
    at_node = np.zeros(3)  # the kept node is β's end: no lever arm
    eye = np.eye(3)
    longest = int((kept - start).max()) + 1 if k else 1
    H_R = np.empty((longest + 1, 3, 3))
    H_x = np.empty((longest + 1, 3))
    H_R[0] = eye
    H_x[0] = 0.0
    for j in range(k):
        length = kept[j] - start[j] + 1
        compose_into(tree_R, tree_t, domain[start[j]:kept[j] + 1], H_R, H_x)
        R = H_R[length]
        R_par = H_R[length - 1]
        x = H_x[length]
        _, _, Jb = endpoint_jacobians_one(0, eye, at_node, R, x, R_beta[j], t_beta[j])
        for a in range(p):
            for c in range(6):
                A[a, c] = Jb[dof[a], c]
        chain_block_into(A, R_par, R, at_node, dof, raw)
        for a in range(p):
            for b in range(p):
                Sd[a, b] = S_beta[j, a, b] if restricted else S_beta[j, dof[a], dof[b]]
        for a in range(p):  # Sd raw, then rawᵀ (Sd raw): loops beat two tiny BLAS calls
            for b in range(p):
                acc = 0.0
                for c in range(p):
                    acc += Sd[a, c] * raw[c, b]
                tmp[a, b] = acc
        for a in range(p):
            for b in range(p):
                acc = 0.0
                for c in range(p):
                    acc += raw[c, a] * tmp[c, b]
                out[j, a, b] = acc
    return out


@kernel
def give_way(
    adjust: Array, B_c: Array, domain: np.ndarray, kept: np.ndarray, start: np.ndarray,
    top: np.ndarray, tree_edge: np.ndarray, own_node: np.ndarray, own_block: Array,
) -> None:
    """Turn ``J_βᵀJ_β`` of each kept node (``adjust``, ``(k, p, p)``) into eq. 3.36's
    ``B_c − J_αᵀJ_α + J_βᵀJ_β`` in place (``B_c`` over the domain): α, the kept node's tree
    edge, gives way to β where its contribution to ``B`` is that node's alone
    (``own_node[α]`` is the node, ``own_block[α]`` the block) and the segment is longer than
    the node; otherwise, or when the segment holds a subtree top (``top`` per domain
    position), the node keeps ``B_c``.
    """
    for j in range(len(kept)):
        node = domain[kept[j]]
        alpha = tree_edge[node]
        use = start[j] < kept[j] and alpha >= 0 and own_node[alpha] == node
        for pos in range(start[j], kept[j] + 1):
            use = use and not top[pos]
        for a in range(adjust.shape[1]):
            for b in range(adjust.shape[2]):
                base = B_c[kept[j], a, b]
                merged = base + (adjust[j, a, b] - own_block[alpha, a, b])
                adjust[j, a, b] = merged if use else base


@kernel
def compliance(B: Array) -> Array:
    """Distribution weights ``1 / diag(B)`` over the rotational coordinates (TORO) of
    regularizer blocks ``(d, p, p)`` (rotation in the last ``p // 2`` coordinates, one for
    planar ``p = 3``), kept finite where a block is zero."""
    d, p = B.shape[0], B.shape[1]
    first = p - (p // 2 if p == 6 else 1)
    rot = np.empty(d)
    largest = 0.0
    for i in range(d):
        acc = 0.0
        for q in range(first, p):
            acc += B[i, q, q]
        rot[i] = acc
        largest = max(largest, acc)
    floor = 1e-9 * max(largest, 1e-12)
    for i in range(d):
        rot[i] = 1.0 / (rot[i] + floor)
    return rot


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
    # Per node: one exponential and a few 3×3 products, written on scalars (a view of a
    # row per helper call would cost as much as the arithmetic).
    longest = int((kept - start).max()) + 1 if len(kept) else 1
    H_R = np.empty((longest + 1, 3, 3))  # H_R[i + 1]: node i's rotation in the segment frame
    H_x = np.empty((longest + 1, 3))
    R_new = np.empty((longest + 1, 3, 3))  # the same after the turn
    frac = np.empty(longest)
    E = np.empty((3, 3))
    tmp = np.empty((3, 3))
    w = np.empty(3)
    target_x = np.empty(3)
    miss = np.empty(3)
    H_R[0] = np.eye(3)
    H_x[0] = 0.0
    R_new[0] = np.eye(3)
    for j in range(len(kept)):
        s0 = start[j]
        length = kept[j] - s0 + 1
        # The segment's poses in the frame of its parent.
        compose_into(tree_R, tree_t, domain[s0:s0 + length], H_R, H_x)
        total = 0.0
        for i in range(length):
            total += compliance[s0 + i]
        # Target of the kept node in that frame: its parent's pose times its local transform
        # with the step applied.
        last = domain[kept[j]]
        for a in range(3):
            target_x[a] = H_x[length - 1, a]
            for b in range(3):
                target_x[a] += H_R[length - 1, a, b] * (tree_t[last, b] + step[j, b])
            w[a] = step[j, 3 + a]
        geo.so3_exp_into(w, E)
        geo.mul3_into(tree_R[last], E, tmp)
        geo.mul3_into(H_R[length - 1], tmp, E)  # the target rotation
        # ω: the turn that takes the segment's end from its rotation to the target's.
        geo.mul3_into(E, H_R[length].T, tmp)
        omega = geo.so3_log_one(tmp)
        # Turn the segment: node i's pose rotates by its share fᵢ of ω about the segment's
        # parent, R'ᵢ = Exp(fᵢ ω) Hᵢ, so its local rotation becomes R'ᵢ₋₁ᵀ R'ᵢ; positions
        # follow with the old local translations, x'ᵢ = x'ᵢ₋₁ + R'ᵢ₋₁ tᵢ.
        cum = 0.0
        miss[:] = target_x
        for i in range(length):
            n = domain[s0 + i]
            cum += compliance[s0 + i]
            frac[i] = cum / total
            for a in range(3):
                w[a] = frac[i] * omega[a]
            geo.so3_exp_into(w, E)
            for a in range(3):
                miss[a] -= (R_new[i, a, 0] * tree_t[n, 0] + R_new[i, a, 1] * tree_t[n, 1]
                            + R_new[i, a, 2] * tree_t[n, 2])
                for b in range(3):
                    R_new[i + 1, a, b] = (E[a, 0] * H_R[i + 1, 0, b] + E[a, 1] * H_R[i + 1, 1, b]
                                          + E[a, 2] * H_R[i + 1, 2, b])
            for a in range(3):
                for b in range(3):
                    tmp[a, b] = (R_new[i, 0, a] * R_new[i + 1, 0, b]
                                 + R_new[i, 1, a] * R_new[i + 1, 1, b]
                                 + R_new[i, 2, a] * R_new[i + 1, 2, b])
            geo.renormalize_into(tmp, tree_R[n])
        # Then shift it: node i's position moves by its share fᵢ of the kept node's miss,
        # which in its parent's turned frame is tᵢ + (fᵢ − fᵢ₋₁) R'ᵢ₋₁ᵀ miss.
        prev_frac = 0.0
        for i in range(length):
            n = domain[s0 + i]
            share = frac[i] - prev_frac
            prev_frac = frac[i]
            for a in range(3):
                tree_t[n, a] += share * (R_new[i, 0, a] * miss[0] + R_new[i, 1, a] * miss[1]
                                         + R_new[i, 2, a] * miss[2])
