"""The PNG plots of a replay: trajectories against the truth with their errors over time,
each node's callback times against bag time, and χ² along the run.

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

from h2o_slam.core.trajectory_error import align_planar, match_stamps
from h2o_slam.io.replay_outputs import NS_PER_S

#: Colours of the trajectories and callback kinds, in order (matplotlib's default cycle
#: without its black-like and grey entries, which the ground truth and GPS fixes use).
_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown",
            "tab:pink", "tab:olive", "tab:cyan")

#: χ² at or below this fraction of a run's largest χ² is a graph without conflicting edges
#: (a tree: only rounding error, ~1e-27, is left), not a value to put on a log axis.
CHI2_ZERO_FRACTION = 1e-9


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
            cols: int = 1, legend: str = "right", legend_columns: int = 3) -> Iterator[Any]:
    """Axes to draw on (one, or an array of ``rows × cols`` in reading order, columns
    sharing x); saved as a PNG at ``path`` when the block ends without error.

    Legends stay outside the data: ``"right"`` puts each axes' legend right of it,
    ``"below"`` puts one legend of every labelled line below the figure, in
    ``legend_columns`` columns (filled column by column). The saved picture grows to hold
    them.
    """
    import matplotlib

    matplotlib.use("Agg")  # files only: no display on a robot or in CI
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(rows, cols, figsize=size, sharex="col", squeeze=False)
    flat = axes.ravel()
    try:
        yield flat if len(flat) > 1 else flat[0]
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


def plot_trajectories(
    path: str | os.PathLike[str],
    trajectories: Mapping[str, Any],
    gps_enu: Any = None,
    title: str = "trajectories",
    truth: str = "ground truth",
    stamps_ns: Mapping[str, Any] | None = None,
) -> Path:
    """Plot planar trajectories over each other (and GPS fixes) into a PNG.

    The trajectory labelled ``truth`` is drawn last, black and dashed, so it stays visible
    on top of estimates that follow it closely; GPS fixes are grey dots beneath all. With
    ``stamps_ns`` of the truth and of an estimate, a second panel shows that estimate's
    position error over time after the alignment of :func:`ate_m` (matched as the summary's
    ATE is, within 50 ms), and the legend, below both, gives each estimate's ATE.

    Args:
        trajectories: label → positions ``(N, 2+)`` m, in one world frame (ENU), drawn in
            this order.
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
    colour_of = dict(zip(estimates, _COLOURS, strict=False))
    shown = {k: f"{k} (ATE {float(np.sqrt(np.mean(errors[k][1] ** 2))):.3f} m)"
             if k in errors else k for k in estimates}
    with _figure(path, (13, 6) if errors else (7.5, 6), cols=2 if errors else 1,
                 legend="below" if errors else "right") as axes:
        ax = axes[0] if errors else axes
        if gps_enu is not None and len(gps_enu):
            gps = np.asarray(gps_enu, dtype=float)
            ax.plot(gps[:, 0], gps[:, 1], ".", color="0.6", ms=3, zorder=1,
                    label=f"GPS fixes ({len(gps)})")
        for label in estimates:
            xy = np.asarray(trajectories[label], dtype=float)
            ax.plot(xy[:, 0], xy[:, 1], "-", lw=1.4, color=colour_of[label], zorder=2,
                    label=shown[label])
        xy = np.asarray(trajectories.get(truth, np.zeros((0, 2))), dtype=float)
        if len(xy):
            ax.plot(xy[:, 0], xy[:, 1], "--", lw=1.3, color="black", zorder=3, label=truth)
            ax.plot(xy[0, 0], xy[0, 1], "o", color="black", ms=5, zorder=3, label="start")
        ax.set(xlabel="east / x (m)", ylabel="north / y (m)", title=title, aspect="equal")
        if errors:
            right = axes[1]
            for label, (t_s, err) in errors.items():
                right.plot(t_s, err, "-", lw=1.2, color=colour_of[label], label=shown[label])
            right.set_yscale("log")
            right.set(xlabel="time (s)", ylabel="position error after alignment (m, log)",
                      title=f"distance to the {truth} (RMS: the ATE)")
    return Path(path)


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
        ax.set_ylim(max(float(positive.min()) / 1.5, 1e-3), top * 1.6)
        ax.set_ylabel("time (ms, log)")
    else:
        ax.set_ylim(0, top * 1.15)
        ax.set_ylabel("time (ms)")
    ax.set_title(name + ("\n" + "; ".join(notes) if notes else ""), loc="left", fontsize=9)


def plot_chi2(
    path: str | os.PathLike[str],
    runs: Mapping[str, tuple[Any, Any]],
    title: str = "χ² of the graph over bag time",
) -> Path:
    """Plot each run's χ² (sum over edges) against bag time into a PNG.

    A graph without conflicting edges (before the first loop closure or GPS alignment) has
    χ² at rounding level (~1e-27); such samples (at most :data:`CHI2_ZERO_FRACTION` of the
    run's largest χ²) are not drawn on the axis but shaded as "no conflict yet", so the
    axis starts near the first meaningful value. Logarithmic when the values span more
    than a decade and a half.

    Args:
        runs: label → (bag time ``(N,)`` s since the start, χ² ``(N,)``).
    """
    with _figure(path, (9, 4.5), legend="below", legend_columns=max(len(runs), 1)) as ax:
        colours = iter(_COLOURS)
        meaningful: list[np.ndarray] = []
        t_end = 0.0
        for label, (stamps, chi2) in runs.items():
            t = np.asarray(stamps, dtype=float)
            values = np.asarray(chi2, dtype=float)
            colour = next(colours)
            if not len(values):
                continue
            t_end = max(t_end, float(t.max()))
            finite = np.isfinite(values)
            largest = float(values[finite].max()) if finite.any() else 0.0
            real = finite & (values > CHI2_ZERO_FRACTION * largest) & (values > 0)
            if real.any():
                first = int(np.argmax(real))
                if first > 0:
                    ax.axvspan(float(t[0]), float(t[first]), color=colour, alpha=0.08,
                               label=f"{label}: χ² ≈ 0 until {t[first]:.0f} s (no edge in "
                                     "conflict yet)")
                ax.plot(t[real], values[real], ".-", lw=1.3, ms=4, color=colour,
                        label=f"{label}: final χ² {values[finite][-1]:.4g}")
                meaningful.append(values[real])
            else:
                ax.axvspan(float(t[0]), float(t[-1]), color=colour, alpha=0.08,
                           label=f"{label}: χ² ≈ 0 throughout (no edge in conflict)")
        values = np.concatenate(meaningful) if meaningful else np.zeros(0)
        if len(values) and values.max() / values.min() > 30:
            ax.set_yscale("log")
            ax.set_ylim(values.min() / 1.5, values.max() * 1.5)
            ax.set_ylabel("χ² (sum over edges, log)")
        else:
            ax.set_ylim(0, (values.max() if len(values) else 1.0) * 1.1)
            ax.set_ylabel("χ² (sum over edges)")
        ax.set_xlim(0, max(t_end, 1e-9))
        ax.set(xlabel="bag time (s)", title=title)
    return Path(path)
