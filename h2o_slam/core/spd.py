"""Sparse symmetric positive definite solves: the one factorization LAGO and exact mode use.

:class:`SPDFactor` factors matrices that share one sparsity pattern. The fill-reducing
ordering and the symbolic analysis are done once per pattern; each new set of values is a
numeric refactorization (exact mode's Gauss–Newton iterations and damping retries all keep
the pattern of ``JᵀJ``). Backends, in the order ``auto`` tries them:

* ``cholmod`` — SuiteSparse's CHOLMOD (supernodal Cholesky with BLAS, AMD ordering) from
  cvxopt's wheel, which bundles SuiteSparse and OpenBLAS: nothing to compile;
* ``qdldl`` — OSQP's QDLDL, a simplicial LDLᵀ with AMD ordering (a small wheel);
* ``splu`` — scipy's SuperLU in symmetric mode, minimum-degree ordering on ``Aᵀ + A`` and
  diagonal pivots; always installed, no symbolic reuse.

``auto`` factors a matrix of at most :data:`DENSE_MAX` unknowns as a dense one with LAPACK
(a 9-pose graph's Gauss–Newton system: a sparse backend's bookkeeping costs more than the
factorization).

Measured on the public graphs' LAGO and exact-mode matrices (``bench/spd.py``; README,
"Dependencies and why"): CHOLMOD's numeric refactorization is 2–7× faster than QDLDL's on
city10000, parking-garage and sphere2500 and within 10 % of it on the sparsest planar
systems; a fresh CHOLMOD factorization is 2–4× faster than SuperLU's.

A backend that finds no factor (the matrix is not positive definite to working precision)
hands over to ``splu``; when that fails too :class:`numpy.linalg.LinAlgError` is raised.
Matrices are given as their upper triangle in CSC form with sorted row indices.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import scipy.sparse as sp

from h2o_slam.core.geometry import Array

#: Factorizations by name; ``auto`` is the first of the others that is installed.
METHODS = ("auto", "cholmod", "qdldl", "splu")

#: The package that provides each optional backend (the install hint names it).
PACKAGES = {"cholmod": "cvxopt", "qdldl": "qdldl"}

#: Most unknowns ``auto`` factors as a dense matrix: exact mode's solves from the chordal
#: start of 3-D grids took 1.24 against 1.38 ms at 54 unknowns, 2.0 against 2.0 ms at 114,
#: and 3.5 against 2.3 ms at 174.
DENSE_MAX = 120


def _module(name: str) -> Any:
    """An optional backend's module, or None when it is not installed (imported by name so
    that type checking does not depend on it)."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def available(method: str) -> bool:
    """Whether the backend ``method`` (not ``auto``) can run here."""
    if method == "cholmod":
        return _module("cvxopt.cholmod") is not None
    if method == "qdldl":
        return _module("qdldl") is not None
    return method == "splu"


def resolve(method: str) -> str:
    """The backend ``method`` names: ``auto`` becomes the first installed one.

    Raises:
        ValueError: ``method`` is unknown, or names a backend that is not installed.
    """
    if method not in METHODS:
        raise ValueError(f"unknown factorization {method!r}; choose one of {', '.join(METHODS)}")
    if method == "auto":
        return next(m for m in METHODS[1:] if available(m))
    if not available(method):
        raise ValueError(f"factorization {method!r} needs the {PACKAGES[method]} package "
                         f"(pip install {PACKAGES[method]})")
    return method


def upper(matrix: Any) -> sp.csc_matrix:
    """The upper triangle of a square sparse matrix, CSC with sorted indices."""
    out = sp.triu(sp.csc_matrix(matrix), format="csc")
    out.sort_indices()
    return out


