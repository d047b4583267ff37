"""A planar g2o graph fed through the node's back end, as a robot would feed it.

:func:`stream_graph` drives :class:`h2o_slam.ros.mapper.Mapper` (``h2o_node`` without ROS)
with the graph's odometry chain as odometry samples one second apart (each one a keyframe,
so keyframe ``k`` is node ``k``), its loop closures by node id at the arrival of their newer
end, and its GPS fixes by stamp. Each message is its own callback ending in one budgeted
step, as ``h2o_node`` handles it (the odometry sample, then each closure or fix that
arrives with it), with :data:`GAP_S` between callbacks, as an executor waits for the next
message. Then it idles (budgeted steps, as the node's idle timer) and solves
exactly (``~/exact_solve``). The mapper's odometry noise model is its own
(``MapperConfig``), so its map is compared with its own map of the outlier-free graph.
"""

from __future__ import annotations

import resource
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EdgeKind, PoseGraph
from h2o_slam.core.modes import arrivals
from h2o_slam.core.robust import odometry_edges
from h2o_slam.ros.mapper import Mapper, MapperConfig

NS = 1_000_000_000
START_NS = 1_700_000_000 * NS

#: Seconds between one callback's end and the next one's start: a node's executor waits for
#: the next message (odometry at 20-100 Hz leaves 5-45 ms), 1 ms is a node kept almost
#: saturated. Callbacks back to back with no wait never let the callbacks' thread sleep,
#: and the scheduler time-sliced it with the worker process that had woken on its core:
#: measured on CSAIL (8 rows of bench/robust.py), 5 rows with callbacks of 12-13 ms at a
#: 5 ms budget, the thread waiting 8-12 ms of them (``/proc/<tid>/schedstat``); with 1 ms
#: between callbacks, none above 4.63 ms.
GAP_S = 1e-3


@dataclass
class StreamResult:
    """The mapper's map after the stream, the idle steps and its exact solve.

    Attributes:
        R, t: world poses of the graph's nodes.
        weights: the mapper's final weight of each of the graph's edges (0 for a closure it
            refused outright).
        callback_ms: wall time of each message's callback (an odometry sample, a closure
            or a fix, and one budgeted step).
        callback_cpu_ms: the CPU time the callbacks' thread spent in each (without time
            it waited for a core; a pause of the virtual machine's host may still be
            charged to it, in part or whole: measured, 19.4 ms of a 28 ms callback whose
            work takes 0.5 ms).
        callback_stolen: whether the host took CPU time from this machine during each
            callback (:func:`stolen_during`). All False where there is no steal counter.
        callback_off_ms: time of each callback in which its thread neither ran nor waited
            for a core although it never blocked (:func:`thread_clocks`): the virtual CPU
            itself was paused by the host. 0 where the kernel keeps no schedstat.
        seconds: wall time of the whole stream, idle and exact solve.
    """

    R: np.ndarray
    t: np.ndarray
    weights: np.ndarray
    callback_ms: np.ndarray
    callback_cpu_ms: np.ndarray
    callback_stolen: np.ndarray
    callback_off_ms: np.ndarray
    seconds: float


def odometry_poses(graph: PoseGraph) -> np.ndarray:
    """``(x, y, yaw)`` of each node by composing the odometry chain from node 0."""
    odo = np.flatnonzero(odometry_edges(graph.kind, graph.a, graph.b))
    step = {}
    for e in odo.tolist():
        d = np.array([graph.meas_t[e, 0], graph.meas_t[e, 1],
                      float(geo.matrix_to_yaw(graph.meas_R[e]))])
        a, b = int(graph.a[e]), int(graph.b[e])
        step[max(a, b)] = d if b > a else geo.planar_between(d, np.zeros(3))
    poses = np.zeros((graph.num_nodes, 3))
    for k in range(1, graph.num_nodes):
        poses[k] = geo.planar_compose(poses[k - 1], step.get(k, np.zeros(3)))
    return poses


