"""LAGO: the linear approximation of planar pose-graph optimization with full covariance.

Implements Carlone, Yin, Rosa and Yuan, *Graph optimization with unstructured covariance:
fast, accurate, linear approximation* (SIMPAR 2014; equation numbers below are the
paper's). No initial guess is needed.

0. **The paper's frame.** The paper's residual (3) measures the translation error in the
   frame of node ``i``; the project's χ² (doc/design.md, Conventions; like g2o and GTSAM)
   in the frame of the measurement. The information matrices are rotated accordingly
   (:func:`paper_information`), which makes the paper's cost equal the project's χ²
   exactly (up to yaw wrapping). Skipping this is harmless only for isotropic position
   information; on CSAIL it costs three orders of magnitude in χ².
1. **Regularization** (the paper's reference [3]): a breadth-first spanning forest of the
   relative edges; orientations are propagated along it from each component's anchor by
   summing the measured relative orientations without wrapping, and every measured relative
   orientation ``δ̄_ij`` (in ``(-π, π]``) becomes ``δ̄_ij - 2π k_ij`` with the integer
   ``k_ij`` that makes it agree with the tree. Tree edges get ``k = 0``; the chords of loops
   that turn many times get the multiple of 2π the loop needs.
2. **Phase 1**, (8)–(9): ``Ω_z ẑ = b_z`` for ``ẑ = [Δ̂ˡ; θ̂]``. The 2×2 blocks ``Ω_Δ`` are
   eliminated first (exactly: a block elimination of (8), the appendix's (15)), which leaves
   the reduced graph Laplacian ``A P_δ⁻¹ Aᵀ θ̂ = A P_δ⁻¹ δ̄`` with the *marginal* orientation
   information ``P_δ⁻¹ = Ω_δ - Ω_δΔ Ω_Δ⁻¹ Ω_Δδ`` of every edge, then
   ``Δ̂ˡ = Δ̄ˡ + Ω_Δ⁻¹ Ω_Δδ (δ̄ - Aᵀθ̂)``.
3. **Phases 2 and 3**, (10)–(14): ``ŷ = [R̂ Δ̂ˡ; θ̂]``, ``Ω_y = T̂⁻ᵀ Ω_z T̂⁻¹`` with
   ``T̂ = [[R̂, J], [0, I]]``, then ``Ω_x x* = b_x`` with ``Ω_x = Bᵀ Ω_y B`` and
   ``b_x = Bᵀ Ω_y ŷ``. ``Ω_x`` and ``b_x`` are assembled edge by edge: since
   ``Ω_z = Zᵀ Ω Z`` with ``Ω`` block diagonal per edge, ``(Bx - ŷ)ᵀ Ω_y (Bx - ŷ)`` is a sum
   over edges of ``r_kᵀ Ω_k r_k`` with
   ``r_k = [R̂_iᵀ (p_j - p_i - J_k (θ_i - θ̂_i)) - Δ̂ˡ_k; (θ_j - θ_i) - (θ̂_j - θ̂_i)]``,
   the same matrices without forming the ``(2m + n)``-square ``Ω_y``.

The Jacobian ``J`` of (12): the block of edge ``k = (i, j)`` is
``∂(R(θ_i) Δˡ_k)/∂θ_i = R̂_i [0 -1; 1 0] Δˡ_k``. Equation (12) evaluates it at ``ẑ``, i.e.
with ``Δ̂ˡ`` (``jacobian="estimate"``); Theorem 1's Gauss–Newton step linearizes
``R(θ) Δ̄ˡ``, i.e. uses the measurement ``Δ̄ˡ`` (``jacobian="measurement"``). The two agree
when ``Ω_Δδ = 0`` (then ``Δ̂ˡ = Δ̄ˡ``); with correlated covariances only the
``"measurement"`` variant is *exactly* one Gauss–Newton step from ``(p̂, θ̂)`` (the proof
in the appendix uses one ``J`` for both). The default is the paper's (12): on the two
benchmark graphs with position–yaw correlation it gave the lower χ² (intel 45.0095 against
45.0097, kitti_00 98.3495 against 98.3502; identical elsewhere; ``bench/RESULTS.md``).

Gauge: the first (lowest-index) node of each connected component is fixed at the origin
with yaw 0, as the paper fixes ``x_0``. Components of a disconnected graph are each solved
in that frame (their relative placement is unobservable); an isolated node stays at the
origin. Global edges (GPS positions, compass orientations) do not fit the method: a
component with GPS but no orientation edge has an unknown global rotation that the linear
phases cannot estimate. :func:`lago` refuses them unless ``ignore_global=True``, which
solves the relative edges alone.

``covariance="structured"`` runs the original linear approximation for structured covariance
(Carlone, Aragues, Castellanos and Bona 2011/2012, the paper's reference [3] and the
"structured covariance" column of its Table 1): the position–orientation cross terms
``Ω_Δδ`` are dropped (as [3] reads the ``Ω_Δ`` and ``Ω_δ`` blocks only), so phase 1 weighs
each edge by ``Ω_δ`` instead of the marginal ``P_δ⁻¹`` and ``Δ̂ˡ = Δ̄ˡ``. On graphs without
such correlations the two variants are the same computation.

Only sparse matrices and sparse direct factorizations are used (:func:`solve_spd`): CHOLMOD
from cvxopt's wheel by default, QDLDL or scipy's SuperLU when it is not installed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import sparse

from h2o_slam.core import geometry as geo
from h2o_slam.core import spd
from h2o_slam.core.errors import InputError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, INFO_EIG_FLOOR, EdgeKind, PoseGraph

LOG = logging.getLogger(__name__)

#: Where :math:`J` of (12) is evaluated: at the phase-1 estimate ``Δ̂ˡ`` (the paper's (12))
#: or at the measurement ``Δ̄ˡ`` (Theorem 1's Gauss–Newton step). See the module docstring.
JACOBIANS = ("estimate", "measurement")

#: Which covariance LAGO uses: all of each 3×3 block ("full", the paper's Algorithm 1) or
#: its position and orientation blocks only ("structured", the 2012 approximation [3]).
COVARIANCES = ("full", "structured")

#: Sparse direct factorizations :func:`solve_spd` offers ("auto": the fastest installed).
FACTORIZATIONS = ("auto", "cholmod", "qdldl", "splu-mmd", "splu-colamd", "spsolve")

_TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class LagoResult:
    """What :func:`lago` computes.

    Attributes:
        R, t: world poses of the approximation ``x*``, shapes ``(N, 3, 3)`` and ``(N, 3)``
            (``z = 0``); each component's anchor is at the origin with yaw 0.
        yaw_rad: ``θ*``, the solved yaw of every node, *not* wrapped (continuous along the
            spanning tree), shape ``(N,)``.
        yaw_hat_rad: ``θ̂`` of phase 1 (8), not wrapped, shape ``(N,)``.
        edges: indices (into the graph's edges) of the relative edges used, shape ``(m,)``;
            the per-edge arrays below follow this order.
        k: regularization terms ``k_ij``, shape ``(m,)``: the regularized relative yaw is
            ``δ̄ - 2π k`` (rad).
        delta_rad: the regularized relative yaw measurements ``δ̄ - 2π k``, shape ``(m,)``.
        delta_hat: ``Δ̂ˡ`` of phase 1, the relative positions in the frame of ``a`` (m),
            shape ``(m, 2)``.
        component: connected-component label of every node, shape ``(N,)``.
        anchors: the anchor (first node) of each component, shape ``(C,)``.
        free: the nodes that are unknowns (all but the anchors), shape ``(n,)``.
        information: ``Ω_x`` of (13)–(14), the information matrix of ``x*`` — sparse CSC,
            shape ``(3n, 3n)``, unknowns ordered node-major ``(x, y, θ)`` per node of
            ``free`` (the paper orders ``[p; θ]``: a permutation of this).
    """

    R: Array
    t: Array
    yaw_rad: Array
    yaw_hat_rad: Array
    edges: np.ndarray
    k: np.ndarray
    delta_rad: Array
    delta_hat: Array
    component: np.ndarray
    anchors: np.ndarray
    free: np.ndarray
    information: Any  # scipy.sparse.csc_matrix (scipy ships no type information)


def lago_estimate(graph: PoseGraph) -> tuple[Array, Array]:
    """World poses ``(R, t)`` of the LAGO approximation of a planar graph (see :func:`lago`).

    Raises:
        InputError: the graph is 3-D or has global (GPS / compass) edges.
    """
    result = lago(graph)
    return result.R, result.t


def lago(
    graph: PoseGraph,
    *,
    jacobian: str = "estimate",
    ignore_global: bool = False,
    factorization: str = "auto",
    covariance: str = "full",
) -> LagoResult:
    """The LAGO approximation (paper Algorithm 1) of a planar pose graph.

    Uses the relative edges with their full 3×3 (x, y, yaw) information matrices,
    correlations between position and orientation included. The graph's own estimate is
    not used (LAGO needs no initial guess).

    Args:
        graph: a planar graph.
        jacobian: where ``J`` of (12) is evaluated, one of :data:`JACOBIANS`.
        ignore_global: solve the relative edges alone when the graph also has GPS or compass
            edges, instead of refusing it.
        factorization: one of :data:`FACTORIZATIONS` (see :func:`solve_spd`).
        covariance: one of :data:`COVARIANCES`; ``"structured"`` drops the position–yaw
            cross terms of every information matrix (the 2012 approximation, module
            docstring).

    Raises:
        InputError: the graph is 3-D, or has global edges and ``ignore_global`` is false, or
            a linear system is singular beyond what the eigen-clamped information allows.
        ValueError: ``jacobian``, ``factorization`` or ``covariance`` is unknown.
    """
    if jacobian not in JACOBIANS:
        raise ValueError(f"unknown jacobian {jacobian!r}; choose one of {', '.join(JACOBIANS)}")
    if factorization not in FACTORIZATIONS:
        raise ValueError(f"unknown factorization {factorization!r}; choose one of "
                         f"{', '.join(FACTORIZATIONS)}")
    if covariance not in COVARIANCES:
        raise ValueError(f"unknown covariance {covariance!r}; choose one of "
                         f"{', '.join(COVARIANCES)}")
    if not graph.planar:
        raise InputError("LAGO handles planar graphs only; this graph is 3-D")
    rel = graph.kind == EdgeKind.RELATIVE
    if not ignore_global and not np.all(rel):
        num = int(np.sum(~rel))
        raise InputError(f"LAGO uses relative edges only; this graph has {num} global "
                         "(GPS or compass) edge(s)")
    edges = np.flatnonzero(rel)
    n_nodes = graph.num_nodes
    a, b = graph.a[edges], graph.b[edges]
    delta_l = graph.meas_t[edges, :2]
    yaw_meas = geo.matrix_to_yaw(graph.meas_R[edges])
    omega = paper_information(graph.info[edges], graph.meas_R[edges])
    if covariance == "structured":
        omega[:, :2, 2] = omega[:, 2, :2] = 0.0
    om_dd, om_dt, om_tt = _split_information(omega)
    # Ω_Δ⁻¹ Ω_Δδ per edge, and the marginal orientation information P_δ⁻¹ (Schur complement).
    gain = _solve2(om_dd, om_dt)
    marginal = _marginal_yaw_information(omega, om_tt, om_dt, gain)

    component, anchors, parent, tree_edge = spanning_forest(n_nodes, a, b, marginal)
    k, delta = regularize(n_nodes, a, b, yaw_meas, parent, tree_edge)

    free_mask = np.ones(n_nodes, dtype=bool)
    free_mask[anchors] = False
    free = np.flatnonzero(free_mask)
    index = np.full(n_nodes, -1, dtype=np.int64)
    index[free] = np.arange(len(free))

    # Phase 1: (8)–(9), with the 2×2 Ω_Δ blocks eliminated.
    yaw_hat = np.zeros(n_nodes)
    if len(free):
        lap, rhs = _laplacian(index[a], index[b], marginal, delta, len(free))
        yaw_hat[free] = solve_spd(lap, rhs, factorization)
    residual = delta - (yaw_hat[b] - yaw_hat[a])  # δ̄ - Aᵀθ̂
    delta_hat = delta_l + gain * residual[:, None]  # (15)

    # Phases 2 and 3: (10)–(14).
    lin = delta_hat if jacobian == "estimate" else delta_l
    info, rhs3 = _phase3_system(index[a], index[b], yaw_hat[a], yaw_hat[b], delta_hat, lin,
                                omega, len(free))
    x = solve_spd(info, rhs3, factorization) if len(free) else np.zeros(0)
    yaw = np.zeros(n_nodes)
    t = np.zeros((n_nodes, 3))
    xs = x.reshape(-1, 3)
    t[free, :2] = xs[:, :2]
    yaw[free] = xs[:, 2]
    return LagoResult(
        R=geo.yaw_to_matrix(yaw), t=t, yaw_rad=yaw, yaw_hat_rad=yaw_hat, edges=edges, k=k,
        delta_rad=delta, delta_hat=delta_hat, component=component, anchors=anchors,
        free=free, information=info,
    )


def paper_information(info: Array, meas_R: Array) -> Array:
    """Information matrices of the paper's residual (1) from the project's, shape (m, 3, 3).

    The project's error (doc/design.md, Conventions; as g2o and GTSAM) puts the translation
    error in the frame of the *measurement*: ``e_t = R_Kᵀ (R_iᵀ (p_j - p_i) - t_K)``; the paper's
    residual (3) has it in the frame of node ``i``: ``r_t = R_iᵀ (p_j - p_i) - Δ̄ˡ``. So
    ``e_t = R_Kᵀ r_t`` and ``eᵀ S e = rᵀ Ω r`` exactly for
    ``Ω = diag(R_K, 1) S diag(R_Kᵀ, 1)``. Using ``S`` unrotated would be exact only for
    isotropic position information; on graphs with anisotropic information and turning
    measurements (CSAIL, Manhattan) it costs orders of magnitude in χ².

    Args:
        info: 6×6 information matrices in the project's error order, shape ``(m, 6, 6)``.
        meas_R: the measured relative rotations ``R_K`` (about z), shape ``(m, 3, 3)``.
    """
    dof = geo.PLANAR_DOF
    out = np.asarray(info, dtype=float)[:, dof][:, :, dof].copy()
    c = np.asarray(meas_R, dtype=float)[:, 0, 0]
    s = np.asarray(meas_R, dtype=float)[:, 1, 0]
    # Written out rather than as stacked 3×3 products: several times faster for large m.
    xx, xy, yy = out[:, 0, 0].copy(), out[:, 0, 1].copy(), out[:, 1, 1].copy()
    out[:, 0, 0] = c * c * xx - 2.0 * c * s * xy + s * s * yy
    out[:, 1, 1] = s * s * xx + 2.0 * c * s * xy + c * c * yy
    out[:, 0, 1] = out[:, 1, 0] = c * s * (xx - yy) + (c * c - s * s) * xy
    xt, yt = out[:, 0, 2].copy(), out[:, 1, 2].copy()
    out[:, 0, 2] = out[:, 2, 0] = c * xt - s * yt
    out[:, 1, 2] = out[:, 2, 1] = s * xt + c * yt
    return out


# --- regularization ----------------------------------------------------------------------------


def spanning_forest(
    num_nodes: int, a: np.ndarray, b: np.ndarray, weight: Array | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A breadth-first spanning forest of the graph with edges ``(a, b)``.

    Each connected component is rooted at its first (lowest-index) node, its anchor.
    Breadth-first keeps tree paths short, and so the orientation drift that the
    regularization must stay within (less than π around every cycle a chord closes). Of
    parallel edges the one with the largest ``weight`` (e.g. the yaw information) is the
    tree edge.

    Returns:
        ``(component, anchors, parent, tree_edge)``: the component label of every node,
        shape ``(N,)``; the anchor of every component, shape ``(C,)``; every node's parent,
        :data:`~h2o_slam.core.graph.EARTH` at anchors, shape ``(N,)``; and the index into
        ``(a, b)`` of the edge joining each node to its parent (-1 at anchors).
    """
    # Imported on use: scipy.sparse.csgraph brings scipy.sparse.linalg, 0.1-0.2 s of every
    # command's start.
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    m = len(a)
    adj = sparse.csr_matrix((np.ones(m), (a, b)), shape=(num_nodes, num_nodes))
    _, component = connected_components(adj, directed=False)
    _, anchors = np.unique(component, return_index=True)
    # One breadth-first search from a virtual root joined to every anchor covers the forest.
    root = num_nodes
    rows = np.concatenate([a, b, np.full(len(anchors), root)])
    cols = np.concatenate([b, a, anchors])
    adj = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)),
                            shape=(num_nodes + 1, num_nodes + 1))
    _, pred = breadth_first_order(adj, root, directed=True, return_predecessors=True)
    parent = pred[:num_nodes].astype(np.int64)
    parent[anchors] = EARTH

    # The tree edge of each non-anchor node: the best edge between it and its parent.
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * num_nodes + hi
    w = np.zeros(m) if weight is None else np.asarray(weight, dtype=float)
    order = np.lexsort((-w, key))
    first = np.ones(m, dtype=bool)
    first[1:] = key[order][1:] != key[order][:-1]
    best = order[first]  # one edge per node pair, sorted by key
    tree_edge = np.full(num_nodes, -1, dtype=np.int64)
    child = np.flatnonzero(parent != EARTH)
    p = parent[child]
    want = np.minimum(p, child) * num_nodes + np.maximum(p, child)
    tree_edge[child] = best[np.searchsorted(key[best], want)]
    return component, anchors, parent, tree_edge


