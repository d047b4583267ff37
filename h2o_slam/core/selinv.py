"""The selected inverse: entries of ``A⁻¹`` on the pattern of ``A``'s Cholesky factor.

The covariance blocks a robust solve tests edges against (each loop closure's ends, and
the ends of every closure of one place together) are entries of ``Σ = H⁻¹`` where ``H`` or
its factor ``L`` has entries. Takahashi's recurrence (Takahashi, Fagan & Chin, "Formation
of a sparse bus impedance matrix and its application to short circuit study", 1973; in
the form of Erisman & Tinney, "On computing certain elements of the inverse of a sparse
matrix", CACM 1975) gives all of those from ``A = L D Lᵀ`` (``L`` unit lower triangular),
the last column first::

    Z_ij = − Σ_{k ∈ L(:,j), k > j} Z_ik L_kj          (i ∈ L(:,j), i > j)
    Z_jj = 1 / D_j − Σ_{k ∈ L(:,j), k > j} Z_kj L_kj

Each ``Z_ik`` the sum reads lies in the pattern too (``i`` and ``k`` both in column ``j``'s
pattern means ``L_ik`` is filled in), so the work is about that of the factorization.
Taken a supernode at a time (columns with one pattern below them), the sums are dense
matrix products: a 1,000-pose 3-D grid's inverse on its factor's 221,000 entries takes
6.5 ms (33 ms a column at a time), where solving for the ``p`` columns of ``H⁻¹`` at
each of its 433 closures took about 0.4 s.

Entries outside the pattern are not computed: :func:`selected_inverse` takes the pairs of
unknowns whose entries the caller will read, and adds them to the pattern (as zeros of
``A``) before it factors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from h2o_slam.core.compiled import kernel
from h2o_slam.core.geometry import Array
from h2o_slam.core.spd import cholesky_factor, with_entries

#: Most multiply-adds (:func:`_work`) :func:`selected_inverse` takes on: a 2,200-pose
#: sphere's 9.1e8 take 0.4 s with its factorization (its closures' columns of ``H⁻¹``, 16 of
#: them, 0.45 s), the 2,500-pose sphere's 5.2e8 0.19 s, city10000's 1.5e8 0.14 s.
MAX_WORK = 1.5e9


@dataclass(frozen=True)
class SelectedInverse:
    """``A⁻¹`` on the pattern of ``A``'s permuted factor: ``A⁻¹[u, v] = Z[iperm[u],
    iperm[v]]``, ``Z``'s strictly lower entries in CSC (``indptr``, ``indices``,
    ``values``, each column's diagonal first) and its diagonal in ``diagonal``."""

    iperm: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    values: Array
    diagonal: Array

    def blocks(self, unknowns: np.ndarray) -> Array:
        """``A⁻¹[u, v]`` for every pair of each row of ``unknowns`` (``G × K``, -1 for an
        unknown that is held: its row and column are zero): ``G × K × K``.

        Raises:
            KeyError: a pair lies outside the pattern (it was not asked for).
        """
        unknowns = np.ascontiguousarray(unknowns, dtype=np.int64)
        out = np.zeros((unknowns.shape[0], unknowns.shape[1], unknowns.shape[1]))
        if not _gather(self.indptr, self.indices, self.values, self.diagonal, self.iperm,
                       unknowns, out):
            raise KeyError("an entry of the inverse outside the factor's pattern")
        return out


def selected_inverse(upper: sp.csc_matrix, pairs: np.ndarray,
                     max_work: float | None = None) -> SelectedInverse | None:
    """The selected inverse of the symmetric positive definite matrix whose upper triangle
    is ``upper`` (CSC, sorted), on the factor's pattern widened by the unknown ``pairs``
    (``k × 2``): ``None`` when it would take more than ``max_work`` multiply-adds
    (:data:`MAX_WORK` by default), no
    factorization is available (CHOLMOD is not installed), or the matrix does not factor.
    """
    widened = with_entries(upper, pairs)
    factor = cholesky_factor(widened)
    if factor is None:
        return None
    perm, indptr, indices, lower, d = factor
    if _work(indptr, indices) > (MAX_WORK if max_work is None else max_work):
        return None
    values = np.zeros_like(lower)
    diagonal = np.zeros(len(d))
    if not _takahashi(indptr, indices, lower, d, values, diagonal):
        return None
    iperm = np.empty_like(perm)
    iperm[perm] = np.arange(len(perm))
    return SelectedInverse(iperm, indptr, indices, values, diagonal)


@kernel
def _work(indptr: np.ndarray, indices: np.ndarray) -> float:
    """Multiply-adds of Takahashi's recurrence one column at a time on this pattern (each
    column walks the columns of its rows): what :func:`_takahashi` computes, in dense
    blocks at several times the speed."""
    total = 0.0
    for j in range(len(indptr) - 1):
        for pos in range(indptr[j] + 1, indptr[j + 1]):
            c = indices[pos]
            total += indptr[c + 1] - indptr[c]
    return total


