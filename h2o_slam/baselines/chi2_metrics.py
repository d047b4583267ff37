"""χ² of a pose graph as GTSAM and g2o compute it, beside this package's own.

The three tools weigh the same information matrices against different error vectors of the
relative pose ``E = K⁻¹ (A⁻¹ B)`` (measurement ``K``, poses ``A``, ``B``):

* ``h2o`` (:func:`h2o_slam.core.graph.chi2`): ``[t_E; Log(R_E)]``.
* ``gtsam``: ``BetweenFactor``'s local coordinates, the group logarithm of ``E``
  (``Pose2::Logmap`` / ``Pose3::Logmap``): rotation ``Log(R_E)`` and translation
  ``V(Log R_E)⁻¹ t_E``, ``V`` being SO(3)'s left Jacobian (Pose2's ``V(θ)`` in the plane).
  GTSAM orders Pose3 coordinates rotation first; the number is the same as long as the
  information is permuted alike, as GTSAM's ``readG2o`` does. GTSAM's
  ``NonlinearFactorGraph.error`` prints *half* of this sum.
* ``g2o``: ``EdgeSE2`` uses ``[t_E; wrap(θ_E)]``, the same as ``h2o``; ``EdgeSE3`` uses
  ``[t_E; q_xyz]``, the vector part of ``R_E``'s unit quaternion with ``w ≥ 0`` (about half
  the rotation angle), and its ``EdgeSE3Prior`` likewise for orientation priors.

Position (GPS) and orientation edges: the three agree on position errors ``t − t_K``; an
orientation error is ``Log(R_Kᵀ R)`` for ``h2o`` and ``gtsam`` and the quaternion's vector
part for ``g2o``.
"""

from __future__ import annotations

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EdgeKind, PoseGraph, chi2, edge_errors

#: The metrics :func:`chi2_as` knows, this package's first.
METRICS = ("h2o", "gtsam", "g2o")


def chi2_as(metric: str, graph: PoseGraph, R: Array | None = None,
            t: Array | None = None) -> float:
    """Total χ² ``Σ eᵀ S e`` of ``graph`` at ``(R, t)`` (default: its estimate) with the
    error vectors of ``metric`` (one of :data:`METRICS`)."""
    if metric not in METRICS:
        raise ValueError(f"unknown metric {metric!r}; choose one of {', '.join(METRICS)}")
    if metric == "h2o":
        return chi2(graph, R, t)
    R = graph.R if R is None else R
    t = graph.t if t is None else t
    err = edge_errors(graph, R, t)
    if metric == "gtsam":
        rel = graph.kind == EdgeKind.RELATIVE
        # V(ω)⁻¹ = J_l(ω)⁻¹ = J_r(−ω)⁻¹.
        V_inv = geo.so3_right_jacobian_inv(-err[rel, 3:])
        err[rel, :3] = np.einsum("mij,mj->mi", V_inv, err[rel, :3])
    elif metric == "g2o" and not graph.planar:
        err[:, 3:] = _quaternion_vector(graph, R)
    dof = graph.dof
    e = err[:, dof]
    S = graph.info[np.ix_(np.arange(graph.num_edges), dof, dof)]
    return float(np.einsum("mi,mij,mj->", e, S, e))


def _quaternion_vector(graph: PoseGraph, R: Array) -> Array:
    """g2o's rotation error of every edge: ``q_xyz`` of the error rotation (``w ≥ 0``),
    zero for position edges, shape ``(M, 3)``."""
    out = np.zeros((graph.num_edges, 3))
    rel = graph.kind == EdgeKind.RELATIVE
    ori = graph.kind == EdgeKind.ORIENTATION
    Rk_t = np.swapaxes(graph.meas_R, -1, -2)
    R_err = np.broadcast_to(np.eye(3), (graph.num_edges, 3, 3)).copy()
    a, b = graph.a[rel], graph.b[rel]
    R_err[rel] = Rk_t[rel] @ np.swapaxes(R[a], -1, -2) @ R[b]
    R_err[ori] = Rk_t[ori] @ R[graph.b[ori]]
    q = geo.matrix_to_quat(R_err)  # (x, y, z, w), w ≥ 0
    out[rel | ori] = q[rel | ori, :3]
    return out


def all_chi2(graph: PoseGraph, R: Array | None = None, t: Array | None = None
             ) -> dict[str, float]:
    """χ² under every metric of :data:`METRICS`, keyed by name."""
    return {metric: chi2_as(metric, graph, R, t) for metric in METRICS}
