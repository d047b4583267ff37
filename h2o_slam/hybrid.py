"""The single-edge hybrid-Hessian solve (thesis 3.3.5, eq. 3.34) in O(d).

Solves ``min_x ‖J x + r‖² + Σᵢ xᵢᵀ Bᵢ xᵢ`` where ``J = [J₁ … J_d]`` is one edge's whitened
Jacobian (``m`` rows, ``d`` blocks of ``p`` columns) and ``B = diag(B₁ … B_d)`` is the
block-diagonal regularizer ``B_c``. The thesis triangularizes (3.35) with Givens rotations in
O(d²); because ``B`` is block diagonal, the same ``x`` comes out of the ``m × m`` measurement
space in O(d) (Woodbury):

* diagonalize each block, ``Bᵢ = Uᵢ Λᵢ Uᵢᵀ``, and split coordinates ``y = Uᵀx`` into
  regularized ones (``λ > 0``) and free ones (``λ = 0``: a node no other edge constrains);
* whiten the regularized ones, ``u = Λ^½ y_R``: they form a ridge regression with design
  ``Ã = J U Λ^-½`` (``m × dp``), solved through the thin SVD ``Ã = P Σ Qᵀ`` —
  ``u = −Q Σ(I + Σ²)⁻¹ Pᵀ s`` with ``s = F y_F + r`` — which stays accurate when ``B`` is
  ill-conditioned, where the textbook Woodbury inverse ``(I + J B⁻¹ Jᵀ)⁻¹`` loses digits;
* the free ones minimize ``sᵀ (I + ÃÃᵀ)⁻¹ s``, an ``m``-row least-squares problem solved for
  its minimum-norm solution, which makes the whole ``x`` the minimum-norm least-squares
  solution of (3.34), as a dense solver returns it.
"""

from __future__ import annotations

import numpy as np

from h2o_slam.geometry import Array

#: Eigenvalues of B below this fraction of the problem's scale count as exactly zero.
NULL_TOLERANCE = 1e-12


def solve_hybrid(J: Array, r: Array, B: Array) -> Array:
    """Minimum-norm minimizer of ``‖Σᵢ Jᵢ xᵢ + r‖² + Σᵢ xᵢᵀ Bᵢ xᵢ``.

    Args:
        J: Jacobian blocks, ``(d, m, p)``.
        r: residual, ``(m,)``.
        B: symmetric positive semi-definite regularizer blocks, ``(d, p, p)``.

    Returns:
        ``x`` with shape ``(d, p)``.
    """
    lam, U = np.linalg.eigh(B)
    scale = max(float(np.max(lam, initial=0.0)), float(np.max(np.abs(J), initial=0.0)) ** 2)
    regular = lam > NULL_TOLERANCE * max(scale, 1e-300)
    inv_sqrt = np.where(regular, 1.0 / np.sqrt(np.where(regular, lam, 1.0)), 0.0)
    A = J @ U
    m = len(r)
    whitened = np.swapaxes(A * inv_sqrt[:, None, :], 0, 1).reshape(m, -1)
    if whitened.shape[1] < m:
        whitened = np.hstack([whitened, np.zeros((m, m - whitened.shape[1]))])
    P, sigma, Qt = np.linalg.svd(whitened, full_matrices=False)
    free = ~regular
    y = np.zeros(lam.shape)
    s = r
    if np.any(free):
        F = np.swapaxes(A, 1, 2)[free].T
        C = (P / np.sqrt(1.0 + sigma**2)) @ P.T
        y_free = -np.linalg.lstsq(C @ F, C @ r, rcond=None)[0]
        y[free] = y_free
        s = F @ y_free + r
    u = -(Qt.T @ (sigma / (1.0 + sigma**2) * (P.T @ s)))
    y += (u[: lam.size].reshape(lam.shape)) * inv_sqrt
    return np.einsum("dpq,dq->dp", U, y)