def fitted_odometry(graph: PoseGraph) -> dict[str, float]:
    """The mapper's odometry noise model (``MapperConfig.odom_*``) fitted to the graph's
    odometry information, as a user calibrates the node for their robot: translation σ per
    metre the median over increments of at least 0.1 m; heading σ per metre the median over
    those that turn less than 0.05 rad, and per radian turned the median of what remains
    over the turning ones (none below 0)."""
    odo = np.flatnonzero(odometry_edges(graph.kind, graph.a, graph.b))
    dof = geo.PLANAR_DOF
    cov = np.linalg.inv(graph.info[odo][:, dof[:, None], dof[None, :]])
    dist = np.linalg.norm(graph.meas_t[odo, :2], axis=1)
    turn = np.abs(geo.matrix_to_yaw(graph.meas_R[odo]))
    sig_t = np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))
    sig_r = np.sqrt(cov[:, 2, 2])
    moving = dist >= 0.1
    per_m = float(np.median(sig_t[moving] / dist[moving])) if np.any(moving) else 0.05
    straight = moving & (turn < 0.05)
    yaw_per_m = float(np.median(sig_r[straight] / dist[straight])) if np.any(straight) else 0.0
    turning = turn >= 0.05
    yaw_per_rad = (float(np.median(np.maximum(sig_r[turning] - yaw_per_m * dist[turning], 0.0)
                                   / turn[turning])) if np.any(turning) else 0.0)
    return {"odom_sigma_per_m": per_m, "odom_yaw_sigma_per_m": yaw_per_m,
            "odom_yaw_sigma_per_rad": yaw_per_rad}


def stream_graph(graph: PoseGraph, budget_ms: float = 5.0, idle_s: float = 1.0,
                 background: str = "process", odometry_model: dict[str, float] | None = None
                 ) -> StreamResult:
    """Feed ``graph`` (planar) through a :class:`Mapper`; see the module docstring.
    ``odometry_model``: ``MapperConfig`` odometry noise fields (:func:`fitted_odometry`);
    ``None``: the mapper's defaults."""
    poses = odometry_poses(graph)
    odometry = odometry_edges(graph.kind, graph.a, graph.b)
    config = MapperConfig(keyframe_distance=0.0, keyframe_angle=0.0,
                          keyframe_period=0.5, budget_ms=budget_ms, background=background,
                          **(odometry_model or {}))
    mapper = Mapper(config)
    mapped = np.full(graph.num_edges, -1)
    times: list[tuple[float, float, float, int]] = []
    begin = time.perf_counter()
    try:
        for k, edges in enumerate(arrivals(graph)):
            times.append(_callback(mapper, lambda k=k: mapper.add_odometry(
                START_NS + k * NS, poses[k])))
            for e in edges.tolist():
                if not odometry[e]:
                    times.append(_callback(mapper, lambda e=e: mapped.__setitem__(
                        e, _add_edge(mapper, graph, e))))
        until = time.perf_counter() + idle_s
        while time.perf_counter() < until:
            mapper.step(mapper.config.budget_s)
        mapper.exact_solve()
        seconds = time.perf_counter() - begin
        weights = _graph_weights(mapper, graph, mapped, odometry)
        R, t = mapper.h2o.solver.world_poses()
    finally:
        mapper.close()
    start, wall, cpu, steal, off = (np.array(column) for column in zip(*times, strict=True))
    stolen = stolen_during(start, start + 1e-3 * wall, steal, host_steal_ticks())
    return StreamResult(R, t, weights, wall, cpu, stolen, off, seconds)


#: Seconds after a callback in which the host's theft of its time may still be counted: the
#: guest kernel adds stolen time to ``/proc/stat`` at its next tick on that CPU (a CPU with
#: nothing to run has no tick until it wakes). Measured with a tight loop alone on this
#: machine for 60 s: its two pauses over 10 ms (10.1 and 11.6 ms, the loop's thread doing
#: nothing else) both had the counter advance within 30 ms, as it does in about 1 of 6,000
#: other ms.
STEAL_WINDOW_S = 0.03