def regularize(
    num_nodes: int, a: np.ndarray, b: np.ndarray, yaw_meas_rad: Array, parent: np.ndarray,
    tree_edge: np.ndarray,
) -> tuple[np.ndarray, Array]:
    """The regularization terms ``k_ij`` (paper §2, reference [3]) of edges ``(a, b)``.

    Orientations are propagated down the spanning forest ``parent`` / ``tree_edge`` (from
    :func:`spanning_forest`) by summing the measured relative yaws ``yaw_meas_rad`` without
    wrapping, anchors at 0; then ``k_ij = round((δ̄_ij - (θ_j - θ_i)) / 2π)``.

    Returns:
        ``(k, delta)``: the integers ``k``, shape ``(m,)``, and the regularized relative
        yaws ``δ̄ - 2π k`` (rad), shape ``(m,)``.
    """
    yaw_meas_rad = np.asarray(yaw_meas_rad, dtype=float)
    tree_yaw = tree_orientations(num_nodes, a, b, yaw_meas_rad, parent, tree_edge)
    k = np.rint((yaw_meas_rad - (tree_yaw[b] - tree_yaw[a])) / _TWO_PI).astype(np.int64)
    return k, yaw_meas_rad - _TWO_PI * k


def tree_orientations(
    num_nodes: int, a: np.ndarray, b: np.ndarray, yaw_meas_rad: Array, parent: np.ndarray,
    tree_edge: np.ndarray,
) -> Array:
    """Yaw of every node (rad, not wrapped) from summing the tree edges' relative yaws down
    from its anchor (yaw 0).

    Pointer jumping: ``⌈log₂ depth⌉`` vectorized rounds instead of a walk per node.
    """
    child = np.flatnonzero(parent != EARTH)
    e = tree_edge[child]
    step = np.zeros(num_nodes)
    # A tree edge measures yaw(b) - yaw(a); walked from b to a it counts negatively.
    step[child] = np.where(b[e] == child, yaw_meas_rad[e], -yaw_meas_rad[e])
    up = np.where(parent == EARTH, np.arange(num_nodes), parent)
    # Invariant: step[v] = yaw(v) - yaw(up[v]); anchors point to themselves with step 0.
    while True:
        nxt = up[up]
        if np.array_equal(nxt, up):
            return step
        step = step + step[up]
        up = nxt


