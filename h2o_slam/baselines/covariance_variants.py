"""The three covariance variants of a planar pose graph in Carlone et al.'s Table 1.

Carlone, Yin, Rosa and Yuan, *Graph optimization with unstructured covariance*
(SIMPAR 2014, §4) test every data set in
three variants that keep its relative pose measurements and change their covariance:

* ``"I"`` — identity covariance, ``ε ~ N(0, I₃)``;
* ``"P_s"`` — a *structured* covariance (the paper's (4): no position–orientation
  correlation). The paper gives no values; here the graph's own covariance with its
  position–orientation cross terms removed (the marginal ``P_Δ`` and ``P_δ`` blocks kept).
  Its public CSAIL and Manhattan (M3500) files are already of this form, so for them this
  variant is the file itself;
* ``"P_f"`` — a *full* covariance from the standard odometry model (Thrun, Burgard and Fox,
  §5.4): the relative pose ``(Δx, Δy, δ)`` in the frame of the first node is a rotation
  ``γ_r1 = atan2(Δy, Δx)``, a translation ``γ_t = ‖(Δx, Δy)‖`` and a second rotation
  ``γ_r2 = δ - γ_r1``; with independent ``σ = (0.05 rad, 0.05 m, 0.01 rad)`` on the three
  (the paper's values), first-order propagation gives ``P_f = G diag(σ²) Gᵀ``, ``G`` the
  Jacobian of :func:`odometry_pose`.

``G`` is singular at ``γ_t = 0`` (``det G = -γ_t``: the direction of a zero translation is
undefined), so it is evaluated at ``max(γ_t, min_trans_m)``; a pure rotation then gets a
tight but finite position covariance across the (arbitrary) heading. The paper does not
say how it treated such edges.

Covariances are built in the paper's frame (translation error in the frame of the first
node); the project stores information in the frame of the measurement (doc/design.md,
Conventions), so each one is rotated back (the inverse of
:func:`h2o_slam.core.lago.paper_information`). The graph's estimate and measurements are
kept as they are.
"""

from __future__ import annotations

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.geometry import Array
from h2o_slam.core.graph import EdgeKind, PoseGraph
from h2o_slam.core.lago import paper_information

#: The variants of the paper's Table 1, in its order.
VARIANTS = ("I", "P_s", "P_f")

#: Standard deviations of the odometry model's ``(γ_r1 [rad], γ_t [m], γ_r2 [rad])`` (§4).
ODOMETRY_SIGMAS = (0.05, 0.05, 0.01)

#: Smallest translation (m) at which the odometry model's Jacobian is evaluated.
MIN_TRANS_M = 0.01


def odometry_parameters(delta_xy: Array, delta_yaw_rad: Array) -> Array:
    """``(γ_r1, γ_t, γ_r2)`` of relative poses, shape ``(m, 3)``.

    Args:
        delta_xy: translations in the frame of the first node (m), shape ``(m, 2)``.
        delta_yaw_rad: relative yaws (rad), shape ``(m,)``; ``γ_r2`` is wrapped to
            ``(-π, π]``.
    """
    delta_xy = np.asarray(delta_xy, dtype=float).reshape(-1, 2)
    rot1 = np.arctan2(delta_xy[:, 1], delta_xy[:, 0])
    trans = np.hypot(delta_xy[:, 0], delta_xy[:, 1])
    rot2 = geo.wrap_angle(np.asarray(delta_yaw_rad, dtype=float).reshape(-1) - rot1)
    return np.column_stack([rot1, trans, rot2])


def odometry_pose(params: Array) -> Array:
    """The relative pose ``(Δx, Δy, δ)`` of odometry parameters ``(γ_r1, γ_t, γ_r2)``;
    shapes ``(m, 3)`` to ``(m, 3)`` (``δ`` not wrapped)."""
    params = np.asarray(params, dtype=float).reshape(-1, 3)
    rot1, trans, rot2 = params[:, 0], params[:, 1], params[:, 2]
    return np.column_stack([trans * np.cos(rot1), trans * np.sin(rot1), rot1 + rot2])


