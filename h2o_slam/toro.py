"""TORO, the tree-based stochastic gradient descent of Grisetti et al. (RSS 2007), as a baseline.

G. Grisetti, C. Stachniss, S. Grzonka and W. Burgard, "A tree parameterization for
efficiently computing maximum likelihood maps using gradient descent", RSS 2007 — the 2-D
method the thesis compares H₂O against (its [17]). Planar graphs of relative edges only; the
3-D variant (Grisetti et al., IROS 2007) is not implemented.

API (what the benchmarks import)::

    from h2o_slam.toro import solve_toro
    graph_out, history = solve_toro(graph, iterations=100)
    history.chi2      # χ² (h2o_slam.graph.chi2) of the start, then after each iteration
    history.seconds   # cumulative wall time (s): tree and start, then after each iteration
    graph_out         # a copy of ``graph`` holding TORO's estimate

The method, as the paper states it:

* **Tree parameterization.** A breadth-first spanning tree of the graph (the same
  :func:`~h2o_slam.tree.spanning_parents` tree H₂O uses, root node 0). Each node's parameter
  is the difference of its pose and its parent's, ``x_i = p_i − p_parent(i)`` in world
  (x, y, θ) coordinates, so a pose is the sum of the parameters on its path to the root and
  an edge's residual depends only on the parameters of its tree path (below its *top*, the
  lowest common ancestor). The start is the tree initialization: tree edges' measurements
  composed down from the root (TORO's ``initializeOnTree``; :func:`h2o_slam.modes.tree_estimate`).
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

Differences from the released code, both deliberate: poses are always the exact sum of their
root path's parameters (the code keeps stale poses off the updated path within an iteration),
and ``Ω`` is turned by the rotation of ``p_a ⊕ K`` (the frame this package's χ² measures an
edge's error in) rather than of ``p_a`` alone (the code's ``R``, a χ² of its own; for the
preconditioner the code uses the measurement's rotation). χ² is always scored by
:func:`h2o_slam.graph.chi2`, the evaluator every solver here shares.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from h2o_slam import geometry as geo
from h2o_slam.compiled import kernel
from h2o_slam.errors import InputError
from h2o_slam.geometry import Array
from h2o_slam.graph import EARTH, EdgeKind, PoseGraph, chi2
from h2o_slam.tree import spanning_parents


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
        down: nodes in breadth-first order (every parent before its children).
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
        if np.any(graph.kind != EdgeKind.RELATIVE):
            raise InputError("TORO relaxes relative edges only; the graph has global edges")
        if init not in ("tree", "input"):
            raise ValueError(f"unknown init {init!r}; choose 'tree' or 'input'")
        parent = spanning_parents(graph.num_nodes, graph.a, graph.b)
        R, t = graph.R, graph.t
        if init == "tree":
            from h2o_slam.modes import tree_estimate

            R, t = tree_estimate(graph, parent)
        level, down = _levels(parent)
        top = _lowest_common_ancestors(parent, level, graph.a, graph.b)
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
    problem = ToroProblem.from_graph(graph, init)
    spent = time.perf_counter() - begin
    history = ToroHistory([chi2(graph, *problem.estimate())], [spent])
    for _ in range(iterations):
        begin = time.perf_counter()
        problem.iterate()
        spent += time.perf_counter() - begin
        history.chi2.append(chi2(graph, *problem.estimate()))
        history.seconds.append(spent)
    return graph.with_estimate(*problem.estimate()), history


def _levels(parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth of every node (roots 0) and the nodes in breadth-first order."""
    n = len(parent)
    level = np.full(n, -1, dtype=np.int64)
    level[parent == EARTH] = 0
    frontier = np.flatnonzero(parent == EARTH)
    down = [frontier]
    children = np.argsort(np.where(parent == EARTH, -1, parent), kind="stable")
    sorted_parent = parent[children]
    while len(frontier):
        lo = np.searchsorted(sorted_parent, frontier, side="left")
        hi = np.searchsorted(sorted_parent, frontier, side="right")
        nxt = np.concatenate([children[s:e] for s, e in zip(lo, hi, strict=True)]) \
            if len(frontier) else np.zeros(0, np.int64)
        level[nxt] = level[parent[nxt]] + 1
        down.append(nxt)
        frontier = nxt
    return level, np.concatenate(down).astype(np.int64)


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