class SPDFactor:
    """Factorizations of symmetric positive definite matrices with one sparsity pattern.

    Args:
        indptr, indices: the pattern of the upper triangle, CSC with sorted row indices;
            it must hold the whole diagonal.
        method: one of :data:`METHODS`.

    Raises:
        ValueError: ``method`` is unknown or not installed.
    """

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, method: str = "auto") -> None:
        self.method = resolve(method)
        self.n = len(indptr) - 1
        self.indptr = np.asarray(indptr, dtype=np.int64)
        self.indices = np.asarray(indices, dtype=np.int64)
        # ``auto`` factors a small matrix densely: LAPACK's call costs less than a sparse
        # backend's bookkeeping there.
        self._dense = method == "auto" and self.n <= DENSE_MAX
        self._backend: _Cholmod | _QDLDL | _Dense | None = None

    @property
    def analyzed(self) -> bool:
        """The next solve pays no symbolic analysis: one ran and is kept (SuperLU keeps none
        and pays it every time)."""
        return self.method == "splu" or self._backend is not None

    def solve(self, data: Array, rhs: Array) -> Array:
        """Factor the matrix with values ``data`` (in the pattern's order) and solve
        ``A x = rhs`` (``rhs`` a vector, or a matrix of right-hand sides as columns).

        Raises:
            numpy.linalg.LinAlgError: no backend finds a factor (a singular matrix) or the
                solution is not finite.
        """
        if self.n == 0:
            return np.zeros(0)
        if self.method != "splu":
            try:
                x = self._factored(data, rhs)
                if np.isfinite(x).all():
                    return x
            except (ArithmeticError, ValueError, RuntimeError):
                self._backend = None  # a failed factorization is not reused
        return self._splu(data, rhs)

    def split_solve(self, data: Array, rhs: Array) -> tuple[Array, Array]:
        """``(Y, Z)`` with ``Yᵀ Z = rhsᵀ A⁻¹ rhs`` for the matrix ``A`` with values ``data``:
        with CHOLMOD's factor ``A = Pᵀ L D Lᵀ P``, ``Y = L⁻¹ P rhs`` and ``Z = D⁻¹ Y``, half
        the triangular solves of :meth:`solve` (the quadratic forms of many right-hand sides
        at once: :func:`~h2o_slam.core.robust.innovation_chi2`); else ``rhs`` and
        ``A⁻¹ rhs``.

        Raises:
            numpy.linalg.LinAlgError: as :meth:`solve`.
        """
        if self.method == "cholmod" and self.n and not self._dense:
            try:
                if self._backend is None:
                    self._backend = _Cholmod(self.indptr, self.indices)
                assert isinstance(self._backend, _Cholmod)
                Y, Z = self._backend.split_solve(data, rhs)
                if np.all(np.isfinite(Z)):
                    return Y, Z
            except (ArithmeticError, ValueError, RuntimeError):
                self._backend = None
        return np.asarray(rhs, dtype=float), self.solve(data, rhs)

    def _factored(self, data: Array, rhs: Array) -> Array:
        if self._backend is None:
            cls = _Dense if self._dense else _Cholmod if self.method == "cholmod" else _QDLDL
            self._backend = cls(self.indptr, self.indices)
        return self._backend.solve(data, rhs)

    def _splu(self, data: Array, rhs: Array) -> Array:
        U = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        full = (U + sp.triu(U, k=1).T).tocsc()
        try:
            x = np.asarray(symmetric_lu(full).solve(np.asarray(rhs, dtype=float)), dtype=float)
        except RuntimeError as err:  # "Factor is exactly singular"
            raise np.linalg.LinAlgError(f"singular matrix ({err})") from None
        if not np.all(np.isfinite(x)):
            raise np.linalg.LinAlgError("singular matrix (non-finite solution)")
        return x


class _Cholmod:
    """CHOLMOD through cvxopt: the symbolic analysis of the first call is kept."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray) -> None:
        import cvxopt
        from cvxopt import cholmod

        self._cvxopt, self._cholmod = cvxopt, cholmod
        self._A = _cvxopt_pattern(indptr, indices)
        self._F: Any = None

    def solve(self, data: Array, rhs: Array) -> Array:
        self._numeric(data)
        x = self._cvxopt.matrix(np.array(rhs, dtype=float))
        self._cholmod.solve(self._F, x)
        return np.array(x, dtype=float).reshape(np.shape(rhs))

    def split_solve(self, data: Array, rhs: Array) -> tuple[Array, Array]:
        """``(L⁻¹ P rhs, D⁻¹ L⁻¹ P rhs)`` (:meth:`SPDFactor.split_solve`), both in column-major
        order: ``L⁻¹ P rhs`` is a view of cvxopt's own result, since converting cvxopt's
        column-major matrices to numpy's row-major order element by element took as long as
        the solves (a 1,000-pose 3-D grid's robust solve: 1.1 of 3.3 s)."""
        self._numeric(data)
        y = self._cvxopt.matrix(np.asfortranarray(rhs, dtype=float))
        for system in (7, 4):  # cvxopt's sys: 7 applies P, 4 solves with L, 6 with D
            self._cholmod.solve(self._F, y, sys=system)
        shape = np.shape(rhs)
        Y = np.asarray(memoryview(y)).reshape(shape, order="F")
        d_inv = self._cvxopt.matrix(1.0, (self._A.size[0], 1))
        self._cholmod.solve(self._F, d_inv, sys=6)  # D⁻¹ (ones for an LLᵀ factor)
        scale = np.asarray(memoryview(d_inv)).ravel()
        if np.all(scale == 1.0):  # an LLᵀ factor (every supernodal one): Z is Y, no copy
            return Y, Y
        return Y, Y * (scale[:, None] if Y.ndim == 2 else scale)

    def _numeric(self, data: Array) -> None:
        cvxopt, cholmod = self._cvxopt, self._cholmod
        # cvxopt keeps triplets in column-major order with sorted rows: the CSC order.
        self._A.V = cvxopt.matrix(np.asarray(data, dtype=float))
        with _chosen_by_fill(cholmod):
            if self._F is None:
                self._F = cholmod.symbolic(self._A, uplo="U")
            cholmod.numeric(self._A, self._F)  # ArithmeticError: not positive definite


def _cvxopt_pattern(indptr: np.ndarray, indices: np.ndarray) -> Any:
    """A cvxopt sparse matrix with the CSC pattern ``(indptr, indices)``, ones as values
    (a stored zero would be dropped from the pattern; the values are set after).

    Raises:
        ValueError: the pattern has duplicate entries.
    """
    import cvxopt

    n = len(indptr) - 1
    cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr))
    A = cvxopt.spmatrix(1.0, cvxopt.matrix(np.asarray(indices, dtype=np.int64)),
                        cvxopt.matrix(cols), (n, n))
    if A.V.size[0] != len(indices):
        raise ValueError("the pattern has duplicate entries")
    return A


