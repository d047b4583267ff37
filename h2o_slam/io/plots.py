"""The PNG plots of a replay: trajectories against the truth with their errors over time,
each node's callback times against bag time, and χ² per degree of freedom along the run.

Everything here takes plain arrays, so the replay and the demo call it with whatever they
collected; matplotlib (Agg) is imported only when a plot is drawn.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from h2o_slam.core.geometry import PLANAR_DOF
from h2o_slam.core.graph import KIND_ROWS, EdgeKind
from h2o_slam.core.trajectory_error import align_planar, match_stamps
from h2o_slam.io.replay_outputs import NS_PER_S

#: Colours of the trajectories and callback kinds, in order (matplotlib's default cycle
#: without its black-like and grey entries, which the ground truth and GPS fixes use).
_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown",
            "tab:pink", "tab:olive", "tab:cyan")

#: χ² at or below this fraction of a run's largest χ² is a graph without conflicting edges
#: (a tree: only rounding error, ~1e-27, is left), not a value to put on a log axis.
CHI2_ZERO_FRACTION = 1e-9

#: What chi2.png says under its title when it shows χ² per degree of freedom: of one graph
#: (:data:`CHI2_NOTE`), and of runs of different graphs (:data:`CHI2_COMPARE`).
CHI2_NOTE = ("χ²/DOF says how well the edges agree (≈ 1: residuals as their σ predict), not how "
             "accurate the map is\n(that is the ATE, in trajectories.png).")
CHI2_COMPARE = ("Raw χ² grows with the edges a graph holds: with GPS every fix adds its own "
                "terms, and the map is pulled into the GPS frame.\nχ²/DOF compares the graphs: "
                "it says how well the edges agree (≈ 1: residuals as their σ predict), not how "
                "accurate\nthe map is (that is the ATE, in trajectories.png).")

#: The ground truth in trajectories.png: thin, dashed, neutral grey, beneath everything.
TRUTH_STYLE = {"ls": "--", "lw": 0.9, "color": "0.45", "zorder": 1}

#: Line width of the estimates in trajectories.png; the best one (lowest ATE) gets
#: :data:`BEST_LW` and is drawn on top of the others.
ESTIMATE_LW, BEST_LW = 1.2, 2.0


@dataclass(frozen=True)
class NodeCallbacks:
    """One node's callbacks for :func:`plot_callback_times`.

    Attributes:
        stamps_s: ``(N,)`` bag time of each callback, s since the start of the bag.
        ms: ``(N,)`` duration of each callback, ms.
        kinds: ``(N,)`` what each callback handled (e.g. ``"odometry"``); one colour each.
        budget_ms: the node's time per callback, drawn as a line; ``None`` for none.
        budget_label: what the line is (default ``"budget X ms"``).
        hidden_kinds: kinds counted in the panel's note but not drawn (e.g. image callbacks
            that only buffer the first image of a stereo pair).
        note: one line under the panel's name (e.g. why there is no budget).
    """

    stamps_s: Any
    ms: Any
    kinds: Any
    budget_ms: float | None = None
    budget_label: str = ""
    hidden_kinds: tuple[str, ...] = ()
    note: str = ""


def node_callbacks(calls: Any, **options: Any) -> NodeCallbacks:
    """:class:`NodeCallbacks` from ``(bag time s, ms, kind)`` triples; ``options`` are its
    other fields."""
    rows = list(calls)
    return NodeCallbacks(stamps_s=np.array([r[0] for r in rows], dtype=float),
                         ms=np.array([r[1] for r in rows], dtype=float),
                         kinds=np.array([r[2] for r in rows], dtype=object), **options)


@contextmanager
def _figure(path: str | os.PathLike[str], size: tuple[float, float], rows: int = 1,
            cols: int = 1, legend: str = "right", legend_columns: int = 3,
            mosaic: list[list[str]] | None = None,
            ratios: tuple[list[float] | None, list[float] | None] = (None, None)
            ) -> Iterator[Any]:
    """Axes to draw on (one, or an array of ``rows × cols`` in reading order, columns
    sharing x; or, with ``mosaic``, a dict of name → axes laid out as
    :func:`matplotlib.pyplot.subplot_mosaic` lays them, ``ratios`` its column widths and
    row heights); saved as a PNG at ``path`` when the block ends without error.

    Legends stay outside the data: ``"right"`` puts each axes' legend right of it,
    ``"below"`` puts one legend of every labelled line below the figure, in
    ``legend_columns`` columns (filled column by column). The saved picture grows to hold
    them.
    """
    import matplotlib

    matplotlib.use("Agg")  # files only: no display on a robot or in CI
    import matplotlib.pyplot as plt

    if mosaic is not None:
        layout: Any = mosaic
        fig, named = plt.subplot_mosaic(layout, figsize=size, width_ratios=ratios[0],
                                        height_ratios=ratios[1])
        flat = list(named.values())
        shown: Any = named
    else:
        fig, axes = plt.subplots(rows, cols, figsize=size, sharex="col", squeeze=False)
        flat = list(axes.ravel())
        shown = axes.ravel() if len(flat) > 1 else flat[0]
    try:
        yield shown
        for ax in flat:
            ax.grid(True, which="major", alpha=0.3)
        fig.tight_layout()
        if legend == "right":
            for ax in flat:
                if ax.get_legend_handles_labels()[0]:  # an empty plot has nothing to explain
                    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                              borderaxespad=0.0, frameon=False)
        else:
            labelled: dict[str, Any] = {}
            for ax in flat:
                for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
                    labelled.setdefault(label, handle)
            if labelled:
                fig.legend(labelled.values(), labelled.keys(), fontsize=8, frameon=False,
                           loc="upper center", bbox_to_anchor=(0.5, 0.0),
                           ncol=min(legend_columns, len(labelled)))
        fig.savefig(Path(path), dpi=110, format="png", bbox_inches="tight")
    finally:
        plt.close(fig)  # pyplot keeps every open figure alive otherwise


def _metres(value: float) -> str:
    """A length for a tick label: mm under 1 cm, cm under 1 m, m above."""
    if value < 0.01:
        return f"{value * 1e3:.3g} mm"
    if value < 1.0:
        return f"{value * 1e2:.3g} cm"
    return f"{value:.3g} m"


def _readable_log_ticks(axis: Any, low: float, high: float,
                        label: Any = lambda v: f"{v:g}") -> None:
    """Label a log ``axis`` spanning ``low``–``high`` at 1-2-5 steps (at 1-3 over more than
    three decades, at the decades over more than five) in plain numbers (``label``), so
    values can be read off it; unlabelled minor ticks at the other integers."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    decades = np.log10(max(high, 1e-300) / max(low, 1e-300))
    subs = (1.0, 2.0, 5.0) if decades <= 3.2 else (1.0, 3.0) if decades <= 5.2 else (1.0,)
    axis.set_major_locator(LogLocator(base=10.0, subs=subs, numticks=100))
    axis.set_major_formatter(FuncFormatter(lambda v, _pos: label(v)))
    axis.set_minor_locator(LogLocator(base=10.0, subs=tuple(range(1, 10)), numticks=100))
    axis.set_minor_formatter(NullFormatter())