def odometry_jacobian(params: Array, min_trans_m: float = MIN_TRANS_M) -> Array:
    """``∂ odometry_pose / ∂ (γ_r1, γ_t, γ_r2)``, shape ``(m, 3, 3)``, with the
    translation floored at ``min_trans_m`` (module docstring)."""
    params = np.asarray(params, dtype=float).reshape(-1, 3)
    rot1 = params[:, 0]
    trans = np.maximum(params[:, 1], min_trans_m)
    c, s = np.cos(rot1), np.sin(rot1)
    G = np.zeros((len(params), 3, 3))
    G[:, 0, 0], G[:, 0, 1] = -trans * s, c
    G[:, 1, 0], G[:, 1, 1] = trans * c, s
    G[:, 2, 0] = G[:, 2, 2] = 1.0
    return G


def odometry_covariance(
    delta_xy: Array, delta_yaw_rad: Array, sigmas: tuple[float, float, float] = ODOMETRY_SIGMAS,
    min_trans_m: float = MIN_TRANS_M,
) -> Array:
    """``P_f`` of relative poses in the paper's frame: ``G diag(σ²) Gᵀ``, shape ``(m, 3, 3)``
    over ``(Δx [m], Δy [m], δ [rad])``; ``sigmas`` are of ``(γ_r1 [rad], γ_t [m],
    γ_r2 [rad])``.

    Raises:
        ValueError: a standard deviation or ``min_trans_m`` is not positive.
    """
    if min(sigmas) <= 0.0 or min_trans_m <= 0.0:
        raise ValueError("odometry standard deviations and min_trans_m must be positive")
    G = odometry_jacobian(odometry_parameters(delta_xy, delta_yaw_rad), min_trans_m)
    var = np.square(np.asarray(sigmas, dtype=float))
    P = np.einsum("mij,j,mkj->mik", G, var, G)
    return 0.5 * (P + P.transpose(0, 2, 1))  # exactly symmetric (einsum's sums may differ)


def structured_covariance(omega_paper: Array) -> Array:
    """The structured (4) part of covariances given as information matrices in the paper's
    frame, shape ``(m, 3, 3)``: the marginal ``P_Δ`` and ``P_δ`` kept, their cross terms
    zeroed."""
    P = np.linalg.inv(np.asarray(omega_paper, dtype=float))
    P[:, :2, 2] = P[:, 2, :2] = 0.0
    return P


def project_information(omega_paper: Array, meas_R: Array) -> Array:
    """Inverse of :func:`h2o_slam.core.lago.paper_information`: the project's 6×6 information
    matrices, shape ``(m, 6, 6)``, from 3×3 information in the paper's frame,
    ``S = diag(R_Kᵀ, 1) Ω diag(R_K, 1)`` (``R_K`` the measured rotation about z)."""
    omega_paper = np.asarray(omega_paper, dtype=float)
    m = len(omega_paper)
    rot = np.zeros((m, 3, 3))
    rot[:, :2, :2] = np.asarray(meas_R, dtype=float)[:, :2, :2]
    rot[:, 2, 2] = 1.0
    S = rot.transpose(0, 2, 1) @ omega_paper @ rot
    out = np.zeros((m, 6, 6))
    dof = geo.PLANAR_DOF
    out[:, dof[:, None], dof[None, :]] = 0.5 * (S + S.transpose(0, 2, 1))
    return out


def variant_covariance(graph: PoseGraph, variant: str) -> Array:
    """The paper-frame covariance of every edge of ``graph`` in ``variant`` (one of
    :data:`VARIANTS`), shape ``(M, 3, 3)``.

    Raises:
        ValueError: ``variant`` is unknown.
        InputError: the graph is 3-D or has global edges.
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    if not graph.planar:
        raise InputError("covariance variants are defined for planar graphs only")
    if np.any(graph.kind != EdgeKind.RELATIVE):
        raise InputError("covariance variants are defined for relative edges only")
    m = graph.num_edges
    if variant == "I":
        return np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    if variant == "P_s":
        return structured_covariance(paper_information(graph.info, graph.meas_R))
    yaw = geo.matrix_to_yaw(graph.meas_R)
    return odometry_covariance(graph.meas_t[:, :2], yaw)


def with_variant(graph: PoseGraph, variant: str) -> PoseGraph:
    """A copy of ``graph`` whose information matrices are those of ``variant`` (one of
    :data:`VARIANTS`); measurements and estimate unchanged.

    Raises:
        ValueError: ``variant`` is unknown.
        InputError: the graph is 3-D or has global edges.
    """
    P = variant_covariance(graph, variant)
    out = graph.copy()
    out.info = project_information(np.asarray(np.linalg.inv(P), dtype=float), graph.meas_R)
    return out
