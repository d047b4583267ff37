"""Replay a recording through hybrid_vo_node and h2o_node in-process (``h2o-replay``).

The bag's messages go, in bag-time order, straight into the nodes' ``on_*`` callbacks (no
DDS in between, no executor spinning), and what the nodes publish comes back through
their ``sink``: the run is as fast as the CPU allows and the same bag gives the same
outputs. Time is the bag's: the nodes' periodic work (map→odom, diagnostics, graph) is
called when bag time passes its period, and every output is stamped from its inputs.

The back end's time budget is what makes a robot's output depend on its CPU; a replay
therefore solves every new edge in full unless ``budget_ms`` is given (then it runs as on
the robot, and its outputs depend on timing, which the summary says).

Odometry for the back end: hybrid VO's output when the bag has stereo images, wheel
odometry otherwise (or when asked for).

Writes into the output folder: ``outputs/`` (an MCAP bag of everything the nodes
published), TUM trajectories (``wheel.tum``, ``hybrid_vo.tum``, ``h2o.tum``; also
``ground_truth.tum`` when the bag has it), ``graph.g2o`` (+ ``graph.json``), PNG plots
and ``summary.json``. Damage in the bag ends the replay with a clear error after writing
out everything processed until then.

A replay is complete when it read every message the bag declares on the mapped topics
(``metadata.yaml`` or the storage's index), nothing stopped it, and the back end built a
graph. Anything less is listed in the summary's ``problems`` and, unless
``ReplayOptions.salvage`` accepts a partial replay, raised as :class:`ReplayError` once
every output is written. Every failure after the output folder is made writes
``summary.json``, with the error, whatever stopped the replay.
"""

from __future__ import annotations

import importlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.logging import LoggingSeverity
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message

import msg_adapters as ma
from h2o_slam.app.progress import Progress
from h2o_slam.core.errors import InputError
from h2o_slam.core.graph import EdgeKind
from h2o_slam.core.trajectory_error import ate_m, final_error_m, match_stamps
from h2o_slam.core.warmup import warm_up
from h2o_slam.io.bag_reader import BagMessage, BagReader, BagStats
from h2o_slam.io.bag_writer import BagWriter
from h2o_slam.io.bags import ReplayError, Storage, jazzy_typestore
from h2o_slam.io.plots import (
    Chi2Trace,
    NodeCallbacks,
    chi2_dof,
    chi2_trace,
    node_callbacks,
    plot_callback_times,
    plot_chi2,
    plot_trajectories,
)
from h2o_slam.io.replay_outputs import write_summary, write_tum
from h2o_slam.io.topic_map import REQUIRED_ROLES
from h2o_slam.ros.h2o_node import H2ONode
from hybrid_vo.vo_node import HybridVoNode

NS = 1_000_000_000

#: How the trajectories are named in trajectories.png, by track.
TRACK_LABELS = {"wheel": "wheel odometry", "hybrid_vo": "hybrid VO",
                "h2o_online": "H₂O online (~/pose)", "h2o": "H₂O final graph",
                "ground_truth": "ground truth"}


@dataclass
class ReplayOptions:
    """What ``h2o-replay`` is asked to do.

    Attributes:
        bag: the recording.
        output: folder to write into (created; must be empty if it exists).
        topics: role → topic (see :func:`h2o_slam.io.topic_map.topic_map`).
        odometry: ``"auto"`` (hybrid VO when the bag has images), ``"hybrid"`` or
            ``"wheel"``.
        budget_ms: h2o_node's per-callback budget; ``None`` solves every edge in full.
        use_gps: feed GPS to the back end.
        storage: storage of the output bag.
        graph_period_s: bag seconds between graph outputs (PoseArray/Path/markers) and χ²
            samples; the graph is large, so this is slower than on a robot.
        h2o_params, vo_params: further node parameters.
        progress: draw a progress bar (only on a terminal).
        verbose: let the nodes log warnings (each rejected message); the summary counts
            them either way.
        salvage: accept a partial replay (a damaged bag, messages missing against the
            counts the bag declares, an empty graph): its problems are in the summary and
            :func:`replay` returns instead of raising.
    """

    bag: Path
    output: Path
    topics: dict[str, str | None] = field(default_factory=dict)
    odometry: str = "auto"
    budget_ms: float | None = None
    use_gps: bool = True
    storage: Storage = "mcap"
    graph_period_s: float = 10.0
    h2o_params: dict[str, Any] = field(default_factory=dict)
    vo_params: dict[str, Any] = field(default_factory=dict)
    progress: bool = True
    verbose: bool = False
    salvage: bool = False