# --- linear algebra ----------------------------------------------------------------------------


def _split_information(omega: Array) -> tuple[Array, Array, Array]:
    """Blocks ``Ω_Δ`` (m, 2, 2), ``Ω_Δδ`` (m, 2) and ``Ω_δ`` (m,) of planar information."""
    return omega[:, :2, :2], omega[:, :2, 2], omega[:, 2, 2]


def _solve2(M: Array, v: Array) -> Array:
    """``M⁻¹ v`` for stacks of 2×2 matrices ``M`` (m, 2, 2) and vectors ``v`` (m, 2)."""
    det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
    out = np.empty_like(v)
    out[:, 0] = M[:, 1, 1] * v[:, 0] - M[:, 0, 1] * v[:, 1]
    out[:, 1] = M[:, 0, 0] * v[:, 1] - M[:, 1, 0] * v[:, 0]
    return out / det[:, None]


def _marginal_yaw_information(omega: Array, om_tt: Array, om_dt: Array, gain: Array) -> Array:
    """``P_δ⁻¹ = Ω_δ - Ω_δΔ Ω_Δ⁻¹ Ω_Δδ`` per edge, floored at the eigen-clamp floor.

    In exact arithmetic it is at least the smallest eigenvalue of ``Ω``, itself at least
    :data:`~h2o_slam.core.graph.INFO_EIG_FLOOR` × the largest (``make_graph`` clamps). Rounding
    can push the difference of nearly equal terms below that, or below zero, for a
    near-singular ``Ω``; the floor keeps every edge's weight positive (and so the phase-1
    Laplacian positive definite), never NaN.
    """
    schur = om_tt - np.einsum("mi,mi->m", om_dt, gain)
    floor = INFO_EIG_FLOOR * np.trace(omega, axis1=1, axis2=2) / 3.0
    low = schur < floor
    if np.any(low):
        LOG.info("LAGO: marginal yaw information of %d edge(s) raised to the floor",
                 int(np.sum(low)))
    return np.maximum(schur, floor)


