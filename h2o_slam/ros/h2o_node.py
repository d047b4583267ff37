"""``h2o_node``: the H₂O back end as a ROS 2 node (a thin shell around :mod:`h2o_slam.ros.mapper`).

Subscribes to odometry (keyframes), loop closures (``nav_msgs/Odometry`` in the convention
of :mod:`msg_adapters.loop_closure`) and ``sensor_msgs/NavSatFix``; runs one solver step
per callback within ``budget_ms``; publishes the graph (PoseArray, Path, MarkerArray,
reliable and transient-local), the latest optimized pose, ``map → odom`` (on ``/tf`` and
as a TransformStamped topic) and ``/diagnostics``. The README lists every topic,
parameter and service.

For replay, every subscription callback is a public ``on_*`` method that takes rclpy or
rosbags messages, and every publication goes through :meth:`H2ONode.emit`, which also
hands the message to :attr:`H2ONode.sink` when one is set. Output stamps come from input
stamps, never the wall clock.

No input ends the node: every subscription callback, timer, service and parameter callback
runs behind the boundary of the shell both nodes share (:class:`ros_node_base.node.NodeBase`),
which turns any exception into a logged rejection counted by reason in ``/diagnostics``
(``rejected <input>: unexpected <Type>`` for anything but the package's own errors, which
name their reason). Parameters come from one typed tree,
:class:`h2o_slam.ros.node_config.H2ONodeConfig`: read as one snapshot (:attr:`H2ONode.config`),
changed at run time as a whole.
"""

from __future__ import annotations

import gc
import math
import os
import re
import sys
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import NavSatFix
from std_srvs.srv import SetBool, Trigger
from visualization_msgs.msg import MarkerArray

import msg_adapters as ma
from h2o_slam.core import geometry as geo
from h2o_slam.core import warmup
from h2o_slam.core.errors import H2OError, InputError
from h2o_slam.core.graph import EdgeKind, edge_chi2
from h2o_slam.core.timing import CallbackTimes, CostShare, InputHealth
from h2o_slam.ros.mapper import Mapper, restore
from h2o_slam.ros.node_config import H2ONodeConfig
from h2o_slam.ros.realtime import fifo_callbacks
from h2o_slam.ros.realtime import restore as restore_scheduling
from ros_node_base.main import run_node
from ros_node_base.node import NodeBase

NODE_NAME = "h2o_node"

#: The inputs, as /diagnostics names them.
INPUTS = ("odometry", "loop_closure", "gps")

#: Numbers in rejection reasons, replaced so that one reason is one diagnostics key.
_NUMBER = re.compile(r"[-+]?\d[\d.]*(e[-+]?\d+)?")


