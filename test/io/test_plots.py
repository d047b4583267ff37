"""The replay's plots: PNG files, and what each draws where (read back from the figure)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from h2o_slam.core.graph import EdgeKind
from h2o_slam.io.plots import (
    CHI2_COMPARE,
    Chi2Trace,
    chi2_dof,
    node_callbacks,
    plot_callback_times,
    plot_chi2,
    plot_trajectories,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png_size(path: Path) -> tuple[int, int]:
    blob = path.read_bytes()
    assert blob[:8] == PNG_MAGIC and len(blob) > 5000
    return int.from_bytes(blob[16:20], "big"), int.from_bytes(blob[20:24], "big")


@pytest.fixture
def saved_axes(monkeypatch: pytest.MonkeyPatch) -> list[list[Any]]:
    """The axes of every figure saved, as they were when saved (one list per figure)."""
    from matplotlib.figure import Figure

    saved: list[list[Any]] = []
    original = Figure.savefig

    def savefig(fig: Figure, *args: Any, **kwargs: Any) -> None:
        saved.append(list(fig.axes))
        original(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    return saved


def _labels(ax: Any) -> list[str]:
    return [str(line.get_label()) for line in ax.get_lines()]


def _line(ax: Any, label: str) -> Any:
    return next(line for line in ax.get_lines() if line.get_label() == label)


def _panel(axes: list[Any], title_start: str) -> Any:
    return next(ax for ax in axes if ax.get_title().startswith(title_start))


def _tick_labels(axis: Any) -> list[str]:
    """The labels of the major ticks inside the axis' view, as drawn."""
    low, high = sorted(axis.get_view_interval())
    formatter = axis.get_major_formatter()
    return [formatter(v, i) for i, v in enumerate(axis.get_majorticklocs())
            if low <= v <= high]


def test_plots_are_png_files(tmp_path: Path) -> None:
    t = np.linspace(0, 10, 50)
    xy = np.stack([t, np.sin(t)], axis=1)
    calls = [(float(s), float(s) / 2, "odometry") for s in t]
    paths = [
        plot_trajectories(tmp_path / "traj.png", {"wheel": xy, "h2o": xy + 0.1},
                          gps_enu=xy[::5] + 0.3),
        plot_trajectories(tmp_path / "empty.png", {"wheel": np.zeros((0, 2))}),
        plot_callback_times(tmp_path / "cb.png", {"h2o_node": node_callbacks(calls, budget_ms=5.0),
                                                  "hybrid_vo_node": node_callbacks(calls)}),
        plot_callback_times(tmp_path / "cb_empty.png", {"h2o_node": node_callbacks([])}),
        plot_chi2(tmp_path / "chi2.png", {"run": (t, np.exp(-t) + 1.0)}),
        plot_chi2(tmp_path / "chi2_zero.png", {"tree": (t, np.full(len(t), 1e-27))}),
    ]
    for path in paths:
        width, height = _png_size(path)
        assert width > 300 and height > 200


