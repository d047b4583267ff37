"""The pose tree (thesis 3.3.1): world poses and trees rebuilt from them."""

from __future__ import annotations

import numpy as np

from h2o_slam import geometry as geo
from h2o_slam.tree import EARTH, PoseTree


def _orthonormality_error(R: np.ndarray) -> float:
    return float(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max())


def test_trees_rebuilt_from_their_world_poses_stay_rotations() -> None:
    # Every exact solve seeds its tree from the last solution's world poses: on a deep
    # chain the rounding of each level compounded to NaN within 30 rebuilds.
    rng = np.random.default_rng(3)
    n = 20000
    parent = np.arange(n) - 1
    parent[0] = EARTH
    tree = PoseTree.from_local(parent, geo.so3_exp(rng.normal(size=(n, 3))),
                               rng.normal(size=(n, 3)))
    for _ in range(30):
        tree = PoseTree.from_parents(parent, *tree.world_poses())
    R, t = tree.world_poses()
    assert np.all(np.isfinite(t))
    assert _orthonormality_error(R) < 1e-9