class H2ONode(NodeBase[H2ONodeConfig]):
    """The H₂O back end as a ROS 2 node: odometry, loop closures and GPS fixes in; the
    optimized graph, pose, ``map → odom`` and ``/diagnostics`` out.

    Parameters, the boundary, the input counts and the outputs are the shell's
    (:class:`ros_node_base.node.NodeBase`); :attr:`config` is an :class:`H2ONodeConfig`
    (the README lists its parameters) and the mapping itself is :attr:`mapper`'s. Every
    input is held while the compiled kernels load, then handled and timed behind the
    boundary; a bad message is logged, counted and skipped.

    Args:
        **kwargs: passed to :class:`rclpy.node.Node` (``context``, ``namespace``,
            ``parameter_overrides``, ``cli_args``, ...).

    Attributes:
        mapper: the back end without ROS (keyframes, gated loop closures, GPS, the solver).
        paused: inputs are counted as discarded instead of handled (the ``~/pause`` service).
        times, idle_times: the input callbacks' and the idle steps' time against their
            budgets.
        rejected: inputs the boundary rejected, by reason (the mapper counts those it
            refuses itself; ``/diagnostics`` reports both).
        held_while_warming: inputs held while the kernels loaded.
    """

    expected_errors = (H2OError,)

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, H2ONodeConfig, **kwargs)
        self._held: deque[tuple[str, Callable[[], None]]] = deque()
        self.held_while_warming = 0
        self.paused = False
        self.times = CallbackTimes()
        self.idle_times = CallbackTimes()
        self.rejected: Counter[str] = Counter()
        #: The mapper's rejection count when the input being handled came in (None outside).
        self._mapper_rejections: int | None = None
        self._last_gps_ns: int | None = None
        self._last_stamp_ns = 0
        self._graph_dirty = True
        self._reset_load_state()
        self._make_interfaces()
        # The compiled kernels load (or, on a first start after the sources changed, compile)
        # beside the executor: the node answers at once and holds its inputs until then.
        # Started before the mapper, whose solver would otherwise load them here.
        warmup.warm_up_in_background()
        # After the warm-up thread started (it keeps the default policy: loading the kernels
        # at a real-time priority would hold a core from everything else for seconds).
        self.realtime = fifo_callbacks(self.config.realtime_priority)
        if self.config.realtime_priority and not self.realtime.applied:
            self.get_logger().warning(f"realtime_priority: {self.realtime.words}")
        self._started_s = time.perf_counter()
        self.mapper = self._start_mapper()
        self._datum = self._configured_datum()
        self._warming_timer = self.create_timer(
            WARMING_PERIOD_S, self.boundary("warming_timer", self._warming_tick))
        self._log_ready()

    def destroy_node(self) -> None:
        """Destroy the node and let the garbage collector reclaim it.

        The solver freezes the collector after each step (``OnlineConfig.freeze_gc``), which
        would keep this node's reference cycles, and with them its DDS participant, alive
        for the rest of the process.
        """
        self.mapper.close()
        super().destroy_node()
        restore_scheduling(self.realtime)
        gc.unfreeze()
        gc.collect()

    # -- set-up -------------------------------------------------------------------------------

    def _start_mapper(self) -> Mapper:
        # A damaged map ends the start with one line (restore validates everything a timer
        # would later use); a map never saved is a new graph.
        path = self.config.map_file
        if self.config.load_map_on_start and path:
            mapper = restore(path, self.config.mapper)
            if mapper is not None:
                self.get_logger().info(
                    f"continuing the graph of {path}: {mapper.num_nodes} nodes")
                return mapper
            self.get_logger().info(f"no map saved at {path} yet: starting a new graph")
        return Mapper(self.config.mapper)

    def _reset_load_state(self) -> None:
        """Input health, the cached map->odom correction and χ², and the rate limits of the
        outputs whose cost grows with the graph."""
        c = self.config
        late_ms, share = c.input_late_ms, c.output_time_share
        self.health = {"odometry": InputHealth(late_ms), "gps": InputHealth(late_ms)}
        self._last_odom_handled_ns = 0
        #: ``map -> odom`` as of the last refresh (by the transform timer, or on demand).
        self._map_to_odom: np.ndarray | None = None
        self._map_revision = -1
        self._chi2_cache: dict[str, object] | None = None
        self._chi2_at_s = 0.0
        self.shares = {
            "graph": CostShare(c.graph_publish_period, share),
            "map_to_odom": CostShare(c.transform_publish_period, share),
            "chi2": CostShare(c.diagnostics_period, share),
        }
        self.idle_yielded = 0

    def _configured_datum(self) -> ma.Datum | None:
        """The restored map's datum, else the parameter's (``None``: the first fix's)."""
        if self.mapper.datum is not None:
            return ma.Datum(*self.mapper.datum)
        return self.config.messages.configured_datum

    def rejection_reason(self, what: str, exc: Exception) -> str:
        """``<input>: <message>``, numbers replaced: one kind of problem, one name."""
        return f"{what}: {_NUMBER.sub('#', str(exc))[:80]}"

    def record_rejection(self, reason: str, exc: Exception) -> None:
        """Counted in :attr:`rejected`, unless the mapper counted it under its own reason."""
        before = self._mapper_rejections
        counted = before is not None and sum(self.mapper.rejected.values()) != before
        if not (isinstance(exc, H2OError) and counted):
            self.rejected[reason] += 1

    def _make_interfaces(self) -> None:
        c = self.config
        sensor = QoSProfile(depth=c.input_queue_depth, reliability=ReliabilityPolicy.BEST_EFFORT)
        reliable = QoSProfile(depth=c.loop_closure_queue_depth,
                              reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.subscribe("odometry", Odometry, "odom", self.on_odom, sensor)
        self.subscribe("loop_closure", Odometry, "loop_closure", self.on_loop_closure, reliable)
        self.subscribe("gps", NavSatFix, "gps/fix", self.on_gps, sensor)
        self.advertise("poses", PoseArray, "~/graph/poses", latched)
        self.advertise("path", PathMsg, "~/graph/path", latched)
        self.advertise("markers", MarkerArray, "~/graph/markers", latched)
        self.advertise("pose", PoseStamped, "~/pose", 10)
        self.advertise("map_to_odom", TransformStamped, "~/map_to_odom", 10)
        self.advertise_diagnostics()
        self.advertise_tf("map->odom goes to ~/map_to_odom only, not /tf")
        guard = self.boundary
        self.create_service(Trigger, "~/save_map", guard("save_map", self._srv_save))
        self.create_service(Trigger, "~/exact_solve", guard("exact_solve", self._srv_exact))
        self.create_service(Trigger, "~/reset", guard("reset", self._srv_reset))
        self.create_service(SetBool, "~/pause", guard("pause", self._srv_pause))
        self.create_timer(c.graph_publish_period, guard("graph_timer", self._graph_timer))
        self.create_timer(c.transform_publish_period,
                          guard("map_to_odom_timer", self._map_to_odom_timer))
        self.create_timer(c.diagnostics_period,
                          guard("diagnostics_timer", self._diagnostics_timer))
        self.create_timer(c.idle_period, guard("idle_timer", self._idle_timer))

    def _log_ready(self) -> None:
        """One line at start-up: the node is up, the topics it reads and writes, and the
        parameters that decide its cost."""
        out, c = self.output_topics, self.config
        budget = c.mapper.budget_ms
        solves = "exact solves in a worker process" if budget > 0.0 else (
            "every edge solved in full, deterministic")
        tf = " and /tf" if "tf" in out and c.publish_tf else ""
        self.get_logger().info(
            f"{self.get_fully_qualified_name()} ready: in "
            + ", ".join(f"{topic} ({what})" for what, topic in self.input_topics.items())
            + f"; out {out['poses']}, {out['path']}, {out['markers']}, {out['pose']}, "
            f"{out['map_to_odom']}{tf}, {out['diagnostics']}; budget_ms {budget:g} "
            f"({solves}), robust {str(c.mapper.robust).lower()}, queue depths "
            f"{c.input_queue_depth} (odometry, GPS) / "
            f"{c.loop_closure_queue_depth} (loop closures), callbacks at "
            f"{self.realtime.words if self.realtime.applied else 'the default policy'}, "
            f"map_frame {c.map_frame}, map_file {c.map_file or 'unset'}")

    def on_config_change(self, old: H2ONodeConfig) -> None:
        """The mapper takes its new settings whole (a budget, keyframe or gate change)."""
        self.mapper.config = self.config.mapper

    # -- inputs -------------------------------------------------------------------------------

    def _guarded(self, what: str, handler: Callable[[], None]) -> None:
        """The boundary of every input callback: while the kernels load the input is held
        (in order, none dropped), then handled (:meth:`_handle`)."""
        if not warmup.is_ready():
            self._held.append((what, handler))
            self.held_while_warming += 1
            return
        self._release_held()
        self._handle(what, handler)

    def _release_held(self) -> None:
        """Handle the inputs held while the kernels loaded, in their order of arrival."""
        while self._held:
            self._handle(*self._held.popleft())

    def _handle(self, what: str, handler: Callable[[], None]) -> None:
        """Run one input's handling behind the boundary, timing it. Validation comes first in
        the mapper, so a refused input leaves nothing behind in the track or the graph."""
        start = time.perf_counter()
        self._mapper_rejections = sum(self.mapper.rejected.values())
        if self.paused:
            self.inputs[what].discarded += 1
        else:
            self.guarded(what, handler)
        self._mapper_rejections = None
        for held, reason in self.mapper.released_errors:  # taken in earlier, refused now
            self.inputs[held].move("rejected")
            self.log_throttled(f"held {held}", f"held {held} rejected: {reason}")
        self.mapper.released_errors.clear()
        elapsed_ms = 1e3 * (time.perf_counter() - start)
        budget_ms = self.config.mapper.budget_ms
        self.times.add(elapsed_ms, None if self.paused or budget_ms == 0.0 else budget_ms)

    def _step(self, start: float) -> None:
        self.mapper.callback_step(start)
        self._graph_dirty = True

    def idle_step(self) -> None:
        """Work the input callbacks left, in time the node would otherwise sit idle: edges
        that did not fit (e.g. a GPS edge whose path is longer than ``budget_ms`` allows),
        and the exact solution of the graph (merged, or started in the worker). It delays
        the next input by at most ``idle_budget_ms`` and never runs when nothing waits, so
        it costs nothing once the map is at its optimum."""
        budget_ms = self.config.idle_budget_ms
        h2o = self.mapper.h2o
        waiting = h2o.pending or h2o.converger.busy or h2o.converger.outside()
        if self.paused or budget_ms == 0.0 or not waiting:
            return
        start = time.perf_counter()
        self.mapper.step(1e-3 * budget_ms)
        self.idle_times.add(1e3 * (time.perf_counter() - start), budget_ms)
        self._graph_dirty = True

    def _arrived(self, what: str, stamp_ns: int) -> None:
        """Count the messages of ``what`` missing before this one, and whether it is late."""
        now = time.monotonic_ns()
        self.health[what].observe(stamp_ns, now)
        self.inputs[what].lost_in_stamps = self.health[what].dropped
        if what == "odometry":
            self._last_odom_handled_ns = now

    def behind(self) -> bool:
        """Odometry is waiting: the newest sample, handled within the last 0.2 s, was
        handled later after its stamp than an idle step may delay it (``idle_budget_ms``, at
        least twice ``budget_ms``). Work that can wait (idle steps, graph publication) then
        yields to the inputs."""
        odom = self.health["odometry"]
        if time.monotonic_ns() - self._last_odom_handled_ns > 200_000_000:
            return False
        allowed = max(self.config.idle_budget_ms, 2.0 * self.config.mapper.budget_ms)
        return odom.lag_ms > allowed

    def _idle_timer(self) -> None:
        if not warmup.is_ready():
            return
        if self.behind():
            self.idle_yielded += 1
            return
        self.idle_step()

    def on_odom(self, msg: Any) -> None:
        """An odometry message: maybe a keyframe, its pose in ``map`` out, then one solver
        step with what is left of the budget (publishing first keeps the output's latency
        and the callback's length both independent of the solver)."""
        start = time.perf_counter()

        def handle() -> None:
            sample = ma.odometry_from_msg(msg)
            self._arrived("odometry", sample.stamp_ns)
            x, y, yaw, _ = sample.planar()
            self.mapper.add_odometry(sample.stamp_ns, np.array([x, y, yaw]))
            self._last_stamp_ns = max(self._last_stamp_ns, sample.stamp_ns)
            self.publish_pose()
            revision = self.mapper.map_revision()
            self._step(start)
            if self.mapper.map_revision() != revision:
                # The step merged a solution (the map moved as a whole): the pose just sent
                # carries the old map->odom, so the corrected one follows at once.
                self.publish_pose()

        self._guarded("odometry", handle)

    def on_loop_closure(self, msg: Any) -> None:
        """A loop closure: gated, then added and stepped."""
        start = time.perf_counter()

        def handle() -> None:
            default = self.config.messages.loop_default_covariance()
            closure = ma.loop_closure_from_msg(msg, default_covariance=default)
            cov3 = closure.covariance[np.ix_(geo.PLANAR_DOF, geo.PLANAR_DOF)]
            delta = np.array([closure.t[0], closure.t[1], float(geo.matrix_to_yaw(closure.R))])
            self.mapper.add_loop_closure(_ref(closure.from_ref), _ref(closure.to_ref), delta,
                                         cov3)
            self._step(start)

        self._guarded("loop_closure", handle)

    def on_gps(self, msg: Any) -> None:
        """A NavSatFix: dropped with the reason, or a position edge."""
        start = time.perf_counter()

        def handle() -> None:
            stamp = ma.stamp_ns(msg.header, "NavSatFix.header.stamp")
            self._arrived("gps", stamp)
            ma.check_stamp_order(self._last_gps_ns, stamp, field="NavSatFix.header.stamp",
                                 strict=True)
            if self._datum is None:
                self._datum = ma.datum_from_fix(msg)
                self.mapper.datum = (self._datum.lat_deg, self._datum.lon_deg,
                                     self._datum.alt_m)
                self.get_logger().info(f"GPS datum set from the first good fix: {self._datum}")
            gps = self.config.messages
            fix = ma.gps_fix_from_msg(
                msg, self._datum, unknown_sigma_m=gps.gps_unknown_sigma,
                sigma_floor_m=gps.gps_sigma_floor, max_sigma_m=gps.gps_max_sigma,
                zero_altitude=gps.zero_altitude)
            self._last_gps_ns = stamp
            self.mapper.add_gps(fix.stamp_ns, fix.enu, fix.covariance)
            self._step(start)

        self._guarded("gps", handle)

    # -- outputs ------------------------------------------------------------------------------

    def publish_pose(self) -> None:
        """The newest odometry sample's pose in ``map``."""
        latest = self.mapper.latest_pose(self._correction())
        if latest is None:
            return
        stamp, pose = latest
        msg = PoseStamped()
        ma.fill_header(msg.header, stamp, self.config.map_frame)
        ma.fill_pose(msg.pose, geo.yaw_to_matrix(pose[2]), np.array([pose[0], pose[1], 0.0]))
        self.emit("pose", msg)

    def _correction(self) -> np.ndarray:
        """``map -> odom`` as of the last refresh, computed anew when there is none or the map
        has moved as a whole since (a merged exact solution would otherwise reach ``~/pose``
        only at the next transform refresh)."""
        revision = self.mapper.map_revision()
        if self._map_to_odom is None or revision != self._map_revision:
            self._map_to_odom = self.mapper.map_to_odom()
            self._map_revision = revision
        return self._map_to_odom

    def _shared(self, key: str, publish: Callable[[bool], None]) -> None:
        """``publish(refresh)``, refreshing its costly part only when ``shares[key]`` allows."""
        share = self.shares[key]
        start = time.perf_counter()
        refresh = share.due(start)
        publish(refresh)
        if refresh:
            share.ran(start, time.perf_counter() - start)

    def _map_to_odom_timer(self) -> None:
        if not warmup.is_ready():
            return
        self._shared("map_to_odom", self.publish_map_to_odom)

    def publish_map_to_odom(self, refresh: bool = True) -> None:
        """``map → odom``, stamped with the newest input stamp. ``refresh``: compute the
        correction anew (O(tree depth)), else publish the one ``~/pose`` uses now; the
        transform timer refreshes it within ``output_time_share`` of the node's time."""
        if not self.mapper.num_nodes:
            return
        if refresh or self._map_to_odom is None:
            self._map_to_odom = self.mapper.map_to_odom()
            self._map_revision = self.mapper.map_revision()
        x, y, yaw = self._map_to_odom
        msg = ma.fill_transform(TransformStamped, geo.yaw_to_matrix(yaw), np.array([x, y, 0.0]),
                                stamp_ns=self._last_stamp_ns, frame_id=self.config.map_frame,
                                child_frame_id=self.config.odom_frame)
        self.emit("map_to_odom", msg)
        if self.tf_message is not None and self.config.publish_tf:
            self.emit_tf(msg)

    def _graph_timer(self) -> None:
        if not warmup.is_ready():
            return
        share = self.shares["graph"]
        start = time.perf_counter()
        if not (self._graph_dirty and self.mapper.num_nodes and share.due(start)):
            return
        keys = {"poses", "path", "markers"}
        if self.sink is None:  # live: only what someone listens to (it stays due)
            keys = {k for k in keys if self.publishers_by_key[k].get_subscription_count()}
        if not keys or self.behind():
            return
        self.publish_graph(keys)
        share.ran(start, time.perf_counter() - start)

    def publish_graph(self, keys: set[str] | None = None) -> None:
        """PoseArray, Path and MarkerArray of the graph, or those of ``keys`` (on a timer:
        they cost ms per thousand poses, which must not come out of the solver's budget;
        live, the timer publishes at most ``output_time_share`` of the node's time, only
        the topics with subscribers, and not while odometry waits)."""
        if not self._graph_dirty or not self.mapper.num_nodes:
            return
        keys = {"poses", "path", "markers"} if keys is None else keys
        self._graph_dirty = False
        graph = self.mapper.graph()
        frame = self.config.map_frame
        stamp = self._last_stamp_ns
        if "poses" in keys:
            self.emit("poses", ma.fill_pose_array(PoseArray, graph.R, graph.t, stamp_ns=stamp,
                                                  frame_id=frame))
        if "path" in keys:
            self.emit("path", ma.fill_path(PathMsg, graph.R, graph.t, stamp_ns=stamp,
                                           frame_id=frame,
                                           stamps_ns=self.mapper.keyframes.stamps))
        if "markers" not in keys:
            return
        chi2 = edge_chi2(graph)
        rel = graph.kind == EdgeKind.RELATIVE
        gps = graph.kind == EdgeKind.POSITION
        out = self.mapper.h2o.solver.weight <= 0.0
        markers = ma.GraphMarkers(
            positions=graph.t, edges=np.column_stack([graph.a[rel], graph.b[rel]]),
            edge_residuals=chi2[rel], gps_nodes=graph.b[gps],
            gps_positions=graph.meas_t[gps], gps_residuals=chi2[gps],
            edge_dropped=out[rel], gps_dropped=out[gps])
        self.emit("markers", ma.fill_graph_markers(MarkerArray, markers, stamp_ns=stamp,
                                                   frame_id=frame, residual_scale=3.0))

    def _chi2_values(self, refresh: bool) -> dict[str, object]:
        """χ² of every edge and the optimality ratio: O(edges) (the world poses composed
        level by level, then every residual), so kept from the last refresh unless
        ``refresh``; ``chi2_age_s`` says how old they are."""
        now = time.perf_counter()
        if refresh or self._chi2_cache is None:
            per_edge = self.mapper.edge_chi2()
            ratio, outside = self.mapper.optimality(per_edge)
            self._chi2_cache = {"chi2": float(np.sum(per_edge)), "optimality_ratio": ratio,
                                "edges_outside_converged": outside}
            self._chi2_at_s = now
        return {**self._chi2_cache, "chi2_age_s": now - self._chi2_at_s}

    def _load_values(self) -> dict[str, object]:
        """Dropped and late inputs, input lag, deferred outputs and the process's RSS."""
        values: dict[str, object] = {}
        for what, health in self.health.items():
            values[f"dropped {what}"] = health.dropped
            values[f"late {what}"] = health.late
            values[f"lag_max_ms {what}"] = health.max_lag_ms
        for what, counts in self.inputs.items():
            values.update(counts.values(f"input {what} "))
        values["idle_yielded"] = self.idle_yielded
        values["graph_publications"] = self.shares["graph"].runs
        values["graph_publish_ms"] = 1e3 * self.shares["graph"].last_cost_s
        values["rss_mb"] = _rss_mb()
        return values

    def _diagnostics_timer(self) -> None:
        self._shared("chi2", self.publish_diagnostics)

    def diagnostics(self, refresh_chi2: bool = True) -> ma.DiagnosticReport:
        """The node's status: callback times against the budget, graph size, χ², counts of
        accepted, rejected, dropped and late inputs. ``refresh_chi2``: compute χ² anew (else
        the last value, with its age)."""
        if not warmup.is_ready():
            return self._warming_report()
        budget = self.config.mapper.budget_ms
        summary = self.times.summary()
        exact = self.mapper.h2o.converger.state
        values: dict[str, object] = {
            "budget_ms": budget, **summary,
            "nodes": self.mapper.num_nodes, "edges": self.mapper.h2o.solver.num_edges,
            **self._chi2_values(refresh_chi2),
            "exact_solves": exact.solves,
            "exact_failures": exact.failures,
            "deferred_edges": len(self.mapper.h2o.pending),
            "idle_steps": self.idle_times.count,
            "idle_max_ms": self.idle_times.max_ms,
            "idle_overruns": self.idle_times.overruns,
            **self._load_values(),
            "paused": self.paused,
            "warming_up": False,
            "held_while_warming": self.held_while_warming,
            "scheduling": self.realtime.words,
            "tf_available": self.tf_message is not None,
            "gps_datum": "unset" if self._datum is None else
            f"{self._datum.lat_deg:.8f}, {self._datum.lon_deg:.8f}",
        }
        values.update({f"accepted {k}": v for k, v in sorted(self.mapper.accepted.items())})
        values.update({f"robust {k}": v for k, v in self.mapper.decisions().items()})
        rejected = self.rejected + self.mapper.rejected
        values.update({f"rejected {k}": v for k, v in sorted(rejected.items())})
        values["rejected total"] = sum(rejected.values())
        late = budget > 0.0 and summary.get("p99_ms", 0.0) > budget
        message = f"p99 {summary.get('p99_ms', 0.0):.2f} ms against a {budget:g} ms budget"
        if self.paused:
            message = "paused; " + message
        return ma.DiagnosticReport(name=f"{self.get_name()}: solver", level=1 if late else 0,
                                   message=message, values=values, hardware_id="h2o_slam")

    def _warming_tick(self) -> None:
        """While the kernels load: say so on ``/diagnostics`` (sooner than its period);
        once loaded: handle the held inputs and stop."""
        if not warmup.is_ready():
            self.publish_diagnostics()
            return
        self._warming_timer.cancel()
        self._release_held()
        self.get_logger().info(f"solver kernels ready {time.perf_counter() - self._started_s:.1f}"
                               f" s after start ({self.held_while_warming} inputs were held)")

    def _warming_report(self) -> ma.DiagnosticReport:
        """The status while the kernels load: up, holding its inputs, nothing solved yet."""
        return ma.DiagnosticReport(
            name=f"{self.get_name()}: solver", level=1,
            message=f"warming up: loading the solver's compiled kernels ({len(self._held)} "
            "inputs held; a first start after an install that did not compile them takes a "
            "minute or more)",
            values={"warming_up": True, "held_inputs": len(self._held),
                    "held_while_warming": self.held_while_warming, "paused": self.paused,
                    "scheduling": self.realtime.words},
            hardware_id="h2o_slam")

    def publish_diagnostics(self, refresh_chi2: bool = True) -> None:
        """``/diagnostics`` (``refresh_chi2``: as :meth:`diagnostics`)."""
        self.emit_report(self.diagnostics(refresh_chi2), self._last_stamp_ns)

    # -- services -----------------------------------------------------------------------------

    def _srv_save(self, request: Any, response: Any) -> Any:
        if not warmup.is_ready():
            return _warming(response)
        path = self.config.map_file
        if not path:
            response.success, response.message = False, "map_file is not set"
            return response
        try:
            self.mapper.save(path)
        except (InputError, OSError) as exc:  # refused (empty, non-finite) or not writable
            response.success, response.message = False, f"not saved: {exc}"
            self.get_logger().warning(response.message)
            return response
        response.success = True
        response.message = f"saved {self.mapper.num_nodes} nodes to {path}"
        return response

    def _srv_exact(self, request: Any, response: Any) -> Any:
        if not warmup.is_ready():
            return _warming(response)
        before, after = self.mapper.exact_solve()
        self._graph_dirty = True
        response.success, response.message = True, f"chi2 {before:.6g} -> {after:.6g}"
        return response

    def _srv_reset(self, request: Any, response: Any) -> Any:
        if not warmup.is_ready():
            return _warming(response)
        self.mapper.close()
        self.mapper = Mapper(self.config.mapper)
        self._datum = self._configured_datum()
        self._last_gps_ns = None
        self.rejected.clear()
        for counts in self.inputs.values():
            counts.reset()
        self.times = CallbackTimes()
        self.idle_times = CallbackTimes()
        self._reset_load_state()
        self._graph_dirty = True
        response.success, response.message = True, "graph cleared"
        return response

    def _srv_pause(self, request: Any, response: Any) -> Any:
        if self.paused and not request.data:
            for health in self.health.values():
                health.restart()  # the messages ignored meanwhile are counted as dropped
        self.paused = bool(request.data)
        response.success = True
        response.message = "paused" if self.paused else "running"
        return response


#: How often a warming-up node says so on ``/diagnostics``.
WARMING_PERIOD_S = 0.25


def _warming(response: Any) -> Any:
    """A service's answer while the kernels load (the inputs are held, nothing is lost)."""
    response.success = False
    response.message = "warming up: the solver's kernels are loading; try again in a moment"
    return response


def _rss_mb() -> float:
    """Resident set size of this process (MiB; NaN where ``/proc`` is not there)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return math.nan


def _ref(ref: ma.PoseRef) -> int | tuple[str, int]:
    return ref.node_id if isinstance(ref, ma.NodeRef) else ("stamp", ref.stamp_ns)


def main(args: list[str] | None = None) -> int:
    """``ros2 run h2o_slam h2o_node``; a bad parameter or map file ends it with one line and
    exit code 1."""
    return run_node(H2ONode, NODE_NAME, (H2OError, ValueError, OSError), args)


if __name__ == "__main__":
    sys.exit(main())
