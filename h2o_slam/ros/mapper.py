"""The back end a robot runs: keyframes, loop closures and GPS into an online H₂O graph.

This is the h2o_node's logic without ROS (the node only converts messages, times
callbacks and publishes). It is planar: poses are ``(x, y, yaw)`` in ``map`` (ENU when GPS
is used) and odometry is ``(x, y, yaw)`` in ``odom``.

* **Keyframes**: an odometry sample becomes a graph node when the robot has moved
  ``keyframe_distance`` or turned ``keyframe_angle`` since the last one, or
  ``keyframe_period`` has passed. Consecutive keyframes are joined by their odometry
  increment, with a noise model that grows with distance and turn (wheel odometry reports
  the covariance of its integrated pose, which says nothing about one increment).
* **Loop closures** address poses by node id or by stamp (the convention of
  :mod:`msg_adapters.loop_closure`). A stamp resolves to the keyframe nearest in time, and
  the measurement is carried onto that keyframe through the odometry recorded between
  the two instants. A closure must pass a χ² gate: its error at the current estimate,
  weighed by its own covariance plus the dead-reckoning covariance accumulated along the
  keyframe chain between its ends, below ``loop_gate_chi2``. One false closure therefore
  cannot bend the map.
* **GPS** fixes (local ENU, :mod:`msg_adapters.gps`) become position edges on the keyframe
  nearest in time (a new keyframe at the latest odometry sample when that is nearer),
  with the antenna's lever arm removed using the current heading estimate.
* **Saving** writes the graph as g2o plus a JSON sidecar (keyframe stamps and odometry
  poses, the GPS datum), crash-safely and validated on load (:mod:`h2o_slam.io.map_store`),
  from which :meth:`Mapper.load` continues mapping.

Every rejected input raises :class:`~h2o_slam.core.errors.InputError` with the reason and is
counted in :attr:`Mapper.rejected`; nothing already in the graph or the odometry track
changes (every input is validated, and every covariance, information matrix and χ² computed
from it checked finite, before anything is stored). Physics bounds the magnitudes accepted:
coordinates within :data:`MAX_COORDINATE_M`, measurement sigmas (loop closures, GPS) within
:data:`MIN_SIGMA` .. :data:`MAX_SIGMA`.
"""

from __future__ import annotations

import bisect
import math
import os
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from h2o_slam.core import geometry as geo
from h2o_slam.core.errors import GraphError, InputError
from h2o_slam.core.geometry import planar_between, planar_compose
from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, edge_chi2
from h2o_slam.core.modes import add_arrival, arrivals
from h2o_slam.core.online import OnlineConfig, OnlineH2O, StepReport
from h2o_slam.core.parameters import parameter
from h2o_slam.core.robust import EdgeState, RobustConfig, edge_states, odometry_edges
from h2o_slam.core.solver import SolverConfig
from h2o_slam.io.map_store import SavedMap, has_map, load_map, save_map

Array = np.ndarray

#: χ² with 3 degrees of freedom at 99.9 %: the default loop-closure gate.
CHI2_3DOF_999 = 16.266

#: Most inputs held back waiting for odometry; beyond it the oldest is dropped.
MAX_HELD = 1000

#: Largest coordinate (m) of an odometry pose, a loop-closure translation or a GPS position:
#: no frame on or about the Earth holds a point farther (msg_adapters bounds messages alike).
#: Squared, with the noise that grows with distance, it leaves the solver ~1e250 of headroom.
MAX_COORDINATE_M = 1e8
#: Smallest and largest sigma (m or rad) of a loop closure or GPS fix along any direction:
#: no sensor measures a pose to better than a micrometre, and 1e6 m says nothing. Stiffness
#: therefore stays within 1e-12 .. 1e12.
MIN_SIGMA = 1e-6
MAX_SIGMA = 1e6
#: The map's own position uncertainty (m) a GPS fix's gate allows beside the fix's: wide
#: enough for odometry drift over a short outage, narrow against a multipath jump.
GPS_GATE_SIGMA_M = 2.0


