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
from h2o_slam.core.jacobians import ALL_DOF, Dof, chain_block_into, endpoint_jacobians_one


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

    ``S``, ``out`` and the scratch ``work`` are ``(p, p)``. Restricting to ``dof`` before
    turning is exact when ``Q`` maps the coordinates in use onto themselves: any rotation
    for all six, rotations about z for the planar ``(x, y, yaw)``. ``R`` is block diagonal:
    each entry sums over one block's coordinates only, which a tuple ``dof`` lets the
    compiler resolve (216 products for all six, 30 planar).
    """
    p = len(dof)
    for c in range(p):
        for b in range(p):
            acc = 0.0
            for e in range(p):
                if (dof[e] < 3) == (dof[b] < 3):
                    acc += S[c, e] * Q[dof[e] % 3, dof[b] % 3]
            work[c, b] = acc
    for a in range(p):
        for b in range(p):
            acc = 0.0
            for c in range(p):
                if (dof[c] < 3) == (dof[a] < 3):
                    acc += Q[dof[c] % 3, dof[a] % 3] * work[c, b]
            out[a, b] += acc


@kernel
def _merge_segments(
    kept: np.ndarray, start: np.ndarray, k_R: Array, k_t: Array, S: Array, dof: Dof
) -> tuple[Array, Array, Array]:
    k = len(kept)
    p = len(dof)
    R_beta = np.empty((k, 3, 3))
    t_beta = np.zeros((k, 3))
    S_beta = np.empty((k, p, p))
    R_acc = np.empty((3, 3))
    R_next = np.empty((3, 3))
    S_acc = np.empty((p, p))
    S_next = np.empty((p, p))
    work = np.empty((p, p))
    for j in range(k):
        R_acc[:] = np.eye(3)
        S_acc[:] = 0.0
        for pos in range(start[j], kept[j] + 1):
            # k_β grows by the node's transform on the right; the stiffness gathered so far
            # is turned into the node's frame (Horner's rule for eq. 3.38), then its own
            # is added.
            geo.add_mulv3(R_acc, k_t[pos], t_beta[j])
            geo.mul3_into(R_acc, k_R[pos], R_next)
            S_next[:] = S[pos]
            if pos > start[j]:
                add_rotated_stiffness(S_acc, k_R[pos], dof, S_next, work)
            R_acc, R_next = R_next, R_acc
            S_acc, S_next = S_next, S_acc
        R_beta[j] = R_acc
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
            for a in range(p):
                for b in range(p):
                    S[i, a, b] = info[e, dof[a], dof[b]]
        else:
            for a in range(3):
                k_t[i, a] = 0.0
                for b in range(3):
                    k_R[i, a, b] = meas_R[e, b, a]
                    k_t[i, a] -= meas_R[e, b, a] * meas_t[e, b]
            for a in range(p):
                for b in range(p):
                    S_e[a, b] = info[e, dof[a], dof[b]]
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
    prefix = np.empty((3, 3, 3))  # three buffers: the parent's, the node's, the next
    for j in range(k):
        prefix[0] = eye
        x = np.zeros(3)
        cur = 0
        for pos in range(start[j], kept[j] + 1):
            n = domain[pos]
            geo.add_mulv3(prefix[cur], tree_t[n], x)
            geo.mul3_into(prefix[cur], tree_R[n], prefix[(cur + 1) % 3])
            cur = (cur + 1) % 3
        R = prefix[cur]
        R_par = prefix[(cur + 2) % 3]
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
    adjust: Array, domain: np.ndarray, kept: np.ndarray, start: np.ndarray, top: np.ndarray,
    tree_edge: np.ndarray, own_node: np.ndarray, own_block: Array,
) -> None:
    """Turn ``J_βᵀJ_β`` of each kept node (``adjust``, ``(k, p, p)``) into eq. 3.36's
    ``−J_αᵀJ_α + J_βᵀJ_β`` in place: α, the kept node's tree edge, gives way to β where its
    contribution to ``B`` is that node's alone (``own_node[α]`` is the node, ``own_block[α]``
    the block); otherwise, or when the segment holds a subtree top (``top`` per domain
    position), the segment keeps ``B`` (zero adjustment).
    """
    for j in range(len(kept)):
        node = domain[kept[j]]
        alpha = tree_edge[node]
        use = alpha >= 0 and own_node[alpha] == node
        for pos in range(start[j], kept[j] + 1):
            use = use and not top[pos]
        for a in range(adjust.shape[1]):
            for b in range(adjust.shape[2]):
                adjust[j, a, b] = adjust[j, a, b] - own_block[alpha, a, b] if use else 0.0


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
    longest = int((kept - start).max()) + 1 if len(kept) else 1
    H_R = np.empty((longest, 3, 3))
    H_x = np.empty((longest, 3))
    frac = np.empty(longest)
    R_new = np.empty((longest, 3, 3))
    eye = np.eye(3)
    E = np.empty((3, 3))
    tmp = np.empty((3, 3))
    target_R = np.empty((3, 3))
    target_x = np.empty(3)
    moved = np.empty(3)
    w = np.empty(3)
    omega = np.empty(3)
    x_rot = np.empty(3)
    for j in range(len(kept)):
        s0 = start[j]
        length = kept[j] - s0 + 1
        # The segment's poses in the frame of its parent.
        R = eye
        total = 0.0
        for i in range(length):
            n = domain[s0 + i]
            for a in range(3):
                H_x[i, a] = H_x[i - 1, a] if i else 0.0
            geo.add_mulv3(R, tree_t[n], H_x[i])
            geo.mul3_into(R, tree_R[n], H_R[i])
            R = H_R[i]
            total += compliance[s0 + i]
        # Target of the kept node in that frame: its parent's pose times its local transform
        # with the step applied.
        last = domain[kept[j]]
        par_R = H_R[length - 2] if length > 1 else eye
        for a in range(3):
            target_x[a] = H_x[length - 2, a] if length > 1 else 0.0
            moved[a] = tree_t[last, a] + step[j, a]
            w[a] = step[j, 3 + a]
        geo.add_mulv3(par_R, moved, target_x)
        geo.so3_exp_into(w, E)
        geo.mul3_into(tree_R[last], E, tmp)
        geo.mul3_into(par_R, tmp, target_R)
        # ω: the turn that takes the segment's end from its rotation to the target's.
        for a in range(3):
            for b in range(3):
                tmp[a, b] = (target_R[a, 0] * H_R[length - 1, b, 0]
                             + target_R[a, 1] * H_R[length - 1, b, 1]
                             + target_R[a, 2] * H_R[length - 1, b, 2])
        omega[:] = geo.so3_log_one(tmp)
        # Turn the segment: node i's pose rotates by its share of ω about the segment's
        # parent, R'ᵢ = Exp(fᵢ ω) Hᵢ; positions follow with the old local translations,
        # x'ᵢ = x'ᵢ₋₁ + R'ᵢ₋₁ tᵢ.
        cum = 0.0
        x_rot[:] = 0.0
        prev = eye
        for i in range(length):
            cum += compliance[s0 + i]
            frac[i] = cum / total
            for a in range(3):
                w[a] = frac[i] * omega[a]
            geo.so3_exp_into(w, E)
            geo.mul3_into(E, H_R[i], R_new[i])
            geo.add_mulv3(prev, tree_t[domain[s0 + i]], x_rot)
            prev = R_new[i]
        # Then shift it: node i's position moves by its share fᵢ of the kept node's miss,
        # which in its parent's turned frame is tᵢ + (fᵢ − fᵢ₋₁) R'ᵢ₋₁ᵀ miss; its local
        # rotation is R'ᵢ₋₁ᵀ R'ᵢ.
        for a in range(3):
            moved[a] = target_x[a] - x_rot[a]
        prev = eye
        prev_frac = 0.0
        for i in range(length):
            n = domain[s0 + i]
            share = frac[i] - prev_frac
            prev_frac = frac[i]
            for a in range(3):
                tree_t[n, a] += share * (prev[0, a] * moved[0] + prev[1, a] * moved[1]
                                         + prev[2, a] * moved[2])
            geo.mul3t_into(prev, R_new[i], tmp)
            geo.renormalize_into(tmp, tree_R[n])
            prev = R_new[i]
