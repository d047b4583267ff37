"""The single-edge hybrid-Hessian solve (thesis 3.3.5, eq. 3.34) in O(d).

Solves ``min_x ‖J x + r‖² + Σᵢ xᵢᵀ Bᵢ xᵢ`` where ``J = [J₁ … J_d]`` is one edge's whitened
Jacobian (``m`` rows, ``d`` blocks of ``p`` columns) and ``B = diag(B₁ … B_d)`` is the
block-diagonal regularizer ``B_c``. The thesis triangularizes (3.35) with Givens rotations in
O(d²); because ``B`` is block diagonal, the same ``x`` comes out of the ``m × m`` measurement
space in O(d) (Woodbury):

* diagonalize each block, ``Bᵢ = Uᵢ Λᵢ Uᵢᵀ``, and split coordinates ``y = Uᵀx`` into
  regularized ones (``λ > 0``) and free ones (``λ = 0``: a node no other edge constrains);
* whiten the regularized ones, ``u = Λ^½ y_R``: they form a ridge regression with design
  ``Ã = J U Λ^-½`` (``m × dp``), solved through the thin SVD ``Ã = P Σ Qᵀ`` (from a QR of
  ``Ãᵀ``) —
  ``u = −Q Σ(I + Σ²)⁻¹ Pᵀ s`` with ``s = F y_F + r`` — which stays accurate when ``B`` is
  ill-conditioned, where the textbook Woodbury inverse ``(I + J B⁻¹ Jᵀ)⁻¹`` loses digits;
* the free ones minimize ``sᵀ (I + ÃÃᵀ)⁻¹ s``, an ``m``-row least-squares problem solved for
  its minimum-norm solution, which makes the whole ``x`` the minimum-norm least-squares
  solution of (3.34), as a dense solver returns it.
"""

from __future__ import annotations

import numpy as np

from h2o_slam.core.compiled import kernel
from h2o_slam.core.geometry import Array

#: Eigenvalues of B below this fraction of the problem's scale count as exactly zero.
NULL_TOLERANCE = 1e-12

_EPS = float(np.finfo(np.float64).eps)
_JACOBI_TOLERANCE = 1e-30


@kernel
def symmetric_eigen_into(A: Array, lam: Array, V: Array, work: Array) -> None:
    """Eigenvalues ``lam`` and orthonormal eigenvectors (columns of ``V``) of a small
    symmetric matrix ``A``, unordered, by cyclic Jacobi rotations.

    For the ``p × p`` blocks of ``B`` (``p`` ≤ 6) this is 5–10× faster than a LAPACK call
    (≈0.2 µs against ≈1.3 µs, most of it the call's fixed cost), and as accurate: Jacobi
    finds small eigenvalues to ``ε‖A‖``, as the null test below needs.
    """
    p = A.shape[0]
    for i in range(p):
        for j in range(p):
            work[i, j] = A[i, j]
            V[i, j] = 1.0 if i == j else 0.0
    for _ in range(60):
        off = 0.0
        total = 0.0
        for i in range(p):
            total += work[i, i] * work[i, i]
            for j in range(i + 1, p):
                off += work[i, j] * work[i, j]
        # Off-diagonal mass below (1e-15)² of the whole: the eigenvalues are settled to
        # ~1e-15 relative. (Down at ε² rounding can keep a sweep from ever getting there.)
        if off <= _JACOBI_TOLERANCE * (total + 2.0 * off):
            break
        for i in range(p - 1):
            for j in range(i + 1, p):
                a_ij = work[i, j]
                if a_ij == 0.0:
                    continue
                theta = (work[j, j] - work[i, i]) / (2.0 * a_ij)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(p):
                    a_ki, a_kj = work[k, i], work[k, j]
                    work[k, i] = c * a_ki - s * a_kj
                    work[k, j] = s * a_ki + c * a_kj
                for k in range(p):
                    a_ik, a_jk = work[i, k], work[j, k]
                    work[i, k] = c * a_ik - s * a_jk
                    work[j, k] = s * a_ik + c * a_jk
                for k in range(p):
                    v_ki, v_kj = V[k, i], V[k, j]
                    V[k, i] = c * v_ki - s * v_kj
                    V[k, j] = s * v_ki + c * v_kj
    for i in range(p):
        lam[i] = work[i, i]