def stolen_during(start: np.ndarray, end: np.ndarray, steal: np.ndarray, final: int
                  ) -> np.ndarray:
    """Whether the host's steal counter advanced from each callback's start (``steal``,
    read then) to :data:`STEAL_WINDOW_S` after its ``end``: the reading at the first
    callback to start that late, or ``final`` (read after the stream)."""
    later = np.searchsorted(start, end + STEAL_WINDOW_S)
    after = np.append(steal, final)[later]
    return after > steal


def host_steal_ticks() -> int:
    """The machine's stolen CPU time so far (``/proc/stat``, in 10 ms ticks): time the
    hypervisor gave this virtual machine's CPUs to others. 0 where there is none."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return 0
    return int(fields[8]) if len(fields) > 8 and fields[0] == "cpu" else 0


def thread_clocks() -> tuple[float, float, int]:
    """The calling thread's time on a CPU and waiting in the run queue (s, from
    ``/proc/thread-self/schedstat``; 0 where there is none) and its voluntary context
    switches so far."""
    try:
        with open("/proc/thread-self/schedstat") as f:
            run_ns, wait_ns = (int(x) for x in f.read().split()[:2])
    except (OSError, ValueError):
        run_ns = wait_ns = 0
    return 1e-9 * run_ns, 1e-9 * wait_ns, resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw


def _callback(mapper: Mapper, handle: Callable[[], object]
              ) -> tuple[float, float, float, int, float]:
    """One message's callback as ``h2o_node`` runs it: ``handle`` it, then one step with
    what is left of the budget (the callback as a whole in budget); its start (s), wall and
    CPU time (ms), the host's steal counter at its start and the time its thread was off
    every CPU without blocking (ms; see :attr:`StreamResult.callback_off_ms`), after which
    the executor waits :data:`GAP_S` for the next message."""
    steal = host_steal_ticks()
    run, wait, switches = thread_clocks()
    cpu = time.thread_time()
    start = time.perf_counter()
    handle()
    mapper.callback_step(start)
    elapsed = time.perf_counter() - start
    cpu_ms = 1e3 * (time.thread_time() - cpu)
    run_end, wait_end, switches_end = thread_clocks()
    # A thread that never blocked was running or waiting for a core all the time, as far
    # as this kernel knows: the rest is time the host did not run the virtual CPU.
    off = 0.0
    if switches_end == switches and run_end > run:
        off = max(elapsed - (run_end - run) - (wait_end - wait), 0.0)
    time.sleep(GAP_S)
    return start, 1e3 * elapsed, cpu_ms, steal, 1e3 * off


def _add_edge(mapper: Mapper, graph: PoseGraph, e: int) -> int:
    """A loop closure or GPS fix of the graph into the mapper; its edge there (-1: refused)."""
    try:
        if graph.kind[e] == EdgeKind.POSITION:
            cov = np.eye(3)
            cov[:2, :2] = np.linalg.inv(graph.info[e][:2, :2])
            edge = mapper.add_gps(START_NS + int(graph.b[e]) * NS, graph.meas_t[e], cov)
        else:
            delta = np.array([graph.meas_t[e, 0], graph.meas_t[e, 1],
                              float(geo.matrix_to_yaw(graph.meas_R[e]))])
            cov = np.linalg.inv(graph.info[e][np.ix_(geo.PLANAR_DOF, geo.PLANAR_DOF)])
            edge = mapper.add_loop_closure(int(graph.a[e]), int(graph.b[e]), delta, cov)
    except InputError:
        return -1
    return -1 if edge is None else int(edge)


def _graph_weights(mapper: Mapper, graph: PoseGraph, mapped: np.ndarray,
                   odometry: np.ndarray) -> np.ndarray:
    weights = np.ones(graph.num_edges)
    solver_weight = mapper.h2o.solver.weight
    closures = ~odometry
    weights[closures] = np.where(mapped[closures] >= 0,
                                 solver_weight[np.maximum(mapped[closures], 0)], 0.0)
    return weights
