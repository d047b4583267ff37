"""Sparse SPD factorizations (h2o_slam.core.spd): every backend against scipy's solve."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from h2o_slam.core import spd
from h2o_slam.core.spd import METHODS, SPDFactor, solve_spd, upper

BACKENDS = [m for m in METHODS[1:] if spd.available(m)]
#: The backends and ``auto``, which factors these tests' matrices (60 unknowns) densely.
WITH_DENSE = [*BACKENDS, "auto"]


def random_spd(seed: int, n: int = 60, density: float = 0.05) -> sp.csc_matrix:
    """A random sparse SPD matrix: ``AAᵀ`` plus a small diagonal."""
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=density, random_state=rng)
    return (A @ A.T + 0.1 * sp.eye(n)).tocsc()


def test_the_default_install_has_cholmod():
    # requirements.txt installs cvxopt: CI and every fresh venv run the default backend.
    assert spd.available("cholmod")
    assert spd.resolve("auto") == "cholmod"


@pytest.mark.parametrize("method", WITH_DENSE)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_solves_equal_scipy(method, seed):
    H = random_spd(seed)
    g = np.random.default_rng(seed + 10).standard_normal(H.shape[0])
    expected = spla.spsolve(H, g)
    np.testing.assert_allclose(solve_spd(H, g, method), expected, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("method", WITH_DENSE)
@pytest.mark.parametrize("seed", [0, 1])
def test_split_solves_give_the_quadratic_forms_of_the_inverse(method, seed):
    """``Yᵀ Z = Bᵀ H⁻¹ B`` for several right-hand sides, whatever factor the backend keeps
    (CHOLMOD's simplicial LDLᵀ or supernodal LLᵀ: both orders of density)."""
    H = random_spd(seed, density=0.05 if seed == 0 else 0.3)
    B = np.random.default_rng(seed + 20).standard_normal((H.shape[0], 7))
    U = upper(H)
    Y, Z = SPDFactor(U.indptr, U.indices, method).split_solve(U.data, B)
    expected = B.T @ np.linalg.solve(H.toarray(), B)
    np.testing.assert_allclose(Y.T @ Z, expected, rtol=1e-9, atol=1e-9)
    y, z = SPDFactor(U.indptr, U.indices, method).split_solve(U.data, B[:, 2])
    np.testing.assert_allclose(y @ z, expected[2, 2], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("method", WITH_DENSE)
def test_refactorization_with_the_kept_pattern_equals_a_fresh_one(method):
    H = random_spd(3)
    U = upper(H)
    factor = SPDFactor(U.indptr, U.indices, method)
    rng = np.random.default_rng(4)
    for k in range(4):  # new values in the same pattern, as Gauss–Newton iterations bring
        data = U.data * (1.0 + 0.5 * k) + np.where(U.indices == np.repeat(
            np.arange(U.shape[0]), np.diff(U.indptr)), float(k), 0.0)
        g = rng.standard_normal(U.shape[0])
        fresh = SPDFactor(U.indptr, U.indices, method).solve(data, g)
        np.testing.assert_allclose(factor.solve(data, g), fresh, rtol=1e-12, atol=1e-12)
        full = sp.csc_matrix((data, U.indices, U.indptr), shape=U.shape)
        full = full + sp.triu(full, k=1).T
        np.testing.assert_allclose(full @ fresh, g, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", WITH_DENSE)
def test_only_the_upper_triangle_is_read(method):
    H = random_spd(5)
    g = np.ones(H.shape[0])
    skewed = (sp.triu(H) + 7.0 * sp.tril(H, k=-1)).tocsc()  # the lower triangle is wrong
    np.testing.assert_allclose(solve_spd(skewed, g, method), spla.spsolve(H, g), rtol=1e-9)


@pytest.mark.parametrize("method", WITH_DENSE)
def test_a_singular_matrix_is_a_linalg_error(method):
    singular = sp.csc_matrix(np.diag([1.0, 0.0, 2.0]))
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        solve_spd(singular, np.ones(3), method)


@pytest.mark.parametrize("method", WITH_DENSE)
def test_an_indefinite_matrix_is_handed_to_superlu(method):
    # Not positive definite: CHOLMOD finds no factor; SuperLU solves it all the same.
    H = sp.csc_matrix(np.array([[1.0, 2.0], [2.0, 1.0]]))
    np.testing.assert_allclose(solve_spd(H, np.array([3.0, 3.0]), method), [1.0, 1.0])


def test_auto_factors_small_matrices_densely():
    for n, dense in ((spd.DENSE_MAX, True), (spd.DENSE_MAX + 1, False)):
        H = random_spd(n, n=n)
        U = upper(H)
        factor = SPDFactor(U.indptr, U.indices)
        g = np.ones(n)
        np.testing.assert_allclose(factor.solve(U.data, g), spla.spsolve(H, g), rtol=1e-9)
        assert isinstance(factor._backend, spd._Dense) == dense


def test_an_empty_system_has_an_empty_solution():
    factor = SPDFactor(np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64))
    assert factor.solve(np.zeros(0), np.zeros(0)).shape == (0,)


def test_unknown_and_missing_backends_are_refused(monkeypatch):
    with pytest.raises(ValueError, match="unknown factorization 'lu'"):
        SPDFactor(np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), "lu")
    monkeypatch.setattr(spd, "_module", lambda name: None)
    assert spd.resolve("auto") == "splu"
    with pytest.raises(ValueError, match="needs the qdldl package"):
        spd.resolve("qdldl")


@pytest.mark.skipif(not spd.available("cholmod"), reason="cvxopt not installed")
def test_cvxopt_options_are_left_as_found():
    from cvxopt import cholmod

    H = random_spd(6)
    g = np.ones(H.shape[0])
    assert "supernodal" not in cholmod.options
    solve_spd(H, g, "cholmod")
    assert "supernodal" not in cholmod.options
    cholmod.options["supernodal"] = 2
    try:
        solve_spd(H, g, "cholmod")
        assert cholmod.options["supernodal"] == 2
    finally:
        del cholmod.options["supernodal"]
