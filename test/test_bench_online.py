"""The pure pieces of bench/online.py (no solver run): which samples close a loop, the CPU-bound
processes of ``--busy``, and the targets and tables of issues 11 and 25."""

from __future__ import annotations

import importlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from graphs import random_graph

from h2o_slam.core.graph import EARTH, EdgeKind, PoseGraph, make_graph
from h2o_slam.core.modes import sample_points

_BENCH = Path(__file__).resolve().parent.parent / "bench"
if str(_BENCH) not in sys.path:
    sys.path.insert(0, str(_BENCH))
online = importlib.import_module("online")


def _chain_with_loops() -> PoseGraph:
    """Eight planar poses on a line: odometry 0→1 ... 6→7 (5→6 stored backwards), loop
    closures 0→3, 5→2 (stored newest first) and 7→0, and a GPS position edge on pose 6."""
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (6, 5), (6, 7), (0, 3), (5, 2), (7, 0)]
    n, m = 8, len(pairs) + 1
    t = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)])
    a = np.array([i for i, _ in pairs] + [EARTH])
    b = np.array([j for _, j in pairs] + [6])
    kind = np.array([EdgeKind.RELATIVE] * len(pairs) + [EdgeKind.POSITION])
    meas_t = np.array([t[j] - t[i] for i, j in pairs] + [t[6]])
    info = np.zeros((m, 6, 6))
    info[:, [0, 1, 5], [0, 1, 5]] = 1.0
    info[-1, 2:, 2:] = 0.0  # GPS: x and y only
    return make_graph(True, np.arange(n), np.broadcast_to(np.eye(3), (n, 3, 3)), t, kind, a, b,
                      np.broadcast_to(np.eye(3), (m, 3, 3)), meas_t, info)


# --- samples at a loop closure -----------------------------------------------------------------


def test_closing_poses_are_the_newest_ends_of_loop_edges() -> None:
    graph = _chain_with_loops()
    # 3 (0→3), 5 (5→2 stored backwards), 7 (7→0); not 6: its edges are odometry and GPS.
    assert online.closing_poses(graph).tolist() == [3, 5, 7]


def test_a_sample_closes_a_loop_by_its_pose_not_by_how_it_was_picked() -> None:
    graph = _chain_with_loops()
    points = sample_points(graph, 2)  # spread: 0 and 7; at closures: 3 and 7 of 3, 5, 7
    assert points == [0, 3, 7]
    # 7 is both a spread sample and a closing pose; 0 is a spread sample only.
    assert online.closing_samples(graph, points).tolist() == [False, True, True]
    assert online.closing_samples(graph, [1, 4, 5, 6]).tolist() == [False, False, True, False]
    assert online.closing_samples(graph, []).shape == (0,)


@pytest.mark.parametrize("seed", range(5))
def test_closing_poses_are_the_set_sample_points_picks_closures_from(seed: int) -> None:
    graph = random_graph(seed, planar=seed % 2 == 0, n=40, loops=6, gps=3)
    closing = set(online.closing_poses(graph).tolist())
    assert closing and all(0 < k < 40 for k in closing)
    # With as many closure samples as closing poses, sample_points takes every one of them.
    assert closing <= set(sample_points(graph, len(closing)))
    # With 3, the samples that do not close a loop are the three spread ones at most.
    points = sample_points(graph, 3)
    flags = online.closing_samples(graph, points)
    assert {k for k, f in zip(points, flags, strict=True) if not f} <= {0, 20, 39}
    assert flags.sum() >= min(3, len(closing))


# --- --busy ------------------------------------------------------------------------------------


