"""The configuration tree of ``h2o_node``: every parameter it declares, one frozen snapshot
(no rclpy here: the tree is read, checked and documented without ROS).

The root holds the node's own settings (frames, output periods, the map file, queues, idle
steps); :class:`h2o_slam.ros.mapper.MapperConfig` the back end's, :class:`MessageConfig`
how messages become measurements (loop-closure defaults, GPS). All keep the names users set
(the groups are flat). Each field's ``metadata`` holds its description, range and whether it
changes at run time (:mod:`ros_node_base.params`); ``config/h2o.yaml`` and the table in
``doc/nodes.md`` are written from this tree.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import msg_adapters as ma
from h2o_slam.core.errors import InputError
from h2o_slam.core.parameters import parameter
from h2o_slam.ros.mapper import MapperConfig


@dataclass(frozen=True)
class MessageConfig:
    """How loop-closure and GPS messages become measurements (the fields' ``doc``)."""

    loop_default_sigma_xy: float = parameter(
        0.1, "Loop closure sigma (m) when its covariance is all zero.", bounds=(1e-6, 100.0))
    loop_default_sigma_yaw: float = parameter(
        0.02, "Loop closure sigma (rad) when its covariance is zero.", bounds=(1e-6, 10.0))
    datum: tuple[float, ...] = parameter(
        (0.0,), "GPS datum [lat_deg, lon_deg, alt_m]; [0.0] takes the first good fix.")
    zero_altitude: bool = parameter(True, "Ignore GPS altitude.")
    gps_sigma_floor: float = parameter(
        0.05, "Smallest GPS sigma in m (a zero covariance never reaches the solver).",
        bounds=(1e-4, 100.0))
    gps_max_sigma: float = parameter(
        10.0, "Fixes with a larger horizontal sigma (m) are dropped.", bounds=(1e-3, 1e4))
    gps_unknown_sigma: float = parameter(
        5.0, "Sigma (m) for fixes whose covariance type is UNKNOWN.", bounds=(1e-3, 1e4))

    def __post_init__(self) -> None:
        if len(self.datum) != 3 and self.datum not in ((), (0.0,)):
            raise InputError(f"datum: expected [lat_deg, lon_deg, alt_m] or [0.0], got "
                             f"{list(self.datum)}")

    @property
    def configured_datum(self) -> ma.Datum | None:
        """The datum set by the parameter (``None``: the first good fix sets it)."""
        return ma.Datum(*self.datum) if len(self.datum) == 3 else None

    def loop_default_covariance(self) -> np.ndarray:
        """The covariance a loop closure with an all-zero one gets (6×6, ROS order)."""
        sxy, syaw = self.loop_default_sigma_xy, self.loop_default_sigma_yaw
        return ma.planar_covariance(sxy, sxy, syaw, unobserved_variance=1.0)


@dataclass(frozen=True)
class H2ONodeConfig:
    """Every parameter of ``h2o_node`` (module docstring)."""

    map_frame: str = parameter("map", "Frame of the optimized graph (ENU when GPS is used).")
    odom_frame: str = parameter("odom", "Frame of the incoming odometry.")
    base_frame: str = parameter("base_link", "Robot body frame.")
    publish_tf: bool = parameter(True, "Publish map->odom on /tf.", runtime=True)
    transform_publish_period: float = parameter(
        0.05, "Seconds between map->odom publications.", bounds=(0.001, 10.0))
    graph_publish_period: float = parameter(
        1.0, "Seconds between graph publications.", bounds=(0.01, 60.0))
    diagnostics_period: float = parameter(
        1.0, "Seconds between /diagnostics publications.", bounds=(0.05, 60.0))
    mapper: MapperConfig = field(default_factory=MapperConfig, metadata={"flat": True})
    messages: MessageConfig = field(default_factory=MessageConfig, metadata={"flat": True})
    map_file: str = parameter("", "g2o file for the save service and for load_map_on_start.")
    load_map_on_start: bool = parameter(False, "Continue the graph saved in map_file.")
    input_queue_depth: int = parameter(
        1000, "Subscription queue depth of the odometry and GPS inputs (10 s of odometry at "
        "100 Hz: what a stall of the node leaves waiting).", bounds=(1, 100_000))
    loop_closure_queue_depth: int = parameter(
        10000, "Subscription queue depth of the loop-closure input (a detector catching up "
        "after a revisit sends thousands at once).", bounds=(1, 1_000_000))
    idle_budget_ms: float = parameter(
        10.0, "Solver time of an idle step, for edges that did not fit into the input "
        "callbacks' budget and for merging exact solutions; 0 disables.",
        bounds=(0.0, 1000.0), runtime=True)
    realtime_priority: int = parameter(
        0, "Run every callback under SCHED_FIFO at this priority (1-99; 0: the default "
        "policy). On a computer busy with CPU-bound work at the default priority the kernel "
        "cuts a callback mid-budget for a scheduler tick, whatever its nice value; needs "
        "CAP_SYS_NICE or an rtprio limit (refused: a warning, and the default policy).",
        bounds=(0, 99))
    idle_period: float = parameter(
        0.05, "Seconds between idle steps; they run only while edges wait or the map is not "
        "at a converged solution.", bounds=(0.001, 10.0))
    input_late_ms: float = parameter(
        100.0, "An odometry or GPS message handled more than this many ms after its stamp, "
        "less the smallest stamp-to-handling delay seen (so the sender's clock need "
        "not agree with the node's), counts as late in /diagnostics.", bounds=(0.1, 1e6))
    output_time_share: float = parameter(
        0.05, "Largest share of the node's time for each periodic output whose cost grows "
        "with the graph (graph topics, the map->odom correction, chi2 in "
        "/diagnostics): its period stretches beyond the configured one as the graph "
        "grows.", bounds=(0.001, 1.0))