def _laplacian(
    ia: np.ndarray, ib: np.ndarray, weight: Array, delta: Array, n: int
) -> tuple[Any, Array]:
    """``A W Aᵀ`` and ``A W δ`` over the free nodes (index -1: an anchor, dropped)."""
    rows = np.concatenate([ia, ib, ia, ib])
    cols = np.concatenate([ia, ib, ib, ia])
    vals = np.concatenate([weight, weight, -weight, -weight])
    keep = (rows >= 0) & (cols >= 0)
    lap = sparse.csc_matrix((vals[keep], (rows[keep], cols[keep])), shape=(n, n))
    rhs = np.zeros(n)
    wd = weight * delta
    np.add.at(rhs, ia[ia >= 0], -wd[ia >= 0])
    np.add.at(rhs, ib[ib >= 0], wd[ib >= 0])
    return lap, rhs


def _phase3_system(
    ia: np.ndarray, ib: np.ndarray, yaw_a: Array, yaw_b: Array, delta_hat: Array,
    delta_lin: Array, omega: Array, n: int,
) -> tuple[Any, Array]:
    """``Ω_x`` and ``b_x`` of (13)–(14), assembled edge by edge (module docstring).

    Edge ``k = (i, j)`` contributes ``r_kᵀ Ω_k r_k`` with ``r_k = G_k u_k - d_k`` over
    ``u_k = (p_i, θ_i, p_j, θ_j)``:
    ``G_k = [[-R̂_iᵀ, -S Δ_k, R̂_iᵀ, 0], [0, -1, 0, 1]]`` and
    ``d_k = [Δ̂ˡ_k - S Δ_k θ̂_i; θ̂_j - θ̂_i]``, where ``S = [0 -1; 1 0]`` and ``Δ_k`` is the
    point at which ``J`` is evaluated (``R̂_iᵀ J_k = S Δ_k``).
    """
    m = len(ia)
    c, s = np.cos(yaw_a), np.sin(yaw_a)
    s_delta = np.column_stack([-delta_lin[:, 1], delta_lin[:, 0]])  # S Δ
    G = np.zeros((m, 3, 6))
    G[:, 0, 0], G[:, 0, 1] = -c, -s  # -R̂ᵀ
    G[:, 1, 0], G[:, 1, 1] = s, -c
    G[:, :2, 2] = -s_delta
    G[:, :2, 3:5] = -G[:, :2, 0:2]  # R̂ᵀ
    G[:, 2, 2], G[:, 2, 5] = -1.0, 1.0
    d = np.empty((m, 3))
    d[:, :2] = delta_hat - s_delta * yaw_a[:, None]
    d[:, 2] = yaw_b - yaw_a
    GtO = np.einsum("mki,mkl->mil", G, omega)  # Gᵀ Ω, (m, 6, 3)
    H = GtO @ G  # (m, 6, 6)
    g = np.einsum("mil,ml->mi", GtO, d)  # (m, 6)

    var = np.empty((m, 6), dtype=np.int64)  # unknown index of each column of G
    for node, base in ((ia, 0), (ib, 3)):
        for c3 in range(3):
            var[:, base + c3] = np.where(node >= 0, 3 * node + c3, -1)
    rows = np.broadcast_to(var[:, :, None], (m, 6, 6)).ravel()
    cols = np.broadcast_to(var[:, None, :], (m, 6, 6)).ravel()
    keep = (rows >= 0) & (cols >= 0)
    info = sparse.csc_matrix((H.ravel()[keep], (rows[keep], cols[keep])), shape=(3 * n, 3 * n))
    rhs = np.zeros(3 * n)
    vflat, gflat = var.ravel(), g.ravel()
    ok = vflat >= 0
    np.add.at(rhs, vflat[ok], gflat[ok])
    return info, rhs