@kernel
def _supernodes(indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """The first column of each supernode, and ``n`` last: runs of columns where each
    column's pattern below its diagonal is the next column's whole pattern (their entries
    form a dense trapezoid)."""
    n = len(indptr) - 1
    starts = np.empty(n + 1, dtype=np.int64)
    count = 1
    starts[0] = 0
    for j in range(n - 1):
        size = indptr[j + 1] - indptr[j]
        joined = (size > 1 and size == indptr[j + 2] - indptr[j + 1] + 1
                  and indices[indptr[j] + 1] == j + 1)
        if not joined:
            starts[count] = j + 1
            count += 1
    starts[count] = n
    return starts[:count + 1]


@kernel
def _takahashi(indptr: np.ndarray, indices: np.ndarray, lower: np.ndarray, d: np.ndarray,
               z: np.ndarray, diagonal: np.ndarray) -> bool:
    """Takahashi's recurrence (module docstring) by supernodes into ``z`` (``L``'s strictly
    lower pattern; each column's first entry, the diagonal, unused) and ``diagonal``: for a
    supernode ``K`` of ``s`` columns whose rows below are ``R``, with ``Z_RR`` already
    known, ``Z_RK = −Z_RR L_RK L_KK⁻¹`` and ``Z_KK = L_KK⁻ᵀ (D_K⁻¹ L_KK⁻¹ − L_RKᵀ Z_RK)``,
    dense products (BLAS) in place of one column at a time. ``False`` when the pattern is
    not closed (an entry of ``Z_RR`` is not stored) or not sorted with the diagonal
    first."""
    starts = _supernodes(indptr, indices)
    for k in range(len(starts) - 2, -1, -1):
        f, s = starts[k], starts[k + 1] - starts[k]
        below = indices[indptr[f + s - 1] + 1:indptr[f + s]]
        m = len(below)
        L_KK, L_RK = np.eye(s), np.empty((m, s))
        for c in range(s):
            base = indptr[f + c]
            if indices[base] != f + c:
                return False
            for i in range(c + 1, s):
                L_KK[i, c] = lower[base + i - c]
            for a in range(m):
                L_RK[a, c] = lower[base + s - c + a]
        Z_RR = np.empty((m, m))
        if not _gathered(indptr, indices, z, diagonal, below, Z_RR):
            return False
        inv_KK = _unit_lower_inverse(L_KK)
        Z_RK = -(Z_RR @ L_RK) @ inv_KK
        M = inv_KK * (1.0 / d[f:f + s])[:, None] - L_RK.T @ Z_RK
        Z_KK = inv_KK.T @ M
        for c in range(s):
            base = indptr[f + c]
            diagonal[f + c] = Z_KK[c, c]
            for i in range(c + 1, s):
                z[base + i - c] = 0.5 * (Z_KK[i, c] + Z_KK[c, i])
            for a in range(m):
                z[base + s - c + a] = Z_RK[a, c]
    return True


@kernel
def _gathered(indptr: np.ndarray, indices: np.ndarray, z: np.ndarray, diagonal: np.ndarray,
              rows: np.ndarray, out: np.ndarray) -> bool:
    """``Z[rows][:, rows]`` into ``out`` from the stored entries (``rows`` sorted):
    ``False`` where one is not stored."""
    m = len(rows)
    for b in range(m):
        c = rows[b]
        out[b, b] = diagonal[c]
        ptr, stop = indptr[c] + 1, indptr[c + 1]
        for a in range(b + 1, m):
            row = rows[a]
            while ptr < stop and indices[ptr] < row:
                ptr += 1
            if ptr == stop or indices[ptr] != row:
                return False
            out[a, b] = out[b, a] = z[ptr]
    return True


@kernel
def _unit_lower_inverse(L: np.ndarray) -> np.ndarray:
    """The inverse of a unit lower triangular matrix (forward substitution)."""
    s = L.shape[0]
    out = np.eye(s)
    for c in range(s):
        for i in range(c + 1, s):
            acc = 0.0
            for k in range(c, i):
                acc -= L[i, k] * out[k, c]
            out[i, c] = acc
    return out


@kernel
def _entry(indptr: np.ndarray, indices: np.ndarray, z: np.ndarray, diagonal: np.ndarray,
           i: int, k: int) -> tuple[float, bool]:
    """``Z[i, k]`` (permuted indices) and whether it is stored."""
    if i == k:
        return diagonal[i], True
    col, row = min(i, k), max(i, k)
    lo, hi = indptr[col] + 1, indptr[col + 1]
    while lo < hi:  # binary search: the rows are sorted
        mid = (lo + hi) // 2
        if indices[mid] < row:
            lo = mid + 1
        else:
            hi = mid
    if lo < indptr[col + 1] and indices[lo] == row:
        return z[lo], True
    return 0.0, False


@kernel
def _gather(indptr: np.ndarray, indices: np.ndarray, z: np.ndarray, diagonal: np.ndarray,
            iperm: np.ndarray, unknowns: np.ndarray, out: np.ndarray) -> bool:
    """:meth:`SelectedInverse.blocks` into ``out``; ``False`` at an entry not stored."""
    for g in range(unknowns.shape[0]):
        for s in range(unknowns.shape[1]):
            u = unknowns[g, s]
            if u < 0:
                continue
            for t in range(s, unknowns.shape[1]):
                v = unknowns[g, t]
                if v < 0:
                    continue
                value, found = _entry(indptr, indices, z, diagonal, iperm[u], iperm[v])
                if not found:
                    return False
                out[g, s, t] = value
                out[g, t, s] = value
    return True
