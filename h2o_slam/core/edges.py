"""The solver's edge table: every edge's kind, endpoints, measurement, information and
whitening, in growable arrays that vector code reads as views.

An edge's whitening ``W`` (``Wᵀ W = w S``, its information in the solver's coordinates
scaled by its robust weight ``w``, 1 unless :mod:`h2o_slam.core.robust` lowers it) is
computed once, when the edge is stored, and rescaled when its weight changes: every update
that linearizes the edge uses it. A planar table also keeps every edge's measurement as
``(x, y, yaw)``, its information over those and the inverse: a loop closure's correction
inside a callback reads them for thousands of odometry edges at once (kitti_00's last loop:
converting and inverting them there took 2 of its 12.8 ms).
"""

from __future__ import annotations

import numpy as np

from h2o_slam.core.capacity import ArrayRef, ensure
from h2o_slam.core.geometry import Array, matrix_to_yaw


def whitening(info: Array, dof: np.ndarray) -> Array:
    """``W`` with ``Wᵀ W = S`` for information matrices ``S`` restricted to ``dof``."""
    S = info[..., dof[:, None], dof[None, :]]
    if S.ndim == 2:
        try:  # The common case, a positive definite matrix: Cholesky is the cheap factor.
            return np.asarray(np.linalg.cholesky(S).T, dtype=float)
        except np.linalg.LinAlgError:
            pass  # semi-definite (a GPS edge's rotation rows): the eigen factor below
    lam, U = np.linalg.eigh(S)
    return np.sqrt(np.maximum(lam, 0.0))[..., :, None] * np.swapaxes(U, -1, -2)


class EdgeTable:
    """Growable arrays of edges (amortized O(1) appends, array views for vector work)."""

    def __init__(self, p: int, capacity: int = 64) -> None:
        self.m = 0
        self.kind = np.zeros(capacity, dtype=np.int8)
        self.a = np.zeros(capacity, dtype=np.int64)
        self.b = np.zeros(capacity, dtype=np.int64)
        self.meas_R = np.zeros((capacity, 3, 3))
        self.meas_t = np.zeros((capacity, 3))
        self.info = np.zeros((capacity, 6, 6))
        self.W = np.zeros((capacity, p, p))
        self.W_unit = np.zeros((capacity, p, p))  # the whitening at weight 1
        self.weight = np.ones(capacity)
        self.planar = p == 3
        if self.planar:
            self.planar_meas = np.zeros((capacity, 3))
            self.planar_info = np.zeros((capacity, 3, 3))
            self.planar_cov = np.zeros((capacity, 3, 3))

    def append(
        self, kind: int, a: int, b: int, meas_R: Array, meas_t: Array, info: Array,
        dof: np.ndarray,
    ) -> int:
        """Store one edge and return its index."""
        self._reserve(self.m + 1)
        e = self.m
        self.kind[e], self.a[e], self.b[e] = kind, a, b
        self.meas_R[e], self.meas_t[e], self.info[e] = meas_R, meas_t, info
        self.W[e] = self.W_unit[e] = whitening(self.info[e], dof)
        self.weight[e] = 1.0
        if self.planar:
            self._store_planar(slice(e, e + 1), self.info[e:e + 1][:, dof[:, None], dof[None, :]])
        self.m += 1
        return e

    def extend(
        self, kind: np.ndarray, a: np.ndarray, b: np.ndarray, meas_R: Array, meas_t: Array,
        info: Array, dof: np.ndarray,
    ) -> None:
        """Store many edges at once (arrays with one row per edge), as :meth:`append` would
        one by one."""
        k = len(kind)
        end = self.m + k
        self._reserve(end)
        s = slice(self.m, end)
        self.kind[s], self.a[s], self.b[s] = kind, a, b
        self.meas_R[s], self.meas_t[s], self.info[s] = meas_R, meas_t, info
        S = self.info[s][:, dof[:, None], dof[None, :]]
        try:  # all positive definite, the common case: the factor append's Cholesky gives
            self.W[s] = np.swapaxes(np.linalg.cholesky(S), -1, -2)
        except np.linalg.LinAlgError:
            self.W[s] = [whitening(x, dof) for x in self.info[s]]
        self.W_unit[s] = self.W[s]
        self.weight[s] = 1.0
        if self.planar:
            self._store_planar(s, S)
        self.m = end

    def set_weights(self, edges: np.ndarray | slice, weights: Array) -> None:
        """Scale the information of ``edges`` by ``weights`` (each in [0, 1])."""
        self.weight[edges] = weights
        self.W[edges] = np.sqrt(self.weight[edges])[:, None, None] * self.W_unit[edges]

    def _store_planar(self, s: slice, S: Array) -> None:
        """The planar copies of edges ``s``, ``S`` their information over ``(x, y, yaw)``."""
        self.planar_meas[s] = np.column_stack(
            [self.meas_t[s, 0], self.meas_t[s, 1], matrix_to_yaw(self.meas_R[s])])
        self.planar_info[s] = S
        try:
            self.planar_cov[s] = np.linalg.inv(S)
        except np.linalg.LinAlgError:  # a GPS fix's information has no yaw
            self.planar_cov[s] = np.linalg.pinv(S)

    def _reserve(self, size: int) -> None:
        """Room for ``size`` edges: capacity at least doubles, so appends stay O(1)."""
        ensure(self.arrays(), size)

    def arrays(self) -> list[ArrayRef]:
        """The per-edge arrays as ``(owner, name, fill)`` (:mod:`h2o_slam.core.capacity`)."""
        names = ["kind", "a", "b", "meas_R", "meas_t", "info", "W", "W_unit", "weight"]
        if self.planar:
            names += ["planar_meas", "planar_info", "planar_cov"]
        return [(self, name, 0) for name in names]