@kernel
def solve_hybrid(J: Array, r: Array, B: Array) -> Array:
    """Minimum-norm minimizer of ``‖Σᵢ Jᵢ xᵢ + r‖² + Σᵢ xᵢᵀ Bᵢ xᵢ`` (compiled).

    Args:
        J: Jacobian blocks, ``(d, m, p)``, C-contiguous float64.
        r: residual, ``(m,)``.
        B: symmetric positive semi-definite regularizer blocks, ``(d, p, p)``.

    Returns:
        ``x`` with shape ``(d, p)``.
    """
    d, m, p = J.shape
    n = d * p
    lam = np.empty((d, p))
    U = np.empty((d, p, p))
    work = np.empty((p, p))
    for i in range(d):
        symmetric_eigen_into(B[i], lam[i], U[i], work)
    scale = max(max(lam.max(), 0.0), np.abs(J).max() ** 2)
    tol = NULL_TOLERANCE * max(scale, 1e-300)
    inv_sqrt = np.zeros((d, p))
    num_free = 0
    for i in range(d):
        for q in range(p):
            if lam[i, q] > tol:
                inv_sqrt[i, q] = 1.0 / np.sqrt(lam[i, q])
            else:
                num_free += 1
    A = np.zeros((d, m, p))  # J U, blockwise (loops: a BLAS call per tiny block costs more)
    for i in range(d):
        for k in range(m):
            for q in range(p):
                acc = 0.0
                for c in range(p):
                    acc += J[i, k, c] * U[i, c, q]
                A[i, k, q] = acc
    # Whitened design Ã = J U Λ^-½ (m × dp, zero-padded to at least m columns), held
    # transposed. Its thin SVD Ã = P Σ Qᵀ from a QR of the tall Ãᵀ = Q_r R and the SVD of the
    # small R = U_r Σ V_rᵀ (P = V_r, Q = Q_r U_r): LAPACK's SVD of the wide matrix itself
    # takes 15 ms at dp = 4300 where this takes 0.1 ms.
    whitened_t = np.zeros((max(n, m), m))
    for i in range(d):
        for q in range(p):
            for k in range(m):
                whitened_t[i * p + q, k] = A[i, k, q] * inv_sqrt[i, q]
    Q_qr, R_r = np.linalg.qr(whitened_t)
    U_svd, sigma, Vt_r = np.linalg.svd(R_r)
    Q_r = np.ascontiguousarray(Q_qr)
    U_r = np.ascontiguousarray(U_svd)
    P = np.ascontiguousarray(Vt_r.T)
    Pt = np.ascontiguousarray(Vt_r)
    y = np.zeros((d, p))
    s = r.copy()
    if num_free:
        F = np.empty((m, num_free))
        col = 0
        for i in range(d):
            for q in range(p):
                if inv_sqrt[i, q] == 0.0:
                    F[:, col] = A[i, :, q]
                    col += 1
        C = (P / np.sqrt(1.0 + sigma**2)) @ Pt
        # Free directions the edge does not see either (a position edge's turn of a leaf)
        # leave C F rank deficient, with a rounding-noise singular value of ~1e-15 relative:
        # numpy's default cut-off (ε·max(m, n)) can keep it and blow the step up to 1e14.
        rcond = max(_EPS * max(m, num_free), NULL_TOLERANCE)
        y_free = -np.linalg.lstsq(C @ F, C @ r, rcond)[0]
        col = 0
        for i in range(d):
            for q in range(p):
                if inv_sqrt[i, q] == 0.0:
                    y[i, q] = y_free[col]
                    col += 1
        s = F @ y_free + r
    u = -(Q_r @ (U_r @ (sigma / (1.0 + sigma**2) * (Pt @ s))))
    x = np.empty((d, p))
    for i in range(d):
        for q in range(p):
            y[i, q] += u[i * p + q] * inv_sqrt[i, q]
        for c in range(p):
            acc = 0.0
            for q in range(p):
                acc += U[i, c, q] * y[i, q]
            x[i, c] = acc
    return x