def test_trajectory_plot_draws_the_truth_beneath_and_the_best_estimate_and_gps_on_top(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    t_ns = np.arange(200, dtype=np.int64) * 100_000_000
    angle = np.linspace(0, 6 * np.pi, 200)  # three laps of a circle
    truth = 5 * np.stack([np.cos(angle), np.sin(angle)], axis=1)
    wobble = np.stack([np.sin(7 * angle), np.cos(5 * angle)], axis=1)
    best, worse = truth + 0.02 * wobble, truth + 0.3 * wobble
    plot_trajectories(tmp_path / "traj.png",
                      {"worse": worse, "best": best, "ground truth": truth},
                      gps_enu=truth[::10] + 0.01,
                      stamps_ns={"worse": t_ns, "best": t_ns, "ground truth": t_ns})
    axes = saved_axes[0]
    xy_ax = _panel(axes, "trajectories")
    zoom_ax = _panel(axes, "zoom")
    error_ax = _panel(axes, "distance to the ground truth")
    for ax in (xy_ax, zoom_ax):
        truth_line, gps = _line(ax, "ground truth"), _line(ax, "GPS fixes (20)")
        worse_line = _line(ax, next(k for k in _labels(ax) if k.startswith("worse")))
        best_line = _line(ax, next(k for k in _labels(ax) if k.startswith("best")))
        # Beneath everything, thin, dashed and grey: a reference, not a curtain.
        assert truth_line.get_zorder() < min(ln.get_zorder() for ln in ax.get_lines()
                                             if ln is not truth_line)
        assert truth_line.get_linestyle() == "--"
        assert truth_line.get_linewidth() < worse_line.get_linewidth()
        red, green, blue, _ = matplotlib_rgba(truth_line.get_color())
        assert red == green == blue and 0.3 < red < 0.7
        # The best (lowest ATE) over the worse, wider; the GPS fixes over both.
        assert best_line.get_zorder() > worse_line.get_zorder()
        assert best_line.get_linewidth() > worse_line.get_linewidth()
        assert gps.get_zorder() > best_line.get_zorder()
    # The zoom holds the truth's last position and both estimates' last positions.
    (x0, x1), (y0, y1) = zoom_ax.get_xlim(), zoom_ax.get_ylim()
    for xy in (truth, best, worse):
        assert x0 < xy[-1, 0] < x1 and y0 < xy[-1, 1] < y1
    assert x1 - x0 < 2.0  # centimetre scale, not the 10 m of the whole drive
    assert [k.split(" (")[0] for k in _labels(error_ax)] == ["worse", "best"]
    legend = [text.get_text() for text in xy_ax.figure.legends[0].get_texts()]
    assert legend[0] == "ground truth" and "GPS fixes (20)" in legend and "start" in legend
    assert sum(k.startswith("best (ATE 0.0") for k in legend) == 1  # each once, below
    # The error axis is read in mm/cm/m, not in powers of ten.
    assert {"1 cm", "10 cm"} <= set(_tick_labels(error_ax.yaxis))
    assert _png_size(tmp_path / "traj.png")[0] > 1000


def matplotlib_rgba(colour: Any) -> tuple[float, float, float, float]:
    from matplotlib.colors import to_rgba

    return to_rgba(colour)


def test_trajectory_plot_without_stamps_keeps_the_given_order(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    truth = np.stack([np.linspace(0, 10, 50), np.zeros(50)], axis=1)
    plot_trajectories(tmp_path / "traj.png", {"a": truth + 0.1, "b": truth + 0.2,
                                              "ground truth": truth})
    xy_ax = _panel(saved_axes[0], "trajectories")
    assert _line(xy_ax, "b").get_zorder() > _line(xy_ax, "a").get_zorder()
    assert _line(xy_ax, "ground truth").get_zorder() < _line(xy_ax, "a").get_zorder()


def test_chi2_axis_starts_at_the_first_meaningful_value(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    t = np.arange(0.0, 100.0, 1.0)
    # A run without GPS: a tree (χ² at rounding level) until the first loop closure at 34 s.
    chi2 = np.where(t < 34, 1e-27, 0.05 * 1.1 ** (t - 34))
    plot_chi2(tmp_path / "chi2.png", {"without GPS": (t, chi2)})
    (ax,) = saved_axes[0]
    low, high = ax.get_ylim()
    assert 0.01 < low < 0.1 and high > 10
    assert ax.get_yscale() == "log"
    (drawn,) = ax.get_lines()
    assert drawn.get_xdata()[0] == 34
    legend = [text.get_text() for text in ax.figure.legends[0].get_texts()]
    assert legend[0].startswith("without GPS: χ² ≈ 0 until 34 s")


def test_callback_plot_is_per_node_against_bag_time_with_the_budget(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    h2o = [(0.5 * i, 0.3 if i % 3 else 4.0, "odometry" if i % 3 else "GPS fix")
           for i in range(60)]
    vo = [(0.05 * i, 1.5 if i % 2 else 0.02, "stereo pair" if i % 2 else "image buffered")
          for i in range(600)]
    plot_callback_times(tmp_path / "cb.png", {
        "h2o_node": node_callbacks(h2o, budget_ms=5.0),
        "hybrid_vo_node": node_callbacks(vo, budget_ms=100.0, budget_label="frame interval",
                                         hidden_kinds=("image buffered",))})
    h2o_ax, vo_ax = saved_axes[0]
    assert h2o_ax.get_title(loc="left") == "h2o_node"
    # Cheapest kind first, each with its count; then the budget.
    assert [label.split(":")[0] for label in _labels(h2o_ax)] == ["odometry (40)",
                                                                   "GPS fix (20)",
                                                                   "budget 5 ms"]
    odometry = h2o_ax.get_lines()[0]
    assert odometry.get_xdata().max() == pytest.approx(29.5)  # bag time, not the index
    assert [label.split(":")[0] for label in _labels(vo_ax)] == ["stereo pair (300)",
                                                                  "frame interval"]
    assert "300 callbacks 'image buffered' not drawn" in vo_ax.get_title(loc="left")
    assert vo_ax.get_yscale() == "log"  # 1.5 ms against a 100 ms limit
    # Readable between the decades: 1-2-5 steps in plain numbers, not only 10¹ and 10².
    assert _tick_labels(vo_ax.yaxis) == ["1", "2", "5", "10", "20", "50", "100"]
    assert h2o_ax.get_xlabel() == "" and vo_ax.get_xlabel() == "bag time (s)"


def test_chi2_of_graphs_of_different_sizes_is_compared_per_degree_of_freedom(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    t = np.arange(0.0, 100.0, 1.0)
    with_gps = Chi2Trace(t, 0.5 * (2 * t + 3), 2 * t + 3,
                         holds="odometry, 8 loop closures, 101 GPS fixes")
    without = Chi2Trace(t, np.where(t < 34, 1e-27, 0.5), np.where(t < 34, 0, 24),
                        holds="odometry, 8 loop closures")
    plot_chi2(tmp_path / "chi2.png", {"with GPS": with_gps, "without GPS": without})
    (ax,) = saved_axes[0]
    gps_line, no_gps_line, one = ax.get_lines()
    assert np.allclose(gps_line.get_ydata(), 0.5)  # χ² / DOF, not χ²
    assert np.allclose(no_gps_line.get_ydata(), 0.5 / 24)
    assert no_gps_line.get_xdata()[0] == 34  # DOF 0 before: nothing to draw
    assert list(one.get_ydata()) == [1, 1]
    assert ax.get_ylabel().startswith("χ² / DOF")
    assert ax.get_title(loc="left") == CHI2_COMPARE  # why the raw values differ
    legend = [text.get_text() for text in ax.figure.legends[0].get_texts()]
    assert ("with GPS (odometry, 8 loop closures, 101 GPS fixes): final χ² 100.5 over 201 "
            "DOF = 0.5") in legend
    assert "without GPS (odometry, 8 loop closures): final χ² 0.5 over 24 DOF = 0.021" in legend
    assert {"0.05", "0.1", "0.2", "0.5", "1"} <= set(_tick_labels(ax.yaxis))


def test_chi2_dof_is_the_redundancy_of_the_graph() -> None:
    n = 10  # planar poses: 3 coordinates each
    odometry = [EdgeKind.RELATIVE] * (n - 1)
    chain_b = list(range(1, n))

    def dof(kinds: list[EdgeKind], b: list[int], weight: list[float] | None = None) -> int:
        return chi2_dof(np.array(kinds), np.array(b), np.ones(len(kinds)) if weight is None
                        else np.array(weight), n, planar=True)

    assert dof(odometry, chain_b) == 0  # a tree: the first pose holds the gauge
    empty = np.zeros(0, dtype=np.int64)
    assert chi2_dof(empty, empty, np.zeros(0), 0, planar=True) == 0  # no graph yet
    assert chi2_dof(empty, empty, np.zeros(0), 1, planar=True) == 0
    assert dof(odometry + [EdgeKind.RELATIVE], chain_b + [0]) == 3  # a loop closure
    # GPS fixes (x, y) pin the gauge: one fixes the translation, two the heading too.
    assert dof(odometry + [EdgeKind.POSITION], chain_b + [4]) == 2 - 2
    assert dof(odometry + [EdgeKind.POSITION] * 2, chain_b + [4, 8]) == 4 - 3
    assert dof(odometry + [EdgeKind.POSITION] * 3, chain_b + [4, 8, 9]) == 6 - 3
    # A dropped edge (robust weight 0) adds nothing to χ² and no degree of freedom.
    assert dof(odometry + [EdgeKind.RELATIVE], chain_b + [0], [1.0] * (n - 1) + [0.0]) == 0
    assert chi2_dof(np.array(odometry), np.array(chain_b), np.ones(n - 1), n,
                    planar=False) == 0