@dataclass
class Track:
    """A trajectory collected during the replay: stamps (ns) and planar poses."""

    stamps: list[int] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)

    def add_odometry(self, msg: Any) -> None:
        """Append an ``Odometry``'s planar pose."""
        sample = ma.odometry_from_msg(msg)
        x, y, yaw, _ = sample.planar()
        self.stamps.append(sample.stamp_ns)
        self.poses.append((x, y, yaw))

    def array(self) -> np.ndarray:
        """Poses ``(N, 3)``."""
        return np.asarray(self.poses, dtype=float).reshape(-1, 3)


class Periodic:
    """Calls ``action`` each time bag time passes another ``period_ns``."""

    def __init__(self, period_s: float, action: Callable[[int], None]) -> None:
        self.period_ns = max(1, int(period_s * NS))
        self.action = action
        self.next_ns: int | None = None

    def advance(self, now_ns: int) -> None:
        """Run the action if its time has come (at most once per call)."""
        if self.next_ns is None:
            self.next_ns = now_ns + self.period_ns
        elif now_ns >= self.next_ns:
            self.action(now_ns)
            self.next_ns += self.period_ns * max(1, (now_ns - self.next_ns) // self.period_ns + 1)


class Replay:
    """One replay (see the module docstring); :meth:`run` does it all."""

    def __init__(self, options: ReplayOptions) -> None:
        self.options = options
        self.tracks: dict[str, Track] = {name: Track() for name in
                                         ("wheel", "hybrid_vo", "h2o_online", "ground_truth")}
        self.gps_enu: list[np.ndarray] = []
        # Each callback's (bag time s, ms, what it handled): for callback_times.png and the
        # summary's percentiles.
        self.h2o_calls: list[tuple[float, float, str]] = []
        self.vo_calls: list[tuple[float, float, str]] = []
        self._h2o_total_ms = 0.0
        self._vo_frames = 0
        # (bag time s, χ², its degrees of freedom) of the graph every graph period: chi2.png.
        self.chi2_trace: list[tuple[float, float, int]] = []
        self.now_ns = 0
        self.start_ns: int | None = None
        self.context = Context()
        self.writer: BagWriter | None = None
        self.vo: HybridVoNode | None = None
        self.h2o: H2ONode | None = None
        self.use_vo = False
        self.reader: BagReader | None = None
        self.graph_file: str | None = None
        self.datum: list[float] | None = None  # given to h2o_node (None: the first fix)

    # -- set-up -------------------------------------------------------------------------------

    def _make_nodes(self, reader: BagReader) -> None:
        has_images = {"left_image", "right_image"} <= set(reader.stats.roles)
        mode = self.options.odometry
        if mode == "hybrid" and not has_images:
            raise ReplayError(self.options.bag, "--odometry hybrid needs stereo image topics")
        self.use_vo = mode == "hybrid" or (mode == "auto" and has_images)
        rclpy.init(context=self.context)
        budget = self.options.budget_ms
        # The datum the bag's GPS and ground truth are about is the map's origin, as on the
        # robot that recorded it; h2o_params may still set another.
        stated = {"datum": reader.stats.datum} if reader.stats.datum is not None else {}
        h2o_params = {"budget_ms": budget if budget is not None else 0.0, **stated,
                      **self.options.h2o_params}
        self.datum = h2o_params.get("datum")
        # A replay feeds the node without spinning its timers: the kernels are loaded first,
        # so that the node handles each message as it comes instead of holding it.
        warm_up()
        self.h2o = H2ONode(context=self.context, parameter_overrides=_params(h2o_params))
        self.h2o.sink = self._h2o_output
        if self.use_vo:
            self.vo = HybridVoNode(context=self.context,
                                   parameter_overrides=_params(self.options.vo_params))
            self.vo.sink = self._vo_output
        if not self.options.verbose:
            for node in (self.h2o, self.vo):
                if node is not None:
                    node.get_logger().set_level(LoggingSeverity.ERROR)

    def _close_nodes(self) -> None:
        for node in (self.vo, self.h2o):
            if node is not None:
                node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    # -- outputs of the nodes -----------------------------------------------------------------

    def _record(self, topic: str, msg: Any) -> None:
        if self.writer is not None:
            self.writer.write(topic, msg, self.now_ns)

    def _vo_output(self, topic: str, msg: Any) -> None:
        self._record(topic, msg)
        if topic.endswith("odometry/hybrid"):
            self.tracks["hybrid_vo"].add_odometry(msg)
            self._vo_frames += 1
            self._h2o_call("odometry", self._h2o().on_odom, msg)

    def _h2o_output(self, topic: str, msg: Any) -> None:
        self._record(topic, msg)
        if topic.endswith("h2o_node/pose"):
            track = self.tracks["h2o_online"]
            stamp = ma.stamp_ns(msg.header)
            R, t = ma.pose_to_matrix(msg.pose)
            track.stamps.append(stamp)
            track.poses.append((float(t[0]), float(t[1]), float(np.arctan2(R[1, 0], R[0, 0]))))

    def _h2o(self) -> H2ONode:
        assert self.h2o is not None
        return self.h2o

    def _bag_s(self) -> float:
        return (self.now_ns - (self.start_ns or self.now_ns)) / NS

    def _h2o_call(self, kind: str, handler: Callable[[Any], None], msg: Any) -> None:
        mapper = self._h2o().mapper
        nodes, solves = mapper.num_nodes, mapper.h2o.converger.state.solves
        start = time.perf_counter()
        handler(msg)
        ms = 1e3 * (time.perf_counter() - start)
        self._h2o_total_ms += ms
        # What the callback did, for the plot: an exact solution solved inline (or received
        # from the worker and merged) costs far more than the input's own handling.
        if mapper.h2o.converger.state.solves > solves:
            kind = "exact solve or merge"
        elif kind == "odometry" and mapper.num_nodes > nodes:
            kind = "odometry, new keyframe"
        self.h2o_calls.append((self._bag_s(), ms, kind))

    def _vo_image(self, handler: Callable[[Any], None], msg: Any) -> None:
        # The VO's odometry reaches h2o_node inside this call (both nodes in one process);
        # on a robot they run apart, so the back end's time is taken out of the VO's.
        h2o_before, frames_before = self._h2o_total_ms, self._vo_frames
        start = time.perf_counter()
        handler(msg)
        ms = 1e3 * (time.perf_counter() - start) - (self._h2o_total_ms - h2o_before)
        kind = "stereo pair" if self._vo_frames > frames_before else "image buffered"
        self.vo_calls.append((self._bag_s(), ms, kind))

    # -- dispatch -----------------------------------------------------------------------------

    def _dispatch(self, item: BagMessage) -> None:
        h2o = self._h2o()
        role, msg = item.role, item.msg
        if role == "wheel_odom":
            self._keep(self.tracks["wheel"], msg)
            if self.vo is not None:
                self.vo.on_wheel_odom(msg)
            else:
                self._h2o_call("odometry", h2o.on_odom, msg)
        elif role in ("left_image", "right_image", "left_info", "right_info"):
            if self.vo is not None:
                handler = getattr(self.vo, "on_" + role)
                if role.endswith("image"):
                    self._vo_image(handler, msg)
                else:
                    handler(msg)
        elif role == "gps" and self.options.use_gps:
            self._h2o_call("GPS fix", h2o.on_gps, msg)
        elif role == "loop_closure":
            self._h2o_call("loop closure", h2o.on_loop_closure, msg)
        elif role == "ground_truth":
            self._keep(self.tracks["ground_truth"], msg)

    @staticmethod
    def _keep(track: Track, msg: Any) -> None:
        try:
            track.add_odometry(msg)
        except InputError:
            pass  # the node counts and reports bad input; the record just skips it

    def _sample_graph(self, now_ns: int) -> None:
        h2o = self._h2o()
        h2o.publish_graph()
        chi2 = h2o.mapper.chi2()
        solver = h2o.mapper.h2o.solver
        dof = chi2_dof(solver.kind, solver.b, solver.weight, solver.num_nodes, solver.planar)
        self.chi2_trace.append(((now_ns - (self.start_ns or now_ns)) / NS, chi2, dof))

    def _publish_diagnostics(self, now_ns: int) -> None:
        self._h2o().publish_diagnostics()
        if self.vo is not None:
            self.vo.publish_diagnostics(now_ns)

    # -- the run ------------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        """Replay the bag and write every output; returns the summary (also written).

        Raises:
            ReplayError: the bag cannot be replayed, was damaged part-way, or the replay is
                incomplete (see the module docstring) and ``salvage`` is off; outputs up to
                the problem and ``summary.json`` are written first.
        """
        out = self.options.output
        _prepare_output(out)
        wall_start = time.perf_counter()
        try:
            summary = self._run(wall_start)
        except ReplayError as exc:
            self._failure_summary(exc)
            raise
        except Exception as exc:  # whatever a bag provokes, the summary says it
            error = ReplayError(self.options.bag, f"replay failed: {_why(exc)}")
            self._failure_summary(error)
            raise error from None
        problems = summary["problems"]
        if problems and not self.options.salvage:
            more = f" (and {len(problems) - 1} more in summary.json)" if len(problems) > 1 \
                else ""
            raise ReplayError(self.options.bag, problems[0] + more)
        return summary

    def _run(self, wall_start: float) -> dict[str, Any]:
        out = self.options.output
        error: ReplayError | None = None
        required = REQUIRED_ROLES if self.options.odometry == "hybrid" else ("wheel_odom",)
        with BagReader(self.options.bag, self.options.topics, required) as reader:
            self.reader = reader
            self._make_nodes(reader)
            try:
                with BagWriter(out / "outputs", self.options.storage) as writer:
                    self.writer = writer
                    try:
                        self._loop(reader)
                    except Exception as exc:  # damage, or a message no check foresaw
                        error = _stopped(exc, reader)
                    try:
                        self._finish()
                    except Exception as exc:
                        error = error or _stopped(exc, reader)
                    self.writer = None
                return self._write_outputs(reader, time.perf_counter() - wall_start, error)
            finally:
                self._close_nodes()

    def _failure_summary(self, error: ReplayError) -> None:
        """``summary.json`` for a replay that ended before writing its own."""
        path = self.options.output / "summary.json"
        if path.exists():
            return
        stats = self.reader.stats if self.reader is not None else None
        write_summary(path, {
            "bag": str(self.options.bag), "error": str(error), "complete": False,
            "problems": [error.reason], "salvage": self.options.salvage,
            "messages": dict(stats.counts) if stats else {},
            "declared_messages": _mapped(stats, stats.declared) if stats else {},
            "read_messages": dict(stats.read) if stats else {},
            "topics_in_bag": stats.topics if stats else {},
        })

    def _loop(self, reader: BagReader) -> None:
        h2o = self._h2o()
        timers = [Periodic(h2o.config.transform_publish_period,
                           lambda _: h2o.publish_map_to_odom()),
                  Periodic(h2o.config.diagnostics_period, self._publish_diagnostics),
                  Periodic(self.options.graph_period_s, self._sample_graph)]
        if self.options.budget_ms is not None:  # with no budget nothing is ever deferred
            timers.append(Periodic(h2o.config.idle_period, lambda _: h2o.idle_step()))
        progress = Progress((reader.end_ns - reader.start_ns) / NS, "replay") \
            if self.options.progress else None
        for item in reader.messages():
            self.now_ns = item.stamp_ns
            if self.start_ns is None:
                self.start_ns = item.stamp_ns
            self._dispatch(item)
            for timer in timers:
                timer.advance(item.stamp_ns)
            if progress is not None:
                progress.update((item.stamp_ns - reader.start_ns) / NS)
        if progress is not None:
            progress.close()

    def _finish(self) -> None:
        h2o = self._h2o()
        if h2o.mapper.num_nodes:
            self._sample_graph(self.now_ns)
            h2o.publish_map_to_odom()
        self._publish_diagnostics(self.now_ns)

    # -- files --------------------------------------------------------------------------------

    def _write_outputs(self, reader: BagReader, wall_s: float,
                       error: ReplayError | None) -> dict[str, Any]:
        out = self.options.output
        mapper = self._h2o().mapper
        tracks = {name: (np.asarray(t.stamps, dtype=np.int64), t.array())
                  for name, t in self.tracks.items()}
        if mapper.num_nodes:
            tracks["h2o"] = (np.asarray(mapper.keyframes.stamps, dtype=np.int64), mapper.poses())
            try:
                mapper.save(out / "graph.g2o")
            except InputError as exc:  # refused (e.g. no edges): the summary says why
                self.graph_file = f"not saved: {exc}"
        files = {}
        for name, (stamps, poses) in tracks.items():
            if len(stamps) and name != "h2o_online":
                files[name] = str(write_tum(out / f"{name}.tum", stamps, poses[:, :2],
                                            yaw_rad=poses[:, 2]))
        gps = _gps_points(mapper)
        drawn = {TRACK_LABELS[k]: v for k, v in tracks.items() if len(v[0])}
        plot_trajectories(out / "trajectories.png", {k: v[1] for k, v in drawn.items()}, gps,
                          stamps_ns={k: v[0] for k, v in drawn.items()})
        plot_callback_times(out / "callback_times.png", self.callback_panels())
        if self.chi2_trace:
            plot_chi2(out / "chi2.png", {"H₂O graph": self.chi2_samples()})
        summary = self._summary(reader, tracks, wall_s, error, files)
        write_summary(out / "summary.json", summary)
        return summary

    def chi2_samples(self) -> Chi2Trace:
        """What chi2.png shows: the graph's χ² and its degrees of freedom over bag time, and
        what the graph holds at the end."""
        mapper = self._h2o().mapper
        held = mapper.decisions() if mapper.num_nodes else {}
        closures, fixes = held.get("loop_closures in", 0), held.get("gps_fixes in", 0)
        holds = ", ".join(["odometry", f"{closures} loop closure{'s' * (closures != 1)}"]
                          + ([f"{fixes} GPS fixes"] if fixes else []))
        return chi2_trace(self.chi2_trace, holds=holds)

    def callback_panels(self) -> dict[str, NodeCallbacks]:
        """What callback_times.png shows: each node's callbacks against bag time."""
        budget = self.options.budget_ms
        panels = {"h2o_node": node_callbacks(
            self.h2o_calls, budget_ms=budget or None,
            note="" if budget else "no budget (budget_ms 0): every edge solved in full, "
                                   "exact solves inline")}
        if self.vo is not None:
            pairs = [t for t, _, kind in self.vo_calls if kind == "stereo pair"]
            period_ms = 1e3 * float(np.median(np.diff(pairs))) if len(pairs) > 2 else None
            panels["hybrid_vo_node"] = node_callbacks(
                self.vo_calls, budget_ms=period_ms, hidden_kinds=("image buffered",),
                budget_label=f"frame interval {period_ms or 0:.0f} ms (real-time limit)",
                note="the image callback that completes a stereo pair (the frame's work)")
        return panels

    def _summary(self, reader: BagReader, tracks: dict[str, tuple[np.ndarray, np.ndarray]],
                 wall_s: float, error: ReplayError | None,
                 files: dict[str, str]) -> dict[str, Any]:
        h2o = self._h2o()
        duration_s = ((self.now_ns - self.start_ns) / NS) if self.start_ns is not None else 0.0
        summary: dict[str, Any] = {
            "bag": str(self.options.bag),
            "odometry": "hybrid_vo" if self.use_vo else "wheel",
            "budget_ms": self.options.budget_ms,
            "deterministic": self.options.budget_ms is None,
            "bag_duration_s": duration_s,
            "wall_time_s": wall_s,
            "speed_x_realtime": duration_s / wall_s if wall_s > 0 else None,
            "messages": dict(reader.stats.counts),
            "out_of_order": dict(reader.stats.out_of_order),
            "salvaged": reader.stats.salvaged,
            "datum": self.datum,
            "error": None if error is None else str(error),
            "graph": {"nodes": h2o.mapper.num_nodes,
                      "edges": h2o.mapper.graph().num_edges if h2o.mapper.num_nodes else 0,
                      "chi2": self.chi2_trace[-1][1] if self.chi2_trace else None},
            "h2o_callback_ms": _percentiles(_times_ms(self.h2o_calls)),
            "vo_callback_ms": _percentiles(_times_ms(self.vo_calls)),
            "rejected": {k: v for k, v in (h2o.rejected + h2o.mapper.rejected).items()},
            "accepted": dict(h2o.mapper.accepted),
            "files": files,
        }
        summary["accuracy"] = _accuracy(tracks)
        if self.graph_file is not None:
            summary["graph"]["file"] = self.graph_file
        summary.update(self._completeness(reader, error))
        return summary

    def _completeness(self, reader: BagReader, error: ReplayError | None) -> dict[str, Any]:
        """What was read against what the bag declares, and every reason the replay is
        not complete."""
        stats = reader.stats
        problems = [] if error is None else [error.reason]
        short = stats.shortfall()
        if short:
            declared = sum(d for d, _ in short.values())
            read = sum(r for _, r in short.values())
            problems.append(f"read {read} of the {declared} messages the bag declares on "
                            + ", ".join(f"{t} ({r} of {d})" for t, (d, r) in short.items()))
        odom_topic = stats.roles.get("wheel_odom", "?")
        if stats.counts["wheel_odom"] == 0:
            problems.append(f"no message on {odom_topic} (wheel_odom): nothing to map")
        elif not self._h2o().mapper.num_nodes:
            problems.append("the graph is empty: no odometry was accepted (see rejected)")
        return {"declared_messages": _mapped(stats, stats.declared),
                "read_messages": {t: stats.read[t] for t in sorted(set(stats.roles.values()))},
                "lost_messages": {t: d - r for t, (d, r) in short.items()},
                "complete": not problems, "problems": problems,
                "salvage": self.options.salvage}


def _why(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if isinstance(exc, ReplayError) else f"{text} ({type(exc).__name__})"


def _stopped(exc: BaseException, reader: BagReader) -> ReplayError:
    if isinstance(exc, ReplayError):
        return exc
    delivered = sum(reader.stats.counts.values())
    return ReplayError(reader.path, f"stopped after {delivered} messages: {_why(exc)}")


def _mapped(stats: BagStats, counts: dict[str, int]) -> dict[str, int]:
    """``counts`` of the topics mapped to a role."""
    topics = set(stats.roles.values())
    return {t: n for t, n in sorted(counts.items()) if t in topics}


def _times_ms(calls: list[tuple[float, float, str]]) -> np.ndarray:
    return np.array([ms for _, ms, _ in calls], dtype=float)


def _percentiles(ms: np.ndarray) -> dict[str, float] | None:
    if not len(ms):
        return None
    return {"count": int(len(ms)), "mean": float(ms.mean()),
            "p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "max": float(ms.max())}


def _accuracy(tracks: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """ATE (after a planar rigid alignment) and final position error of each trajectory
    against the ground truth, matched by stamp."""
    truth_stamps, truth = tracks.get("ground_truth", (np.zeros(0), np.zeros((0, 3))))
    if not len(truth_stamps):
        return {}
    result = {}
    for name, (stamps, poses) in tracks.items():
        if name == "ground_truth" or not len(stamps):
            continue
        i, j = match_stamps(stamps, truth_stamps, NS // 20)
        if len(i) < 3:
            continue
        result[name] = {"ate_m": ate_m(poses[i, :2], truth[j, :2]),
                        "final_error_m": final_error_m(poses[i, :2], truth[j, :2]),
                        "matched": int(len(i))}
    return result


def _gps_points(mapper: Any) -> np.ndarray | None:
    if not mapper.num_nodes:
        return None
    graph = mapper.graph()
    gps = graph.kind == EdgeKind.POSITION
    return graph.meas_t[gps] if np.any(gps) else None


def _params(values: dict[str, Any]) -> list[Parameter]:
    return [Parameter(name, value=value) for name, value in values.items()]


def _prepare_output(out: Path) -> None:
    if out.exists() and any(out.iterdir()):
        raise ReplayError(out, "output folder exists and is not empty")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ReplayError(out, f"cannot create the output folder ({exc})") from None


def replay(options: ReplayOptions) -> dict[str, Any]:
    """Run one replay (see :class:`Replay`)."""
    return Replay(options).run()


def format_summary(summary: dict[str, Any]) -> str:
    """A few lines for the terminal."""
    lines = [f"replayed {summary['bag_duration_s']:.1f} s of bag in "
             f"{summary['wall_time_s']:.1f} s "
             f"({summary['speed_x_realtime'] or 0:.1f}x real time), odometry from "
             f"{summary['odometry']}; graph {summary['graph']['nodes']} nodes, "
             f"{summary['graph']['edges']} edges"]
    for name, acc in summary.get("accuracy", {}).items():
        lines.append(f"  {name:<12} ATE {acc['ate_m']:.3f} m, final error "
                     f"{acc['final_error_m']:.3f} m")
    if summary.get("rejected"):
        lines.append("  rejected: " + json.dumps(summary["rejected"]))
    return "\n".join(lines)


def publish_realtime(bag: Path, topics: dict[str, str | None], rate: float,
                     delay_s: float = 1.0) -> int:
    """Publish the mapped topics at the recorded pace (``rate`` × real time).

    Every publisher exists ``delay_s`` before the first message, so that subscribers
    already running have matched them (DDS drops what is published before a match), and
    up to ``delay_s`` longer while one has no subscriber yet: on a busy machine discovery
    can take longer than the delay.
    """
    if not rate > 0.0:
        raise ReplayError("--rate", f"must be > 0, got {rate}")
    if not delay_s >= 0.0:
        raise ReplayError("--delay", f"must be >= 0, got {delay_s}")
    store = jazzy_typestore()
    context = Context()
    rclpy.init(context=context)
    node = rclpy.create_node("h2o_replay", context=context)
    try:
        with BagReader(bag, topics, required=()) as reader:
            publishers = {
                topic: node.create_publisher(_message_class(reader.stats.topics[topic]), topic,
                                             100)
                for topic in reader.stats.roles.values()}
            time.sleep(delay_s)
            _await_subscribers(list(publishers.values()), delay_s)
            wall0, bag0 = time.monotonic(), None
            for item in reader.messages():
                bag0 = item.stamp_ns if bag0 is None else bag0
                delay = (item.stamp_ns - bag0) * 1e-9 / rate - (time.monotonic() - wall0)
                if delay > 0:
                    time.sleep(delay)
                publisher = publishers[item.topic]
                raw = store.serialize_cdr(item.msg, item.type_name)
                publisher.publish(deserialize_message(bytes(raw), publisher.msg_type))
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    return 0


def _await_subscribers(publishers: list[Any], timeout_s: float) -> None:
    """Until every publisher has matched a subscriber, at most ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while (any(p.get_subscription_count() == 0 for p in publishers)
           and time.monotonic() < deadline):
        time.sleep(0.05)


def _message_class(type_name: str) -> Any:
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)