def plot_trajectories(
    path: str | os.PathLike[str],
    trajectories: Mapping[str, Any],
    gps_enu: Any = None,
    title: str = "trajectories",
    truth: str = "ground truth",
    stamps_ns: Mapping[str, Any] | None = None,
) -> Path:
    """Plot planar trajectories over each other (and GPS fixes) into a PNG.

    Draw order, bottom to top: the trajectory labelled ``truth`` (thin, grey, dashed: the
    reference the others are read against, :data:`TRUTH_STYLE`), the estimates from the
    worst to the best (the lowest ATE last and widest, so over several laps it stays in
    sight), the GPS fixes (black dots with a white rim, visible on any line) and the start.
    Beside it, a zoom on the end of the run shows the estimates' last poses (dots) against
    the truth's at centimetre scale. With ``stamps_ns`` of the truth and of an estimate, a
    third panel shows that estimate's position error over time after the alignment of
    :func:`ate_m` (matched as the summary's ATE is, within 50 ms), and the legend, below
    all, gives each estimate's ATE.

    Args:
        trajectories: label → positions ``(N, 2+)`` m, in one world frame (ENU); the legend
            lists them in this order.
        gps_enu: ``(K, 2+)`` east/north of GPS fixes, drawn as points; ``None`` for none.
        truth: the label of the ground truth.
        stamps_ns: label → ``(N,)`` int ns of the positions in ``trajectories``.
    """
    stamps = stamps_ns or {}
    estimates = [k for k in trajectories if k != truth and len(trajectories[k])]
    errors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for k in estimates:
        if k in stamps and truth in stamps:
            found = _aligned_errors(stamps[k], trajectories[k], stamps[truth],
                                    trajectories[truth])
            if found is not None:
                errors[k] = found
    ate = {k: float(np.sqrt(np.mean(errors[k][1] ** 2))) for k in errors}
    colour_of = dict(zip(estimates, _COLOURS, strict=False))
    shown = {k: f"{k} (ATE {ate[k]:.3f} m)" if k in ate else k for k in estimates}
    # Worst first: each estimate is drawn over the worse ones, the best last of all.
    # Without ATEs the given order stands (the last on top).
    rank = {k: i for i, k in enumerate(
        sorted(estimates, key=lambda k: -ate[k]) if len(ate) == len(estimates)
        else estimates)}
    best = max(rank, key=rank.__getitem__) if rank else None
    true_xy = np.asarray(trajectories.get(truth, np.zeros((0, 2))), dtype=float)
    gps = (np.asarray(gps_enu, dtype=float) if gps_enu is not None and len(gps_enu)
           else np.zeros((0, 2)))
    zoom = _end_window(true_xy, [np.asarray(trajectories[k], dtype=float)
                                 for k in estimates])
    panels = [["xy", "zoom"], ["xy", "error"]] if errors else [["xy", "zoom"]]
    if zoom is None:
        panels = [["xy", "error"]] if errors else [["xy"]]
    width = 7.5 + 4.5 * (len(panels[0]) - 1)
    with _figure(path, (width, 7.5 if len(panels) > 1 else 6.0), mosaic=panels,
                 ratios=([1.1, 1.0] if len(panels[0]) > 1 else None,
                         [1.25, 1.0] if len(panels) > 1 else None),
                 legend="below" if len(panels[0]) > 1 else "right") as axes:
        for name in ("xy", "zoom") if zoom is not None else ("xy",):
            ax = axes[name]
            in_zoom = name == "zoom"
            if len(true_xy):
                ax.plot(true_xy[:, 0], true_xy[:, 1], label=truth, **TRUTH_STYLE)
            for label in estimates:
                xy = np.asarray(trajectories[label], dtype=float)
                ax.plot(xy[:, 0], xy[:, 1], "-", color=colour_of[label],
                        lw=BEST_LW if label == best else ESTIMATE_LW,
                        zorder=2 + rank[label], label=shown[label])
                if in_zoom:
                    ax.plot(xy[-1, 0], xy[-1, 1], "o", ms=7, color=colour_of[label],
                            mec="black", mew=0.8, zorder=20 + rank[label])
            top = 3 + len(estimates)
            if len(gps):
                ax.plot(gps[:, 0], gps[:, 1], "o", ms=3.5 if in_zoom else 3.0,
                        color="black", mec="white", mew=0.5, zorder=top,
                        label=f"GPS fixes ({len(gps)})")
            if len(true_xy):
                if in_zoom:
                    ax.plot(true_xy[-1, 0], true_xy[-1, 1], "s", ms=7, mfc="none",
                            mec="black", mew=1.2, zorder=top + 30,
                            label=f"end of the {truth}")
                else:
                    ax.plot(true_xy[0, 0], true_xy[0, 1], "*", color="black", ms=10,
                            mec="white", mew=0.6, zorder=top + 1, label="start")
            ax.set(xlabel="east / x (m)", ylabel="north / y (m)", aspect="equal")
        axes["xy"].set_title(title)
        if zoom is not None:
            (x0, x1), (y0, y1) = zoom
            axes["zoom"].set(xlim=(x0, x1), ylim=(y0, y1),
                             title="zoom on the end of the run: last poses (dots) "
                                   "against the truth's (square)")
            axes["zoom"].title.set_fontsize(9)
            axes["xy"].indicate_inset((x0, y0, x1 - x0, y1 - y0), edgecolor="black",
                                      alpha=0.9, lw=1.0, zorder=40)
        if errors:
            right = axes["error"]
            for label, (t_s, err) in errors.items():
                right.plot(t_s, err, "-", color=colour_of[label], label=shown[label],
                           lw=BEST_LW if label == best else ESTIMATE_LW,
                           zorder=2 + rank[label])
            right.set_yscale("log")
            low, high = right.get_ylim()
            _readable_log_ticks(right.yaxis, low, high, _metres)
            right.set(xlabel="time (s)", ylabel="position error after alignment (log)")
            right.set_title(f"distance to the {truth} (RMS: the ATE)", fontsize=9)
    return Path(path)


