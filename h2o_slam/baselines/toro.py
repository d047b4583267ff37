"""TORO, the tree-based stochastic gradient descent of Grisetti et al. (RSS 2007), as a baseline.

G. Grisetti, C. Stachniss, S. Grzonka and W. Burgard, "A tree parameterization for
efficiently computing maximum likelihood maps using gradient descent", RSS 2007 — the 2-D
method the thesis compares H₂O against (its [17]) — for planar graphs; and its 3-D extension
(Grisetti, Grzonka, Stachniss, Pfaff and Burgard, "Efficient estimation of accurate maximum
likelihood maps in 3D", IROS 2007) for 3-D graphs (:class:`ToroProblem3`, below). Graphs of
relative edges only.

API (what the benchmarks import)::

    from h2o_slam.baselines.toro import solve_toro
    graph_out, history = solve_toro(graph, iterations=100)
    history.chi2      # χ² (h2o_slam.core.graph.chi2) of the start, then after each iteration
    history.seconds   # cumulative wall time (s): tree and start, then after each iteration
    graph_out         # a copy of ``graph`` holding TORO's estimate

The method, as the paper states it:

* **Tree parameterization.** A breadth-first spanning tree of the graph (the same
  :func:`~h2o_slam.core.tree.spanning_parents` tree H₂O uses, root node 0). Each node's parameter
  is the difference of its pose and its parent's, ``x_i = p_i − p_parent(i)`` in world
  (x, y, θ) coordinates, so a pose is the sum of the parameters on its path to the root and
  an edge's residual depends only on the parameters of its tree path (below its *top*, the
  lowest common ancestor). The start is the tree initialization: tree edges' measurements
  composed down from the root (TORO's ``initializeOnTree``;
  :func:`h2o_slam.core.modes.tree_estimate`).
* **Order.** Every iteration visits each edge once, by increasing level (depth) of its top,
  so updating an edge never disturbs the nodes above those already handled.
* **Update of one edge** ``a → b`` with measurement ``K`` and information ``Ω``: the residual
  ``r = (p_a ⊕ K) − p_b`` (world frame, angle wrapped) and the information turned into the
  world frame, ``Ω' = R Ω Rᵀ``; the step ``β = ℓ λ · 2Ω' r`` (``ℓ``: the number of path
  nodes below the top; ``λ`` the learning rate, below), each component clipped to ``|r|`` so
  that no update overshoots its own residual. ``β`` is distributed along the path: node
  ``k`` of the path moves by ``± β_j / (M_kj Σ_m 1/M_mj)`` per coordinate ``j`` (``+`` on
  ``b``'s side, ``−`` on ``a``'s), so the path takes up exactly ``β``, each node in
  proportion to its compliance ``1/M``.
* **Preconditioner and learning rate.** ``M_k = Σ diag(Ω'_e)`` over the edges ``e`` whose
  path contains ``k``, recomputed at the start of each iteration; ``γ_j = min_e Ω'_e,jj``;
  iteration ``i`` (1, 2, …) uses ``λ_j = 1/(γ_j (i + 1))`` — the released TORO code's
  schedule (its iteration counter is 2 on the first pass), i.e. ``β = ℓ Ω' r / γ`` clipped on
  the first pass, decaying as ``1/i``.

The 3-D variant (:class:`ToroProblem3`): parameters are local transforms to the parent, and
each edge is relaxed in two steps. *Rotation*: the world-frame turn ``φ = Log(R_a K_R R_bᵀ)``
that would put ``b`` at ``a ⊕ K`` is spread along the path — node ``k`` on ``b``'s side turns
by ``+f s_k φ``, on ``a``'s side by ``−f s_k φ``, ``s_k`` the share of the path's compliance
``1/M_rot`` from ``k`` up to the top — and local rotations are re-derived, local
translations kept (the chain bends). *Translation*: ``b``'s offset from ``a ⊕ K`` is spread
the same way as world-frame position offsets, and local translations are re-derived. The
fractions ``f = min(1, 2 √ℓ ω_rot/(γ_rot (i+1)))`` and ``min(1, 2 ℓ ω_trans/(γ_trans (i+1)))``
use each edge's smallest rotational / translational information ``ω`` (the released code's
scalar weights), with the 2-D schedule; the released 3-D code divides by ``ω`` instead,
which is not scale-free, and takes its path weights from the swapped preconditioner.

Differences from the released code, both deliberate: poses are always the exact sum of their
root path's parameters (the code keeps stale poses off the updated path within an iteration),
and ``Ω`` is turned by the rotation of ``p_a ⊕ K`` (the frame this package's χ² measures an
edge's error in) rather than of ``p_a`` alone (the code's ``R``, a χ² of its own; for the
preconditioner the code uses the measurement's rotation). χ² is always scored by
:func:`h2o_slam.core.graph.chi2`, the evaluator every solver here shares.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.compiled import kernel
from h2o_slam.core.errors import InputError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, chi2
from h2o_slam.core.tree import compose_down, depths, spanning_parents


@dataclass
class ToroHistory:
    """χ² and cumulative time of a TORO run.

    Attributes:
        chi2: χ² of the start (index 0), then after each iteration.
        seconds: wall time (s) spent when each ``chi2`` entry was taken: building the tree and
            the start (index 0), then after each iteration; χ² evaluation is not counted.
    """

    chi2: list[float] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)

    @property
    def iterations(self) -> int:
        """Iterations run."""
        return max(0, len(self.chi2) - 1)


@dataclass
class ToroProblem:
    """The tree and the parameters TORO iterates on (planar, relative edges only).

    Attributes:
        parent: parent of each node in the spanning tree, :data:`EARTH` for the root(s).
        level: depth of each node (roots 0).
        down: nodes by level (every parent before its children).
        a, b: endpoints of each edge; ``top``: their lowest common ancestor in the tree.
        meas: measurement ``(x, y, θ)`` of each edge, shape ``(M, 3)``.
        info: information of each edge in ``(x, y, θ)``, shape ``(M, 3, 3)``.
        order: edges by increasing level of their top (the order of every iteration).
        x: parameters ``p_i − p_parent(i)`` in ``(x, y, θ)``, shape ``(N, 3)``.
    """

    parent: np.ndarray
    level: np.ndarray
    down: np.ndarray
    a: np.ndarray
    b: np.ndarray
    top: np.ndarray
    meas: Array
    info: Array
    order: np.ndarray
    x: Array
    iteration: int = 0

    @classmethod
    def from_graph(cls, graph: PoseGraph, init: str = "tree") -> ToroProblem:
        """The problem of a planar graph of relative edges, started from the tree
        initialization (``init="tree"``) or from the graph's estimate (``"input"``).

        Raises:
            InputError: the graph is 3-D, has global (GPS, compass) edges, or ``init`` is
                unknown.
        """
        if not graph.planar:
            raise InputError("TORO here is the planar (RSS 2007) method; the graph is 3-D")
        parent, level, down, top, R, t = _tree_and_start(graph, init)
        meas = np.column_stack([graph.meas_t[:, :2], geo.matrix_to_yaw(graph.meas_R)])
        info = graph.info[:, geo.PLANAR_DOF][:, :, geo.PLANAR_DOF].copy()
        order = np.argsort(level[top], kind="stable")
        poses = np.column_stack([t[:, :2], geo.matrix_to_yaw(R)])
        x = poses.copy()
        inner = parent != EARTH
        x[inner] -= poses[parent[inner]]
        return cls(parent, level, down, graph.a.copy(), graph.b.copy(), top, meas, info,
                   order, x)

    def poses(self) -> Array:
        """World poses ``(x, y, θ)`` of every node, shape ``(N, 3)`` (θ not wrapped)."""
        return _all_poses(self.down, self.parent, self.x)

    def iterate(self) -> None:
        """One iteration: the preconditioner at the current poses, then every edge once."""
        self.iteration += 1
        M, gamma = _preconditioner(self.parent, self.a, self.b, self.top, self.meas,
                                   self.info, self.poses())
        rate = 1.0 / (gamma * (self.iteration + 1))
        _propagate(self.parent, self.a, self.b, self.top, self.meas, self.info, self.order,
                   self.x, M, rate)

    def estimate(self) -> tuple[Array, Array]:
        """World rotations ``(N, 3, 3)`` and positions ``(N, 3)`` of the current poses."""
        p = self.poses()
        t = np.zeros((len(p), 3))
        t[:, :2] = p[:, :2]
        return geo.yaw_to_matrix(geo.wrap_angle(p[:, 2])), t


def solve_toro(
    graph: PoseGraph, iterations: int = 100, init: str = "tree",
) -> tuple[PoseGraph, ToroHistory]:
    """Run TORO (RSS 2007) on a planar graph of relative edges for ``iterations`` iterations.

    Starts from the tree initialization (``init="tree"``, as TORO does) or from the graph's
    estimate (``"input"``). Returns a copy of ``graph`` holding the result and the χ² /
    time history (see :class:`ToroHistory`).

    Raises:
        InputError: the graph is 3-D or has global edges.
    """
    begin = time.perf_counter()
    problem: ToroProblem | ToroProblem3 = (
        ToroProblem.from_graph(graph, init) if graph.planar
        else ToroProblem3.from_graph(graph, init))
    spent = time.perf_counter() - begin
    history = ToroHistory([chi2(graph, *problem.estimate())], [spent])
    for _ in range(iterations):
        begin = time.perf_counter()
        problem.iterate()
        spent += time.perf_counter() - begin
        history.chi2.append(chi2(graph, *problem.estimate()))
        history.seconds.append(spent)
    return graph.with_estimate(*problem.estimate()), history


def _tree_and_start(
    graph: PoseGraph, init: str,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, Array, Array]:
    """Parents, levels, the nodes by level and each edge's top on the breadth-first tree,
    and the start (``R, t``) — shared by both variants.

    Raises:
        InputError: the graph has global edges.
        ValueError: ``init`` is unknown.
    """
    if np.any(graph.kind != EdgeKind.RELATIVE):
        raise InputError("TORO relaxes relative edges only; the graph has global edges")
    if init not in ("tree", "input"):
        raise ValueError(f"unknown init {init!r}; choose 'tree' or 'input'")
    parent = spanning_parents(graph.num_nodes, graph.a, graph.b)
    R, t = graph.R, graph.t
    if init == "tree":
        from h2o_slam.core.modes import tree_estimate

        R, t = tree_estimate(graph, parent)
    level = depths(parent) - 1  # roots at level 0
    down = np.argsort(level, kind="stable")  # parents before children
    top = _lowest_common_ancestors(parent, level, graph.a, graph.b)
    return parent, level, down, top, R, t


@kernel
def _lowest_common_ancestors(parent: np.ndarray, level: np.ndarray, a: np.ndarray,
                             b: np.ndarray) -> np.ndarray:
    top = np.empty(len(a), dtype=np.int64)
    for e in range(len(a)):
        u, v = a[e], b[e]
        while level[u] > level[v]:
            u = parent[u]
        while level[v] > level[u]:
            v = parent[v]
        while u != v:
            u, v = parent[u], parent[v]
        top[e] = u
    return top


@kernel
def _all_poses(down: np.ndarray, parent: np.ndarray, x: np.ndarray) -> np.ndarray:
    p = np.empty_like(x)
    for k in range(len(down)):
        i = down[k]
        if parent[i] < 0:
            p[i] = x[i]
        else:
            p[i] = p[parent[i]] + x[i]
    return p


@kernel
def _pose_of(parent: np.ndarray, x: np.ndarray, node: int) -> np.ndarray:
    p = np.zeros(3)
    while node >= 0:
        p += x[node]
        node = parent[node]
    return p


@kernel
def _world_info(p_a: np.ndarray, meas: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``Ω`` turned into the world frame by the rotation of ``p_a ⊕ K``."""
    c, s = np.cos(p_a[2] + meas[2]), np.sin(p_a[2] + meas[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot @ info @ rot.T


@kernel
def _preconditioner(parent: np.ndarray, a: np.ndarray, b: np.ndarray, top: np.ndarray,
                    meas: np.ndarray, info: np.ndarray,
                    poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``M`` (per node, diagonal, ``(N, 3)``) and ``γ`` (``(3,)``) at ``poses``."""
    M = np.zeros((len(parent), 3))
    gamma = np.full(3, np.inf)
    for e in range(len(a)):
        W = _world_info(poses[a[e]], meas[e], info[e])
        for j in range(3):
            gamma[j] = min(gamma[j], W[j, j])
        for n in (a[e], b[e]):
            while n != top[e]:
                for j in range(3):
                    M[n, j] += W[j, j]
                n = parent[n]
    return M, gamma


@kernel
def _propagate(parent: np.ndarray, a: np.ndarray, b: np.ndarray, top: np.ndarray,
               meas: np.ndarray, info: np.ndarray, order: np.ndarray, x: np.ndarray,
               M: np.ndarray, rate: np.ndarray) -> None:
    """Every edge of ``order`` once: residual, clipped step, distribution over its path."""
    for e in order:
        p_a = _pose_of(parent, x, a[e])
        p_b = _pose_of(parent, x, b[e])
        c, s = np.cos(p_a[2]), np.sin(p_a[2])
        k = meas[e]
        r = np.array([p_a[0] + c * k[0] - s * k[1] - p_b[0],
                      p_a[1] + s * k[0] + c * k[1] - p_b[1],
                      p_a[2] + k[2] - p_b[2]])
        r[2] = np.arctan2(np.sin(r[2]), np.cos(r[2]))
        d = 2.0 * (_world_info(p_a, k, info[e]) @ r)
        length = 0
        compliance = np.zeros(3)
        for n in (a[e], b[e]):
            while n != top[e]:
                length += 1
                compliance += 1.0 / M[n]
                n = parent[n]
        beta = length * rate * d
        for j in range(3):
            if abs(beta[j]) > abs(r[j]):
                beta[j] = r[j]
        share = beta / compliance
        for side in range(2):
            n = a[e] if side == 0 else b[e]
            sign = -1.0 if side == 0 else 1.0
            while n != top[e]:
                x[n] += sign * share / M[n]
                n = parent[n]


# -- 3-D (Grisetti, Grzonka, Stachniss, Pfaff and Burgard, IROS 2007) ----------------------------


@dataclass
class ToroProblem3:
    """The 3-D variant's tree and parameters: each node's local transform to its parent.

    Attributes as :class:`ToroProblem`, except: ``R, t`` the local transforms, shapes
    ``(N, 3, 3)`` and ``(N, 3)`` (a root's is its world pose); ``meas_R, meas_t`` the
    measurements; ``w_rot, w_trans`` each edge's smallest rotational and translational
    information (the scalar weights the method uses).
    """

    parent: np.ndarray
    level: np.ndarray
    down: np.ndarray
    a: np.ndarray
    b: np.ndarray
    top: np.ndarray
    meas_R: Array
    meas_t: Array
    w_rot: Array
    w_trans: Array
    order: np.ndarray
    R: Array
    t: Array
    iteration: int = 0

    @classmethod
    def from_graph(cls, graph: PoseGraph, init: str = "tree") -> ToroProblem3:
        """As :meth:`ToroProblem.from_graph`, for a graph of relative edges in 3-D (or planar,
        treated as 3-D)."""
        parent, level, down, top, R, t = _tree_and_start(graph, init)
        diag = np.diagonal(graph.info, axis1=1, axis2=2)
        if graph.num_edges and (np.min(diag[:, :3]) <= 0.0 or np.min(diag[:, 3:]) <= 0.0):
            raise InputError("TORO (3-D) needs positive information on every axis of every "
                             "edge")
        local_R, local_t = R.copy(), t.copy()
        inner = np.flatnonzero(parent != EARTH)
        local_R[inner], local_t[inner] = geo.between(R[parent[inner]], t[parent[inner]],
                                                     R[inner], t[inner])
        return cls(parent, level, down, graph.a.copy(), graph.b.copy(), top,
                   graph.meas_R.copy(), graph.meas_t.copy(), diag[:, 3:].min(axis=1).copy(),
                   diag[:, :3].min(axis=1).copy(), np.argsort(level[top], kind="stable"),
                   local_R, local_t)

    def estimate(self) -> tuple[Array, Array]:
        """World rotations ``(N, 3, 3)`` and positions ``(N, 3)``."""
        return compose_down(self.parent, self.down, self.R, self.t)

    def iterate(self) -> None:
        """One iteration over every edge (rotations first, then translations, per edge)."""
        self.iteration += 1
        M_rot, M_trans = _preconditioner3(self.parent, self.a, self.b, self.top, self.w_rot,
                                          self.w_trans)
        _propagate3(self.parent, self.a, self.b, self.top, self.meas_R, self.meas_t,
                    self.w_rot, self.w_trans, self.order, self.R, self.t, M_rot, M_trans,
                    float(self.w_rot.min()), float(self.w_trans.min()),
                    float(self.iteration + 1))


@kernel
def _preconditioner3(parent: np.ndarray, a: np.ndarray, b: np.ndarray, top: np.ndarray,
                     w_rot: np.ndarray, w_trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    M_rot, M_trans = np.zeros(len(parent)), np.zeros(len(parent))
    for e in range(len(a)):
        for n in (a[e], b[e]):
            while n != top[e]:
                M_rot[n] += w_rot[e]
                M_trans[n] += w_trans[e]
                n = parent[n]
    return M_rot, M_trans


@kernel
def _chain(parent: np.ndarray, node: int, stop: int, out: np.ndarray) -> int:
    """Nodes from ``node`` up to ``stop`` (exclusive) into ``out``; returns their count."""
    k = 0
    while node != stop:
        out[k] = node
        k += 1
        node = parent[node]
    return k


@kernel
def _world_of(parent: np.ndarray, R: np.ndarray, t: np.ndarray,
              node: int) -> tuple[np.ndarray, np.ndarray]:
    GR, Gt = np.eye(3), np.zeros(3)
    while node >= 0:
        Gt = R[node] @ Gt + t[node]
        GR = R[node] @ GR
        node = parent[node]
    return GR, Gt


@kernel
def _chain_world(chain: np.ndarray, n: int, R: np.ndarray, t: np.ndarray, top_R: np.ndarray,
                 top_t: np.ndarray, GR: np.ndarray, Gt: np.ndarray) -> None:
    """World poses of ``chain[:n]`` (bottom-up, its last node a child of the top)."""
    pR, pt = top_R, top_t
    for k in range(n - 1, -1, -1):
        i = chain[k]
        GR[k] = pR @ R[i]
        Gt[k] = pt + pR @ t[i]
        pR, pt = GR[k], Gt[k]


@kernel
def _shares(chains: np.ndarray, lens: np.ndarray, M: np.ndarray, out: np.ndarray) -> None:
    """Each path node's signed share of a correction: its side's compliance ``1/M`` from the
    node up to the top over the whole path's, negative on ``a``'s side (``chains[0]``), so
    that ``b`` moves by its side's share and ``a`` by minus its own: a whole correction."""
    total = 0.0
    for s in range(2):
        for k in range(lens[s]):
            total += 1.0 / M[chains[s][k]]
    for s in range(2):
        sign = -1.0 if s == 0 else 1.0
        acc = 0.0
        for k in range(lens[s] - 1, -1, -1):  # from the top's child down to the end
            acc += 1.0 / M[chains[s][k]]
            out[s, k] = sign * acc / total


@kernel
def _propagate3(parent: np.ndarray, a: np.ndarray, b: np.ndarray, top: np.ndarray,
                meas_R: np.ndarray, meas_t: np.ndarray, w_rot: np.ndarray,
                w_trans: np.ndarray, order: np.ndarray, R: np.ndarray, t: np.ndarray,
                M_rot: np.ndarray, M_trans: np.ndarray, gamma_rot: float, gamma_trans: float,
                it: float) -> None:
    n = len(parent)
    chains = np.empty((2, n), np.int64)
    GR = np.empty((2, n, 3, 3))
    Gt = np.empty((2, n, 3))
    lens = np.zeros(2, np.int64)
    share = np.empty((2, n))
    for e in order:
        lens[0] = _chain(parent, a[e], top[e], chains[0])
        lens[1] = _chain(parent, b[e], top[e], chains[1])
        length = lens[0] + lens[1]
        top_R, top_t = _world_of(parent, R, t, top[e])
        for s in range(2):
            _chain_world(chains[s], lens[s], R, t, top_R, top_t, GR[s], Gt[s])
        Ra = GR[0, 0] if lens[0] else top_R
        Rb = GR[1, 0] if lens[1] else top_R
        # Rotation: the world-frame turn that takes b to a·K, spread along the path.
        phi = geo.so3_log_one(Ra @ meas_R[e] @ Rb.T)
        factor = min(1.0, 2.0 * np.sqrt(length) * w_rot[e] / (gamma_rot * it))
        _shares(chains, lens, M_rot, share)
        for s in range(2):
            for k in range(lens[s]):
                GR[s][k] = geo.so3_exp_one((factor * share[s, k]) * phi) @ GR[s][k]
            for k in range(lens[s]):
                pR = GR[s][k + 1] if k + 1 < lens[s] else top_R
                R[chains[s][k]] = geo.renormalize_one(pR.T @ GR[s][k])
        # Translation: b's offset from a·K, spread along the path.
        for s in range(2):
            _chain_world(chains[s], lens[s], R, t, top_R, top_t, GR[s], Gt[s])
        Ra = GR[0, 0] if lens[0] else top_R
        ta = Gt[0, 0] if lens[0] else top_t
        tb = Gt[1, 0] if lens[1] else top_t
        residual = ta + Ra @ meas_t[e] - tb
        factor = min(1.0, 2.0 * length * w_trans[e] / (gamma_trans * it))
        _shares(chains, lens, M_trans, share)
        for s in range(2):
            for k in range(lens[s]):
                Gt[s][k] = Gt[s][k] + (factor * share[s, k]) * residual
            for k in range(lens[s]):
                pR = GR[s][k + 1] if k + 1 < lens[s] else top_R
                pt = Gt[s][k + 1] if k + 1 < lens[s] else top_t
                t[chains[s][k]] = pR.T @ (Gt[s][k] - pt)
