"""The O(d) hybrid-Hessian solve against a dense least-squares solve of (3.34)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from h2o_slam.core.hybrid import NULL_TOLERANCE, solve_hybrid


def _dense_reference(J, r, B):
    d, m, p = J.shape
    lam, U = np.linalg.eigh(B)
    # Γᵢ with Γᵢᵀ Γᵢ = Bᵢ; eigenvalues that are zero by construction stay exactly zero.
    scale = max(lam.max(), np.abs(J).max() ** 2)
    lam = np.where(lam > NULL_TOLERANCE * scale, lam, 0.0)
    gamma = np.sqrt(lam)[:, :, None] * np.swapaxes(U, 1, 2)
    top = np.concatenate(list(J), axis=1)
    bottom = np.zeros((d * p, d * p))
    for i in range(d):
        bottom[i * p:(i + 1) * p, i * p:(i + 1) * p] = gamma[i]
    lhs = np.vstack([top, bottom])
    rhs = np.concatenate([-r, np.zeros(d * p)])
    return np.linalg.lstsq(lhs, rhs, rcond=None)[0].reshape(d, p)


def _psd_blocks(rng, d, p, ranks):
    out = np.zeros((d, p, p))
    for i, k in enumerate(ranks):
        G = rng.normal(size=(k, p)) * rng.uniform(0.1, 10.0)
        out[i] = G.T @ G
    return out


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    d=st.integers(1, 7),
    p=st.sampled_from([3, 6]),
    m=st.sampled_from([3, 6]),
    rank_mode=st.sampled_from(["full", "zero", "mixed"]),
)
def test_matches_dense_least_squares(seed, d, p, m, rank_mode):
    rng = np.random.default_rng(seed)
    if rank_mode == "full":
        ranks = [p] * d
    elif rank_mode == "zero":
        ranks = [0] * d
    else:
        ranks = list(rng.integers(0, p + 1, size=d))
    J = rng.normal(size=(d, m, p)) * rng.uniform(0.1, 10.0)
    r = rng.normal(size=m)
    B = _psd_blocks(rng, d, p, ranks)
    x = solve_hybrid(J, r, B)
    ref = _dense_reference(J, r, B)
    assert np.allclose(x, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_lone_new_node_satisfies_its_edge():
    # A leaf whose only edge is the one being relaxed has a zero B block: the update must
    # satisfy the edge exactly (the minimum-norm solution of an invertible block).
    rng = np.random.default_rng(3)
    J = rng.normal(size=(1, 6, 6))
    r = rng.normal(size=6)
    x = solve_hybrid(J, r, np.zeros((1, 6, 6)))
    assert np.allclose(J[0] @ x[0] + r, 0.0, atol=1e-10)


def test_strong_regularizer_damps_the_step():
    rng = np.random.default_rng(4)
    J = rng.normal(size=(3, 3, 3))
    r = rng.normal(size=3)
    weak = solve_hybrid(J, r, np.tile(np.eye(3), (3, 1, 1)) * 1e-3)
    strong = solve_hybrid(J, r, np.tile(np.eye(3), (3, 1, 1)) * 1e3)
    assert np.linalg.norm(strong) < 0.1 * np.linalg.norm(weak)


@pytest.mark.parametrize("d", [1, 50, 500])
def test_large_domains_match_normal_equations(d):
    rng = np.random.default_rng(d)
    J = rng.normal(size=(d, 6, 6))
    r = rng.normal(size=6)
    B = _psd_blocks(rng, d, 6, [6] * d) + 0.1 * np.eye(6)
    x = solve_hybrid(J, r, B).ravel()
    Jf = np.concatenate(list(J), axis=1)
    H = Jf.T @ Jf
    for i in range(d):
        H[6 * i:6 * i + 6, 6 * i:6 * i + 6] += B[i]
    assert np.allclose(x, np.linalg.solve(H, -Jf.T @ r), rtol=1e-8, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), p=st.sampled_from([1, 3, 6]), rank=st.integers(0, 6))
def test_jacobi_eigen_decomposes_symmetric_blocks(seed, p, rank):
    from h2o_slam.core.hybrid import symmetric_eigen_into

    rng = np.random.default_rng(seed)
    G = rng.normal(size=(min(rank, p), p)) * rng.uniform(0.01, 100.0)
    A = G.T @ G
    lam, V, work = np.empty(p), np.empty((p, p)), np.empty((p, p))
    symmetric_eigen_into(A, lam, V, work)
    scale = max(np.abs(A).max(), 1e-300)
    np.testing.assert_allclose(V.T @ V, np.eye(p), atol=1e-13)
    np.testing.assert_allclose(A @ V, V * lam, atol=1e-13 * scale)
    np.testing.assert_allclose(np.sort(lam), np.linalg.eigvalsh(A), atol=1e-13 * scale)
