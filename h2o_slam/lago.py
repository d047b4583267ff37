"""LAGO: linear approximation for planar pose graphs with full covariance (being written)."""

from __future__ import annotations

from h2o_slam.errors import InputError
from h2o_slam.geometry import Array
from h2o_slam.graph import PoseGraph


def lago_estimate(graph: PoseGraph) -> tuple[Array, Array]:
    """World poses ``(R, t)`` of the LAGO approximation of a planar graph."""
    raise InputError("LAGO is not available yet")