def _alive(pid: int) -> bool:
    """Whether ``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds ``pid`` has used."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_busy_runs_n_cpu_bound_processes_and_leaves_none() -> None:
    with online.busy(2) as procs:
        assert len(procs) == 2 and len({p.pid for p in procs}) == 2
        time.sleep(0.3)
        assert all(p.poll() is None and _alive(p.pid) for p in procs)
        assert all(_cpu_s(p.pid) > 0.02 for p in procs)  # spinning, not sleeping
    assert all(p.returncode is not None for p in procs)  # killed and reaped
    assert not any(_alive(p.pid) for p in procs)
    with online.busy(0) as none:
        assert none == []


@pytest.mark.parametrize(("setting", "words"), [
    ("os.setpriority(os.PRIO_PROCESS, 0, -3)", "at nice -3, the load at 0"),
    ("os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))",
     "at SCHED_FIFO 5, the load at SCHED_OTHER"),
])
def test_the_load_runs_at_the_default_priority_below_runs_given_a_higher_one(
        setting: str, words: str) -> None:
    """``--nice -3`` / ``--fifo 5``: the benchmark (and the runs it starts) above the
    default priority, its load at the default (SCHED_OTHER, nice 0)."""
    child = ("import os, sys\n"
             "sys.path.insert(0, sys.argv[1])\n"
             "import online\n"
             "try:\n"
             f"    {setting}\n"
             "except PermissionError:\n"
             "    sys.exit(3)\n"
             "with online.busy(1) as procs:\n"
             "    pid = procs[0].pid\n"
             "    print(os.getpriority(os.PRIO_PROCESS, pid), os.sched_getscheduler(pid),\n"
             "          online._busy_words(1))\n")
    done = subprocess.run([sys.executable, "-c", child, str(Path(online.__file__).parent)],
                          capture_output=True, text=True, timeout=60)
    if done.returncode == 3:
        pytest.skip("a higher priority needs CAP_SYS_NICE")
    assert done.returncode == 0, done.stderr
    nice, policy, said = done.stdout.split(maxsplit=2)
    assert (int(nice), int(policy)) == (0, os.SCHED_OTHER)
    assert words in said


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_busy_cleans_up_when_the_body_raises(error: type[BaseException]) -> None:
    started: list[subprocess.Popen[bytes]] = []
    with pytest.raises(error, match="stop"), online.busy(2) as procs:
        started += procs
        assert all(p.poll() is None for p in procs)
        raise error("stop")
    assert len(started) == 2
    assert all(p.returncode is not None and not _alive(p.pid) for p in started)


def test_a_busy_process_whose_parent_dies_stops_by_itself() -> None:
    starter = ("import os, subprocess, sys\n"
               "p = subprocess.Popen([sys.executable, '-c', sys.argv[1], str(os.getpid())])\n"
               "print(p.pid)\n")
    out = subprocess.run([sys.executable, "-c", starter, online.BUSY_CODE], check=True,
                         capture_output=True, text=True, timeout=30).stdout
    pid = int(out)
    try:
        deadline = time.monotonic() + 10.0
        while _alive(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(pid)
    finally:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


# --- targets and tables ------------------------------------------------------------------------

#: r at the five samples of :func:`_graph_online`; samples 1 and 3 close a loop.
CLOSING = [False, True, False, True, False]
OPTIMUM = 10.0


def _run(r: list[float], budget_ms: float = 5.0, status: str = "ok",
         callback_ms: tuple[float, ...] = (1.0, 2.0, 4.0)) -> object:
    nodes = [1, 3, 5, 7, 9]
    return online.H2OOnlineRun(
        budget_ms, status, times=online.CallbackTimes(np.array(callback_ms)),
        samples={k: OPTIMUM * x for k, x in zip(nodes, r, strict=True)},
        chi2_end_of_stream=OPTIMUM, chi2_after_idle=1.01 * OPTIMUM, chi2_final=OPTIMUM,
        chi2_final_reported=OPTIMUM, idle_steps=3)


def _graph_online(*runs: object, closing: list[bool] = CLOSING) -> object:
    s = len(closing)
    ref = online.Reference(np.arange(1, 2 * s, 2), np.full(s, OPTIMUM), np.ones(s, bool),
                           np.full(s, np.nan), np.full(s, OPTIMUM), 0.0)
    return online.GraphOnline("toy", 9, 12, True, 100.0, list(runs), None, ref,
                              np.array(closing))


def test_r_after_a_closure_uses_only_the_closing_samples() -> None:
    # 50 at a sample that does not close a loop; 1.5 and 12 at the two that do.
    g = _graph_online(_run([1.0, 1.5, 50.0, 12.0, 1.0]))
    s = online.summarize(g, g.h2o[0])
    assert s.closure_median == pytest.approx(6.75)
    assert s.closure_max == pytest.approx(12.0)
    assert s.median == pytest.approx(1.5)
    assert s.p95 > 12.0


def test_issue_25_targets() -> None:
    met = online.targets(_graph_online(_run([1.0, 1.9, 1.0, 9.0, 1.0])))
    assert met.closure_median is False  # median of 1.9 and 9 is 5.45 > 2
    assert met.closure_max is True  # 9 ≤ 10
    assert met.p95 is False  # 9 is in the top 5 %
    met = online.targets(_graph_online(_run([1.0, 1.4, 1.0, 1.2, 1.1])))
    assert (met.closure_median, met.closure_max, met.p95) == (True, True, True)
    assert (met.after_idle, met.median, met.p99, met.max) == (True, True, True, True)
    met = online.targets(_graph_online(_run([1.0, 1.0, 1.0, 11.0, 1.0])))
    assert (met.closure_median, met.closure_max) == (False, False)  # median of 1 and 11: 6
    three = [False, True, True, True, False]  # closures at 1, 11 and 1.5: median 1.5
    met = online.targets(_graph_online(_run([1.0, 1.0, 11.0, 1.5, 1.0]), closing=three))
    assert (met.closure_median, met.closure_max) == (True, False)
    # A graph without a closing sample is not judged there; p95 still is.
    met = online.targets(_graph_online(_run([1.0] * 5), closing=[False] * 5))
    assert (met.closure_median, met.closure_max, met.p95) == (None, None, True)
    # A failed run fails every target; a missing 5 ms run judges none of them.
    failed = online.targets(_graph_online(_run([1.0] * 5, status="timeout (> 1 s)")))
    assert all(getattr(failed, attr) is False for _, attr in online.TARGET_COLUMNS)
    other = online.targets(_graph_online(_run([1.0] * 5, budget_ms=2.0)))
    assert (other.closure_median, other.closure_max, other.p95) == (None, None, None)


def test_issue_25_targets_count_in_the_summary() -> None:
    good = _graph_online(_run([1.0, 1.4, 1.0, 1.2, 1.1]))
    bad = _graph_online(_run([1.0, 1.0, 1.0, 11.0, 1.0]))
    line = online._summary([good, bad])
    assert "median r after a closure ≤ 2: 1/2" in line
    assert "max r after a closure ≤ 10: 1/2" in line
    assert "p95 r ≤ 1.5: 1/2" in line
    assert "Under load" not in line
    loaded = online._summary([good, bad], busy_count=2)
    assert "Under load (2 CPU-bound processes beside every run)" in loaded
    assert "r after idle ≤ 1.05 and p99 ≤ budget" in loaded


def test_every_table_row_has_as_many_cells_as_its_header() -> None:
    g = _graph_online(_run([1.0, 1.4, 1.0, 1.2, 1.1]),
                      _run([1.0] * 5, budget_ms=20.0, status="failed (exit 1): boom"))
    text = online.format_tables([g], [5.0, 20.0], busy_count=1)
    tables: list[list[int]] = []
    previous = ""
    for line in text.splitlines():
        if line.startswith("|"):
            if not previous.startswith("|"):
                tables.append([])
            tables[-1].append(line.count(" | "))
        previous = line
    assert len(tables) == 4  # optimum, runs, targets, checks
    assert all(len(set(cells)) == 1 for cells in tables), tables
    assert "| toy | H₂O@5ms |" in text and "| 1.3 | 1.4 |" in text  # closures: median, max
    assert "| 5 (2) |" in text  # samples (at a closure)
    assert "Under load (1 CPU-bound process beside every run)" in text


def test_the_section_header_records_the_load() -> None:
    g = _graph_online(_run([1.0] * 5))
    assert "Busy: 2 CPU-bound processes beside every run." in online.render_section(
        [g], [5.0], [], busy_count=2)
    assert "Busy: no CPU-bound process added beside the runs." in online.render_section(
        [g], [5.0], [])


def test_busy_must_not_be_negative(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        online.main(["--busy", "-1", "--no-results"])
    assert exit_info.value.code == 2
    assert "--busy must be a non-negative integer" in capsys.readouterr().err
