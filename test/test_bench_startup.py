"""The pure helpers of bench/startup.py (no ROS graph, no build): environments, the install
tree's reset, the tables and targets, and a child that overruns its timeout."""

from __future__ import annotations

import importlib
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

_BENCH = Path(__file__).resolve().parent.parent / "bench"
if str(_BENCH) not in sys.path:
    sys.path.insert(0, str(_BENCH))
startup = importlib.import_module("startup")


def test_graph_dimension_comes_from_the_first_record(tmp_path: Path) -> None:
    planar, spatial, empty = tmp_path / "a.g2o", tmp_path / "b.g2o", tmp_path / "c.g2o"
    planar.write_text("\n# comment\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    spatial.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")
    empty.write_text("")
    assert not startup.graph_is_3d(planar)
    assert startup.graph_is_3d(spatial)
    assert not startup.graph_is_3d(empty)


def test_child_env_keeps_dds_on_loopback_and_owns_the_kernel_cache(tmp_path: Path) -> None:
    base = {"PATH": "/bin", "NUMBA_CACHE_DIR": "/elsewhere", "ROS_LOCALHOST_ONLY": "1",
            "ROS_STATIC_PEERS": "10.0.0.1", "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp",
            "XDG_CACHE_HOME": "/home/cache", "H2O_SLAM_SKIP_WARMUP": "1"}
    env = startup.child_env(base, tmp_path)
    assert env["XDG_CACHE_HOME"] == str(tmp_path)
    assert "NUMBA_CACHE_DIR" not in env and "H2O_SLAM_SKIP_WARMUP" not in env
    assert "ROS_LOCALHOST_ONLY" not in env and "ROS_STATIC_PEERS" not in env
    assert env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    profile = Path(env["FASTRTPS_DEFAULT_PROFILES_FILE"])
    assert profile == startup.REPO / "config" / "fastdds_localhost.xml" and profile.is_file()
    assert env["PATH"] == "/bin"
    assert base["NUMBA_CACHE_DIR"] == "/elsewhere"  # the input is left alone
    assert startup.child_env(base, None)["XDG_CACHE_HOME"] == "/home/cache"


def test_parse_env_reads_env_dash_0() -> None:
    blob = b"A=1\0B=x=y\0MULTI=line1\nline2\0\0"
    assert startup.parse_env(blob) == {"A": "1", "B": "x=y", "MULTI": "line1\nline2"}


def test_restore_tree_removes_what_runs_added(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "mod.py").write_text("x = 1\n")
    keep = startup.files_under(tmp_path)
    (tmp_path / "pkg" / "__pycache__").mkdir()
    (tmp_path / "pkg" / "__pycache__" / "mod.cpython-311.pyc").write_bytes(b"\0")
    (tmp_path / "pkg" / "kernel.nbi").write_bytes(b"\0")
    added = startup.files_under(tmp_path) - keep
    assert startup.kernel_files(added) == 1  # the .pyc is byte code, not a kernel
    assert startup.restore_tree(tmp_path, keep) == 2
    assert startup.files_under(tmp_path) == keep
    assert not (tmp_path / "pkg" / "__pycache__").exists()


def test_numbers_verdicts_and_scrubbed_paths() -> None:
    assert startup.median([3.0, None, 1.0, 2.0]) == 2.0
    assert startup.median([None]) is None
    assert [startup.seconds(v) for v in (None, 0.000701, 2.876, 10.54, 181.2)] == [
        "—", "0.000701", "2.88", "10.5", "181"]
    assert startup.seconds(0.3) == "0.300"
    assert startup.verdict(1.0, 1.0) == "met"
    assert startup.verdict(1.01, 1.0) == "missed"
    assert startup.verdict(None, 1.0) == "missed"
    assert startup.scrub("h2o-demo: /tmp/h2o-x/demo/input: empty", Path("/tmp/h2o-x")) == \
        "h2o-demo: $TMP/demo/input: empty"
    assert startup.scrub("x" * 300, Path("/tmp/h2o-x")) == "x" * 199 + "…"


def test_warming_up_is_read_from_the_diagnostics_values() -> None:
    def array(*values: dict[str, str]) -> SimpleNamespace:
        return SimpleNamespace(status=[SimpleNamespace(values=[
            SimpleNamespace(key=k, value=v) for k, v in vals.items()]) for vals in values])

    assert startup.reports_warming_up(array({"warming_up": "true", "held_inputs": "3"}))
    assert not startup.reports_warming_up(array({"warming_up": "false"}))
    assert not startup.reports_warming_up(array({"rejected": "0"}, {}))  # hybrid_vo_node
    assert not startup.reports_warming_up(array())


def test_node_ready_is_the_later_of_matched_and_diagnosed() -> None:
    assert startup.NodeRun(0.5, 1.2, "ok").ready_s == 1.2
    assert startup.NodeRun(1.5, 1.2, "ok").ready_s == 1.5
    assert startup.NodeRun(0.5, None, "timeout").ready_s is None


def _opts(tmp_path: Path) -> object:
    return startup.Options(tmp_path / "tinyGrid3D.g2o", tmp_path / "manhattan.g2o", 3,
                           False, False, 180.0, 1)


