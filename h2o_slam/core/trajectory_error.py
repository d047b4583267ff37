"""How far an estimated trajectory is from the truth: ATE after a planar rigid alignment,
final-position error, and pairing of estimate and truth stamps.

Trajectories are position arrays ``(N, 2)`` or ``(N, 3)`` m (only x and y count) with int
ns stamps, as :mod:`h2o_slam.io.replay_outputs` reads and writes them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from h2o_slam.core.geometry import best_fit_transform


def align_planar(est_xy: Any, truth_xy: Any) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``(2, 2)`` and translation ``(2,)`` that best map ``est`` onto ``truth``.

    Least squares over corresponding points (Umeyama/Horn without scale, through
    :func:`~h2o_slam.core.geometry.best_fit_transform`): minimizes ``Σ ‖R eᵢ + t − gᵢ‖²``.
    Points are ``(N, 2)`` or wider (only x, y are used).

    Raises:
        ValueError: fewer than two points, or shapes that do not match.
    """
    a = np.asarray(est_xy, dtype=float)[:, :2]
    b = np.asarray(truth_xy, dtype=float)[:, :2]
    if a.shape != b.shape or len(a) < 2:
        raise ValueError(f"alignment needs two or more matching points, got {a.shape}, {b.shape}")
    pad = np.zeros((len(a), 1))
    R, t = best_fit_transform(np.hstack([a, pad]), np.hstack([b, pad]), np.ones(len(a)),
                              planar=True)
    return R[:2, :2], t[:2]


def ate_m(est_xy: Any, truth_xy: Any) -> float:
    """Absolute trajectory error: position RMSE (m) after :func:`align_planar`."""
    a = np.asarray(est_xy, dtype=float)[:, :2]
    b = np.asarray(truth_xy, dtype=float)[:, :2]
    R, t = align_planar(a, b)
    residual = a @ R.T + t - b
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))


def final_error_m(est_xy: Any, truth_xy: Any) -> float:
    """Distance (m) between the last estimated and the last true position, unaligned.

    Both trajectories start in the same frame (the robot's start), which is what makes the
    end point's drift meaningful without alignment.
    """
    a = np.asarray(est_xy, dtype=float)
    b = np.asarray(truth_xy, dtype=float)
    return float(np.hypot(*(a[-1, :2] - b[-1, :2])))


def match_stamps(stamps_ns: Any, truth_stamps_ns: Any, tolerance_ns: int) -> tuple[Any, Any]:
    """Index pairs ``(i, j)`` of each stamp and the nearest truth stamp within tolerance.

    Args:
        stamps_ns: ``(N,)`` int ns of an estimate.
        truth_stamps_ns: ``(M,)`` int ns, increasing.
        tolerance_ns: largest accepted ``|stamp − truth stamp|``.

    Returns:
        Two int arrays of equal length: estimate indices and truth indices.
    """
    s = np.asarray(stamps_ns, dtype=np.int64)
    g = np.asarray(truth_stamps_ns, dtype=np.int64)
    if not len(s) or not len(g):
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    right = np.clip(np.searchsorted(g, s), 0, len(g) - 1)
    left = np.clip(right - 1, 0, len(g) - 1)
    nearest = np.where(np.abs(g[left] - s) <= np.abs(g[right] - s), left, right)
    keep = np.abs(g[nearest] - s) <= tolerance_ns
    return np.flatnonzero(keep), nearest[keep]
