"""Compiled kernels: warmed up before the first update, and equal to the formulas they
implement (rotations against scipy, merged constraints against numpy and finite
differences)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from graphs import random_graph
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from h2o_slam.core import compiled, hybrid, interpolate, jacobians, solver, warmup
from h2o_slam.core import geometry as geo
from h2o_slam.core.edges import whitening
from h2o_slam.core.graph import EdgeKind
from h2o_slam.core.modes import build_solver

#: The kernels Python calls; the ones they call (``so3_exp_into``, ``symmetric_eigen_into``…)
#: are compiled into them.
KERNELS = [
    geo._so3_exp_many, geo._so3_log_many, geo._right_jacobian_inv_many,
    geo._renormalize_many, jacobians._endpoint_jacobians_many, jacobians._chain_jacobians_many,
    jacobians.path_linearization, hybrid.solve_hybrid, solver._scale_and_apply,
    solver._store_contribution,
    solver._capped_scale, solver._apply_local, solver._gram, interpolate.distribute_into,
    interpolate._merge_segments, interpolate.tree_edge_constraints,
    interpolate.merged_stiffness,
]


def _signatures() -> list[int]:
    return [len(k.signatures) for k in KERNELS]


def test_the_warm_up_compiles_every_kernel() -> None:
    warmup.warm_up()
    assert warmup.is_ready()
    assert all(_signatures()), [k.__name__ for k in KERNELS if not k.signatures]


@pytest.mark.parametrize("planar", [True, False])
def test_updates_after_the_warm_up_compile_nothing(planar: bool) -> None:
    """What a node's callbacks run — full, interpolated, guarded and batch updates — finds
    every kernel compiled for its argument types at solver construction."""
    warmup.warm_up()
    before = _signatures()
    graph = random_graph(7, planar, n=30, loops=8, gps=3, orientation=2)
    s, _ = build_solver(graph)
    for e in range(s.num_edges):
        if s.kind[e] == EdgeKind.POSITION:
            s.relax_batch([e])
        else:
            s.relax(e, d_max=3 if e % 2 else None, guard=e % 3 == 0)
    assert _signatures() == before


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-3.1, 3.1), min_size=3, max_size=3))
def test_exp_and_log_match_scipy(w: list[float]) -> None:
    w_arr = np.array(w)
    want = Rotation.from_rotvec(w_arr).as_matrix()
    np.testing.assert_allclose(geo.so3_exp(w_arr), want, atol=1e-14)
    np.testing.assert_allclose(geo.so3_exp_one(w_arr), want, atol=1e-14)
    np.testing.assert_allclose(geo.so3_log(want), Rotation.from_matrix(want).as_rotvec(),
                               atol=1e-9)


def test_renormalize_is_the_newton_step() -> None:
    rng = np.random.default_rng(2)
    R = geo.so3_exp(rng.normal(size=(10, 3))) + 1e-4 * rng.normal(size=(10, 3, 3))
    want = R @ (1.5 * np.eye(3) - 0.5 * np.swapaxes(R, 1, 2) @ R)
    np.testing.assert_allclose(geo.renormalize(R), want, atol=1e-15)


def test_exponential_of_a_yaw_is_exactly_about_z() -> None:
    for yaw in np.linspace(-3.0, 3.0, 61):
        R = geo.so3_exp_one(np.array([0.0, 0.0, yaw]))
        assert R[2, 2] == 1.0 and not np.any(R[2, :2]) and not np.any(R[:2, 2])


@pytest.mark.parametrize("planar", [True, False])
def test_path_linearization_residual_is_the_edge_error(planar: bool) -> None:
    graph = random_graph(3, planar, n=20, loops=6, gps=2, orientation=2)
    s, _ = build_solver(graph, init="input")
    R, t = s.world_poses()
    for e in range(s.num_edges):
        lin = s.linearize(e)
        a = int(s.a[e])
        Ra, ta = (np.eye(3), np.zeros(3)) if a < 0 else (R[a], t[a])
        err, _, _ = jacobians.endpoint_jacobians(
            s.kind[e:e + 1], Ra[None], ta[None], R[s.b[e]][None], t[s.b[e]][None],
            s.meas_R[e:e + 1], s.meas_t[e:e + 1])
        np.testing.assert_allclose(lin.r, s.W[e] @ err[0][s.dof], atol=1e-9)


def _random_chain(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    return geo.so3_exp(rng.normal(scale=0.4, size=(n, 3))), rng.normal(size=(n, 3))


def test_merged_stiffness_sums_the_rotated_stiffnesses() -> None:
    """Eq. 3.38 with anisotropic stiffnesses, against a numpy transcription."""
    rng = np.random.default_rng(11)
    k_R, k_t = _random_chain(rng, 5)
    G = rng.normal(size=(5, 6, 6))
    S = G @ np.swapaxes(G, 1, 2)
    sel = interpolate.Selection(np.array([1, 4]), np.array([0, 2]))
    R_b, t_b, S_b = interpolate.merge_segments(sel, k_R, k_t, S)
    for j, (lo, hi) in enumerate([(0, 1), (2, 4)]):
        P_R, P_t = geo.cumulative_compose(k_R[lo:hi + 1], k_t[lo:hi + 1])
        np.testing.assert_allclose(R_b[j], P_R[-1], atol=1e-14)
        np.testing.assert_allclose(t_b[j], P_t[-1], atol=1e-14)
        want = np.zeros((6, 6))
        for i in range(hi - lo + 1):
            rot = np.kron(np.eye(2), P_R[i].T @ P_R[-1])
            want += rot.T @ S[lo + i] @ rot
        np.testing.assert_allclose(S_b[j], want, rtol=1e-12)


def test_tree_edge_constraints_invert_backward_edges() -> None:
    rng = np.random.default_rng(4)
    meas_R, meas_t = _random_chain(rng, 3)
    G = rng.normal(size=(3, 6, 6))
    info = G @ np.swapaxes(G, 1, 2)
    tree_edge = np.array([-1, 0, 1, 2])
    forward = np.array([True, True, False, True])
    k_R, k_t, S, top = interpolate.tree_edge_constraints(
        np.array([0, 1, 2, 3]), tree_edge, forward, meas_R, meas_t, info)
    assert top.tolist() == [True, False, False, False]
    np.testing.assert_array_equal(S[0], 0.0)
    np.testing.assert_allclose(k_R[1], meas_R[0])
    inv_R, inv_t = geo.inverse(meas_R[1], meas_t[1])
    np.testing.assert_allclose(k_R[2], inv_R, atol=1e-15)
    np.testing.assert_allclose(k_t[2], inv_t, atol=1e-14)
    rot = np.kron(np.eye(2), meas_R[1])
    np.testing.assert_allclose(S[2], rot.T @ info[1] @ rot, rtol=1e-12)


@pytest.mark.parametrize("planar", [True, False])
def test_merged_stiffness_is_the_gram_of_the_finite_difference_jacobian(planar: bool) -> None:
    """``J_βᵀ J_β`` at a kept node, from the merged constraint's error differentiated
    numerically in the kept node's local coordinates."""
    rng = np.random.default_rng(8)
    n = 4
    R_loc, t_loc = _random_chain(rng, n)
    if planar:
        R_loc = geo.yaw_to_matrix(rng.normal(size=n))
        t_loc[:, 2] = 0.0
    dof = geo.PLANAR_DOF if planar else np.arange(6)
    R_b, t_b = geo.so3_exp(rng.normal(scale=0.3, size=(1, 3))), rng.normal(size=(1, 3))
    G = rng.normal(size=(6, 6))
    S_b = (G @ G.T)[None]
    domain = np.arange(n)
    got = interpolate.merged_stiffness(R_loc, t_loc, domain, np.array([n - 1]), np.array([0]),
                                       R_b, t_b, S_b, dof)

    def error(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        P_R, P_t = geo.chain_product(R, t)
        return geo.relative_error(np.eye(3), np.zeros(3), P_R, P_t, R_b[0], t_b[0])[dof]

    h = 1e-6
    J = np.zeros((len(dof), len(dof)))
    for c, k in enumerate(dof):
        cols = []
        for sign in (1.0, -1.0):
            R, t = R_loc.copy(), t_loc.copy()
            step = np.zeros(6)
            step[k] = sign * h
            t[-1] += step[:3]
            R[-1] = R[-1] @ geo.so3_exp(step[3:])
            cols.append(error(R, t))
        J[:, c] = (cols[0] - cols[1]) / (2 * h)
    W = whitening(S_b[0], dof)
    np.testing.assert_allclose(got[0], (W @ J).T @ (W @ J), rtol=1e-6, atol=1e-6)


def test_long_domain_solve_matches_the_normal_equations() -> None:
    """The QR route to the thin SVD on a domain as long as kitti_00's longest (planar)."""
    rng = np.random.default_rng(1)
    d, p = 1500, 3
    J = rng.normal(size=(d, p, p))
    r = rng.normal(size=p)
    G = rng.normal(size=(d, p, p))
    B = G @ np.swapaxes(G, 1, 2) + 0.1 * np.eye(p)
    x = hybrid.solve_hybrid(J, r, B).ravel()
    Jf = np.concatenate(list(J), axis=1)
    g = Jf.T @ r
    # (JᵀJ + B)⁻¹ by Woodbury: B⁻¹ − B⁻¹Jᵀ(I + J B⁻¹ Jᵀ)⁻¹ J B⁻¹, block-diagonal B.
    Binv_g = np.concatenate([np.linalg.solve(B[i], g[p * i:p * i + p]) for i in range(d)])
    Binv_Jt = np.concatenate([np.linalg.solve(B[i], J[i].T) for i in range(d)])
    inner = np.eye(p) + Jf @ Binv_Jt
    want = -(Binv_g - Binv_Jt @ np.linalg.solve(inner, Jf @ Binv_g))
    np.testing.assert_allclose(x, want, rtol=1e-8, atol=1e-12)


def _cache_path_of_a_copy(root: Path) -> str:
    """Where a copy of the package at ``root`` caches a kernel, asked in a fresh process."""
    shutil.copytree(Path(compiled.__file__).parents[1], root / "h2o_slam")
    code = ("from h2o_slam.core import geometry as g; "
            "print(g._so3_exp_many._cache._cache_path)")
    env = dict(os.environ, PYTHONPATH=str(root))
    env.pop("NUMBA_CACHE_DIR", None)
    done = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, check=True,
                          capture_output=True, text=True, timeout=120)
    return done.stdout.strip()


