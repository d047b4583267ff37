"""False loop closures planted into a pose graph, for testing and benchmarking robust solvers.

The four kinds of Sünderhauf & Protzel ("Switchable constraints for robust pose graph SLAM",
IROS 2012; their Vertigo datasets), which the robust-SLAM literature has measured against
since:

* ``random`` — between two poses drawn anywhere in the graph;
* ``local`` — between a pose and one within ``local_window`` poses of it (the closures a
  place recogniser sends when the robot barely moved: the odometry chain between the ends
  is short and stiff, so each one is cheap to test but many agree with a bent chain);
* ``random_grouped`` / ``local_grouped`` — groups of ``group_size`` closures between
  consecutive poses ``(i + k, j + k)`` that share one false measurement: mutually
  consistent, as perceptual aliasing in a repeated corridor produces them.

Each false measurement is uniform in ±``span_m`` per translation axis with a uniformly
random heading (3-D graphs: a uniformly random rotation), and carries the graph's usual
loop-closure information (the median of its closures', the odometry's when it has none).
The planted edges follow the graph's own edges, so a stream in arrival order
(:func:`h2o_slam.core.modes.arrivals`) meets each at its newer end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EdgeKind, PoseGraph
from h2o_slam.core.robust import odometry_edges

OUTLIER_KINDS = ("random", "local", "random_grouped", "local_grouped")


@dataclass(frozen=True)
class Planted:
    """A graph with false closures appended, and which edges they are."""

    graph: PoseGraph
    outlier: np.ndarray  # bool per edge of ``graph``

    @property
    def num_outliers(self) -> int:
        """False closures planted."""
        return int(np.count_nonzero(self.outlier))


def plant_outliers(
    graph: PoseGraph, kind: str, count: int, seed: int = 0, group_size: int = 10,
    local_window: int = 20, span_m: float = 10.0,
) -> Planted:
    """A copy of ``graph`` with ``count`` false loop closures of ``kind`` appended.

    Raises:
        InputError: an unknown kind, a negative count, or a graph too small to hold them.
    """
    if kind not in OUTLIER_KINDS:
        raise InputError(
            f"unknown outlier kind {kind!r}; choose one of {', '.join(OUTLIER_KINDS)}")
    if count < 0:
        raise InputError(f"outlier count must be >= 0, got {count}")
    grouped = kind.endswith("_grouped")
    size = group_size if grouped else 1
    n = graph.num_nodes
    if n < 2 * size + 2:
        raise InputError(f"a graph of {n} poses cannot hold groups of {size} outliers")
    rng = np.random.default_rng(seed)
    a, b = _endpoints(rng, kind.startswith("local"), count, size, n, local_window)
    groups = (count + size - 1) // size
    meas_R, meas_t = _false_measurements(rng, graph.planar, groups, span_m)
    group = np.arange(count) // size
    info = np.broadcast_to(_loop_information(graph), (count, 6, 6))
    out = graph.with_edges(EdgeKind.RELATIVE, a, b, meas_R[group], meas_t[group], info)
    return Planted(out, np.arange(out.num_edges) >= graph.num_edges)


def _endpoints(rng: np.random.Generator, local: bool, count: int, size: int, n: int,
               window: int) -> tuple[np.ndarray, np.ndarray]:
    """Endpoints ``(a, b)`` of ``count`` closures in groups of ``size`` consecutive pairs;
    ``a < b``, never consecutive poses (those are odometry), never one pose twice."""
    groups = (count + size - 1) // size
    a = np.empty(groups, dtype=np.int64)
    b = np.empty(groups, dtype=np.int64)
    for g in range(groups):
        while True:
            i = int(rng.integers(0, n - size))
            if local:
                j = i + int(rng.integers(2, window + 1)) * int(rng.choice([-1, 1]))
            else:
                j = int(rng.integers(0, n - size))
            if 0 <= j < n - size and abs(i - j) >= 2:
                break
        a[g], b[g] = min(i, j), max(i, j)
    k = np.arange(count)
    return a[k // size] + k % size, b[k // size] + k % size


def _false_measurements(rng: np.random.Generator, planar: bool, count: int, span_m: float
                        ) -> tuple[np.ndarray, np.ndarray]:
    t = rng.uniform(-span_m, span_m, size=(count, 3))
    if planar:
        t[:, 2] = 0.0
        R = geo.yaw_to_matrix(rng.uniform(-np.pi, np.pi, size=count))
    else:
        q = rng.standard_normal((count, 4))  # a uniform rotation: a normalized 4-D Gaussian
        R = geo.quat_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))
    return np.asarray(R).reshape(count, 3, 3), t


def _loop_information(graph: PoseGraph) -> np.ndarray:
    """The median information of the graph's loop closures (its odometry's without any)."""
    rel = graph.kind == EdgeKind.RELATIVE
    odometry = odometry_edges(graph.kind, graph.a, graph.b)
    closures = rel & ~odometry
    pick = closures if closures.any() else rel
    return np.median(graph.info[pick], axis=0)
