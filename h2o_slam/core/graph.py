"""Pose graphs: nodes with an estimate, and edges with measurements and information.

One representation for planar and 3-D graphs: poses are always 3-D ``(R, t)``; a planar
graph keeps ``z = 0`` and rotations about ``z``, and measures its errors and takes its steps
in the (x, y, yaw) coordinates :data:`~h2o_slam.core.geometry.PLANAR_DOF`.

Edge kinds:

* ``RELATIVE`` — ``K`` measures ``A⁻¹ B`` (odometry, loop closures).
* ``POSITION`` — GPS: the position of ``B`` in the earth (world) frame; ``a`` is :data:`EARTH`.
* ``ORIENTATION`` — compass / IMU: the rotation of ``B`` in the earth frame; ``a`` is
  :data:`EARTH`.

The χ² evaluator :func:`chi2` is the single scoring function for every solver compared
in this project (doc/design.md, Conventions).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import GraphError, InputError
from h2o_slam.core.geometry import Array

LOG = logging.getLogger(__name__)

#: Index used for the earth (world) node in an edge's ``a`` column.
EARTH = -1

#: Smallest eigenvalue an information matrix keeps, relative to its largest.
INFO_EIG_FLOOR = 1e-10


class EdgeKind(IntEnum):
    """What an edge measures (see the module docstring)."""

    RELATIVE = 0
    POSITION = 1
    ORIENTATION = 2


#: Error coordinates each kind constrains (indices into the 6-D error).
KIND_ROWS = {
    EdgeKind.RELATIVE: np.arange(6),
    EdgeKind.POSITION: np.arange(3),
    EdgeKind.ORIENTATION: np.arange(3, 6),
}


@dataclass
class PoseGraph:
    """Nodes and edges of a pose graph, stored as arrays.

    Attributes:
        planar: the graph is SE(2) embedded in SE(3).
        ids: external node ids, shape ``(N,)``; node ``i`` of every array is ``ids[i]``.
        R, t: world-frame estimate of each node, shapes ``(N, 3, 3)`` and ``(N, 3)``.
        kind: :class:`EdgeKind` of each edge, shape ``(M,)``.
        a, b: node indices of each edge (``a`` is :data:`EARTH` for global edges).
        meas_R, meas_t: measurement of each edge, shapes ``(M, 3, 3)`` and ``(M, 3)``.
        info: information matrix (stiffness, Σ⁻¹) of each edge in the 6-D error coordinates
            ``(x, y, z, rot x, rot y, rot z)``, shape ``(M, 6, 6)``; rows a kind does not
            constrain are zero.
        clamped_edges: edges whose information :func:`make_graph` eigen-clamped, sorted.
        clamped_info: their information as given (symmetrized, before clamping), shape
            ``(len(clamped_edges), 6, 6)``: :func:`chi2_as_written` weighs with it. The
            solvers never read it; ``info`` is the graph's information.
    """

    planar: bool
    ids: np.ndarray
    R: Array
    t: Array
    kind: np.ndarray
    a: np.ndarray
    b: np.ndarray
    meas_R: Array
    meas_t: Array
    info: Array
    clamped_edges: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    clamped_info: Array = field(default_factory=lambda: np.zeros((0, 6, 6)))

    @property
    def num_nodes(self) -> int:
        """Number of nodes ``N``."""
        return len(self.ids)

    @property
    def num_edges(self) -> int:
        """Number of edges ``M``."""
        return len(self.kind)

    @property
    def dof(self) -> np.ndarray:
        """Tangent / error coordinates in use: (x, y, yaw) when planar, all six otherwise."""
        return geo.PLANAR_DOF if self.planar else np.arange(6)

    def copy(self) -> PoseGraph:
        """A deep copy (every array copied)."""
        return PoseGraph(
            self.planar, self.ids.copy(), self.R.copy(), self.t.copy(), self.kind.copy(),
            self.a.copy(), self.b.copy(), self.meas_R.copy(), self.meas_t.copy(),
            self.info.copy(), self.clamped_edges.copy(), self.clamped_info.copy(),
        )

    def with_estimate(self, R: Array, t: Array) -> PoseGraph:
        """A copy of the graph holding the estimate ``(R, t)``."""
        out = self.copy()
        out.R, out.t = np.array(R, dtype=float), np.array(t, dtype=float)
        return out

    def with_edges(self, kind: int, a: np.ndarray, b: np.ndarray, meas_R: Array, meas_t: Array,
                   info: Array) -> PoseGraph:
        """A new graph (:func:`make_graph`) with edges of one ``kind`` appended after this
        graph's, one row of ``a``, ``b``, ``meas_R``, ``meas_t`` and ``info`` each."""
        return make_graph(
            self.planar, self.ids, self.R, self.t,
            np.concatenate([self.kind, np.full(len(a), kind, np.int8)]),
            np.concatenate([self.a, a]), np.concatenate([self.b, b]),
            np.concatenate([self.meas_R, meas_R]), np.concatenate([self.meas_t, meas_t]),
            np.concatenate([self.info, info]))


