"""H₂O: the hybrid-Hessian pose-graph solver (thesis chapter 3).

:class:`H2OSolver` holds a pose tree (:mod:`h2o_slam.core.tree`), the edges, and the block-diagonal
regularizer ``B = Σₑ 𝔅(Jₑᵀ Jₑ)`` (one ``p × p`` block per node, ``p`` = 3 planar or 6), kept
up to date incrementally (eq. 3.32): every edge remembers the diagonal blocks it last
contributed, and relaxing it swaps the old contribution for the one at its new linearization.

Verbs:

* :meth:`H2OSolver.add_edge` — Algorithm 2 (AddEdge): an edge to a new node becomes that
  node's tree edge and initializes it; any other edge is a cross edge.
* :meth:`H2OSolver.relax` — the single-edge update (3.29)–(3.35) on the edge's domain.
* :meth:`H2OSolver.relax_batch` — the batch update (3.40)–(3.42) of a set of edges.

The batch of all edges, i.e. one Gauss–Newton step (exact mode), is :mod:`h2o_slam.core.exact`.

Updates are scaled by the temperature τ (3.3.11) and capped so that no node turns by more
than π/8 in one update.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from h2o_slam.core import geometry as geo
from h2o_slam.core import interpolate
from h2o_slam.core.capacity import ArrayRef, ensure
from h2o_slam.core.compiled import kernel
from h2o_slam.core.edges import EdgeTable
from h2o_slam.core.errors import GraphError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, chi2
from h2o_slam.core.hybrid import solve_hybrid
from h2o_slam.core.jacobians import ALL_DOF, Dof, endpoint_jacobians_one, path_linearization
from h2o_slam.core.spd import SPDFactor
from h2o_slam.core.tree import EdgePath, PoseTree, tree_edges


@dataclass(frozen=True)
class SolverConfig:
    """Tuning of the H₂O solver; defaults follow the thesis.

    Attributes:
        temperature_decay: factor applied to τ after each full pass (3.3.11).
        max_rotation_step_rad: largest rotation one update may apply to a node (3.3.11).
        gps_batch_size: GPS edges relaxed together in one batch update (3.3.10).
        exact_tolerance: relative χ² decrease below which exact mode stops.
    """

    temperature_decay: float = 0.99
    max_rotation_step_rad: float = math.pi / 8
    gps_batch_size: int = 30
    exact_tolerance: float = 1e-10

    def __post_init__(self) -> None:
        if not 0.0 < self.temperature_decay <= 1.0:
            raise ValueError("temperature_decay must be in (0, 1]")
        if not self.max_rotation_step_rad > 0.0:
            raise ValueError("max_rotation_step_rad must be positive")
        if self.gps_batch_size < 1:
            raise ValueError("gps_batch_size must be at least 1")


@dataclass(frozen=True)
class Linearization:
    """One edge linearized over its domain: ``r + Σᵢ Jᵢ xᵢ`` approximates its whitened error."""

    domain: np.ndarray  # (d,) node indices
    J: Array  # (d, p, p) whitened Jacobian blocks w.r.t. local perturbations
    r: Array  # (p,) whitened residual
    len_a: int  # the domain is the a-chain (this long) followed by the b-chain


@dataclass(frozen=True)
class RelaxOutcome:
    """What one single-edge update did.

    Attributes:
        accepted: the update stands (False: the guard undid it).
        chi2_before: the edge's χ² before the update.
        energy_after: the edge's χ² after, plus the regularizer's price of the moves (equal
            to ``chi2_before`` when unguarded).
        domain: size of the edge's domain.
        solved: nodes solved for (``domain`` unless interpolated).
    """

    accepted: bool
    chi2_before: float
    energy_after: float
    domain: int
    solved: int


class H2OSolver:
    """Pose tree, edges and regularizer of one pose graph; see the module docstring.

    Node ``i`` of the solver is node ``i`` of the graph it was built from.
    """

    def __init__(self, *, planar: bool, config: SolverConfig | None = None) -> None:
        self.config = config or SolverConfig()
        self.planar = planar
        self.dof = geo.PLANAR_DOF if planar else np.arange(6)
        self._dof = tuple(int(q) for q in self.dof)  # for the kernels (jacobians.Dof)
        self.p = len(self.dof)
        self.tree = PoseTree()
        self.B = np.zeros((16, self.p, self.p))
        self.temperature = 1.0
        self._edges = EdgeTable(self.p)
        #: Per node: the edge that ties it to its parent (-1 for subtree tops), and whether
        #: that edge measures parent → node (True) or node → parent (False).
        self.tree_edge = np.full(16, -1, dtype=np.int64)
        self.tree_edge_forward = np.ones(16, dtype=bool)
        self._paths: list[EdgePath | None] = []
        self._contrib: list[tuple[np.ndarray, Array] | None] = []
        #: Per edge: the node its contribution to ``B`` covers when that is a single node
        #: (-1 otherwise), and that block: ``J_αᵀJ_α`` of eq. 3.36, read by the interpolated
        #: update for the kept nodes' tree edges α without a Python loop over ``_contrib``.
        self._own_node = np.full(64, -1, dtype=np.int64)
        self._own_block = np.zeros((64, self.p, self.p))
        self._gps_at: dict[int, list[int]] = {}
        self._incident: dict[int, list[int]] = {}
        #: χ² of the edge most recently added, at the moment it was added.
        self.last_chi2 = 0.0

    # -- building -----------------------------------------------------------------------------

    @property
    def num_nodes(self) -> int:
        """Nodes in the tree."""
        return self.tree.n

    @property
    def num_edges(self) -> int:
        """Edges added so far."""
        return self._edges.m

    # Views of the edge table, valid until the next edge is added.
    @property
    def kind(self) -> np.ndarray:
        """:class:`EdgeKind` of each edge."""
        return self._edges.kind[: self._edges.m]

    @property
    def a(self) -> np.ndarray:
        """First endpoint of each edge (:data:`EARTH` for global edges)."""
        return self._edges.a[: self._edges.m]

    @property
    def b(self) -> np.ndarray:
        """Second endpoint of each edge."""
        return self._edges.b[: self._edges.m]

    @property
    def meas_R(self) -> Array:
        """Measured rotation of each edge."""
        return self._edges.meas_R[: self._edges.m]

    @property
    def meas_t(self) -> Array:
        """Measured translation of each edge."""
        return self._edges.meas_t[: self._edges.m]

    @property
    def info(self) -> Array:
        """Information matrix of each edge (6×6, error order)."""
        return self._edges.info[: self._edges.m]

    @property
    def planar_meas(self) -> Array:
        """A planar solver's measurement of each edge as ``(x, y, yaw)``."""
        return self._edges.planar_meas[: self._edges.m]

    @property
    def planar_info(self) -> Array:
        """A planar solver's information of each edge over ``(x, y, yaw)``."""
        return self._edges.planar_info[: self._edges.m]

    @property
    def planar_cov(self) -> Array:
        """The inverse of :attr:`planar_info` (a pseudo-inverse where it is singular)."""
        return self._edges.planar_cov[: self._edges.m]

    @property
    def W(self) -> Array:
        """Whitening ``W`` (``WᵀW = S`` in the coordinates in use) of each edge."""
        return self._edges.W[: self._edges.m]

    @property
    def weight(self) -> Array:
        """Robust weight of each edge (1 unless :mod:`h2o_slam.core.robust` lowered it)."""
        return self._edges.weight[: self._edges.m]

    def set_weights(self, weights: Array, edges: np.ndarray | None = None) -> None:
        """Set the robust weights of ``edges`` (all when ``None``); each in [0, 1]. The
        contributions to ``B`` keep the old weights until the edges are refreshed."""
        which: np.ndarray | slice = slice(0, self.num_edges) if edges is None else edges
        self._edges.set_weights(which, np.asarray(weights, dtype=float))

    def add_pose(self, R_world: Array, t_world: Array) -> int:
        """Add a node hanging from the earth at a world pose (a new subtree)."""
        node = self.tree.add_node(EARTH, R_world, t_world)
        self._grow_B()
        return node

    def add_edge(
        self, kind: int, a: int, b: int, meas_R: Array, meas_t: Array, info: Array,
        contribute: bool = True,
    ) -> int:
        """Add an edge (Algorithm 2 without rebalancing) and return its index.

        ``b == num_nodes`` (or ``a == num_nodes`` for a relative edge) adds that node as the
        other endpoint's child, initialized through this edge's measurement. The edge's
        contribution is added to the regularizer ``B`` — at once, or (``contribute=False``,
        for a caller on a time budget: it costs time in the edge's path length) when the edge
        is first relaxed or refreshed.

        Raises:
            GraphError: an endpoint does not exist, or a global edge would create a node.
        """
        n = self.num_nodes
        if kind == EdgeKind.RELATIVE and a == n and b < n:
            R_inv, t_inv = geo.inverse(meas_R, meas_t)
            self.tree.add_node(b, R_inv, t_inv)
            self._grow_B()
            self._set_tree_edge(n, self.num_edges, forward=False)
        elif kind == EdgeKind.RELATIVE and b == n and 0 <= a < n:
            self.tree.add_node(a, meas_R, meas_t)
            self._grow_B()
            self._set_tree_edge(n, self.num_edges, forward=True)
        elif kind != EdgeKind.RELATIVE and b == n:
            raise GraphError("a GPS or orientation edge cannot create a node; add it first")
        if not (0 <= b < self.num_nodes) or not (a == EARTH or 0 <= a < self.num_nodes):
            raise GraphError(f"edge ({a}, {b}) refers to an unknown node")
        if (kind == EdgeKind.RELATIVE) == (a == EARTH):
            raise GraphError("relative edges join two nodes; global edges start at the earth")
        edge = self._append_edge(kind, a, b, meas_R, meas_t, info)
        if not contribute and self.num_nodes == n:
            self.last_chi2 = math.nan
            return edge
        lin = self.linearize(edge)
        self._contribute(edge, lin)
        self.last_chi2 = float(lin.r @ lin.r)
        return edge

    def _append_edge(
        self, kind: int, a: int, b: int, meas_R: Array, meas_t: Array, info: Array
    ) -> int:
        edge = self._edges.append(kind, a, b, meas_R, meas_t, info, self.dof)
        self._incident.setdefault(int(b), []).append(edge)
        if a != EARTH:
            self._incident.setdefault(int(a), []).append(edge)
        self._paths.append(None)
        self._contrib.append(None)
        self._grow_own()
        if kind != EdgeKind.RELATIVE:
            self._gps_at.setdefault(int(b), []).append(edge)
        return edge

    def _extend_edges(self, graph: PoseGraph) -> None:
        """:meth:`_append_edge` for every edge of ``graph`` at once (array copies and one
        batched whitening instead of a call per edge)."""
        first = self.num_edges
        self._edges.extend(graph.kind, graph.a, graph.b, graph.meas_R, graph.meas_t,
                           graph.info, self.dof)
        incident, gps_at = self._incident, self._gps_at
        global_kind = graph.kind != EdgeKind.RELATIVE
        for e, (a, b, glob) in enumerate(
                zip(graph.a.tolist(), graph.b.tolist(), global_kind.tolist(), strict=True),
                start=first):
            incident.setdefault(b, []).append(e)
            if a != EARTH:
                incident.setdefault(a, []).append(e)
            if glob:
                gps_at.setdefault(b, []).append(e)
        self._paths.extend([None] * graph.num_edges)
        self._contrib.extend([None] * graph.num_edges)
        self._grow_own()

    def _grow_own(self) -> None:
        ensure(self._own_arrays(), self.num_edges)

    def _own_arrays(self) -> list[ArrayRef]:
        return [(self, "_own_node", -1), (self, "_own_block", 0.0)]

    def node_arrays(self) -> list[ArrayRef]:
        """Every per-node array as ``(owner, name, fill)`` (:mod:`h2o_slam.core.capacity`)."""
        return self.tree.arrays() + self._B_arrays()

    def edge_arrays(self) -> list[ArrayRef]:
        """Every per-edge array as ``(owner, name, fill)``."""
        return self._edges.arrays() + self._own_arrays()

    def _contribute(self, edge: int, lin: Linearization) -> None:
        """Add the edge's contribution ``𝔅(JᵀJ)`` at ``lin`` to ``B`` and remember it."""
        contrib = _gram(lin.J)
        self.B[lin.domain] += contrib
        self._remember(edge, lin.domain, contrib)

    def _remember(self, edge: int, nodes: np.ndarray, blocks: Array) -> None:
        """Record that ``edge`` contributes ``blocks`` to ``B`` at ``nodes``."""
        self._contrib[edge] = (nodes, blocks)
        single = len(nodes) == 1
        self._own_node[edge] = nodes[0] if single else -1
        if single:
            self._own_block[edge] = blocks[0]

    def _grow_B(self) -> None:
        ensure(self._B_arrays(), self.tree.n)

    def _B_arrays(self) -> list[ArrayRef]:
        return [(self, "B", 0.0), (self, "tree_edge", -1), (self, "tree_edge_forward", True)]

    def _set_tree_edge(self, node: int, edge: int, forward: bool) -> None:
        self.tree_edge[node] = edge
        self.tree_edge_forward[node] = forward

    @classmethod
    def from_graph(
        cls, graph: PoseGraph, parents: np.ndarray, config: SolverConfig | None = None,
        regularizer: bool = True,
    ) -> H2OSolver:
        """A solver over all of ``graph`` with the given spanning tree, starting from the
        graph's estimate; ``B`` holds every edge's contribution at that estimate.

        ``regularizer=False`` leaves ``B`` empty and no edge contributing (as
        ``add_edge(..., contribute=False)``): for exact mode, which never reads ``B``,
        building it is a linearization of every edge along its tree path (0.4 s of
        city10000's 1 s).
        """
        solver = cls(planar=graph.planar, config=config)
        solver.tree = PoseTree.from_parents(parents, graph.R, graph.t)
        solver.B = np.zeros((graph.num_nodes, solver.p, solver.p))
        solver.tree_edge, solver.tree_edge_forward = tree_edges(graph, parents)
        solver._extend_edges(graph)
        for e in range(graph.num_edges if regularizer else 0):
            solver._contribute(e, solver.linearize(e))
        return solver

    # -- queries ------------------------------------------------------------------------------

    def path(self, edge: int) -> EdgePath:
        """The tree path of an edge (cached until the tree changes)."""
        cached = self._paths[edge]
        if cached is None:
            cached = self.tree.path(int(self._edges.a[edge]), int(self._edges.b[edge]))
            self._paths[edge] = cached
        return cached

    def contribution_size(self, edge: int) -> int:
        """Nodes the edge's current contribution to ``B`` covers (0: none yet)."""
        old = self._contrib[edge]
        return 0 if old is None else len(old[0])

    def root_depth(self, edge: int) -> int:
        """Depth of the edge's root (0 for the earth)."""
        root = self.path(edge).root
        return 0 if root == EARTH else int(self.tree.depth[root])

    def world_poses(self) -> tuple[Array, Array]:
        """World poses of all nodes, shapes ``(N, 3, 3)`` and ``(N, 3)`` (new arrays)."""
        return self.tree.world_poses()

    def graph(self, copy: bool = True) -> PoseGraph:
        """The solver's nodes and edges as a graph holding the current estimate (edges in the
        order they were added); ``copy=False`` shares the edge arrays (valid until the next
        edge is added)."""
        R, t = self.world_poses()
        edges = [self.kind, self.a, self.b, self.meas_R, self.meas_t, self.info]
        if copy:
            edges = [x.copy() for x in edges]
        return PoseGraph(self.planar, np.arange(self.num_nodes), R, t, *edges)

    def chi2(self, graph: PoseGraph) -> float:
        """χ² of ``graph`` (the graph this solver holds) at the solver's current estimate."""
        R, t = self.world_poses()
        return chi2(graph, R, t)

    def linearize(self, edge: int) -> Linearization:
        """Whitened residual and Jacobian blocks of one edge over its domain (appendix B)."""
        path = self.path(edge)
        table = self._edges
        J, r = path_linearization(
            self.tree.R, self.tree.t, path.a_chain, path.b_chain, int(table.kind[edge]),
            table.meas_R[edge], table.meas_t[edge], table.W[edge], self._dof)
        return Linearization(path.domain, J, r, len(path.a_chain))

    # -- updates ------------------------------------------------------------------------------

    def relax(
        self, edge: int, d_max: int | None = None, scale: float | None = None,
        guard: bool = False,
    ) -> RelaxOutcome:
        """Single-edge hybrid-Hessian update of ``edge`` (thesis 3.3.5).

        With ``d_max`` smaller than the domain, interpolated solving (3.3.6): solve for at most
        ``d_max`` nodes with merged constraints and spread their change over the rest.
        ``scale`` replaces the temperature (the π/8 rotation cap still applies).

        With ``guard``, the update is undone when it raises the energy it set out to lower —
        the edge's own χ² plus ``Σᵢ δᵢᵀ B_c δᵢ``, what the other edges pay for the moves —
        which is how too small a ``d_max`` shows its divergence (Table 3.1).
        """
        lin = self.linearize(edge)
        dom = lin.domain
        B_c = self._regularizer_without(edge, dom)
        saved = (self.tree.R[dom].copy(), self.tree.t[dom].copy()) if guard else None
        interpolated = d_max is not None and len(dom) > d_max
        if interpolated:
            assert d_max is not None
            solved = self._relax_interpolated(lin, B_c, d_max, scale)
        else:
            tau = self.temperature if scale is None else scale
            x = solve_hybrid(lin.J, lin.r, B_c)
            _scale_and_apply(self.tree.R, self.tree.t, dom, x, self.dof, tau,
                             self.config.max_rotation_step_rad)
            solved = len(dom)
        before = float(lin.r @ lin.r)
        after = self._energy_after(edge, dom, B_c, saved) if saved is not None else before
        accepted = after <= before * (1.0 + 1e-9) + 1e-12
        if not accepted:
            assert saved is not None
            self.tree.R[dom], self.tree.t[dom] = saved
        # J was taken at the state kept in either case, so it is the edge's contribution.
        self._remember(edge, dom, _store_contribution(self.B, dom, B_c, lin.J))
        return RelaxOutcome(accepted, before, after, len(dom), solved)

    def _energy_after(
        self, edge: int, dom: np.ndarray, B_c: Array, saved: tuple[Array, Array]
    ) -> float:
        """The edge's χ² after an update plus the regularizer's price of the moves."""
        r = self.residual(edge)
        step_t = self.tree.t[dom] - saved[1]
        step_r = geo.so3_log(np.swapaxes(saved[0], -1, -2) @ self.tree.R[dom])
        delta = np.concatenate([step_t, step_r], axis=1)[:, self.dof]
        return float(r @ r + np.einsum("di,dij,dj->", delta, B_c, delta))

    def residual(self, edge: int) -> Array:
        """Whitened residual of one edge at the current estimate (no Jacobian)."""
        path = self.path(edge)
        Ra, xa = self._end_pose(path.a_chain)
        Rb, xb = self._end_pose(path.b_chain)
        table = self._edges
        e, _, _ = endpoint_jacobians_one(
            int(table.kind[edge]), Ra, xa, Rb, xb, table.meas_R[edge], table.meas_t[edge])
        return table.W[edge] @ e[self.dof]

    def _end_pose(self, chain: np.ndarray) -> tuple[Array, Array]:
        if len(chain) == 0:
            return np.eye(3), np.zeros(3)
        return self.tree.chain_end(chain)

    def _regularizer_without(self, edge: int, domain: np.ndarray) -> Array:
        """``B_c``: the regularizer blocks of ``domain`` without ``edge``'s own contribution."""
        old = self._contrib[edge]
        if old is None:  # added without a contribution yet
            return self.B[domain]
        old_nodes, old_blocks = old
        if old_nodes is domain or np.array_equal(old_nodes, domain):
            return _blocks_without(self.B, domain, old_blocks)
        # The tree changed since this edge last contributed.
        self.B[old_nodes] -= old_blocks
        return self.B[domain]

    def _relax_interpolated(
        self, lin: Linearization, B_c: Array, d_max: int, scale: float | None
    ) -> int:
        dom = lin.domain
        sel = interpolate.select(lin.len_a, len(dom) - lin.len_a, d_max)
        x = solve_hybrid(np.ascontiguousarray(lin.J[sel.kept]), lin.r,
                         self._merged_regularizer(lin, sel, B_c))
        tau = self.temperature if scale is None else scale
        step, compliance = _interpolated_step(x, self._dof, tau,
                                              self.config.max_rotation_step_rad, B_c)
        interpolate.distribute_into(self.tree.R, self.tree.t, dom, sel.kept, sel.start, step,
                                    compliance)
        return len(sel.kept)

    def _merged_regularizer(
        self, lin: Linearization, sel: interpolate.Selection, B_c: Array
    ) -> Array:
        """``B̃ = B_c − J_αᵀJ_α + J_βᵀJ_β`` (eq. 3.36) at the kept nodes, ``(k, p, p)``.

        Segments of one node, and segments that contain a subtree top (tied to the earth by
        no edge), keep ``B_c``.
        """
        dom = lin.domain
        table = self._edges
        k_R, k_t, S, top = interpolate.tree_edge_constraints(
            dom, self.tree_edge, self.tree_edge_forward, table.meas_R, table.meas_t, table.info,
            self._dof)
        R_b, t_b, S_b = interpolate._merge_segments(sel.kept, sel.start, k_R, k_t, S, self._dof)
        out = interpolate.merged_stiffness(
            self.tree.R, self.tree.t, dom, sel.kept, sel.start, R_b, t_b, S_b, self._dof)
        interpolate.give_way(out, B_c, dom, sel.kept, sel.start, top, self.tree_edge,
                             self._own_node, self._own_block)
        return out

    def relax_batch(self, edges: list[int] | np.ndarray) -> None:
        """Batch update of a set of edges (thesis 3.3.7, eq. 3.40–3.42).

        The edges' own contributions are taken out of ``B``; the rest regularizes the step.
        With every edge of the graph in the batch this is the Gauss–Newton step.
        """
        edges = [int(e) for e in edges]
        if not edges:
            return
        lins = [self.linearize(e) for e in edges]
        nodes = np.unique(np.concatenate([lin.domain for lin in lins]))
        if len(edges) == self.num_edges:
            B_c = np.zeros((len(nodes), self.p, self.p))
        else:
            for e in edges:
                old = self._contrib[e]
                if old is not None:
                    np.subtract.at(self.B, old[0], old[1])
            B_c = self.B[nodes]
        J, r = self._stack(lins, nodes)
        x = _solve_regularized(J, r, B_c).reshape(len(nodes), self.p)
        self._apply(nodes, x, self._step_scale(x))
        self.B[nodes] = B_c
        for e, lin in zip(edges, lins, strict=True):
            self._contribute(e, lin)

    def _stack(self, lins: list[Linearization], nodes: np.ndarray) -> tuple[sp.csr_matrix, Array]:
        p = self.p
        rows, cols, vals = [], [], []
        col_of = np.full(self.num_nodes, -1)
        col_of[nodes] = np.arange(len(nodes))
        ii, jj = np.meshgrid(np.arange(p), np.arange(p), indexing="ij")
        for k, lin in enumerate(lins):
            c = col_of[lin.domain]
            rows.append(np.broadcast_to(k * p + ii, lin.J.shape).ravel())
            cols.append((c[:, None, None] * p + jj).ravel())
            vals.append(lin.J.ravel())
        J = sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(len(lins) * p, len(nodes) * p),
        )
        return J, np.concatenate([lin.r for lin in lins])

    def _step_scale(self, x: Array) -> float:
        """τ, reduced so that no node turns by more than the cap (3.3.11)."""
        return float(_capped_scale(np.ascontiguousarray(x), self.temperature,
                                   self.config.max_rotation_step_rad))

    def _apply(self, nodes: np.ndarray, x: Array, scale: float) -> None:
        """Apply a local step ``x`` (``(d, p)``) to ``nodes``, scaled by ``scale``."""
        _apply_local(self.tree.R, self.tree.t, np.ascontiguousarray(nodes, dtype=np.int64),
                     np.ascontiguousarray(x, dtype=float), self.dof, float(scale))

    def apply_step(self, nodes: np.ndarray, x: Array) -> None:
        """Apply a local step in full (no temperature, no cap)."""
        self._apply(nodes, x, scale=1.0)

    # -- bookkeeping --------------------------------------------------------------------------

    def end_pass(self) -> None:
        """Cool the temperature and re-orthonormalize rotations after a full pass."""
        self.temperature *= self.config.temperature_decay
        n = self.num_nodes
        self.tree.R[:n] = geo.orthonormalize(self.tree.R[:n])

    # -- re-parametrization --------------------------------------------------------------------

    def incident(self, node: int) -> list[int]:
        """Edges with ``node`` as an endpoint."""
        return self._incident.get(node, [])

    def world_pose(self, node: int) -> tuple[Array, Array]:
        """World pose of one node, composed down its ancestry (O(depth))."""
        return self.tree.world_pose(node)

    def relative_pose(self, a: int, b: int, path: EdgePath | None = None) -> tuple[Array, Array]:
        """Pose of ``b`` in the frame of ``a`` (``a`` may be :data:`EARTH`), composed along
        their tree path (``tree.path(a, b)``, found when not given): O(path length), where
        two :meth:`world_pose` calls are O(depth)."""
        path = self.tree.path(a, b) if path is None else path
        R_a, t_a = self._chain_end(path.a_chain)
        R_b, t_b = self._chain_end(path.b_chain)
        return geo.between(R_a, t_a, R_b, t_b)

    def _chain_end(self, chain: np.ndarray) -> tuple[Array, Array]:
        if len(chain) == 0:
            return np.eye(3), np.zeros(3)
        return geo.chain_product(self.tree.R[chain], self.tree.t[chain])

    def tree_path(self, a: int, b: int, edge: int = -1) -> EdgePath:
        """``tree.path(a, b)``, from the cache of ``edge`` when it joins ``a`` and ``b``."""
        if edge < 0:
            return self.tree.path(a, b)
        path = self.path(edge)
        if int(self._edges.a[edge]) == a:
            return path
        return EdgePath(path.root, path.b_chain, path.a_chain)

    def reparent(
        self, node: int, parent: int, edge: int, refresh: bool = True,
        path: EdgePath | None = None,
    ) -> tuple[list[int], set[int]]:
        """Hang ``node`` under ``parent`` (tied by ``edge``), keeping every world pose.

        Paths through the moved subtree change, so the edges touching it get new domains and
        new contributions to ``B`` (thesis 3.3.9). With ``refresh=False`` the caller refreshes
        the returned edges itself (:meth:`refresh_edges`), once for many re-parentings.
        ``path`` is ``tree.path(parent, node)`` when the caller has it.

        Returns the moved subtree (its depths changed) and the edges whose paths changed.
        """
        R_loc, t_loc = self.relative_pose(parent, node, path)
        moved = self.tree.reparent(node, parent, geo.renormalize(R_loc), t_loc)
        if edge >= 0:
            self._set_tree_edge(node, edge, forward=int(self._edges.a[edge]) == parent)
        else:
            self._set_tree_edge(node, -1, forward=True)
        affected = {e for n in moved for e in self.incident(n)}
        for e in affected:
            self._paths[e] = None
        if refresh:
            self.refresh_edges(affected)
        return moved, affected

    def refresh_edges(self, edges: set[int] | list[int]) -> None:
        """Recompute the paths and ``B`` contributions of edges whose paths changed."""
        for e in edges:
            self._paths[e] = None
            old = self._contrib[e]
            if old is not None:
                self.B[old[0]] -= old[1]
            self._contribute(e, self.linearize(e))

    def upstream_gps(self, node: int, count: int) -> list[int]:
        """``GetUpstreamGPSes``: the first ``count`` GPS edges found walking up from ``node``."""
        found: list[int] = []
        while node != EARTH and len(found) < count:
            attached = self._gps_at.get(node, ())
            found.extend(e for e in attached if self.kind[e] == EdgeKind.POSITION)
            node = int(self.tree.parent[node])
        return found[:count]