@dataclass(frozen=True)
class MapperConfig:
    """The mapper's settings; ``h2o_node`` declares each documented field as the parameter of
    the same name (``metadata``: :mod:`ros_node_base.params`), so names carry their unit in
    the description, not the name.

    Attributes:
        budget_ms: per-callback solver time; ``0`` solves every new edge in full.
        d_max: most nodes solved for per edge (``0``: as many as the budget allows).
        keyframe_distance, keyframe_angle, keyframe_period: a new keyframe after this much
            travel (m), turn (rad) or time (s); ``0`` disables a criterion.
        odom_sigma_per_m: translation σ of an odometry increment per metre travelled.
        odom_yaw_sigma_per_rad, odom_yaw_sigma_per_m: heading σ per radian turned and per
            metre travelled.
        odom_min_sigma_m, odom_min_sigma_rad: floors of those σ.
        loop_gate_chi2: largest accepted χ² of a loop closure (``inf`` accepts all).
        robust: loop closures and GPS fixes are possible outliers: the exact solves weigh
            them by GNC-TLS (:mod:`h2o_slam.core.robust`) and revise every decision with
            each solve; a closure or fix the χ² gate doubts is kept in the graph at weight
            0 (held) for them to re-admit. ``False``: least squares, and the gate refuses.
        loop_stamp_tolerance: how far (s) a stamp may lie from its nearest keyframe.
        gps_time_tolerance: how far (s) a fix may lie in time from the keyframe it lands on.
        gps_lever_arm: antenna position ``(x, y)`` in ``base_link`` (m).
        background: where the exact solves that take the map to its optimum run
            (``OnlineConfig.background``): ``process``, ``inline`` or ``off``; ``None``
            (the node's choice): a worker process when budgeted, inline when not.
    """

    budget_ms: float = parameter(
        5.0, "Solver time per callback in ms; 0 solves every new edge in full and the graph "
        "exactly, inline, on a fixed schedule (replays: deterministic); > 0 at start-up "
        "starts the exact solver's worker process.", bounds=(0.0, 1000.0), runtime=True)
    d_max: int = parameter(
        0, "Most nodes solved per edge; 0 lets the budget decide.",
        bounds=(0, 1_000_000), runtime=True)
    keyframe_distance: float = parameter(
        0.5, "New keyframe after this travel in m; 0 disables.", bounds=(0.0, 100.0), runtime=True)
    keyframe_angle: float = parameter(
        0.2, "New keyframe after this turn in rad; 0 disables.", bounds=(0.0, 6.3), runtime=True)
    keyframe_period: float = parameter(
        0.0, "New keyframe after this many s; 0 disables.", bounds=(0.0, 3600.0), runtime=True)
    odom_sigma_per_m: float = parameter(
        0.05, "Odometry translation sigma per metre travelled.", bounds=(0.0, 10.0))
    odom_yaw_sigma_per_rad: float = parameter(
        0.05, "Odometry heading sigma per radian turned.", bounds=(0.0, 10.0))
    odom_yaw_sigma_per_m: float = parameter(
        0.01, "Odometry heading sigma (rad) per metre travelled.", bounds=(0.0, 10.0))
    odom_min_sigma_m: float = 0.01
    odom_min_sigma_rad: float = 0.002
    loop_gate_chi2: float = parameter(
        CHI2_3DOF_999, "Largest accepted loop-closure chi2 (3 dof; 16.27 is the 99.9 % quantile).",
        bounds=(0.1, 1e12), runtime=True)
    robust: bool = parameter(
        True, "Weigh loop closures and GPS fixes as possible outliers (GNC-TLS in the exact "
        "solves, every decision revised by each solve); a closure or fix the gate "
        "doubts is held at weight 0 instead of refused. false: least squares, the gate "
        "refuses.")
    loop_stamp_tolerance: float = parameter(
        0.5, "Seconds a loop-closure stamp may lie from a keyframe.", bounds=(0.0, 60.0))
    gps_time_tolerance: float = parameter(
        0.2, "Seconds a fix may lie from the keyframe it lands on.", bounds=(0.0, 10.0))
    gps_lever_arm: tuple[float, float] = parameter(
        (0.0, 0.0), "Antenna position [x, y] in base_frame, m.")
    background: Literal["process", "inline", "off"] | None = None

    def __post_init__(self) -> None:
        for name in ("budget_ms", "keyframe_distance", "keyframe_angle", "keyframe_period",
                     "odom_sigma_per_m", "odom_yaw_sigma_per_rad", "odom_yaw_sigma_per_m",
                     "loop_stamp_tolerance", "gps_time_tolerance"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        for name in ("odom_min_sigma_m", "odom_min_sigma_rad"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0 (a zero sigma is infinite stiffness)")
        if not self.loop_gate_chi2 > 0.0:
            raise ValueError(f"loop_gate_chi2 must be > 0, got {self.loop_gate_chi2!r}")
        if self.d_max < 0:
            raise ValueError(f"d_max must be >= 0, got {self.d_max!r}")
        if len(self.gps_lever_arm) != 2:
            raise InputError(f"gps_lever_arm: expected [x, y], got {list(self.gps_lever_arm)}")

    @property
    def budget_s(self) -> float | None:
        """``budget_ms`` in seconds (``None``: no limit), as :meth:`Mapper.step` takes it."""
        return self.budget_ms * 1e-3 if self.budget_ms else None

    @property
    def solve_in(self) -> Literal["process", "inline", "off"]:
        """Where the exact solves run: :attr:`background`, or by default a worker process
        when budgeted (callbacks stay within the budget) and inline when not (deterministic;
        no worker needed)."""
        if self.background is not None:
            return self.background
        return "process" if self.budget_ms else "inline"


class OdometryTrack:
    """Every odometry sample received, ``(stamp_ns, x, y, unwrapped yaw)``, for carrying
    stamped measurements onto keyframes (a few MB per hour at 50 Hz)."""

    def __init__(self) -> None:
        self._stamps = np.zeros(1024, dtype=np.int64)
        self._poses = np.zeros((1024, 3))
        self.size = 0

    def append(self, stamp_ns: int, pose: Array) -> None:
        """Add a sample (stamps must increase; the caller checks)."""
        if self.size == len(self._stamps):
            self._stamps = np.concatenate([self._stamps, np.zeros_like(self._stamps)])
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
        unwrapped = pose.copy()
        if self.size:
            last = self._poses[self.size - 1, 2]
            unwrapped[2] = last + geo.wrap_angle(pose[2] - last)
        self._stamps[self.size] = stamp_ns
        self._poses[self.size] = unwrapped
        self.size += 1

    def covers(self, stamp_ns: int) -> bool:
        """The stamp lies within the recorded span."""
        return self.size > 0 and self._stamps[0] <= stamp_ns <= self._stamps[self.size - 1]

    def at(self, stamp_ns: int) -> Array:
        """Odometry pose at a stamp inside the span, linearly interpolated."""
        # The two neighbouring samples only: O(log n) on a track of hours at 100 Hz.
        i = int(np.searchsorted(self._stamps[: self.size], stamp_ns, side="left"))
        i = min(max(i, 1), self.size - 1) if self.size > 1 else 0
        if self.size == 1 or self._stamps[i] == stamp_ns:
            pose = self._poses[i].copy()
        else:
            s0, s1 = int(self._stamps[i - 1]), int(self._stamps[i])
            w = (stamp_ns - s0) / (s1 - s0)
            pose = (1.0 - w) * self._poses[i - 1] + w * self._poses[i]
        pose[2] = geo.wrap_angle(pose[2])
        return pose

    def stamps(self) -> np.ndarray:
        """Stamps of all samples (ns)."""
        return self._stamps[: self.size].copy()

    def poses(self) -> Array:
        """All samples ``(x, y, yaw)`` (yaw unwrapped)."""
        return self._poses[: self.size].copy()

    def latest(self) -> tuple[int, Array]:
        """The newest sample."""
        pose = self._poses[self.size - 1].copy()
        pose[2] = geo.wrap_angle(pose[2])
        return int(self._stamps[self.size - 1]), pose


def planar_info(cov3: Array) -> Array:
    """6×6 information (error order x, y, z, rot x, rot y, rot z) of a planar covariance
    over ``(x, y, yaw)``."""
    info = np.zeros((6, 6))
    info[np.ix_(geo.PLANAR_DOF, geo.PLANAR_DOF)] = np.linalg.inv(cov3)
    return info


def _adjoint_inverse(poses: Array) -> Array:
    """SE(2) adjoints ``Ad(T⁻¹)`` of poses ``(k, 3)``, acting on ``(v_x, v_y, ω)``."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x, y = poses[:, 0], poses[:, 1]
    ad = np.zeros((len(poses), 3, 3))
    ad[:, 0, 0], ad[:, 0, 1], ad[:, 1, 0], ad[:, 1, 1] = c, s, -s, c
    # Translation of T⁻¹ is −Rᵀp; its column in the adjoint is (p'_y, −p'_x).
    px, py = -(c * x + s * y), -(-s * x + c * y)
    ad[:, 0, 2], ad[:, 1, 2], ad[:, 2, 2] = py, -px, 1.0
    return ad


@dataclass
class Keyframes:
    """Per-node bookkeeping: stamp, odometry pose, and the increment covariance from the
    previous keyframe (NaN where the chain breaks: the node started a new subtree)."""

    stamps: list[int] = field(default_factory=list)
    odom: list[Array] = field(default_factory=list)
    chain_cov: list[Array] = field(default_factory=list)
    # Running sums behind :meth:`path_covariance`, extended on demand: entry k sums the
    # increments 1..k as W Σ Wᵀ, and counts the chain breaks among them.
    # Room for more entries than ``_done`` (capacity doubling): appending by concatenation
    # copied every sum at each loop closure (0.3 ms per closure on city10000's 10,000 nodes).
    _sums: Array = field(default_factory=lambda: np.zeros((1, 3, 3)), repr=False)
    _breaks: Array = field(default_factory=lambda: np.zeros(1, dtype=np.int64), repr=False)
    _done: int = field(default=1, repr=False)

    def nearest(self, stamp_ns: int) -> tuple[int, float]:
        """Index of the keyframe nearest in time, and the gap in seconds."""
        # Stamps increase (odometry stamps do): bisection, not a scan of every keyframe.
        stamps = self.stamps
        j = bisect.bisect_left(stamps, stamp_ns)
        candidates = [k for k in (j - 1, j) if 0 <= k < len(stamps)]
        i = min(candidates, key=lambda k: (abs(stamps[k] - stamp_ns), k))
        return i, abs(int(stamps[i]) - stamp_ns) * 1e-9

    def path_covariance(self, lo: int, hi: int) -> Array | None:
        """Dead-reckoning covariance of keyframe ``hi`` relative to ``lo`` (``lo < hi``), in
        ``hi``'s frame: the increments ``lo+1 .. hi`` carried to ``hi`` and summed; ``None``
        where the chain breaks between them.

        Carrying increment k to the end is ``Ad(T_k⁻¹ T_hi)⁻¹ = D_hi E_hi W_k``, with
        ``W_k = [[R_k, −J p_k], [0, 1]]``, ``E = [[I, J p_hi], [0, 1]]`` and ``D = diag(R_hiᵀ,
        1)`` (J the 90° rotation), so the sum is ``D E (S_hi − S_lo) Eᵀ Dᵀ`` over running
        sums ``S_k = Σ W Σ Wᵀ``: constant time for a closure across any loop."""
        self._extend()
        if self._breaks[hi] != self._breaks[lo]:
            return None
        x, y, yaw = self.odom[hi]
        c, s = math.cos(yaw), math.sin(yaw)
        carry = np.array([[c, s, -c * y + s * x], [-s, c, s * y + c * x], [0.0, 0.0, 1.0]])
        return carry @ (self._sums[hi] - self._sums[lo]) @ carry.T

    def _extend(self) -> None:
        done, n = self._done, len(self.chain_cov)
        if done > n:  # the lists were replaced (a load): start over
            done = 1
        if done >= n:
            return
        cov = np.asarray(self.chain_cov[done:n], dtype=float).reshape(-1, 3, 3)
        poses = np.asarray(self.odom[done:n], dtype=float).reshape(-1, 3)
        broken = np.isnan(cov).any(axis=(1, 2))
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        w = np.zeros((len(poses), 3, 3))
        w[:, 0, 0], w[:, 0, 1], w[:, 1, 0], w[:, 1, 1] = c, -s, s, c
        w[:, 0, 2], w[:, 1, 2], w[:, 2, 2] = poses[:, 1], -poses[:, 0], 1.0
        terms = np.einsum("kij,kjl,kml->kim", w, np.where(broken[:, None, None], 0.0, cov), w)
        if n > len(self._sums):
            size = max(n, 2 * len(self._sums))
            self._sums = np.concatenate([self._sums[:done], np.zeros((size - done, 3, 3))])
            self._breaks = np.concatenate([self._breaks[:done],
                                           np.zeros(size - done, dtype=np.int64)])
        self._sums[done:n] = self._sums[done - 1] + np.cumsum(terms, axis=0)
        self._breaks[done:n] = self._breaks[done - 1] + np.cumsum(broken)
        self._done = n


class Mapper:
    """See the module docstring. Nodes are numbered from 0 in the order they are made."""

    def __init__(self, config: MapperConfig | None = None,
                 solver: SolverConfig | None = None) -> None:
        self.config = config or MapperConfig()
        self._solver_config = solver
        robust = RobustConfig() if self.config.robust else None
        self.h2o = OnlineH2O(planar=True, config=solver,
                             online=OnlineConfig(d_max=self.config.d_max or None,
                                                 background=self.config.solve_in,
                                                 robust=robust))
        self.keyframes = Keyframes()
        self.track = OdometryTrack()
        self.rejected: Counter[str] = Counter()
        self.accepted: Counter[str] = Counter()
        self.datum: tuple[float, float, float] | None = None
        self.continue_from: int | None = None
        self.last_report = StepReport()
        # Loop closures and fixes stamped after the newest odometry wait for it (messages
        # on different topics arrive in any order): (stamp needed, input, retry).
        self.held: list[tuple[int, str, Callable[[], object]]] = []
        #: Held inputs refused when retried or dropped: (input, reason), for the node to log
        #: and count (``"loop_closure"`` or ``"gps"``).
        self.released_errors: list[tuple[str, str]] = []

    # -- inputs -------------------------------------------------------------------------------

    def reject(self, reason: str, message: str) -> InputError:
        """Count a rejection and return the error to raise."""
        self.rejected[reason] += 1
        return InputError(message)

    def add_odometry(self, stamp_ns: int, pose: Array) -> int | None:
        """An odometry sample ``(x, y, yaw)`` in ``odom``; returns the new node, if any.

        Raises:
            InputError: a stamp not after the previous sample's, a non-finite pose or one
                beyond :data:`MAX_COORDINATE_M`; the track and the graph are unchanged.
        """
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise self.reject("odometry_invalid", f"odometry pose {pose!r} is not finite")
        if max(abs(pose[0]), abs(pose[1])) > MAX_COORDINATE_M:
            raise self.reject("odometry_out_of_range",
                              f"odometry position ({pose[0]:.3g}, {pose[1]:.3g}) m is beyond "
                              f"{MAX_COORDINATE_M:.0e} m")
        if self.track.size and stamp_ns <= self.track.latest()[0]:
            raise self.reject(
                "odometry_time_backwards",
                f"odometry stamp {stamp_ns} is not after the previous {self.track.latest()[0]}",
            )
        node = self._add_keyframe(stamp_ns, pose) if self._wants_keyframe(stamp_ns, pose) else None
        self.track.append(stamp_ns, pose)
        self.accepted["odometry"] += 1
        self._release_held(stamp_ns)
        return node

    def _hold(self, needed_ns: int, what: str, retry: Callable[[], object]) -> bool:
        """Hold input ``what`` until odometry reaches ``needed_ns``; returns whether it was
        held."""
        if self.track.size and needed_ns <= self.track.latest()[0]:
            return False
        if len(self.held) >= MAX_HELD:
            _, oldest, _ = self.held.pop(0)
            self.rejected["held_overflow"] += 1
            self.released_errors.append((oldest, f"more than {MAX_HELD} inputs wait for "
                                                 "odometry: the oldest was dropped"))
        self.held.append((needed_ns, what, retry))
        self.accepted["held"] += 1
        return True

    def _release_held(self, latest_ns: int) -> None:
        ready = [item for item in self.held if item[0] <= latest_ns]
        if not ready:
            return
        self.held = [item for item in self.held if item[0] > latest_ns]
        for _, what, retry in ready:
            try:
                retry()
            except InputError as exc:
                self.released_errors.append((what, str(exc)))

    def _wants_keyframe(self, stamp_ns: int, pose: Array) -> bool:
        if not self.keyframes.stamps or self.continue_from is not None:
            return True
        cfg = self.config
        d = planar_between(self.keyframes.odom[-1], pose)
        dt = (stamp_ns - self.keyframes.stamps[-1]) * 1e-9
        return bool((cfg.keyframe_distance and math.hypot(d[0], d[1]) >= cfg.keyframe_distance)
                    or (cfg.keyframe_angle and abs(d[2]) >= cfg.keyframe_angle)
                    or (cfg.keyframe_period and dt >= cfg.keyframe_period))

    def _add_keyframe(self, stamp_ns: int, pose: Array) -> int:
        kf = self.keyframes
        previous = self.continue_from if self.continue_from is not None else len(kf.stamps) - 1
        if previous < 0:
            node = self.h2o.add_pose(geo.yaw_to_matrix(pose[2]), np.array([*pose[:2], 0.0]))
            kf.chain_cov.append(np.full((3, 3), np.nan))
        else:
            # Everything that can refuse the sample comes before anything is stored.
            d = planar_between(kf.odom[previous], pose)
            cov = self.increment_covariance(d)
            info = self._information(planar_info, cov, "odometry_not_finite", "odometry increment")
            node = self.h2o.solver.num_nodes
            self.h2o.add_edge(EdgeKind.RELATIVE, previous, node, geo.yaw_to_matrix(d[2]),
                              np.array([d[0], d[1], 0.0]), info)
            kf.chain_cov.append(cov)
        self.continue_from = None
        kf.stamps.append(int(stamp_ns))
        kf.odom.append(pose.copy())
        return node

    def increment_covariance(self, d: Array) -> Array:
        """Covariance of an odometry increment ``(dx, dy, dyaw)`` (the noise model).

        Raises:
            InputError: an increment whose covariance is not finite (``odometry_not_finite``;
                not reached for poses within :data:`MAX_COORDINATE_M`).
        """
        cfg = self.config
        dist = math.hypot(d[0], d[1])
        sig_t = max(cfg.odom_min_sigma_m, cfg.odom_sigma_per_m * dist)
        sig_r = max(cfg.odom_min_sigma_rad,
                    cfg.odom_yaw_sigma_per_rad * abs(d[2]) + cfg.odom_yaw_sigma_per_m * dist)
        # Products, not ``**``: a float power that overflows raises OverflowError.
        cov = np.diag([sig_t * sig_t, sig_t * sig_t, sig_r * sig_r])
        if not np.all(np.isfinite(cov)):
            raise self.reject("odometry_not_finite",
                              f"odometry increment {d.tolist()} has no finite covariance")
        return cov

    def _information(self, invert: Callable[[Array], Array], cov: Array, reason: str,
                     what: str) -> Array:
        """``invert(cov)`` (an information matrix), refused with ``reason`` unless finite."""
        with np.errstate(all="ignore"):
            try:
                info = invert(cov)
            except np.linalg.LinAlgError as exc:
                raise self.reject(reason, f"{what}: covariance not invertible ({exc})") from None
        if not np.all(np.isfinite(info)):
            raise self.reject(reason, f"{what}: information matrix not finite")
        return info

    def _check_measurement(self, what: str, reason: str, position: Array, cov: Array) -> None:
        """A loop closure's or fix's position (m) finite and within :data:`MAX_COORDINATE_M`,
        its covariance finite, symmetric, with sigmas within :data:`MIN_SIGMA` ..
        :data:`MAX_SIGMA`."""
        position = np.asarray(position, dtype=float)
        if not np.all(np.isfinite(position)):
            raise self.reject(f"{reason}_not_finite", f"{what} {position.tolist()} is not finite")
        if float(np.max(np.abs(position), initial=0.0)) > MAX_COORDINATE_M:
            raise self.reject(f"{reason}_out_of_range",
                              f"{what} {position.tolist()} m is beyond {MAX_COORDINATE_M:.0e} m")
        if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
            raise self.reject(f"{reason}_not_finite", f"{what} covariance is not finite")
        scale = float(np.max(np.abs(cov)))
        if scale > MAX_SIGMA**2 or not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12 * scale):
            raise self.reject(f"{reason}_bad_covariance",
                              f"{what} covariance is not symmetric or beyond "
                              f"{MAX_SIGMA:.0e}² (largest entry {scale:.3g})")
        low = float(np.linalg.eigvalsh(0.5 * (cov + cov.T))[0])
        if not low >= MIN_SIGMA**2:
            raise self.reject(f"{reason}_bad_covariance",
                              f"{what} covariance has a sigma below {MIN_SIGMA:.0e} "
                              f"(smallest eigenvalue {low:.3g})")

    def add_loop_closure(self, from_ref: int | tuple[str, int], to_ref: int | tuple[str, int],
                         delta: Array, cov3: Array) -> int | None:
        """A relative pose ``delta = (dx, dy, dyaw)`` of *to* in *from*'s frame.

        ``from_ref`` / ``to_ref`` are node ids (``int``) or ``("stamp", stamp_ns)``. A stamp
        newer than the newest odometry is held until odometry reaches it (returns ``None``).

        Raises:
            InputError: a non-finite or out-of-range measurement or covariance (bounds in
                the module docstring), an unknown node, a stamp with no keyframe near it,
                both ends on one node, or a closure the χ² gate rejects (a χ² that is not
                finite included).
        """
        delta = np.asarray(delta, dtype=float)
        cov3 = np.asarray(cov3, dtype=float)
        if delta.shape != (3,) or not np.isfinite(delta[2]):
            raise self.reject("loop_not_finite", f"loop closure {delta.tolist()} is not finite")
        self._check_measurement("loop closure", "loop", delta[:2], cov3)
        needed = max([r[1] for r in (from_ref, to_ref) if not isinstance(r, int)], default=0)
        if needed and self._hold(needed, "loop_closure", lambda: self.add_loop_closure(
                from_ref, to_ref, delta, cov3)):
            return None
        a, carry_a = self._resolve(from_ref)
        b, carry_b = self._resolve(to_ref)
        if a == b:
            raise self.reject("loop_same_node",
                              f"loop closure joins node {a} to itself ({from_ref}, {to_ref})")
        meas = planar_compose(planar_compose(carry_a, delta), planar_between(carry_b, np.zeros(3)))
        if not np.all(np.isfinite(meas)):
            raise self.reject("loop_not_finite",
                              f"loop closure {a}->{b} carried onto keyframes is not finite")
        info = self._information(planar_info, cov3, "loop_not_finite", "loop closure")
        passes = self._gate(a, b, meas, cov3)
        args = (EdgeKind.RELATIVE, a, b, geo.yaw_to_matrix(meas[2]),
                np.array([meas[0], meas[1], 0.0]), info)
        if not passes:  # robust: kept at weight 0 for the exact solves to weigh
            self.accepted["loop_closure_held"] += 1
            return self.h2o.add_held_edge(*args)
        edge = self.h2o.add_edge(*args)
        self.accepted["loop_closure"] += 1
        return edge

    def _resolve(self, ref: int | tuple[str, int]) -> tuple[int, Array]:
        """Node of a reference and the pose of the referenced instant in the node's frame."""
        n = len(self.keyframes.stamps)
        if isinstance(ref, int):
            if not 0 <= ref < n:
                raise self.reject("loop_unknown_node",
                                  f"loop closure names node {ref}; the graph has {n} nodes")
            return ref, np.zeros(3)
        stamp = int(ref[1])
        if not n:
            raise self.reject("loop_unknown_stamp", "loop closure before the first keyframe")
        node, gap = self.keyframes.nearest(stamp)
        if gap > self.config.loop_stamp_tolerance:
            raise self.reject(
                "loop_unknown_stamp",
                f"loop closure stamp {stamp} is {gap:.3f} s from the nearest keyframe "
                f"(tolerance {self.config.loop_stamp_tolerance} s)")
        if not self.track.covers(stamp):
            return node, np.zeros(3)
        return node, planar_between(self.keyframes.odom[node], self.track.at(stamp))

    def _gate(self, a: int, b: int, meas: Array, cov3: Array) -> bool:
        """Whether the closure passes the χ² gate. Without robust estimation a closure that
        does not is refused (``loop_gated``); with it, it is held (returns False)."""
        if not math.isfinite(self.config.loop_gate_chi2):
            return True
        lo, hi = min(a, b), max(a, b)
        path_cov = self.keyframes.path_covariance(lo, hi)
        if path_cov is None:
            return True  # ends in different subtrees: nothing to weigh the error against
        if a > b:  # the path covariance was built in the later node's frame
            d = planar_between(self.keyframes.odom[hi], self.keyframes.odom[lo])
            ad_swap = _adjoint_inverse(d[None, :])[0]
            path_cov = ad_swap @ path_cov @ ad_swap.T
        R_a, t_a = self.h2o.solver.world_pose(a)
        R_b, t_b = self.h2o.solver.world_pose(b)
        est = planar_between(np.array([t_a[0], t_a[1], geo.matrix_to_yaw(R_a)]),
                       np.array([t_b[0], t_b[1], geo.matrix_to_yaw(R_b)]))
        err = planar_between(meas, est)
        with np.errstate(all="ignore"):
            try:
                chi2 = float(err @ np.linalg.solve(cov3 + path_cov, err))
            except np.linalg.LinAlgError:
                chi2 = math.nan
        if not math.isfinite(chi2):  # ``nan > gate`` is False: never let NaN through
            raise self.reject("loop_not_finite",
                              f"loop closure {a}->{b}: chi2 {chi2} is not finite (error "
                              f"{err.tolist()})")
        if chi2 > self.config.loop_gate_chi2 and self.config.robust:
            return False
        if chi2 > self.config.loop_gate_chi2:
            raise self.reject(
                "loop_gated",
                f"loop closure {a}->{b} rejected: chi2 {chi2:.1f} > gate "
                f"{self.config.loop_gate_chi2:.1f} (error {err[0]:.2f} m, {err[1]:.2f} m, "
                f"{err[2]:.3f} rad)")
        return True

    def add_gps(self, stamp_ns: int, enu: Array, cov3: Array) -> int | None:
        """A GPS fix (ENU metres, 3×3 covariance); returns the edge (``None`` while the fix
        waits for odometry to reach its stamp).

        Raises:
            InputError: a non-finite or out-of-range position or covariance (bounds in the
                module docstring), or no keyframe or odometry sample near the fix in time.
        """
        enu = np.asarray(enu, dtype=float)
        cov3 = np.asarray(cov3, dtype=float)
        if enu.shape != (3,):
            raise self.reject("gps_not_finite", f"GPS position {enu.tolist()} is not (3,)")
        self._check_measurement("GPS position", "gps", enu, cov3)
        gps_info = self._information(np.linalg.inv, cov3, "gps_not_finite", "GPS fix")
        if self._hold(stamp_ns, "gps", lambda: self.add_gps(stamp_ns, enu, cov3)):
            return None
        node = self._gps_node(stamp_ns)
        R, _ = self.h2o.solver.world_pose(node)
        lever = np.array([*self.config.gps_lever_arm, 0.0])
        meas_t = enu - R @ lever
        if not np.all(np.isfinite(meas_t)):
            raise self.reject("gps_not_finite", f"GPS fix at {stamp_ns}: antenna position "
                              f"{meas_t.tolist()} is not finite")
        info = np.zeros((6, 6))
        info[:3, :3] = gps_info
        args = (EdgeKind.POSITION, EARTH, node, np.eye(3), meas_t, info)
        if not self._gps_passes(node, meas_t, cov3):  # robust: held for the exact solves
            self.accepted["gps_held"] += 1
            return self.h2o.add_held_edge(*args)
        edge = self.h2o.add_edge(*args)
        self.accepted["gps"] += 1
        return edge

    def _gps_passes(self, node: int, meas_t: Array, cov3: Array) -> bool:
        """Whether a fix on a node already placed by GPS lies within the χ² gate of the map:
        its error weighed by its own covariance plus :data:`GPS_GATE_SIGMA_M` for the map's
        own uncertainty. A multipath jump (tens of metres) is held rather than relaxed into
        the map by the budgeted updates; the robust exact solves weigh it again with the
        map's real uncertainty and re-admit it if it fits."""
        if not (self.config.robust and math.isfinite(self.config.loop_gate_chi2)
                and self.h2o.gps_aligned(node)):
            return True
        _, t = self.h2o.solver.world_pose(node)
        err = (t - meas_t)[:2]
        S = cov3[:2, :2] + GPS_GATE_SIGMA_M**2 * np.eye(2)
        with np.errstate(all="ignore"):
            chi2 = float(err @ np.linalg.solve(S, err))
        return bool(chi2 <= self.config.loop_gate_chi2)

    def _gps_node(self, stamp_ns: int) -> int:
        tol = self.config.gps_time_tolerance
        best = (math.inf, -1)
        if self.keyframes.stamps:
            node, gap = self.keyframes.nearest(stamp_ns)
            best = (gap, node)
        if self.track.size:
            latest_stamp, pose = self.track.latest()
            gap = abs(latest_stamp - stamp_ns) * 1e-9
            newer = not self.keyframes.stamps or latest_stamp > self.keyframes.stamps[-1]
            if newer and gap < best[0] and gap <= tol:
                return self._add_keyframe(latest_stamp, pose)
        if best[0] > tol:
            raise self.reject("gps_no_keyframe",
                              f"GPS fix at {stamp_ns}: no odometry within {tol} s")
        return best[1]

    # -- solving ------------------------------------------------------------------------------

    def step(self, budget_s: float | None) -> StepReport:
        """One solver step within ``budget_s`` seconds (``None``: no limit; the configured
        budget is ``self.config.budget_s``)."""
        d_max = self.config.d_max or None
        if self.h2o.online.d_max != d_max:
            self.h2o.online = replace(self.h2o.online, d_max=d_max)
        self.last_report = self.h2o.step(budget_s)
        return self.last_report

    def callback_step(self, started_s: float) -> StepReport:
        """The step that ends an input's callback: what is left of ``budget_ms`` since the
        callback began at ``started_s`` (``time.perf_counter()``), so the callback as a whole
        keeps the budget (``budget_ms`` of 0: no limit)."""
        if not self.config.budget_ms:
            return self.step(None)
        left_s = 1e-3 * self.config.budget_ms - (time.perf_counter() - started_s)
        return self.step(max(left_s, 0.0))

    def exact_solve(self) -> tuple[float, float]:
        """Solve the graph exactly now (damped Gauss–Newton to convergence) and merge it;
        returns χ² before and after."""
        before = self.chi2()
        self.h2o.converge()
        return before, self.chi2()

    def chi2(self) -> float:
        """χ² of every edge at the current estimate, each weighted by its robust weight (the
        χ² the back end minimizes: a dropped outlier adds nothing)."""
        return float(np.sum(self.edge_chi2()))

    def edge_chi2(self) -> Array:
        """Each edge's χ² at the current estimate times its robust weight."""
        if not self.h2o.solver.num_edges:
            return np.zeros(0)
        return edge_chi2(self.graph()) * self.h2o.solver.weight

    def decisions(self) -> dict[str, int]:
        """The robust back end's account: loop closures and GPS fixes in the map now
        (``accepted``), held or dropped (weight 0), and the decisions merged solutions
        reversed (``dropped`` after being in, ``readmitted`` after being out)."""
        s = self.h2o.solver
        states = edge_states(s.weight, odometry_edges(s.kind, s.a, s.b))
        closures = (s.kind == EdgeKind.RELATIVE) & (states != EdgeState.TRUSTED)
        fixes = s.kind == EdgeKind.POSITION
        out: dict[str, int] = {}
        for name, mask in (("loop_closures", closures), ("gps_fixes", fixes)):
            out[f"{name} in"] = int(np.count_nonzero(mask & (states == EdgeState.ACCEPTED)))
            out[f"{name} down-weighted"] = int(np.count_nonzero(
                mask & (states == EdgeState.DOWNWEIGHTED)))
            out[f"{name} out"] = int(np.count_nonzero(mask & (states == EdgeState.DROPPED)))
        out["decisions dropped"] = self.h2o.decisions["dropped"]
        out["decisions readmitted"] = self.h2o.decisions["readmitted"]
        return out

    def optimality(self, per_edge_chi2: Array | None = None) -> tuple[float, int]:
        """χ² of the edges in the last converged exact solution, at the current estimate, over
        that solution's χ² (1 right after it is merged; NaN before the first), and the edges
        not in it. ``per_edge_chi2``: every edge's weighted χ² now (:meth:`edge_chi2`), when
        the caller has it."""
        state = self.h2o.converger.state
        outside = self.h2o.converger.outside()
        if state.converged_edges == 0:
            return math.nan, outside
        if per_edge_chi2 is None:
            per_edge_chi2 = self.edge_chi2()
        now = float(np.sum(per_edge_chi2[: state.converged_edges]))
        # Rounding leaves ~1e-25 on a graph that fits exactly (a chain): a floor of 1e-12
        # per edge keeps that from reading as a ratio far from 1.
        floor = 1e-12 * state.converged_edges
        return (now + floor) / (state.converged_chi2 + floor), outside

    def close(self) -> None:
        """Stop the exact solver's worker process, if any."""
        self.h2o.close()

    # -- outputs ------------------------------------------------------------------------------

    @property
    def num_nodes(self) -> int:
        """Keyframes in the graph."""
        return len(self.keyframes.stamps)

    def poses(self) -> Array:
        """Optimized poses ``(N, 3)`` in ``map``."""
        R, t = self.h2o.solver.world_poses()
        return np.column_stack([t[:, 0], t[:, 1], geo.matrix_to_yaw(R)])

    def graph(self) -> PoseGraph:
        """The graph with the current estimate (edges in the order they were added)."""
        return self.h2o.solver.graph()

    def map_to_odom(self) -> Array:
        """``T_map_odom`` as ``(x, y, yaw)`` from the newest keyframe (identity before it)."""
        if not self.keyframes.stamps:
            return np.zeros(3)
        node = self.num_nodes - 1
        R, t = self.h2o.solver.world_pose(node)
        in_map = np.array([t[0], t[1], float(geo.matrix_to_yaw(R))])
        return planar_compose(in_map, planar_between(self.keyframes.odom[node], np.zeros(3)))

    def map_revision(self) -> int:
        """Bumped when the map moves as a whole (an exact solution merged, a subtree joined or
        aligned to GPS): a kept :meth:`map_to_odom` older than that is wrong by the move."""
        return self.h2o.converger.state.merges + self.h2o.converger.generation

    def latest_pose(self, map_to_odom: Array | None = None) -> tuple[int, Array] | None:
        """Stamp and ``map`` pose of the newest odometry sample (``None`` before any).

        ``map_to_odom``: the correction ``(x, y, yaw)`` to apply, when the caller keeps a
        recent one (:meth:`map_to_odom` composes the newest keyframe's pose down its tree
        ancestry: O(depth), milliseconds on a graph of 20,000 keyframes)."""
        if not self.track.size:
            return None
        stamp, odom = self.track.latest()
        correction = self.map_to_odom() if map_to_odom is None else map_to_odom
        return stamp, planar_compose(correction, odom)

    # -- persistence --------------------------------------------------------------------------

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the map crash-safely (g2o plus a JSON sidecar of the same name, replaced
        together: :mod:`h2o_slam.io.map_store`); returns the sidecar.

        Raises:
            MapStoreError: an empty or non-finite graph (the saved map is kept), or files
                that cannot be written.
        """
        return save_map(path, SavedMap(
            graph=self.graph(),
            stamps_ns=np.asarray(self.keyframes.stamps, dtype=np.int64),
            odom=np.asarray(self.keyframes.odom, dtype=float).reshape(-1, 3),
            chain_cov=np.asarray(self.keyframes.chain_cov, dtype=float).reshape(-1, 3, 3),
            # The odometry track carries stamped loop closures onto keyframes after a
            # restore too (about 1 MB per 10 minutes at 50 Hz).
            track_stamps_ns=self.track.stamps(), track_poses=self.track.poses(),
            datum=self.datum, config=asdict(self.config),
            weights=self.h2o.solver.weight.copy()))

    @classmethod
    def load(cls, path: str | os.PathLike[str], config: MapperConfig | None = None,
             solver: SolverConfig | None = None) -> Mapper:
        """A mapper holding a saved graph; the next odometry sample continues from its
        newest keyframe through the odometry increment since then.

        Raises:
            InputError: a missing, damaged or inconsistent map, with one line naming the
                file, the field and the reason (:func:`h2o_slam.io.map_store.load_map`).
        """
        saved = load_map(path)  # validated before any solver (or worker) exists
        graph = saved.graph
        mapper = cls(config, solver)
        try:
            order: list[int] = []  # the file's edges in the order the solver holds them
            for node, edges in enumerate(arrivals(graph)):
                order += add_arrival(mapper.h2o, graph, node, edges)
            if saved.weights is not None:  # every decision as it was, revised by the next solve
                mapper.h2o.restore_weights(saved.weights[order])
            _set_estimate(mapper.h2o, graph.R, graph.t)
            kf = mapper.keyframes
            kf.stamps = [int(s) for s in saved.stamps_ns]
            kf.odom = [p.copy() for p in saved.odom]
            kf.chain_cov = [c.copy() for c in saved.chain_cov]
            for stamp, pose in zip(saved.track_stamps_ns, saved.track_poses, strict=True):
                mapper.track.append(int(stamp), pose)
            mapper.datum = saved.datum
            mapper.continue_from = graph.num_nodes - 1
            if not (np.all(np.isfinite(mapper.poses())) and math.isfinite(mapper.chi2())):
                raise InputError("the rebuilt estimate is not finite")
        except (InputError, GraphError, ValueError, np.linalg.LinAlgError) as exc:
            mapper.close()
            raise InputError(f"{os.fspath(path)}: graph: cannot be rebuilt: {exc}") from None
        return mapper


def restore(path: str | os.PathLike[str], config: MapperConfig | None = None,
            solver: SolverConfig | None = None) -> Mapper | None:
    """The map ``h2o_node`` continues with ``load_map_on_start``: ``None`` when nothing was
    ever saved at ``path``.

    Raises:
        InputError: as :meth:`Mapper.load` (a damaged map is never replaced by a new one).
    """
    return Mapper.load(path, config, solver) if has_map(path) else None


def _set_estimate(h2o: OnlineH2O, R_world: Array, t_world: Array) -> None:
    """Put a saved world estimate into the tree's local poses and relinearize every edge,
    so a restored graph starts where it was saved rather than where re-adding put it."""
    solver = h2o.solver
    tree = solver.tree
    n = solver.num_nodes
    parent = tree.parent[:n]
    has_parent = parent != EARTH
    R_par = np.where(has_parent[:, None, None], R_world[np.maximum(parent, 0)], np.eye(3))
    t_par = np.where(has_parent[:, None], t_world[np.maximum(parent, 0)], 0.0)
    tree.R[:n], tree.t[:n] = geo.between(R_par, t_par, R_world, t_world)
    solver.refresh_edges(list(range(solver.num_edges)))