def make_graph(
    planar: bool,
    ids: np.ndarray,
    R: Array,
    t: Array,
    kind: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    meas_R: Array,
    meas_t: Array,
    info: Array,
) -> PoseGraph:
    """Build a :class:`PoseGraph`, validating it and conditioning its information matrices.

    Information matrices are symmetrized and eigen-clamped (doc/design.md, Conventions):
    eigenvalues below :data:`INFO_EIG_FLOOR` × the largest are raised to that floor, so that
    no edge is indefinite or singular in the coordinates it constrains. Clamped edges are logged
    and listed in ``clamped_edges``, their information as given kept in ``clamped_info``.

    Raises:
        GraphError: an edge refers to a node that does not exist, or is a self-loop.
        InputError: a value is not finite, or an information matrix has no positive part.
    """
    n = len(ids)
    kind = np.asarray(kind, dtype=np.int8)
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    _check_endpoints(kind, a, b, n)
    for name, arr in (("estimate", t), ("measurement", meas_t), ("information", info)):
        if not np.all(np.isfinite(arr)):
            raise InputError(f"non-finite {name} values in the graph")
    given = np.asarray(info, dtype=float)
    info, clamped = condition_information(kind, given, planar)
    as_given = 0.5 * (given[clamped] + np.swapaxes(given[clamped], -1, -2))
    return PoseGraph(
        planar, np.asarray(ids, dtype=np.int64), np.asarray(R, float), np.asarray(t, float),
        kind, a, b, np.asarray(meas_R, float), np.asarray(meas_t, float), info, clamped,
        as_given,
    )


def _check_endpoints(kind: np.ndarray, a: np.ndarray, b: np.ndarray, n: int) -> None:
    relative = kind == EdgeKind.RELATIVE
    if np.any((b < 0) | (b >= n)):
        raise GraphError("edge endpoint b refers to an unknown node")
    if np.any(relative & ((a < 0) | (a >= n))):
        raise GraphError("relative edge endpoint a refers to an unknown node")
    if np.any(~relative & (a != EARTH)):
        raise GraphError("global edges must have the earth as endpoint a")
    if np.any(relative & (a == b)):
        raise GraphError("relative edge from a node to itself")


def condition_information(
    kind: np.ndarray, info: Array, planar: bool
) -> tuple[Array, np.ndarray]:
    """Symmetrize and eigen-clamp information matrices in the coordinates each edge uses.

    Returns the conditioned matrices and the indices of the edges that were clamped.

    Raises:
        InputError: an information matrix has no positive eigenvalue.
    """
    info = 0.5 * (info + np.swapaxes(info, -1, -2))
    out = np.zeros_like(info)
    clamped: list[np.ndarray] = []
    dof = geo.PLANAR_DOF if planar else np.arange(6)
    for k, rows in KIND_ROWS.items():
        sel = np.flatnonzero(kind == k)
        rows = np.intersect1d(rows, dof)
        if len(sel) == 0:
            continue
        block = info[np.ix_(sel, rows, rows)]
        lam, vec = np.linalg.eigh(block)
        top = lam[:, -1]
        if np.any(top <= 0.0):
            bad = sel[np.argmax(top <= 0.0)]
            raise InputError(f"edge {bad}: information matrix has no positive eigenvalue")
        floor = INFO_EIG_FLOOR * top[:, None]
        hit = np.any(lam < floor, axis=1)
        clamped.append(sel[hit])
        # Only clamped matrices are rebuilt from their eigen-decomposition: rebuilding the
        # others would perturb them in the last bits, and a graph read from a file must
        # keep exactly the information the file states (round trips are bitwise).
        out[np.ix_(sel, rows, rows)] = block
        if np.any(hit):
            lam_c = np.maximum(lam[hit], floor[hit])
            out[np.ix_(sel[hit], rows, rows)] = np.einsum(
                "mij,mj,mkj->mik", vec[hit], lam_c, vec[hit]
            )
    clamped_idx = np.sort(np.concatenate(clamped)) if clamped else np.zeros(0, np.int64)
    if len(clamped_idx):
        LOG.info("eigen-clamped %d information matrices (floor %.0e × largest eigenvalue)",
                 len(clamped_idx), INFO_EIG_FLOOR)
    return out, clamped_idx


