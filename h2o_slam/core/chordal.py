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
from h2o_slam.core.spd import SPDFactor, dense_cholesky_solve


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
    n = graph.num_nodes
    # R_b = R_a R_ab row by row: with u a row of a rotation as a column vector,
    # u_b − R_abᵀ u_a = 0, three right-hand sides (one per row), node 0's rows those of I.
    C = -np.swapaxes(graph.meas_R[keep], 1, 2)
    U = _anchored_least_squares(n, a, b, C, np.zeros((len(a), 3, 3)), w_rot, np.eye(3))
    R = _nearest_rotations(U.transpose(0, 2, 1))
    # Given the rotations, t_b − t_a = R_a t_ab is linear in the translations.
    d = np.einsum("eij,ej->ei", R[a], graph.meas_t[keep])[:, None, :]
    t = _anchored_least_squares(n, a, b, np.full((len(a), 1, 1), -1.0), d, w_pos,
                                np.zeros((1, 3)))
    return R, t[:, 0, :]


#: Most unknowns solved as one dense matrix: below it LAPACK's dense Cholesky is faster than
#: assembling and analysing a sparse one (measured: 0.3 against 0.6 ms at 24 unknowns, 1.4
#: against 1.1 ms at 150).
DENSE_MAX = 96


def _anchored_least_squares(n: int, a: np.ndarray, b: np.ndarray, C: Array, d: Array,
                            w: Array, anchor: Array) -> Array:
    """``min Σ_e w_e ‖x_b + C_e x_a − d_e‖²`` over every node's ``x`` ``(k, c)``: ``C``
    ``(m, k, k)``, ``d`` ``(m, k, c)``, node 0 held at ``anchor`` ``(k, c)``. Returns ``x``
    ``(n, k, c)``.

    Raises:
        GraphError: the edges leave a node's unknowns undetermined.
    """
    k = C.shape[1]
    # Node 0's known unknowns move to the right-hand side.
    d = d - (a == 0)[:, None, None] * (C @ anchor) - (b == 0)[:, None, None] * anchor
    J = np.concatenate([C, np.broadcast_to(np.eye(k), C.shape)], axis=2)  # [x_a | x_b]
    JtW = np.swapaxes(J, 1, 2) * w[:, None, None]
    H, g = JtW @ J, JtW @ d  # (m, 2k, 2k), (m, 2k, c)
    size = (n - 1) * k
    var = np.concatenate([(a - 1)[:, None] * k, (b - 1)[:, None] * k], axis=1)
    var = (np.repeat(var, k, axis=1) + np.tile(np.arange(k), 2))
    var[np.repeat(np.stack([a == 0, b == 0], axis=1), k, axis=1)] = size  # held: dropped
    c = d.shape[2]
    # bincount, not np.add.at: several times faster at summing repeated indices.
    rhs = np.asarray(np.bincount((var[:, :, None] * c + np.arange(c)).ravel(), g.ravel(),
                                 minlength=(size + 1) * c), dtype=float).reshape(size + 1, c)
    rows = np.broadcast_to(var[:, :, None], H.shape).ravel()
    cols = np.broadcast_to(var[:, None, :], H.shape).ravel()
    solve = _dense_solve if size <= DENSE_MAX else _sparse_solve
    X = solve(rows, cols, H.ravel(), rhs[:size], size)
    if not np.all(np.isfinite(X)):
        raise GraphError("the edges do not connect every node to node 0")
    return np.concatenate([anchor[None], X.reshape(n - 1, k, -1)])


def _dense_solve(rows: np.ndarray, cols: np.ndarray, values: Array, rhs: Array,
                 size: int) -> Array:
    if size == 0:
        return rhs
    sums = np.bincount(rows * (size + 1) + cols, values, minlength=(size + 1) ** 2)
    H: Array = np.asfortranarray(sums.reshape(size + 1, size + 1)[:size, :size], dtype=float)
    try:
        return dense_cholesky_solve(H, rhs, min_pivot=1e-12)
    except ArithmeticError:
        raise GraphError("the edges do not connect every node to node 0") from None


def _sparse_solve(rows: np.ndarray, cols: np.ndarray, values: Array, rhs: Array,
                  size: int) -> Array:
    keep = (rows < size) & (cols < size) & (rows <= cols)
    U = sp.csc_matrix((values[keep], (rows[keep], cols[keep])), shape=(size, size))
    U.sort_indices()
    try:  # the exact mode's sparse Cholesky (CHOLMOD where installed)
        return SPDFactor(U.indptr, U.indices).solve(U.data, rhs)
    except np.linalg.LinAlgError as err:
        raise GraphError(f"the edges do not connect every node to node 0 ({err})") from None


def _nearest_rotations(M: Array) -> Array:
    """The rotation nearest each 3×3 matrix in the Frobenius norm (SVD, determinant +1)."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    return U @ Vt
