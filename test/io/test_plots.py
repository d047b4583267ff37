"""The replay's plots: PNG files, and what each draws where (read back from the figure)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from h2o_slam.io.plots import node_callbacks, plot_callback_times, plot_chi2, plot_trajectories

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


def test_trajectory_plot_draws_the_truth_on_top_dashed_and_the_errors_beside(
        tmp_path: Path, saved_axes: list[list[Any]]) -> None:
    t_ns = np.arange(50, dtype=np.int64) * 100_000_000
    truth = np.stack([np.linspace(0, 10, 50), np.zeros(50)], axis=1)
    est = truth + [0.0, 0.2]
    plot_trajectories(tmp_path / "traj.png", {"estimate": est, "ground truth": truth},
                      stamps_ns={"estimate": t_ns, "ground truth": t_ns})
    xy_ax, error_ax = saved_axes[0]
    truth_line = next(ln for ln in xy_ax.get_lines() if ln.get_label() == "ground truth")
    assert truth_line.get_linestyle() == "--"
    assert truth_line.get_zorder() > max(ln.get_zorder() for ln in xy_ax.get_lines()
                                         if ln is not truth_line and ln.get_label() != "start")
    # A constant offset is removed by the ATE's alignment: the error is ~0, as the ATE is.
    assert _labels(error_ax) == ["estimate (ATE 0.000 m)"]
    assert "estimate (ATE 0.000 m)" in _labels(xy_ax)
    legend = [text.get_text() for text in xy_ax.figure.legends[0].get_texts()]
    assert legend == ["estimate (ATE 0.000 m)", "ground truth", "start"]  # each once, below
    assert _png_size(tmp_path / "traj.png")[0] > 1000


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
    assert h2o_ax.get_xlabel() == "" and vo_ax.get_xlabel() == "bag time (s)"