def has_global(graph: PoseGraph) -> bool:
    """The graph has GPS or compass edges (ones to the earth frame)."""
    return bool(np.any(graph.kind != EdgeKind.RELATIVE))


def edge_errors(graph: PoseGraph, R: Array | None = None, t: Array | None = None) -> Array:
    """Error vector of every edge at the estimate ``(R, t)`` (default: the graph's own).

    Returns shape ``(M, 6)``; coordinates an edge kind does not constrain are zero.
    Planar graphs get their yaw error wrapped (a rotation vector about ``z``).
    """
    R = graph.R if R is None else R
    t = graph.t if t is None else t
    err = np.zeros((graph.num_edges, 6))
    rel = graph.kind == EdgeKind.RELATIVE
    if np.any(rel):
        a, b = graph.a[rel], graph.b[rel]
        err[rel] = geo.relative_error(R[a], t[a], R[b], t[b], graph.meas_R[rel], graph.meas_t[rel])
    pos = graph.kind == EdgeKind.POSITION
    if np.any(pos):
        err[pos, :3] = t[graph.b[pos]] - graph.meas_t[pos]
    ori = graph.kind == EdgeKind.ORIENTATION
    if np.any(ori):
        Rk_t = np.swapaxes(graph.meas_R[ori], -1, -2)
        err[ori, 3:] = geo.so3_log(Rk_t @ R[graph.b[ori]])
    return err


def edge_chi2(graph: PoseGraph, R: Array | None = None, t: Array | None = None) -> Array:
    """χ² of every edge, ``eᵀ S e``, shape ``(M,)``."""
    dof = graph.dof
    e = edge_errors(graph, R, t)[:, dof]
    S = graph.info[np.ix_(np.arange(graph.num_edges), dof, dof)]
    return np.einsum("mi,mij,mj->m", e, S, e)


def chi2(graph: PoseGraph, R: Array | None = None, t: Array | None = None) -> float:
    """Total χ² (the thesis' "energy") of the graph at the estimate ``(R, t)``."""
    return float(np.sum(edge_chi2(graph, R, t)))


def chi2_as_written(graph: PoseGraph, R: Array | None = None, t: Array | None = None
                    ) -> float:
    """χ² of the problem as given, at the estimate ``(R, t)``: the eigen-clamped edges weighed
    with their information before clamping (``clamped_info``), the others as in
    :func:`chi2`. An information matrix the reader let through slightly indefinite can make
    its edge's term negative."""
    info = graph.info.copy()
    info[graph.clamped_edges] = graph.clamped_info
    dof = graph.dof
    e = edge_errors(graph, R, t)[:, dof]
    S = info[np.ix_(np.arange(graph.num_edges), dof, dof)]
    return float(np.einsum("mi,mij,mj->", e, S, e))


def odometry_chain(graph: PoseGraph) -> tuple[Array, Array]:
    """World poses from composing the odometry edges ``(i, i+1)`` from node 0 at the origin.

    Nodes the chain cannot reach (no edge between ``i`` and ``i+1`` in either direction)
    start at the pose of the previous node.
    """
    n = graph.num_nodes
    rel = np.flatnonzero(graph.kind == EdgeKind.RELATIVE)
    steps_R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    steps_t = np.zeros((n, 3))
    a, b = graph.a[rel], graph.b[rel]
    fwd = rel[b == a + 1]
    steps_R[graph.b[fwd]] = graph.meas_R[fwd]
    steps_t[graph.b[fwd]] = graph.meas_t[fwd]
    back = rel[(a == b + 1) & ~np.isin(a, graph.b[fwd])]
    inv_R, inv_t = geo.inverse(graph.meas_R[back], graph.meas_t[back])
    steps_R[graph.a[back]] = inv_R
    steps_t[graph.a[back]] = inv_t
    steps_R[0], steps_t[0] = np.eye(3), np.zeros(3)
    return geo.cumulative_compose(steps_R, steps_t)
