"""Chordal initialization of 3-D pose graphs: rotations first, by a linear relaxation, then
translations.

Carlone, Tron, Daniilidis & Dellaert, "Initialization techniques for 3D SLAM: a survey on
rotation estimation and its use in pose graph optimization" (ICRA 2015), the chordal
relaxation: minimize ``Σ w ‖R_b − R_a R_ab‖²_F`` over unconstrained 3×3 matrices (linear
least squares, one sparse system with three right-hand sides, one per row of the
rotations), with the first pose held at the identity, then project each matrix to the
nearest rotation. Given the rotations, ``t_b − t_a = R_a t_ab`` is linear in the
translations. No initial guess enters, so there is no local minimum to fall into: the 3-D
sibling of LAGO (:mod:`h2o_slam.core.lago`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from h2o_slam.core.errors import GraphError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EdgeKind, PoseGraph
from h2o_slam.core.spd import SPDFactor, upper


def chordal(graph: PoseGraph, weights: Array | None = None) -> tuple[Array, Array]:
    """World rotations ``(N, 3, 3)`` and translations ``(N, 3)`` of ``graph``'s relative
    edges, each weighted by its information's scale times ``weights`` (0: left out), node 0
    at the origin.

    Raises:
        GraphError: the kept edges do not connect every node to node 0.
    """
    keep = graph.kind == EdgeKind.RELATIVE
    w = np.ones(graph.num_edges) if weights is None else np.asarray(weights, dtype=float)
    keep &= w > 0.0
    a, b = graph.a[keep], graph.b[keep]
    info = graph.info[keep]
    # One scalar weight per edge and block: the mean of the information's diagonal.
    w_rot = w[keep] * np.mean(np.diagonal(info[:, 3:, 3:], axis1=1, axis2=2), axis=1)
    w_pos = w[keep] * np.mean(np.diagonal(info[:, :3, :3], axis1=1, axis2=2), axis=1)
    R = _rotations(graph.num_nodes, a, b, graph.meas_R[keep], w_rot)
    t = _translations(graph.num_nodes, a, b, R, graph.meas_t[keep], w_pos)
    return R, t


def _rotations(n: int, a: np.ndarray, b: np.ndarray, meas_R: Array, w: Array) -> Array:
    """``R_b = R_a R_ab`` row by row: with ``u`` a row of a rotation as a column vector,
    ``u_b − R_abᵀ u_a = 0``; three right-hand sides, one per row, node 0's rows known."""
    m = len(a)
    rows = np.arange(3 * m).reshape(m, 3)
    # u_b: identity blocks; u_a: −R_abᵀ blocks.
    r_b = rows.ravel()
    c_b = (3 * b[:, None] + np.arange(3)).ravel()
    v_b = np.ones(3 * m)
    r_a = np.repeat(rows[:, :, None], 3, axis=2).ravel()
    c_a = np.repeat((3 * a[:, None] + np.arange(3))[:, None, :], 3, axis=1).ravel()
    v_a = -np.swapaxes(meas_R, 1, 2).ravel()
    A = sp.csr_matrix((np.concatenate([v_b, v_a]), (np.concatenate([r_b, r_a]),
                                                    np.concatenate([c_b, c_a]))),
                      shape=(3 * m, 3 * n))
    u0 = np.eye(3)  # node 0's three rows, as the three right-hand sides' known unknowns
    X = _anchored_least_squares(A, np.zeros((3 * m, 3)), np.repeat(w, 3), 3, u0, n)
    M = X.reshape(n, 3, 3).transpose(0, 2, 1)  # node i: rows of its matrix
    return _nearest_rotations(M)


def _translations(n: int, a: np.ndarray, b: np.ndarray, R: Array, meas_t: Array,
                  w: Array) -> Array:
    """``t_b − t_a = R_a t_ab`` for the rotations found, node 0 at the origin."""
    m = len(a)
    D = sp.csr_matrix((np.concatenate([np.ones(m), -np.ones(m)]),
                       (np.tile(np.arange(m), 2), np.concatenate([b, a]))), shape=(m, n))
    rhs = np.einsum("eij,ej->ei", R[a], meas_t)
    return _anchored_least_squares(D, rhs, w, 1, np.zeros((1, 3)), n)


def _anchored_least_squares(A: sp.csr_matrix, B: Array, w: Array, block: int,
                            anchor: Array, n: int) -> Array:
    """``min Σ w (A X − B)²`` with node 0's ``block`` unknowns fixed to ``anchor``; returns
    every node's unknowns ``(n·block, k)``."""
    A = A.tocsc()
    fixed = A[:, :block]
    free = A[:, block:]
    rhs = B - fixed @ anchor
    W = sp.diags(w)
    U = upper(free.T @ W @ free)
    g = np.asarray(free.T @ (W @ rhs))
    try:  # the exact mode's sparse Cholesky (CHOLMOD where installed)
        X = SPDFactor(U.indptr, U.indices).solve(U.data, g).reshape(-1, rhs.shape[1])
    except np.linalg.LinAlgError as err:
        raise GraphError(f"the edges do not connect every node to node 0 ({err})") from None
    if not np.all(np.isfinite(X)):
        raise GraphError("the edges do not connect every node to node 0")
    return np.vstack([anchor, X]).reshape(n * block, -1)


def _nearest_rotations(M: Array) -> Array:
    """The rotation nearest each 3×3 matrix in the Frobenius norm (SVD, determinant +1)."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    return U @ Vt
