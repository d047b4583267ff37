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

Segments are processed together as padded ``(length, segments, …)`` arrays so that the work
is a few batched numpy operations rather than a Python loop per segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h2o_slam import geometry as geo
from h2o_slam.geometry import Array
from h2o_slam.jacobians import chain_jacobians, endpoint_jacobians


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


def _padded(values: Array, sel: Selection, fill: Array) -> tuple[Array, np.ndarray]:
    """Gather per-segment values into ``(max_len, k, …)``, padding after each segment's end.

    Returns the padded array and the valid mask ``(max_len, k)``.
    """
    lengths = sel.lengths
    max_len = int(lengths.max())
    offsets = np.arange(max_len)[:, None]
    valid = offsets < lengths[None, :]
    idx = np.where(valid, sel.start[None, :] + offsets, 0)
    out = np.where(valid.reshape(valid.shape + (1,) * (values.ndim - 1)), values[idx], fill)
    return out, valid


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
    R, valid = _padded(k_R, sel, np.eye(3))
    t, _ = _padded(k_t, sel, np.zeros(3))
    Sp, _ = _padded(S, sel, np.zeros((6, 6)))
    P_R, P_t = geo.cumulative_compose(R, t)
    last = sel.lengths - 1
    cols = np.arange(len(last))
    R_beta, t_beta = P_R[last, cols], P_t[last, cols]
    R_is = np.swapaxes(P_R, -1, -2) @ R_beta[None]
    rot = np.zeros(R_is.shape[:2] + (6, 6))
    rot[..., :3, :3] = R_is
    rot[..., 3:, 3:] = R_is
    S_beta = np.sum(np.swapaxes(rot, -1, -2) @ Sp @ rot * valid[..., None, None], axis=0)
    return R_beta, t_beta, S_beta


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
        New local transforms of the domain nodes. Each kept node ends exactly where its
        step puts it relative to the segment's parent; the nodes in between take a share of
        the rotation and translation in proportion to their cumulative compliance.
    """
    R, valid = _padded(R_loc, sel, np.eye(3))
    t, _ = _padded(t_loc, sel, np.zeros(3))
    w, _ = _padded(compliance, sel, np.zeros(()))
    last = sel.lengths - 1
    cols = np.arange(len(last))
    H_R, H_x = geo.cumulative_compose(R, t)
    # Target of each kept node in its segment's frame: its parent's pose times its local
    # transform with the step applied.
    par_R = np.where((last > 0)[:, None, None], H_R[np.maximum(last - 1, 0), cols], np.eye(3))
    par_x = np.where((last > 0)[:, None], H_x[np.maximum(last - 1, 0), cols], 0.0)
    new_local_R = R[last, cols] @ geo.so3_exp(step[:, 3:])
    target_R = par_R @ new_local_R
    target_x = par_x + np.einsum("kij,kj->ki", par_R, t[last, cols] + step[:, :3])
    omega = geo.so3_log(target_R @ np.swapaxes(H_R[last, cols], -1, -2))
    frac = np.cumsum(w, axis=0) / np.sum(w, axis=0)[None, :]
    frac = np.where(valid, frac, 1.0)
    R_new = geo.so3_exp(frac[..., None] * omega[None]) @ H_R
    R_prev = np.concatenate([np.broadcast_to(np.eye(3), R_new[:1].shape), R_new[:-1]])
    local_R = np.swapaxes(R_prev, -1, -2) @ R_new
    _, x_rot = geo.cumulative_compose(local_R, t)
    x_new = x_rot + frac[..., None] * (target_x - x_rot[last, cols])[None]
    x_prev = np.concatenate([np.zeros_like(x_new[:1]), x_new[:-1]])
    local_t = np.einsum("lkji,lkj->lki", R_prev, x_new - x_prev)
    out_R = R_loc.copy()
    out_t = t_loc.copy()
    offsets = np.arange(len(valid))[:, None]
    idx = sel.start[None, :] + offsets
    out_R[idx[valid]] = geo.renormalize(local_R[valid])
    out_t[idx[valid]] = local_t[valid]
    return out_R, out_t


def merged_stiffness(
    sel: Selection, R_loc: Array, t_loc: Array, R_beta: Array, t_beta: Array, W_beta: Array,
    dof: np.ndarray,
) -> Array:
    """``J_βᵀ J_β`` at each kept node: the diagonal block the merged constraint β of its
    segment contributes to ``B`` (eq. 3.36), for a perturbation of the kept node's local
    transform.

    Args:
        sel: the selection.
        R_loc, t_loc: local transforms of the domain nodes.
        R_beta, t_beta: merged measurements, ``(k, 3, 3)`` and ``(k, 3)``.
        W_beta: whitening of the merged stiffness in the coordinates ``dof``, ``(k, p, p)``.
        dof: the tangent coordinates in use.

    Returns:
        ``(k, p, p)`` blocks.
    """
    R, _ = _padded(R_loc, sel, np.eye(3))
    t, _ = _padded(t_loc, sel, np.zeros(3))
    H_R, H_x = geo.cumulative_compose(R, t)
    last = sel.lengths - 1
    cols = np.arange(len(last))
    R_s, x_s = H_R[last, cols], H_x[last, cols]
    R_par = np.where((last > 0)[:, None, None], H_R[np.maximum(last - 1, 0), cols], np.eye(3))
    k = len(last)
    ident = np.broadcast_to(np.eye(3), (k, 3, 3))
    kind = np.zeros(k, dtype=np.int8)
    _, _, Jb = endpoint_jacobians(kind, ident, np.zeros((k, 3)), R_s, x_s, R_beta, t_beta)
    J = (Jb @ chain_jacobians(R_par, R_s, x_s, x_s))[:, dof[:, None], dof[None, :]]
    J = W_beta @ J
    return np.swapaxes(J, -1, -2) @ J