def _end_window(truth: np.ndarray, estimates: list[np.ndarray]
                ) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """A square (x and y limits) holding the truth's last position and the last positions
    of the estimates that end near it (within a sixth of the truth's extent: one that
    drifted away, as wheel odometry does, would zoom the zoom out), with a margin; ``None``
    without a truth or an estimate."""
    if len(truth) < 2 or not estimates:
        return None
    end = truth[-1, :2]
    extent = float(np.linalg.norm(np.ptp(truth[:, :2], axis=0)))
    if extent <= 0:
        return None
    ends = np.array([end] + [xy[-1, :2] for xy in estimates if len(xy)])
    ends = ends[np.linalg.norm(ends - end, axis=1) <= extent / 6]
    low, high = ends.min(axis=0), ends.max(axis=0)
    centre = (low + high) / 2
    half = max(0.65 * float(np.max(high - low)), 0.03 * extent)
    return (centre[0] - half, centre[0] + half), (centre[1] - half, centre[1] + half)


def _aligned_errors(stamps_ns: Any, est: Any, truth_stamps_ns: Any,
                    truth: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """Time (s from the truth's start) and position error (m) of an estimate matched to
    the truth by stamp and aligned as :func:`ate_m` aligns it; ``None`` under 3 matches."""
    g_stamps = np.asarray(truth_stamps_ns, dtype=np.int64)
    i, j = match_stamps(stamps_ns, g_stamps, NS_PER_S // 20)
    if len(i) < 3:
        return None
    a = np.asarray(est, dtype=float)[i, :2]
    b = np.asarray(truth, dtype=float)[j, :2]
    R, t = align_planar(a, b)
    err = np.linalg.norm(a @ R.T + t - b, axis=1)
    return (np.asarray(stamps_ns, dtype=np.int64)[i] - g_stamps[0]) / NS_PER_S, err


def plot_callback_times(
    path: str | os.PathLike[str],
    nodes: Mapping[str, NodeCallbacks],
    title: str = "time per callback",
) -> Path:
    """Plot each node's callback durations against bag time, one panel a node.

    Each kind of callback has its colour, with its count, median and largest time in the
    legend; the budget, where one applies, is a red dashed line. The time axis is
    logarithmic when the times drawn span more than a decade and a half (a few slow
    callbacks would otherwise flatten the rest onto zero).
    """
    rows = max(len(nodes), 1)
    with _figure(path, (9, 1.0 + 2.6 * rows), rows=rows) as axes:
        axes = np.atleast_1d(axes)
        for ax, (name, node) in zip(axes, nodes.items(), strict=False):
            _callback_panel(ax, name, node)
        axes[-1].set_xlabel("bag time (s)")
        axes[0].figure.suptitle(title)
    return Path(path)


def _callback_panel(ax: Any, name: str, node: NodeCallbacks) -> None:
    t = np.asarray(node.stamps_s, dtype=float)
    ms = np.asarray(node.ms, dtype=float)
    kinds = np.asarray(node.kinds, dtype=object)
    shown = ~np.isin(kinds, node.hidden_kinds) if len(kinds) else np.zeros(0, dtype=bool)
    notes = [node.note] if node.note else []
    for kind in node.hidden_kinds:
        hidden = ms[kinds == kind]
        if len(hidden):
            notes.append(f"{len(hidden)} callbacks '{kind}' not drawn "
                         f"(≤ {hidden.max():.2f} ms each)")
    colours = iter(_COLOURS)
    # Cheapest first: the legend then lists the kinds in the order they stack in the plot.
    for kind in sorted(set(kinds[shown]), key=lambda k: float(np.median(ms[kinds == k]))):
        sel = shown & (kinds == kind)
        ax.plot(t[sel], ms[sel], ".", ms=3, color=next(colours),
                label=f"{kind} ({int(sel.sum())}): median {np.median(ms[sel]):.2g} ms, "
                      f"max {ms[sel].max():.3g} ms")
    drawn = ms[shown]
    top = float(drawn.max()) if len(drawn) else 1.0
    if node.budget_ms is not None and node.budget_ms > 0:
        ax.axhline(node.budget_ms, color="red", ls="--", lw=1.2,
                   label=node.budget_label or f"budget {node.budget_ms:g} ms")
        top = max(top, node.budget_ms)
    positive = drawn[drawn > 0]
    if len(positive) and top / max(float(np.percentile(positive, 5)), 1e-6) > 30:
        ax.set_yscale("log")
        low, high = max(float(positive.min()) / 1.5, 1e-3), top * 1.6
        ax.set_ylim(low, high)
        _readable_log_ticks(ax.yaxis, low, high)
        ax.set_ylabel("time (ms, log)")
    else:
        ax.set_ylim(0, top * 1.15)
        ax.set_ylabel("time (ms)")
    ax.set_title(name + ("\n" + "; ".join(notes) if notes else ""), loc="left", fontsize=9)


@dataclass(frozen=True)
class Chi2Trace:
    """One run's χ² for :func:`plot_chi2`.

    Attributes:
        stamps_s: ``(N,)`` bag time of each sample, s since the start of the bag.
        chi2: ``(N,)`` χ² of the graph (sum over its edges) at each sample.
        dof: ``(N,)`` degrees of freedom of that χ² (:func:`chi2_dof`); ``None`` when not
            known (then the plot shows χ² itself).
        holds: what the graph is made of, for the legend (e.g. ``"odometry, 8 loop
            closures, 101 GPS fixes"``).
    """

    stamps_s: Any
    chi2: Any
    dof: Any = None
    holds: str = ""


def chi2_trace(samples: Any, holds: str = "") -> Chi2Trace:
    """:class:`Chi2Trace` from ``(bag time s, χ²)`` or ``(bag time s, χ², dof)`` rows."""
    rows = np.asarray(list(samples), dtype=float)
    rows = rows if rows.ndim == 2 and len(rows) else np.zeros((0, 2))
    return Chi2Trace(rows[:, 0], rows[:, 1], rows[:, 2] if rows.shape[1] > 2 else None, holds)


def chi2_dof(kind: Any, b: Any, weight: Any, num_nodes: int, planar: bool) -> int:
    """Degrees of freedom of a pose graph's χ² (its redundancy): the error coordinates of
    its edges in use (robust weight > 0; a dropped edge adds nothing to χ²) less the pose
    coordinates the edges determine (all of them less the gauge: the pose of the whole map,
    left free unless global edges — GPS fixes, orientations — pin it). At the optimum a
    graph whose residuals are as large as its edges' σ say has χ² ≈ DOF: χ²/DOF compares
    graphs of different sizes, the raw sum does not.

    Args:
        kind, b: :class:`EdgeKind` and second node of each edge (a GPS fix's pose is
            its ``b``).
        weight: robust weight of each edge.
        num_nodes: poses in the graph.
        planar: (x, y, yaw) per pose, else six.
    """
    dof = PLANAR_DOF if planar else np.arange(6)
    kind = np.asarray(kind)
    used = np.asarray(weight, dtype=float) > 0
    rows = sum(int(np.count_nonzero(used & (kind == k))) * len(np.intersect1d(KIND_ROWS[k], dof))
               for k in EdgeKind)
    fixed = np.unique(np.asarray(b)[used & (kind == EdgeKind.POSITION)])
    oriented = bool(np.any(used & (kind == EdgeKind.ORIENTATION)))
    translation = 0 if len(fixed) else (2 if planar else 3)
    if oriented:
        rotation = 0
    elif planar:
        rotation = 0 if len(fixed) >= 2 else 1
    else:
        rotation = 3 if len(fixed) < 2 else 1 if len(fixed) == 2 else 0
    return rows - max(len(dof) * num_nodes - translation - rotation, 0)


def plot_chi2(
    path: str | os.PathLike[str],
    runs: Mapping[str, Chi2Trace | tuple[Any, Any]],
    title: str = "χ² per degree of freedom of the graph over bag time",
) -> Path:
    """Plot each run's χ² against bag time into a PNG: per degree of freedom when every
    run has its DOF, so graphs of different sizes (with GPS fixes and without) read on one
    scale, with the line χ²/DOF = 1 (residuals as large as the edges' σ say); the legend
    gives each run's graph, final χ², DOF and their ratio. Raw χ² otherwise.

    A graph without redundant edges (before the first loop closure or GPS alignment: DOF
    0, χ² at rounding level, ~1e-27) has nothing to show; such samples (DOF ≤ 0, or at most
    :data:`CHI2_ZERO_FRACTION` of the run's largest χ²) are not drawn on the axis but
    shaded as "no conflict yet", so the axis starts near the first meaningful value.
    Logarithmic (ticks at 1-2-5) when the values span more than a decade and a half.

    Args:
        runs: label → :class:`Chi2Trace`, or (bag time ``(N,)`` s since the start, χ²
            ``(N,)``).
    """
    traces = {k: v if isinstance(v, Chi2Trace) else Chi2Trace(*v) for k, v in runs.items()}
    per_dof = bool(traces) and all(v.dof is not None for v in traces.values())
    with _figure(path, (9, 4.8), legend="below", legend_columns=1) as ax:
        colours = iter(_COLOURS)
        meaningful: list[np.ndarray] = []
        t_end = 0.0
        for label, run in traces.items():
            t = np.asarray(run.stamps_s, dtype=float)
            values = np.asarray(run.chi2, dtype=float)
            dof = (np.asarray(run.dof, dtype=float) if run.dof is not None
                   else np.ones(len(values)))
            colour = next(colours)
            if not len(values):
                continue
            t_end = max(t_end, float(t.max()))
            finite = np.isfinite(values)
            largest = float(values[finite].max()) if finite.any() else 0.0
            real = finite & (values > CHI2_ZERO_FRACTION * largest) & (values > 0) & (dof > 0)
            name = f"{label} ({run.holds})" if run.holds else label
            if real.any():
                first = int(np.argmax(real))
                if first > 0:
                    ax.axvspan(float(t[0]), float(t[first]), color=colour, alpha=0.08,
                               label=f"{label}: χ² ≈ 0 until {t[first]:.0f} s (no edge in "
                                     "conflict yet)")
                shown = (np.divide(values, dof, out=np.full(len(values), np.nan),
                                   where=dof > 0) if per_dof else values)
                last = int(np.flatnonzero(finite)[-1])
                final = f"final χ² {values[last]:.4g}"
                if per_dof:
                    final += (f" over {dof[last]:.0f} DOF = {values[last] / dof[last]:.2g}"
                              if dof[last] > 0 else " (no DOF left)")
                ax.plot(t[real], shown[real], ".-", lw=1.3, ms=4, color=colour,
                        label=f"{name}: {final}")
                meaningful.append(shown[real])
            else:
                ax.axvspan(float(t[0]), float(t[-1]), color=colour, alpha=0.08,
                           label=f"{name}: χ² ≈ 0 throughout (no edge in conflict)")
        values = np.concatenate(meaningful) if meaningful else np.zeros(0)
        quantity = "χ² / DOF" if per_dof else "χ² (sum over edges)"
        if per_dof:
            ax.axhline(1.0, color="black", ls=":", lw=1.2, zorder=0,
                       label="χ²/DOF = 1: residuals as large as the edges' σ say")
            values = np.append(values, 1.0)
        if len(values) and values.max() / values.min() > 30:
            low, high = values.min() / 1.5, values.max() * 1.5
            ax.set_yscale("log")
            ax.set_ylim(low, high)
            _readable_log_ticks(ax.yaxis, low, high)
            ax.set_ylabel(f"{quantity} (log)")
        else:
            ax.set_ylim(0, (values.max() if len(values) else 1.0) * 1.1)
            ax.set_ylabel(quantity)
        ax.set_xlim(0, max(t_end, 1e-9))
        ax.set_xlabel("bag time (s)")
        if per_dof:
            ax.figure.suptitle(title)
            ax.set_title(CHI2_COMPARE if len(traces) > 1 else CHI2_NOTE, loc="left",
                         fontsize=8)
        else:
            ax.set_title(title)
    return Path(path)
