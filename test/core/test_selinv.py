"""The selected inverse: Takahashi's recurrence against the dense inverse, on both kinds of
CHOLMOD factor, the pattern widened by the pairs asked for, and its refusals."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core import selinv
from h2o_slam.core.selinv import selected_inverse
from h2o_slam.core.spd import available, cholesky_factor, upper

pytestmark = pytest.mark.skipif(not available("cholmod"), reason="needs CHOLMOD (cvxopt)")


def _spd(n: int, density: float, seed: int) -> sp.csc_matrix:
    """A sparse symmetric positive definite matrix with a random pattern."""
    M = sp.random(n, n, density, random_state=seed, format="csc") + sp.eye(n)
    return (M @ M.T + 0.1 * sp.eye(n)).tocsc()


def _pattern_pairs(S: selinv.SelectedInverse) -> np.ndarray:
    """Every (row, column) of the original matrix that the selected inverse stores."""
    perm = np.argsort(S.iperm)
    cols = np.repeat(np.arange(len(S.indptr) - 1), np.diff(S.indptr))
    return np.stack([perm[S.indices], perm[cols]], axis=1)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(2, 60), density=st.floats(0.0, 0.2), seed=st.integers(0, 2**31 - 1),
       asked=st.lists(st.tuples(st.integers(0, 59), st.integers(0, 59)), max_size=10))
def test_the_selected_inverse_equals_the_inverse_on_its_pattern(n, density, seed, asked):
    A = _spd(n, density, seed)
    pairs = np.array([(i % n, j % n) for i, j in asked], dtype=np.int64).reshape(-1, 2)
    S = selected_inverse(upper(A), pairs, max_work=np.inf)
    assert S is not None
    inverse = np.linalg.inv(A.toarray())
    read = np.concatenate([_pattern_pairs(S), pairs])
    got = S.blocks(read)  # each pair's 2 × 2 block
    want = inverse[read[:, :, None], read[:, None, :]]
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10 * np.abs(inverse).max())
    np.testing.assert_allclose(S.diagonal, np.diag(inverse)[np.argsort(S.iperm)], rtol=1e-8)


@pytest.mark.parametrize("density", [0.02, 1.0])
def test_both_kinds_of_factor_give_the_inverse(density):
    """A sparse matrix factors simplicial (LDLᵀ), a dense one supernodal (LLᵀ): the
    unit-triangular form both are brought to gives the same inverse."""
    A = _spd(120, density, 3)
    perm, indptr, indices, L, d = cholesky_factor(upper(A))
    Ld = sp.csc_matrix((L, indices, indptr), shape=A.shape).toarray()
    np.testing.assert_allclose(np.diag(Ld), 1.0)
    np.testing.assert_allclose(Ld @ np.diag(d) @ Ld.T, A.toarray()[np.ix_(perm, perm)],
                               atol=1e-9 * abs(A).max())
    S = selected_inverse(upper(A), np.array([[0, 119], [0, 5], [5, 119]]), max_work=np.inf)
    block = S.blocks(np.array([[0, 119, 5]]))[0]
    np.testing.assert_allclose(block, np.linalg.inv(A.toarray())[np.ix_([0, 119, 5],
                                                                         [0, 119, 5])],
                               rtol=1e-8)


def test_held_unknowns_read_as_zero():
    A = _spd(10, 0.3, 1)
    S = selected_inverse(upper(A), np.zeros((0, 2), dtype=np.int64))
    block = S.blocks(np.array([[2, -1, 2]]))[0]
    assert np.all(block[1] == 0.0) and np.all(block[:, 1] == 0.0)
    assert block[0, 2] == block[0, 0]
    np.testing.assert_allclose(block[0, 0], np.linalg.inv(A.toarray())[2, 2], rtol=1e-12)


def test_an_entry_not_asked_for_outside_the_pattern_is_refused():
    """A tridiagonal matrix's factor holds no fill: the corner entry of its (dense) inverse
    is only there when asked for."""
    n = 30
    A = sp.diags([np.full(n - 1, -1.0), np.full(n, 4.0), np.full(n - 1, -1.0)], [-1, 0, 1],
                 format="csc")
    S = selected_inverse(upper(A), np.zeros((0, 2), dtype=np.int64))
    with pytest.raises(KeyError, match="outside the factor's pattern"):
        S.blocks(np.array([[0, n - 1]]))
    asked = selected_inverse(upper(A), np.array([[n - 1, 0]]))
    np.testing.assert_allclose(asked.blocks(np.array([[0, n - 1]]))[0, 0, 1],
                               np.linalg.inv(A.toarray())[0, n - 1], rtol=1e-10)


def test_a_matrix_that_is_not_positive_definite_has_none():
    A = sp.csc_matrix(np.array([[1.0, 2.0], [2.0, 1.0]]))
    assert selected_inverse(upper(A), np.zeros((0, 2), dtype=np.int64)) is None
    assert cholesky_factor(upper(A)) is None


def test_work_beyond_the_cap_has_none():
    A = _spd(80, 1.0, 2)  # dense: 80 columns of up to 80 entries
    _, indptr, indices, _, _ = cholesky_factor(upper(A))
    assert len(indices) == 80 * 81 // 2
    work = selinv._work(indptr, indices)
    assert work > 80 * 80
    assert selected_inverse(upper(A), np.zeros((0, 2), dtype=np.int64), work - 1) is None
    assert selected_inverse(upper(A), np.zeros((0, 2), dtype=np.int64), work) is not None


def test_a_pattern_that_is_not_closed_is_refused():
    """Column 0 holds rows 1 and 2 but column 1 does not hold row 2: the recurrence would
    read an entry that is not stored."""
    indptr = np.array([0, 3, 4, 5])
    indices = np.array([0, 1, 2, 1, 2])
    lower = np.array([1.0, 0.5, 0.5, 1.0, 1.0])
    z, diagonal = np.zeros(5), np.zeros(3)
    assert not selinv._takahashi(indptr, indices, lower, np.ones(3), z, diagonal)
    indices[3] = 2  # column 1's diagonal is not first
    assert not selinv._takahashi(indptr, indices, lower, np.ones(3), z, diagonal)