@kernel
def _gram(J: Array) -> Array:
    """Diagonal blocks ``Jᵢᵀ Jᵢ`` of ``JᵀJ``, ``(d, p, p)`` from ``(d, m, p)``."""
    d, m, p = J.shape
    out = np.empty((d, p, p))
    # Block sizes as tuples, so that numba compiles the loops for them: with the sizes
    # known only at run time the same loops take 7x as long.
    if m == p == 3:
        _gram_into(J, (0, 1, 2), (0, 1, 2), out)
    elif m == p == 6:
        _gram_into(J, ALL_DOF, ALL_DOF, out)
    else:
        _gram_into(J, np.arange(m), np.arange(p), out)
    return out


@kernel
def _gram_into(J: Array, rows: Dof, cols: Dof, out: Array) -> None:
    """:func:`_gram` into ``out``; ``rows``/``cols`` are ``range(m)``/``range(p)``."""
    for i in range(J.shape[0]):
        for a in range(len(cols)):
            for b in range(a, len(cols)):
                acc = 0.0
                for k in range(len(rows)):
                    acc += J[i, k, a] * J[i, k, b]
                out[i, a, b] = acc
                out[i, b, a] = acc


@kernel
def _store_contribution(B: Array, nodes: np.ndarray, B_c: Array, J: Array) -> Array:
    """``B[nodes] = B_c + 𝔅(JᵀJ)``; returns the new contribution ``𝔅(JᵀJ)``."""
    contrib = _gram(J)
    size = contrib.shape[1] * contrib.shape[2]
    flat_B = B.reshape(B.shape[0], size)
    flat_c = contrib.reshape(len(nodes), size)
    flat_B_c = B_c.reshape(len(nodes), size)
    for i in range(len(nodes)):
        for q in range(size):
            flat_B[nodes[i], q] = flat_B_c[i, q] + flat_c[i, q]
    return contrib