@contextmanager
def _chosen_by_fill(cholmod: Any) -> Iterator[None]:
    """CHOLMOD's option ``supernodal`` at 1 while in the block: it picks a simplicial or a
    supernodal factor by the fill it finds (cvxopt's default, 2, is always supernodal:
    1.3-1.6x slower on the sparse planar systems, e.g. kitti_00 2.4 ms against 1.6).
    cvxopt's options are global, so the caller's setting is put back."""
    options = cholmod.options
    saved = options.get("supernodal")
    options["supernodal"] = 1
    try:
        yield
    finally:
        if saved is None:
            del options["supernodal"]
        else:
            options["supernodal"] = saved


class _QDLDL:
    """QDLDL: the ordering and elimination tree of the first call are kept."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray) -> None:
        import qdldl

        self._qdldl = qdldl
        self._indptr, self._indices = indptr, indices
        self._solver: Any = None

    def solve(self, data: Array, rhs: Array) -> Array:
        n = len(self._indptr) - 1
        U = sp.csc_matrix((np.asarray(data, dtype=float), self._indices, self._indptr),
                          shape=(n, n))
        if self._solver is None:
            self._solver = self._qdldl.Solver(U)
        else:
            self._solver.update(U)
        rhs = np.asarray(rhs, dtype=float)
        if rhs.ndim == 2:  # QDLDL solves one right-hand side at a time
            return np.column_stack([self._solver.solve(np.ascontiguousarray(col))
                                    for col in rhs.T]).reshape(rhs.shape)
        return np.asarray(self._solver.solve(rhs), dtype=float)


def symmetric_lu(matrix: Any) -> Any:
    """SuperLU (scipy's ``SuperLU`` object, for repeated solves) of a symmetric matrix in
    symmetric mode with diagonal pivots: the minimum-degree ordering of ``Aᵀ + A`` applied to
    rows and columns alike, so the pivots' signs are the matrix's inertia (with SuperLU's
    default partial pivoting a 15 000-unknown sphere took 80 s: 10-100× more fill).

    Raises:
        RuntimeError: an exactly singular pivot.
    """
    import scipy.sparse.linalg as spla  # on use only: 0.1 s of import

    return spla.splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})


def dense_cholesky_solve(A: Array, rhs: Array, min_pivot: float = 0.0) -> Array:
    """``A⁻¹ rhs`` by LAPACK's Cholesky factorization (``potrf``/``potrs``) of the lower
    triangle of the Fortran-ordered ``A`` (overwritten).

    Raises:
        ArithmeticError: ``A`` is not positive definite, or a pivot's square is at most
            ``min_pivot`` × its largest diagonal entry (a direction left undetermined
            leaves a pivot at rounding level rather than failing).
    """
    from scipy.linalg import lapack  # on use: the online path never loads scipy.linalg

    scale = min_pivot * float(np.max(np.diagonal(A), initial=0.0))
    L, info = lapack.dpotrf(A, lower=1, overwrite_a=1)
    if info != 0:
        raise ArithmeticError(f"not positive definite (LAPACK potrf info {info})")
    if min_pivot and np.min(np.diagonal(L), initial=np.inf) ** 2 <= scale:
        raise ArithmeticError("not positive definite (a pivot at rounding level)")
    x, info = lapack.dpotrs(L, np.asarray(rhs, dtype=float), lower=1)
    if info != 0:
        raise ValueError(f"LAPACK potrs info {info}")
    return np.asarray(x).reshape(np.shape(rhs))


class _Dense:
    """LAPACK's dense Cholesky factorization (``potrf``/``potrs``) of the matrix the upper
    triangle's pattern is filled into."""

    def __init__(self, indptr: np.ndarray, indices: np.ndarray) -> None:
        n = len(indptr) - 1
        self._n = n
        # Row-major (i, j) with j the column: LAPACK's lower triangle of the Fortran-order
        # array it is handed is this upper triangle.
        cols = np.repeat(np.arange(n), np.diff(indptr))
        self._flat = indices * n + cols

    def solve(self, data: Array, rhs: Array) -> Array:
        A = np.zeros(self._n * self._n)
        A[self._flat] = data
        return dense_cholesky_solve(A.reshape(self._n, self._n).T, rhs)


def cholesky_factor(upper: sp.csc_matrix
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Array, Array] | None:
    """CHOLMOD's factor of the matrix whose upper triangle is ``upper`` (CSC, sorted; a
    stored zero stays in the pattern) as ``(perm, indptr, indices, L, d)``:
    ``A[perm][:, perm] = L diag(d) Lᵀ`` with ``L`` unit lower triangular in CSC (each
    column's diagonal first and stored as 1); ``None`` without CHOLMOD or when the matrix
    does not factor. The factor's own entries, for
    :func:`~h2o_slam.core.selinv.selected_inverse`; solves go through :class:`SPDFactor`.
    """
    if not available("cholmod"):
        return None
    import cvxopt
    from cvxopt import cholmod

    n = upper.shape[0]
    try:
        A = _cvxopt_pattern(upper.indptr, upper.indices)
        A.V = cvxopt.matrix(np.asarray(upper.data, dtype=float))
        with _chosen_by_fill(cholmod):
            F = cholmod.symbolic(A, uplo="U")
            cholmod.numeric(A, F)
    except (ArithmeticError, ValueError):
        return None
    order = cvxopt.matrix(np.arange(n, dtype=float))
    cholmod.solve(F, order, sys=7)  # P applied to 0..n-1: the permutation itself
    d_inv = cvxopt.matrix(1.0, (n, 1))
    cholmod.solve(F, d_inv, sys=6)  # ones for an LLᵀ factor
    simplicial = not np.all(np.asarray(d_inv) == 1.0)
    L = cholmod.getfactor(F)  # F is spent: cvxopt converts it in place
    # Through the buffer protocol: np.array() of a cvxopt matrix converts element by
    # element (0.12 s of a 2,200-pose sphere's 3 million entries).
    indptr, indices, values = (np.asarray(memoryview(m)).ravel() for m in L.CCS)
    indptr, indices = indptr.astype(np.int64, copy=False), indices.astype(np.int64, copy=False)
    values = np.array(values, dtype=float)  # cvxopt's own buffer: scaled below, so a copy
    first = values[indptr[:-1]]  # the diagonal: D (LDLᵀ, packed), or L_jj (LLᵀ)
    if simplicial:
        d = first.copy()
    else:
        d = first ** 2
        values /= np.repeat(first, np.diff(indptr))
    if not np.all(d > 0.0):  # an LDLᵀ factor of an indefinite matrix: no Cholesky factor
        return None
    values[indptr[:-1]] = 1.0
    return np.asarray(order).ravel().astype(np.int64), indptr, indices, values, d


def with_entries(upper: sp.csc_matrix, pairs: np.ndarray) -> sp.csc_matrix:
    """``upper`` (CSC, sorted) with explicit zeros at ``pairs`` (``k × 2``, either order)
    where it has no entry: a pattern that holds entries a later matrix will have."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    lo, hi = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    coo = upper.tocoo()
    rows = np.concatenate([coo.row, lo])
    cols = np.concatenate([coo.col, hi])
    # Ones for the pattern (a zero would be pruned), then the values summed into it.
    pattern = sp.csc_matrix((np.ones(len(rows)), (rows, cols)), shape=upper.shape)
    pattern.sort_indices()
    data = np.zeros(pattern.nnz)
    pos = positions(pattern, coo.row, coo.col)
    np.add.at(data, pos, coo.data)
    return sp.csc_matrix((data, pattern.indices, pattern.indptr), shape=upper.shape)


def positions(csc: sp.csc_matrix, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Where each entry ``(rows, cols)`` of ``csc``'s pattern is stored."""
    key = cols.astype(np.int64) * csc.shape[0] + rows
    stored = np.repeat(np.arange(csc.shape[1], dtype=np.int64), np.diff(csc.indptr))
    return np.searchsorted(stored * csc.shape[0] + csc.indices, key)


def solve_spd(matrix: Any, rhs: Array, method: str = "auto") -> Array:
    """Solve ``matrix · x = rhs`` once for a sparse symmetric positive definite matrix
    (only its upper triangle is read).

    Raises:
        ValueError: ``method`` is unknown or not installed.
        numpy.linalg.LinAlgError: the matrix is singular to working precision.
    """
    U = upper(matrix)
    return SPDFactor(U.indptr, U.indices, method).solve(U.data, rhs)