def solve_spd(matrix: Any, rhs: Array, method: str = "auto") -> Array:
    """Solve the sparse symmetric positive definite system ``matrix · x = rhs``.

    Sparse direct factorizations only (no dense matrix is ever formed):

    * ``cholmod`` — CHOLMOD's supernodal Cholesky (cvxopt's wheel; AMD ordering);
    * ``qdldl`` — QDLDL's LDLᵀ (AMD ordering);
    * ``splu-mmd`` — SuperLU with the minimum-degree ordering of ``Aᵀ + A``, symmetric
      mode and diagonal pivots (the right SuperLU settings for SPD matrices);
    * ``splu-colamd`` — SuperLU with its default COLAMD ordering;
    * ``spsolve`` — ``scipy.sparse.linalg.spsolve`` with its defaults;
    * ``auto`` — the first of ``cholmod``, ``qdldl``, ``splu-mmd`` that is installed
      (:mod:`h2o_slam.core.spd`, which exact mode uses too).

    ``cholmod`` and ``qdldl`` hand a matrix they find no factor of to ``splu-mmd``.

    Raises:
        InputError: the matrix is singular (to working precision) or the solution is not
            finite.
        ValueError: ``method`` is unknown, or names a backend that is not installed.
    """
    if method not in FACTORIZATIONS:
        raise ValueError(f"unknown factorization {method!r}; choose one of "
                         f"{', '.join(FACTORIZATIONS)}")
    try:
        if method in ("splu-colamd", "spsolve"):
            matrix = sparse.csc_matrix(matrix)
            from scipy.sparse import linalg as sla  # only here: 0.1 s of import

            x = (sla.splu(matrix, permc_spec="COLAMD").solve(rhs) if method == "splu-colamd"
                 else sla.spsolve(matrix, rhs))
        else:
            x = spd.solve_spd(matrix, rhs, _SPD_METHOD.get(method, method))
    except (RuntimeError, np.linalg.LinAlgError) as err:  # SuperLU: exactly singular
        raise InputError(f"LAGO: singular linear system ({err})") from None
    if not np.all(np.isfinite(x)):
        raise InputError("LAGO: singular linear system (non-finite solution)")
    return np.asarray(x, dtype=float)


#: :func:`solve_spd`'s names for the :mod:`h2o_slam.core.spd` backends that differ.
_SPD_METHOD = {"splu-mmd": "splu"}