@kernel
def _blocks_without(B: Array, nodes: np.ndarray, blocks: Array) -> Array:
    """``B[nodes] − blocks``, a new ``(len(nodes), p, p)`` array."""
    out = np.empty(blocks.shape)
    size = blocks.shape[1] * blocks.shape[2]
    flat_out = out.reshape(len(nodes), size)
    flat_B = B.reshape(B.shape[0], size)
    flat_blocks = blocks.reshape(len(nodes), size)
    for i in range(len(nodes)):
        for q in range(size):
            flat_out[i, q] = flat_B[nodes[i], q] - flat_blocks[i, q]
    return out


@kernel
def _capped_scale(x: Array, tau: float, cap: float) -> float:
    """τ, reduced so that no row of the local step ``x`` (``(d, p)``, rotation in the last
    ``p // 2`` columns — one for planar ``p = 3``) turns by more than ``cap`` (3.3.11)."""
    p = x.shape[1]
    first = p - (p // 2 if p == 6 else 1)
    largest = 0.0
    for i in range(x.shape[0]):
        acc = 0.0
        for q in range(first, p):
            acc += x[i, q] * x[i, q]
        largest = max(largest, np.sqrt(acc))
    return tau if largest * tau <= cap else cap / largest


@kernel
def _interpolated_step(
    x: Array, dof: Dof, tau: float, cap: float, B_c: Array
) -> tuple[Array, Array]:
    """The kept nodes' local steps ``(δt, δθ)`` (``(k, 6)``) from ``x`` (``(k, p)``) scaled by τ
    and capped (3.3.11), and the distribution weights of the domain from ``B_c``."""
    scale = _capped_scale(x, tau, cap)
    step = np.zeros((x.shape[0], 6))
    for i in range(x.shape[0]):
        for q in range(len(dof)):
            step[i, dof[q]] = x[i, q] * scale
    return step, interpolate.compliance(B_c)


@kernel
def _apply_local(
    tree_R: Array, tree_t: Array, nodes: np.ndarray, x: Array, dof: np.ndarray, scale: float
) -> None:
    """``t ← t + δt``, ``R ← R Exp(δθ)`` (renormalized) for the scaled local step ``x``."""
    full = np.zeros(6)
    # Scratch matrices reused for every node: three allocations a node were 170 µs of the
    # full update on a 1427-node path.
    turn = np.empty((3, 3))
    moved = np.empty((3, 3))
    for i in range(len(nodes)):
        for q in range(len(dof)):
            full[dof[q]] = scale * x[i, q]
        n = nodes[i]
        for k in range(3):
            tree_t[n, k] += full[k]
        geo.so3_exp_into(full[3:], turn)
        geo.mul3_into(tree_R[n], turn, moved)
        geo.renormalize_into(moved, tree_R[n])


@kernel
def _scale_and_apply(
    tree_R: Array, tree_t: Array, nodes: np.ndarray, x: Array, dof: np.ndarray, tau: float,
    cap: float,
) -> None:
    """Apply the local step ``x`` scaled by τ, capped (3.3.11)."""
    _apply_local(tree_R, tree_t, nodes, x, dof, _capped_scale(x, tau, cap))


def _solve_regularized(J: sp.csr_matrix, r: Array, B: Array) -> Array:
    """Minimizer of ``‖J x + r‖² + Σᵢ xᵢᵀ Bᵢ xᵢ`` for sparse ``J`` and blocks ``B``."""
    H = (J.T @ J + sp.block_diag(list(B), format="csr")).tocsc()
    g = J.T @ r
    U = sp.triu(H, format="csc")
    U.sort_indices()
    try:
        return -SPDFactor(U.indptr, U.indices).solve(U.data, g)
    except np.linalg.LinAlgError:  # an unconstrained direction: the minimum-norm step
        import scipy.sparse.linalg as spla  # singular systems only: 0.1 s of import

        return -spla.lsqr(H, g, atol=1e-14, btol=1e-14, iter_lim=10 * H.shape[0])[0]