def test_every_install_of_the_same_sources_shares_one_cache(tmp_path: Path) -> None:
    """A new install tree (a colcon build, a fresh venv) finds the kernels compiled from the
    same sources elsewhere: numba's own locator keyed the folder by the install path."""
    first = _cache_path_of_a_copy(tmp_path / "a")
    second = _cache_path_of_a_copy(tmp_path / "b")
    assert first == second
    assert str(tmp_path) not in first
    assert first.startswith(compiled._cache_dir())


#: Run in a fresh process (kernels load once per process, and other tests load them all):
#: prints the kernels that loaded a new signature during a solve after h2o-solve's loading.
_LOADED_DURING_SOLVE = """
import gc, sys
from numba.core.registry import CPUDispatcher
from h2o_slam.app.cli.solve import SolveOptions, _load
from h2o_slam.core import robust
from h2o_slam.core.modes import solve_exact
from h2o_slam.core.robust import RobustConfig
from h2o_slam.core.warmup import false_ring
from h2o_slam.io.synthetic import grid3d, manhattan

planar, init = sys.argv[1] == "planar", sys.argv[2]
graph = (manhattan if planar else grid3d)(60, seed=3).graph
_load(graph, SolveOptions(init=init))
# A graph this small scores every closure from columns of H⁻¹; the selected inverse, and
# the neighbourhood bounds on drop candidates where only those are scored, that larger
# ones use are taken here for any number of closures, so that their kernels count too.
robust.SELECTED_FROM = 1
robust.DELETION_WORK = 0  # only candidates: every accepted closure, with no strain asked
robust.STRAIN = 0.0
kernels = [k for k in gc.get_objects() if isinstance(k, CPUDispatcher)]
before = {k: len(k.signatures) for k in kernels}
solve_exact(graph, init=init, robust=RobustConfig())
solve_exact(false_ring(planar, 30), init=init, robust=RobustConfig())  # scores its closures
print(" ".join(k.__name__ for k in kernels if len(k.signatures) != before[k]))
"""


@pytest.mark.parametrize(("kind", "init"), [("planar", "tree"), ("3-D", "chordal")])
def test_an_exact_solve_after_its_loading_loads_no_kernel(kind: str, init: str) -> None:
    """``h2o-solve`` loads exact mode's kernels before its clock starts: a robust solve of a
    graph of the same kind then loads nothing inside the clock."""
    root = Path(compiled.__file__).parents[2]
    done = subprocess.run([sys.executable, "-c", _LOADED_DURING_SOLVE, kind, init], cwd=root,
                          check=True, capture_output=True, text=True, timeout=300)
    assert done.stdout.split() == []


@pytest.mark.parametrize("planar", [True, False])
def test_the_loading_ring_drops_its_false_closure(planar: bool) -> None:
    """The ring exact mode's loading solves runs the robust solve's paths: its false closure
    (the last edge) is dropped, the true one closing the ring kept."""
    from h2o_slam.core.modes import solve_exact
    from h2o_slam.core.robust import RobustConfig

    result = solve_exact(warmup.false_ring(planar), init="tree", robust=RobustConfig())
    assert result.weights is not None
    np.testing.assert_array_equal(result.weights[-2:], [1.0, 0.0])