def test_section_marks_targets_and_lists_failures(tmp_path: Path) -> None:
    run, node = startup.Run, startup.NodeRun
    small = startup.Row("`h2o-solve --mode exact`", "tinyGrid3D", {
        startup.EMPTY: [run(70.0, "ok", written=300)],
        startup.WARM: [run(0.8, "ok", solve_s=0.01), run(0.9, "ok"), run(None, "timeout")],
        startup.INSTALL: [run(0.85, "ok", written=0)]})
    large = startup.Row("`h2o-solve --mode exact`", "manhattan", {
        startup.EMPTY: [run(None, "exit 1", detail="boom")],
        startup.WARM: [run(3.0, "ok")], startup.INSTALL: [run(75.0, "ok", written=12)]})
    peer = startup.Row("GTSAM peer (`readG2o` + LM)", "tinyGrid3D", {
        startup.EMPTY: [run(0.4, "ok")], startup.WARM: [run(0.3, "ok", solve_s=0.001)]})
    replay = startup.Row("`h2o-replay`", "demo bag", note="h2o-demo: timeout")
    h2o = startup.Row("h2o_node", "odom", {
        startup.EMPTY: [node(1.0, 1.5, "ok", 30.0, stop="clean", stop_s=0.3, written=200)],
        startup.WARM: [node(0.9, 1.1, "ok", stop="clean", stop_s=0.2)] * 3,
        startup.INSTALL: [node(None, None, "timeout", stop="killed", leftovers=True)]})
    text = startup.render_section([small, large], [peer], [replay], [h2o],
                                  _opts(tmp_path), 12.0, ["a note"])
    assert text.startswith(startup.SECTION + "\n")
    assert "| `h2o-solve --mode exact` | tinyGrid3D | 70.0 | 0.850 " \
        "| 0.850 (0.800–0.900) (1 of 3: timeout) | 0.0100 | 300 / 0 / 0 " \
        "| warm ≤ 1 s: met; after install compiles nothing: met |" in text
    assert "| manhattan | exit 1 | 75.0 | 3.00 |" in text
    assert "| GTSAM peer (`readG2o` + LM) | tinyGrid3D | 0.400 (first run) | — | 0.300 |" in text
    assert "not run: h2o-demo: timeout" in text
    assert "| h2o_node | ready (both) | 1.50 | timeout | 1.10 (1.10–1.10) | 200 / 0 / 0 " \
        "| ≤ 2 s: empty cache met, after install missed, warm met |" in text
    assert "| h2o_node | kernels loaded | 30.0 | timeout | — (3 of 3: not reached) |  |  |" \
        in text
    assert "| h2o_node | SIGINT → exit | clean 0.300 s | killed, processes left behind " \
        "| 3 of 3 clean, ≤ 0.200 s |  |  |" in text
    assert "- warm `h2o-solve` on tinyGrid3D ≤ 1 s: met (0.850 s)" in text
    assert "- installed h2o_node ready ≤ 2 s, cold, after install: missed (timeout)" in text
    assert "manhattan, empty: exit 1 — `boom`" in text
    assert "h2o_node odom, install: timeout" in text
    assert "tinyGrid3D, warm: timeout (1 of 3 runs)" in text
    assert "a note" in text and str(startup.REPO) not in text


def test_a_child_over_its_timeout_is_killed_with_its_group(tmp_path: Path) -> None:
    pid_file = tmp_path / "grandchild.pid"
    script = ("import subprocess, sys, time\n"
              "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
              f"open({str(pid_file)!r}, 'w').write(str(p.pid))\n"
              "time.sleep(60)\n")
    start = time.monotonic()
    run = startup.run_timed([sys.executable, "-c", script], dict(os.environ), tmp_path, 2.0,
                            tmp_path / "out.log")
    assert run.status == "timeout" and run.seconds is None
    assert time.monotonic() - start < 20
    grandchild = int(pid_file.read_text())
    deadline = time.monotonic() + 5.0
    while True:  # SIGKILL is delivered at once, the exit takes a moment
        try:
            state = Path(f"/proc/{grandchild}/stat").read_text().split(")")[-1].split()[0]
        except FileNotFoundError:
            state = "gone"
        if state in ("gone", "Z") or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert state in ("gone", "Z"), state  # killed (a zombie until init reaps it)


def test_a_failing_child_reports_its_exit_code_and_last_line(tmp_path: Path) -> None:
    run = startup.run_timed([sys.executable, "-c", "import sys; print('bad input'); "
                             "sys.exit(3)"], dict(os.environ), tmp_path, 30.0,
                            tmp_path / "out.log")
    assert (run.status, run.detail, run.seconds) == ("exit 3", "bad input", None)
    ok = startup.run_timed([sys.executable, "-c", "pass"], dict(os.environ), tmp_path, 30.0,
                           tmp_path / "ok.log")
    assert ok.status == "ok" and ok.seconds is not None and ok.seconds > 0


@pytest.mark.parametrize("argv", [["--graphs", "intel"], ["--repeats", "0"]])
def test_bad_command_lines_are_refused(argv: list[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        startup.main(argv)
    assert exc.value.code == 2
