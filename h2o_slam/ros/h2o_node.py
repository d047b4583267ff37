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
runs inside one boundary (:meth:`H2ONode._guarded` for inputs, :meth:`H2ONode._boundary`
for the rest) that turns any exception into a logged rejection counted by reason in
``/diagnostics`` (``rejected <input>: unexpected <Type>`` for anything but the package's
own errors, which name their reason).
"""

from __future__ import annotations

import gc
import importlib
import math
import os
import re
import sys
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import fields, replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
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
from h2o_slam.ros.boundary import behind_boundary
from h2o_slam.ros.inputs import InputCounts, counted_subscription
from h2o_slam.ros.mapper import Mapper, MapperConfig, restore
from h2o_slam.ros.node_main import run_node

NODE_NAME = "h2o_node"

#: The inputs, as /diagnostics names them.
INPUTS = ("odometry", "loop_closure", "gps")

#: Numbers in rejection reasons, replaced so that one reason is one diagnostics key.
_NUMBER = re.compile(r"[-+]?\d[\d.]*(e[-+]?\d+)?")

#: (name, default, description, (low, high) or None). Ranges bound what can be set.
PARAMETERS: list[tuple[str, Any, str, tuple[float, float] | None]] = [
    ("map_frame", "map", "Frame of the optimized graph (ENU when GPS is used).", None),
    ("odom_frame", "odom", "Frame of the incoming odometry.", None),
    ("base_frame", "base_link", "Robot body frame.", None),
    ("publish_tf", True, "Publish map->odom on /tf.", None),
    ("transform_publish_period", 0.05, "Seconds between map->odom publications.",
     (0.001, 10.0)),
    ("graph_publish_period", 1.0, "Seconds between graph publications.", (0.01, 60.0)),
    ("diagnostics_period", 1.0, "Seconds between /diagnostics publications.", (0.05, 60.0)),
    ("budget_ms", 5.0, "Solver time per callback in ms; 0 solves every new edge in full and "
     "revisits nothing (replays: deterministic) (run-time changeable).", (0.0, 1000.0)),
    ("d_max", 0, "Most nodes solved per edge; 0 lets the budget decide (run-time).",
     (0, 1_000_000)),
    ("keyframe_distance", 0.5, "New keyframe after this travel in m; 0 disables (run-time).",
     (0.0, 100.0)),
    ("keyframe_angle", 0.2, "New keyframe after this turn in rad; 0 disables (run-time).",
     (0.0, 6.3)),
    ("keyframe_period", 0.0, "New keyframe after this many s; 0 disables (run-time).",
     (0.0, 3600.0)),
    ("odom_sigma_per_m", 0.05, "Odometry translation sigma per metre travelled.", (0.0, 10.0)),
    ("odom_yaw_sigma_per_rad", 0.05, "Odometry heading sigma per radian turned.", (0.0, 10.0)),
    ("odom_yaw_sigma_per_m", 0.01, "Odometry heading sigma (rad) per metre travelled.",
     (0.0, 10.0)),
    ("loop_gate_chi2", 16.266,
     "Largest accepted loop-closure chi2 (3 dof; 16.27 is the 99.9 % quantile).",
     (0.1, 1e12)),
    ("robust", True, "Weigh loop closures and GPS fixes as possible outliers (GNC-TLS in the "
     "exact solves, every decision revised by each solve); a closure or fix the gate doubts "
     "is held at weight 0 instead of refused. false: least squares, the gate refuses.", None),
    ("loop_stamp_tolerance", 0.5, "Seconds a loop-closure stamp may lie from a keyframe.",
     (0.0, 60.0)),
    ("loop_default_sigma_xy", 0.1, "Loop closure sigma (m) when its covariance is all zero.",
     (1e-6, 100.0)),
    ("loop_default_sigma_yaw", 0.02, "Loop closure sigma (rad) when its covariance is zero.",
     (1e-6, 10.0)),
    ("datum", [0.0], "GPS datum [lat_deg, lon_deg, alt_m]; [0.0] takes the first good fix.",
     None),
    ("zero_altitude", True, "Ignore GPS altitude.", None),
    ("gps_sigma_floor", 0.05, "Smallest GPS sigma in m (a zero covariance never reaches "
     "the solver).", (1e-4, 100.0)),
    ("gps_max_sigma", 10.0, "Fixes with a larger horizontal sigma (m) are dropped.",
     (1e-3, 1e4)),
    ("gps_unknown_sigma", 5.0, "Sigma (m) for fixes whose covariance type is UNKNOWN.",
     (1e-3, 1e4)),
    ("gps_lever_arm", [0.0, 0.0], "Antenna position [x, y] in base_frame, m.", None),
    ("gps_time_tolerance", 0.2, "Seconds a fix may lie from the keyframe it lands on.",
     (0.0, 10.0)),
    ("map_file", "", "g2o file for the save service and for load_map_on_start.", None),
    ("load_map_on_start", False, "Continue the graph saved in map_file.", None),
    ("input_queue_depth", 1000, "Subscription queue depth of the odometry and GPS inputs "
     "(10 s of odometry at 100 Hz: what a stall of the node leaves waiting).", (1, 100_000)),
    ("loop_closure_queue_depth", 10000, "Subscription queue depth of the loop-closure input "
     "(a detector catching up after a revisit sends thousands at once).", (1, 1_000_000)),
    ("idle_budget_ms", 10.0, "Solver time of an idle step, for edges that did not fit into "
     "the input callbacks' budget; 0 disables (run-time).", (0.0, 1000.0)),
    ("idle_period", 0.05, "Seconds between idle steps; they run only while edges wait.",
     (0.001, 10.0)),
    ("input_late_ms", 100.0, "An odometry or GPS message handled more than this many ms "
     "after its stamp (less the smallest such delay seen) counts as late in /diagnostics.",
     (0.1, 1e6)),
    ("output_time_share", 0.05, "Largest share of the node's time for each periodic output "
     "whose cost grows with the graph (graph topics, map->odom refresh, chi2 in "
     "/diagnostics): its period stretches as the graph grows.", (0.001, 1.0)),
]

#: Parameters whose changes take effect while running (the rest need a restart).
RUNTIME = {"budget_ms", "d_max", "keyframe_distance", "keyframe_angle", "keyframe_period",
           "loop_gate_chi2", "publish_tf", "idle_budget_ms"}


def _descriptor(name: str, default: Any, text: str,
                bounds: tuple[float, float] | None) -> ParameterDescriptor:
    desc = ParameterDescriptor(name=name, description=text,
                               read_only=name not in RUNTIME and name != "publish_tf")
    if bounds is not None and isinstance(default, bool):
        return desc
    if bounds is not None and isinstance(default, int):
        desc.integer_range = [IntegerRange(from_value=int(bounds[0]), to_value=int(bounds[1]),
                                           step=1)]
    elif bounds is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(bounds[0]),
                                                        to_value=float(bounds[1]))]
    return desc


def _load_tf_message() -> Any:
    """``tf2_msgs/TFMessage``, or ``None`` where tf2_msgs is not installed."""
    try:
        return importlib.import_module("tf2_msgs.msg").TFMessage
    except ImportError:
        return None


class H2ONode(Node):
    """The H₂O back end as a ROS 2 node: odometry, loop closures and GPS fixes in; the
    optimized graph, pose, ``map → odom`` and ``/diagnostics`` out.

    Parameters are declared from :data:`PARAMETERS` (the README lists them); the mapping
    itself is :attr:`mapper`'s. Every input runs behind one boundary (:meth:`_guarded`):
    held while the compiled kernels load, then handled and timed; a bad message is logged,
    counted and skipped.

    Args:
        **kwargs: passed to :class:`rclpy.node.Node` (``context``, ``namespace``,
            ``parameter_overrides``, ``cli_args``, ...).

    Attributes:
        mapper: the back end without ROS (keyframes, gated loop closures, GPS, the solver).
        sink: callable ``(topic, msg)`` that also receives every published message (replay
            records through it), or None.
        paused: inputs are counted as discarded instead of handled (the ``~/pause`` service).
        times, idle_times: the input callbacks' and the idle steps' time against their
            budgets.
        inputs: what became of each input's messages (accepted, rejected, discarded, lost).
        rejected: inputs the boundary rejected, by reason (the mapper counts those it
            refuses itself; ``/diagnostics`` reports both).
        held_while_warming: inputs held while the kernels loaded.
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._held: deque[tuple[str, Callable[[], None]]] = deque()
        self.held_while_warming = 0
        for name, default, text, bounds in PARAMETERS:
            self.declare_parameter(name, default, _descriptor(name, default, text, bounds))
        self.sink: Callable[[str, Any], None] | None = None
        self.paused = False
        self.times = CallbackTimes()
        self.idle_times = CallbackTimes()
        self.rejected: Counter[str] = Counter()
        #: What became of each input's messages (h2o_slam.ros.inputs).
        self.inputs = {what: InputCounts() for what in INPUTS}
        self._last_gps_ns: int | None = None
        self._last_stamp_ns = 0
        self._graph_dirty = True
        self._tf_cls = _load_tf_message()
        self._reset_load_state()
        self._make_interfaces()
        # The compiled kernels load (or, on a first start after the sources changed, compile)
        # beside the executor: the node answers at once and holds its inputs until then.
        # Started before the mapper, whose solver would otherwise load them here.
        warmup.warm_up_in_background()
        self._started_s = time.perf_counter()
        self.mapper = self._start_mapper()
        self._datum = self._configured_datum()
        self._warming_timer = self.create_timer(
            WARMING_PERIOD_S, self._boundary("warming_timer", self._warming_tick))
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._boundary("parameters", self._apply_parameters))
        self._log_ready()

    def destroy_node(self) -> None:
        """Destroy the node and let the garbage collector reclaim it.

        The solver freezes the collector after each step (``OnlineConfig.freeze_gc``), which
        would keep this node's reference cycles, and with them its DDS participant, alive
        for the rest of the process.
        """
        self.mapper.close()
        super().destroy_node()
        gc.unfreeze()
        gc.collect()

    # -- set-up -------------------------------------------------------------------------------

    def p(self, name: str) -> Any:
        """A parameter's value."""
        return self.get_parameter(name).value

    def mapper_config(self) -> MapperConfig:
        """The mapper settings the parameters describe."""
        d_max = int(self.p("d_max"))
        lever = [float(v) for v in self.p("gps_lever_arm")]
        if len(lever) != 2:
            raise InputError(f"gps_lever_arm: expected [x, y], got {lever}")
        return MapperConfig(
            keyframe_distance_m=float(self.p("keyframe_distance")),
            keyframe_angle_rad=float(self.p("keyframe_angle")),
            keyframe_period_s=float(self.p("keyframe_period")),
            odom_sigma_per_m=float(self.p("odom_sigma_per_m")),
            odom_yaw_sigma_per_rad=float(self.p("odom_yaw_sigma_per_rad")),
            odom_yaw_sigma_per_m=float(self.p("odom_yaw_sigma_per_m")),
            loop_gate_chi2=float(self.p("loop_gate_chi2")),
            loop_stamp_tolerance_s=float(self.p("loop_stamp_tolerance")),
            gps_time_tolerance_s=float(self.p("gps_time_tolerance")),
            gps_lever_arm_m=(lever[0], lever[1]),
            robust=bool(self.p("robust")),
            budget_ms=float(self.p("budget_ms")) or None,
            d_max=d_max if d_max > 0 else None,
            # Budgeted callbacks get a worker process for the exact solves; unbudgeted
            # (deterministic) ones solve inline and need none.
            background="process" if float(self.p("budget_ms")) > 0.0 else "inline",
        )

    def _start_mapper(self) -> Mapper:
        # A damaged map ends the start with one line (restore validates everything a timer
        # would later use); a map never saved is a new graph.
        path = str(self.p("map_file"))
        if self.p("load_map_on_start") and path:
            mapper = restore(path, self.mapper_config())
            if mapper is not None:
                self.get_logger().info(
                    f"continuing the graph of {path}: {mapper.num_nodes} nodes")
                return mapper
            self.get_logger().info(f"no map saved at {path} yet: starting a new graph")
        return Mapper(self.mapper_config())

    def _reset_load_state(self) -> None:
        """Input health, the cached map->odom correction and χ², and the rate limits of the
        outputs whose cost grows with the graph."""
        late_ms = float(self.p("input_late_ms"))
        share = float(self.p("output_time_share"))
        self.health = {"odometry": InputHealth(late_ms), "gps": InputHealth(late_ms)}
        self._last_odom_handled_ns = 0
        #: ``map -> odom`` as of the last refresh (by the transform timer, or on demand).
        self._map_to_odom: np.ndarray | None = None
        self._map_revision = -1
        self._chi2_cache: dict[str, object] | None = None
        self._chi2_at_s = 0.0
        self.shares = {
            "graph": CostShare(float(self.p("graph_publish_period")), share),
            "map_to_odom": CostShare(float(self.p("transform_publish_period")), share),
            "chi2": CostShare(float(self.p("diagnostics_period")), share),
        }
        self.idle_yielded = 0

    def _configured_datum(self) -> ma.Datum | None:
        values = [float(v) for v in self.p("datum")]
        if self.mapper.datum is not None:
            return ma.Datum(*self.mapper.datum)
        if len(values) == 3:
            return ma.Datum(*values)
        if values not in ([], [0.0]):
            raise InputError(f"datum: expected [lat_deg, lon_deg, alt_m] or [0.0], got {values}")
        return None

    def _boundary(self, what: str, work: Callable[..., Any]) -> Callable[..., Any]:
        """``work`` (a timer, service or parameter callback) behind the node's boundary: an
        exception is logged and counted as ``rejected <what>: ...``, never raised into the
        executor. A service then answers ``success=False`` with the reason."""
        return behind_boundary(what, work, self._count_rejection)

    def _count_rejection(self, what: str, exc: Exception) -> None:
        """Log and count a refused input (or failed timer / service) by reason."""
        if isinstance(exc, H2OError):
            reason = f"{what}: {_NUMBER.sub('#', str(exc))[:80]}"
            self.get_logger().warning(f"{what} rejected: {exc}", throttle_duration_sec=1.0)
        else:  # a bug, not bad input: say so loudly, and keep running
            reason = f"{what}: unexpected {type(exc).__name__}"
            self.get_logger().error(f"{what}: unexpected {type(exc).__name__}: {exc}",
                                    throttle_duration_sec=1.0)
        self.rejected[reason] += 1

    def _make_interfaces(self) -> None:
        depth = int(self.p("input_queue_depth"))
        sensor = QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT)
        reliable = QoSProfile(depth=int(self.p("loop_closure_queue_depth")),
                              reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        specs = (("odometry", Odometry, "odom", self.on_odom, sensor),
                 ("loop_closure", Odometry, "loop_closure", self.on_loop_closure, reliable),
                 ("gps", NavSatFix, "gps/fix", self.on_gps, sensor))
        #: Resolved topic of each input.
        self.input_topics = {
            what: counted_subscription(self, self.inputs[what], msg_type, topic, callback,
                                       qos).topic_name
            for what, msg_type, topic, callback, qos in specs}
        self.publishers_by_key = {
            "poses": self.create_publisher(PoseArray, "~/graph/poses", latched),
            "path": self.create_publisher(PathMsg, "~/graph/path", latched),
            "markers": self.create_publisher(MarkerArray, "~/graph/markers", latched),
            "pose": self.create_publisher(PoseStamped, "~/pose", 10),
            "map_to_odom": self.create_publisher(TransformStamped, "~/map_to_odom", 10),
            "diagnostics": self.create_publisher(DiagnosticArray, "/diagnostics", 10),
        }
        if self._tf_cls is not None:
            self.publishers_by_key["tf"] = self.create_publisher(self._tf_cls, "/tf", 100)
        else:
            self.get_logger().warning(
                "tf2_msgs is not installed: map->odom goes to ~/map_to_odom only, not /tf")
        guard = self._boundary
        self.create_service(Trigger, "~/save_map", guard("save_map", self._srv_save))
        self.create_service(Trigger, "~/exact_solve", guard("exact_solve", self._srv_exact))
        self.create_service(Trigger, "~/reset", guard("reset", self._srv_reset))
        self.create_service(SetBool, "~/pause", guard("pause", self._srv_pause))
        self.create_timer(float(self.p("graph_publish_period")),
                          guard("graph_timer", self._graph_timer))
        self.create_timer(float(self.p("transform_publish_period")),
                          guard("map_to_odom_timer", self._map_to_odom_timer))
        self.create_timer(float(self.p("diagnostics_period")),
                          guard("diagnostics_timer", self._diagnostics_timer))
        self.create_timer(float(self.p("idle_period")), guard("idle_timer", self._idle_timer))

    def _log_ready(self) -> None:
        """One line at start-up: the node is up, the topics it reads and writes, and the
        parameters that decide its cost."""
        out = {key: pub.topic_name for key, pub in self.publishers_by_key.items()}
        budget = float(self.p("budget_ms"))
        solves = "exact solves in a worker process" if budget > 0.0 else (
            "every edge solved in full, deterministic")
        tf = " and /tf" if "tf" in out and self.p("publish_tf") else ""
        self.get_logger().info(
            f"{self.get_fully_qualified_name()} ready: in "
            + ", ".join(f"{topic} ({what})" for what, topic in self.input_topics.items())
            + f"; out {out['poses']}, {out['path']}, {out['markers']}, {out['pose']}, "
            f"{out['map_to_odom']}{tf}, {out['diagnostics']}; budget_ms {budget:g} "
            f"({solves}), robust {str(bool(self.p('robust'))).lower()}, queue depths "
            f"{self.p('input_queue_depth')} (odometry, GPS) / "
            f"{self.p('loop_closure_queue_depth')} (loop closures), map_frame "
            f"{self.p('map_frame')}, map_file {str(self.p('map_file')) or 'unset'}")

    # -- parameters at run time -----------------------------------------------------------------

    def _check_parameters(self, params: list[Parameter]) -> SetParametersResult:
        changed = {p.name: p.value for p in params}
        frozen = sorted(set(changed) - RUNTIME)
        if frozen:
            return SetParametersResult(successful=False,
                                       reason=f"{frozen} take effect only at start-up")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        config = self.mapper_config()
        self.mapper.config = replace(self.mapper.config, **{
            f.name: getattr(config, f.name) for f in fields(MapperConfig)})
        self.get_logger().info(
            "parameters changed: " + ", ".join(f"{p.name}={p.value}" for p in params))

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
        """Run one input's handling, timing it. Bad input is logged, counted and survived,
        and so is any other exception (counted as ``<what>: unexpected <Type>``); validation
        comes first in the mapper, so a refused input leaves nothing behind in the track or
        the graph."""
        start = time.perf_counter()
        counted = sum(self.mapper.rejected.values())
        counts = self.inputs[what]
        try:
            if self.paused:
                counts.discarded += 1
            else:
                handler()
                counts.accepted += 1
        except Exception as exc:  # the boundary: no message ends the node (issue 13)
            counts.rejected += 1
            if isinstance(exc, H2OError) and sum(self.mapper.rejected.values()) != counted:
                # the mapper counted it under its own reason
                self.get_logger().warning(f"{what} rejected: {exc}", throttle_duration_sec=1.0)
            else:
                self._count_rejection(what, exc)
        for held, reason in self.mapper.released_errors:  # taken in earlier, refused now
            self.inputs[held].move("rejected")
            self.get_logger().warning(f"held {held} rejected: {reason}",
                                      throttle_duration_sec=1.0)
        self.mapper.released_errors.clear()
        elapsed_ms = 1e3 * (time.perf_counter() - start)
        budget_ms = float(self.p("budget_ms"))
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
        budget_ms = float(self.p("idle_budget_ms"))
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
        allowed = max(float(self.p("idle_budget_ms")), 2.0 * float(self.p("budget_ms")))
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
            sx, syaw = float(self.p("loop_default_sigma_xy")), float(
                self.p("loop_default_sigma_yaw"))
            default = ma.planar_covariance(sx, sx, syaw, unobserved_variance=1.0)
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
            fix = ma.gps_fix_from_msg(
                msg, self._datum, unknown_sigma_m=float(self.p("gps_unknown_sigma")),
                sigma_floor_m=float(self.p("gps_sigma_floor")),
                max_sigma_m=float(self.p("gps_max_sigma")),
                zero_altitude=bool(self.p("zero_altitude")))
            self._last_gps_ns = stamp
            self.mapper.add_gps(fix.stamp_ns, fix.enu, fix.covariance)
            self._step(start)

        self._guarded("gps", handle)

    # -- outputs ------------------------------------------------------------------------------

    def emit(self, key: str, msg: Any) -> None:
        """Publish on the output ``key`` and hand the message to the sink, if any."""
        publisher = self.publishers_by_key[key]
        publisher.publish(msg)
        if self.sink is not None:
            self.sink(publisher.topic_name, msg)

    def publish_pose(self) -> None:
        """The newest odometry sample's pose in ``map``."""
        latest = self.mapper.latest_pose(self._correction())
        if latest is None:
            return
        stamp, pose = latest
        msg = PoseStamped()
        ma.fill_header(msg.header, stamp, str(self.p("map_frame")))
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
                                stamp_ns=self._last_stamp_ns, frame_id=str(self.p("map_frame")),
                                child_frame_id=str(self.p("odom_frame")))
        self.emit("map_to_odom", msg)
        if self._tf_cls is not None and self.p("publish_tf"):
            self.emit("tf", ma.fill_tf_message(self._tf_cls, [msg]))

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
        frame = str(self.p("map_frame"))
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
        budget = float(self.p("budget_ms"))
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
            "tf_available": self._tf_cls is not None,
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
                    "held_while_warming": self.held_while_warming, "paused": self.paused},
            hardware_id="h2o_slam")

    def publish_diagnostics(self, refresh_chi2: bool = True) -> None:
        """``/diagnostics`` (``refresh_chi2``: as :meth:`diagnostics`)."""
        self.emit("diagnostics", ma.fill_diagnostic_array(
            DiagnosticArray, [self.diagnostics(refresh_chi2)], stamp_ns=self._last_stamp_ns))

    # -- services -----------------------------------------------------------------------------

    def _srv_save(self, request: Any, response: Any) -> Any:
        if not warmup.is_ready():
            return _warming(response)
        path = str(self.p("map_file"))
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
        self.mapper = Mapper(self.mapper_config())
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
