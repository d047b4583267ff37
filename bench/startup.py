"""Benchmark: start-up. Cold and warm wall times of whole processes — ``h2o-solve`` (exact) on
a small and a large public pose graph, ``h2o-replay`` on the demo bag, a GTSAM peer on the
same graphs — and the time until each node, as ``colcon build`` installs it, has matched a
subscription and published its first ``/diagnostics``.

    .venv/bin/python bench/startup.py [--data DIR] [--small NAME] [--large NAME] [--repeats N]
                                      [--skip-nodes] [--skip-cold] [--timeout S]
                                      [--results FILE | --no-write]

Protocol:

1. ``colcon build`` (as ``test/test_package_build.py`` runs it) into a fresh temporary
   workspace per cold variant; every process of the benchmark is the installed executable
   (``<install>/h2o_slam/lib/h2o_slam/<name>``) run in the environment ``source
   install/setup.bash`` produces, with the loopback Fast DDS profile, ``NUMBA_CACHE_DIR``
   removed and ``XDG_CACHE_HOME`` (where the kernel cache lives, ``$XDG_CACHE_HOME/h2o_slam``)
   set per run.
2. Cold, two variants, each process with a kernel cache of its own and the install tree as
   the build left it (files written into it by earlier runs are removed first):
   *empty cache*: a fresh, empty ``XDG_CACHE_HOME`` (the build ran with another one, and
   with ``H2O_SLAM_SKIP_WARMUP=1``: setup.py need not fill a cache no run sees);
   *after install*: a copy of the ``XDG_CACHE_HOME`` the build itself ran with, i.e. whatever
   the install step put there.
3. Warm: right after the empty-cache cold run, the same process ``--repeats`` times with the
   cache that run left; the median. ``--skip-cold``: one build and one shared cache, primed by
   one ``h2o-solve`` run that is not reported.
4. Nodes: this process holds an rclpy tester under a unique namespace (the node is started
   with ``-r __ns:=/startup…`` and ``/diagnostics`` remapped into it). From just before
   ``Popen``: the time until the tester's publisher on the node's input (``odom``) counts a
   matched subscription, and until the first ``/diagnostics`` message arrives; *ready* is
   the later of the two; *kernels loaded*: the first ``/diagnostics`` without
   ``warming_up: true``. Then SIGINT to the node; *clean* = exit code 0 within
   :data:`STOP_S`.
5. GTSAM peer: :data:`PEER`, written to a temporary file and run with this Python:
   ``gtsam.readG2o``, a prior on the first pose, ``LevenbergMarquardtOptimizer`` with
   ``bench/solvers.py``'s settings; its first run stands in the cold columns.

Kernel-cache files written by a run (files new in its ``XDG_CACHE_HOME``, or new non-``.pyc``
files in the install tree) tell whether it compiled. A run over ``--timeout`` is killed with
its whole process group and reported as a timeout. Everything is written under one temporary
folder, removed at the end. Output: a markdown section, printed and written as
``## Start-up (bench/startup.py)`` of ``bench/RESULTS.md`` (``--results FILE``;
``--no-write``: print only).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from results_md import (
    add_graph_arguments,
    command,
    publish,
    results_path,
    revision,
    select_graphs,
    table_head,
)
from solvers import LM_ABSOLUTE_TOL, LM_MAX_ITERATIONS, LM_RELATIVE_TOL, PRIOR_SIGMA

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Start-up (bench/startup.py)"
PACKAGE = "h2o_slam"
DDS_PROFILE = REPO / "config" / "fastdds_localhost.xml"
#: Variables that would override the loopback profile's discovery (the Makefile drops them).
DISCOVERY_VARIABLES = ("ROS_LOCALHOST_ONLY", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS")
#: setup.py's switch that skips compiling the kernels at build time: set only for the build of
#: the empty-cache variant (whose cache no run sees), removed everywhere else.
SKIP_WARMUP = "H2O_SLAM_SKIP_WARMUP"

DEFAULT_SMALL = "tinyGrid3D"
DEFAULT_LARGE = "manhattan"
DEFAULT_REPEATS = 3
DEFAULT_TIMEOUT_S = 180.0
#: Laps of ``h2o-demo``'s 36 s square in the replayed bag (the demo's default is 3).
DEFAULT_DEMO_LAPS = 1
#: Seconds a node has to exit after SIGINT.
STOP_S = 5.0

TARGET_SOLVE_WARM_S = 1.0
TARGET_READY_S = 2.0

EMPTY, INSTALL, WARM = "empty", "install", "warm"
COLD = (EMPTY, INSTALL)
COLUMN = {EMPTY: "cold, empty cache", INSTALL: "cold, after install"}


@dataclass(frozen=True)
class NodeSpec:
    """An installed node: its executable, parameter file and the input the tester offers."""

    name: str
    params: str
    input_topic: str


NODES = (NodeSpec("h2o_node", "h2o.yaml", "odom"),
         NodeSpec("hybrid_vo_node", "hybrid_vo.yaml", "odom"))

#: The GTSAM peer of ``h2o-solve --mode exact``: argv = graph, 2d|3d, prior sigma, LM
#: max iterations, relative and absolute tolerance. A graph without vertices (kitti_00) gets
#: its initial estimate by composing the edges from the first node, in file order.
PEER = '''\
"""GTSAM peer of h2o-solve --mode exact, written and run by bench/startup.py."""
import json
import sys
import time

import gtsam

path, dim = sys.argv[1], sys.argv[2]
sigma, iterations, rel_tol, abs_tol = (float(v) for v in sys.argv[3:7])
is3d = dim == "3d"
graph, initial = gtsam.readG2o(path, is3d)
if initial.size() == 0:
    edges = []
    with open(path) as f:
        for line in f:
            tok = line.split()
            if tok and not is3d and tok[0] == "EDGE_SE2":
                edges.append((int(tok[1]), int(tok[2]), gtsam.Pose2(*map(float, tok[3:6]))))
            elif tok and is3d and tok[0] == "EDGE_SE3:QUAT":
                x, y, z, qx, qy, qz, qw = map(float, tok[3:10])
                edges.append((int(tok[1]), int(tok[2]), gtsam.Pose3(
                    gtsam.Rot3.Quaternion(qw, qx, qy, qz), gtsam.Point3(x, y, z))))
    at = initial.atPose3 if is3d else initial.atPose2
    if edges:
        initial.insert(min(min(a, b) for a, b, _ in edges),
                       gtsam.Pose3() if is3d else gtsam.Pose2())
    grown = True
    while grown:
        grown = False
        for a, b, z in edges:
            if initial.exists(a) and not initial.exists(b):
                initial.insert(b, at(a).compose(z))
                grown = True
            elif initial.exists(b) and not initial.exists(a):
                initial.insert(a, at(b).compose(z.inverse()))
                grown = True
first = min(initial.keys())
if is3d:
    prior = gtsam.PriorFactorPose3(first, initial.atPose3(first),
                                   gtsam.noiseModel.Isotropic.Sigma(6, sigma))
else:
    prior = gtsam.PriorFactorPose2(first, initial.atPose2(first),
                                   gtsam.noiseModel.Isotropic.Sigma(3, sigma))
graph.add(prior)
params = gtsam.LevenbergMarquardtParams()
params.setMaxIterations(int(iterations))
params.setRelativeErrorTol(rel_tol)
params.setAbsoluteErrorTol(abs_tol)
start = time.perf_counter()
result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
solve_s = time.perf_counter() - start
print(json.dumps({"solve_s": solve_s, "poses": initial.size(), "chi2": 2 * graph.error(result)}))
'''


# --- results --------------------------------------------------------------------------------


@dataclass
class Run:
    """One whole process: wall time from just before ``Popen`` to its exit."""

    seconds: float | None
    status: str  # "ok", "timeout", "exit N", "failed: ..."
    written: int = 0  # kernel-cache files the run wrote
    solve_s: float | None = None  # the solve alone, as the process reports it
    detail: str = ""  # last line of the output of a failed run


@dataclass
class NodeRun:
    """One node start: times from just before ``Popen``, and how SIGINT stopped it."""

    matched_s: float | None
    diag_s: float | None
    status: str  # "ok", "timeout", "exit N" (died before it was ready), "failed: ..."
    loaded_s: float | None = None  # first /diagnostics that does not say warming_up
    stop: str = "—"  # "clean", "exit N", "killed"
    stop_s: float | None = None
    leftovers: bool = False  # processes of its group still alive after it exited
    written: int = 0
    detail: str = ""

    @property
    def ready_s(self) -> float | None:
        """Matched and diagnosed: the later of the two, or None when either is missing."""
        if self.matched_s is None or self.diag_s is None:
            return None
        return max(self.matched_s, self.diag_s)


@dataclass
class Row:
    """One command (or node) on one input: its runs by variant (:data:`COLD`, :data:`WARM`)."""

    command: str
    input: str
    runs: dict[str, list[Any]] = field(default_factory=dict)
    note: str = ""  # why it did not run


# --- pure helpers ---------------------------------------------------------------------------


def graph_is_3d(path: Path) -> bool:
    """Whether a .g2o file holds 3-D poses: its first VERTEX_/EDGE_ record is an SE3 one."""
    with path.open() as f:
        for line in f:
            tag = line.split(maxsplit=1)[0] if line.strip() else ""
            if tag.startswith(("VERTEX_", "EDGE_")):
                return "SE3" in tag
    return False


def reports_warming_up(msg: Any) -> bool:
    """Whether a ``DiagnosticArray`` says the node is still loading its kernels (a status
    value ``warming_up: true``; a node without that key is never warming up)."""
    return any(kv.key == "warming_up" and kv.value.strip().lower() in ("true", "1")
               for status in msg.status for kv in status.values)


def parse_env(blob: bytes) -> dict[str, str]:
    """``env -0`` output as a dict (what ``source install/setup.bash`` leaves)."""
    env = {}
    for entry in blob.split(b"\0"):
        if b"=" in entry:
            key, _, value = entry.decode(errors="surrogateescape").partition("=")
            env[key] = value
    return env


def dds_env(env: dict[str, str]) -> dict[str, str]:
    """``env`` with DDS kept on this machine: Fast DDS with the repository's loopback
    profile, and none of the ROS variables that would override its discovery."""
    out = dict(env)
    out["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    out["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(DDS_PROFILE)
    out["FASTDDS_DEFAULT_PROFILES_FILE"] = str(DDS_PROFILE)
    for name in DISCOVERY_VARIABLES:
        out.pop(name, None)
    return out


def child_env(env: dict[str, str], cache_home: Path | None) -> dict[str, str]:
    """A child's environment: :func:`dds_env`, no ``NUMBA_CACHE_DIR`` (it would win over
    the package's cache folder) nor :data:`SKIP_WARMUP`, and ``XDG_CACHE_HOME`` =
    ``cache_home`` when given."""
    out = dds_env(env)
    out.pop("NUMBA_CACHE_DIR", None)
    out.pop(SKIP_WARMUP, None)
    if cache_home is not None:
        out["XDG_CACHE_HOME"] = str(cache_home)
    return out


def files_under(root: Path) -> set[Path]:
    """Every file under ``root`` (none when it does not exist)."""
    return {p for p in root.rglob("*") if p.is_file()} if root.is_dir() else set()


def kernel_files(paths: set[Path]) -> int:
    """How many of ``paths`` are compiled kernels or their index: not byte code (``.pyc``),
    and not another program's cache that shares ``XDG_CACHE_HOME`` (matplotlib writes its
    font list there on first use)."""
    return sum(1 for p in paths if p.suffix != ".pyc" and "matplotlib" not in p.parts)


def restore_tree(root: Path, keep: set[Path]) -> int:
    """Remove the files under ``root`` that are not in ``keep`` (and folders left empty
    that held them): the install tree as the build left it. Returns the files removed."""
    removed = 0
    for path in sorted(root.rglob("*"), key=lambda p: len(p.parts), reverse=True):
        if path.is_file() and path not in keep:
            path.unlink()
            removed += 1
        elif path.is_dir() and path.name == "__pycache__" and not any(path.iterdir()):
            path.rmdir()
    return removed


def median(values: Sequence[float | None]) -> float | None:
    """Median of the values that are not None (None if there are none)."""
    got = [v for v in values if v is not None]
    return statistics.median(got) if got else None


def seconds(value: float | None) -> str:
    """A duration for the table: 3 significant digits (whole seconds from 100 s), "—" for
    None."""
    if value is None:
        return "—"
    return f"{value:.0f}" if value >= 100 else f"{value:#.3g}"


def verdict(value: float | None, limit: float) -> str:
    """``met`` / ``missed`` against ``value ≤ limit`` (no value: missed)."""
    return "met" if value is not None and value <= limit else "missed"


# --- processes ------------------------------------------------------------------------------


def scrub(text: str, tmp: Path, limit: int = 200) -> str:
    """``text`` with the temporary folder's path shown as ``$TMP``, cut at ``limit``."""
    text = text.replace(str(tmp), "$TMP")
    return text if len(text) <= limit else text[: limit - 1] + "…"


def kill_group(proc: subprocess.Popen[bytes]) -> bool:
    """SIGKILL what is left of ``proc``'s process group (it leads its own session) and reap
    ``proc``; True when some process of the group was still there."""
    alive = True
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        alive = False
    proc.wait()
    return alive


def last_line(log: Path) -> str:
    """The last non-empty line of a log (for the failures list)."""
    try:
        lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1] if lines else ""


def run_timed(cmd: Sequence[str], env: dict[str, str], cwd: Path, timeout_s: float,
              log: Path) -> Run:
    """Run ``cmd`` in a session of its own, output to ``log``; its wall time, or a timeout
    after which the whole group is killed."""
    with log.open("wb") as out:
        start = time.monotonic()
        try:
            proc = subprocess.Popen(list(cmd), env=env, cwd=cwd, stdout=out,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True)
        except OSError as exc:
            return Run(None, f"failed: {exc}")
        try:
            rc = proc.wait(timeout=timeout_s)
            elapsed = time.monotonic() - start
        except subprocess.TimeoutExpired:
            kill_group(proc)
            return Run(None, "timeout", detail=f"over {timeout_s:g} s")
        finally:
            kill_group(proc)  # a child it left behind
    if rc != 0:
        return Run(None, f"exit {rc}", detail=last_line(log))
    return Run(elapsed, "ok")


# --- the install ----------------------------------------------------------------------------


@dataclass
class Install:
    """One ``colcon build`` into a temporary workspace, and its sourced environment."""

    root: Path
    env: dict[str, str]
    cache_after: Path  # the XDG_CACHE_HOME the build ran with
    tree: set[Path]  # the files of the install tree right after the build

    @property
    def prefix(self) -> Path:
        """``<install>/h2o_slam``."""
        return self.root / "install" / PACKAGE

    def exe(self, name: str) -> Path:
        """An installed executable, where ``ros2 run`` finds it."""
        return self.prefix / "lib" / PACKAGE / name

    def reset(self) -> None:
        """The install tree as the build left it."""
        restore_tree(self.prefix, self.tree)

    def written(self) -> set[Path]:
        """Files the runs added to the install tree since the build (or the last reset)."""
        return files_under(self.prefix) - self.tree


def colcon_build(root: Path, cache_home: Path, timeout_s: float,
                 skip_warmup: bool = False) -> Install:
    """Build the repository into ``root`` with ``XDG_CACHE_HOME=cache_home`` (raises
    ``RuntimeError`` when the build or the sourcing fails); ``skip_warmup``: without
    compiling the kernels at build time (the install tree is the same)."""
    root.mkdir(parents=True)
    cache_home.mkdir(parents=True, exist_ok=True)
    env = child_env(dict(os.environ), cache_home)
    env["COLCON_HOME"] = str(root / "colcon_home")  # no user-level colcon defaults
    if skip_warmup:
        env[SKIP_WARMUP] = "1"
    cmd = [sys.executable, "-m", "colcon", "--log-base", str(root / "log"), "build",
           "--base-paths", str(REPO), "--build-base", str(root / "build"),
           "--install-base", str(root / "install"),
           "--event-handlers", "desktop_notification-", "status-"]
    start = time.monotonic()
    run = run_timed(cmd, env, root, timeout_s, root / "colcon.log")
    if run.status != "ok":
        raise RuntimeError(f"colcon build: {run.status} {run.detail}".strip())
    print(f"  colcon build {root.name}: {time.monotonic() - start:.1f} s", file=sys.stderr)
    proc = subprocess.run(["bash", "-c", 'source "$1/setup.bash" && env -0', "_",
                           str(root / "install")], env=env, capture_output=True,
                          timeout=timeout_s, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"source setup.bash: {proc.stderr.decode(errors='replace')}")
    sourced = parse_env(proc.stdout)
    sourced.pop(SKIP_WARMUP, None)
    install = Install(root, sourced, cache_home, set())
    install.tree = files_under(install.prefix)
    return install


# --- the tester (rclpy in this process) -------------------------------------------------------


class Tester:
    """One rclpy context for the whole run; one tester node per node start."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.context import Context

        self.context = Context()
        rclpy.init(context=self.context)

    def close(self) -> None:
        """Shut the context down."""
        self.context.try_shutdown()

    def start_node(self, cmd: list[str], namespace: str, spec: NodeSpec, env: dict[str, str],
                   cwd: Path, timeout_s: float, log: Path) -> NodeRun:
        """Start ``cmd`` (a node under ``namespace``); time its matched input, its first
        ``/diagnostics`` and the first that no longer says ``warming_up`` (then the cache
        holds every kernel the node loads); stop it with SIGINT."""
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        node = Node("startup_tester", namespace=namespace, context=self.context)
        publisher = node.create_publisher(Odometry, f"{namespace}/{spec.input_topic}", 10)
        diagnostics: list[float] = []
        loaded: list[float] = []

        def on_diagnostics(msg: Any) -> None:
            now = time.monotonic()
            if not diagnostics:
                diagnostics.append(now)
            if not loaded and not reports_warming_up(msg):
                loaded.append(now)

        node.create_subscription(DiagnosticArray, f"{namespace}/diagnostics", on_diagnostics, 10)
        executor = SingleThreadedExecutor(context=self.context)
        executor.add_node(node)
        out = log.open("wb")
        proc: subprocess.Popen[bytes] | None = None
        try:
            start = time.monotonic()
            try:
                proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=out,
                                        stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                        start_new_session=True)
            except OSError as exc:
                return NodeRun(None, None, f"failed: {exc}")
            matched: float | None = None
            status = "ok"
            while True:
                executor.spin_once(timeout_sec=0.01)
                now = time.monotonic()
                if matched is None and publisher.get_subscription_count() > 0:
                    matched = now - start
                if matched is not None and loaded:
                    break
                if proc.poll() is not None:
                    status = f"exit {proc.returncode}"
                    break
                if now - start > timeout_s:
                    status = "timeout" if matched is None or not diagnostics else "ok"
                    break
            run = NodeRun(matched, diagnostics[0] - start if diagnostics else None, status,
                          loaded[0] - start if loaded else None)
            self._stop(proc, run)
            if run.status != "ok" or run.stop != "clean":
                run.detail = last_line(log)
            return run
        finally:
            if proc is not None:
                kill_group(proc)
            out.close()
            executor.remove_node(node)
            executor.shutdown()
            node.destroy_node()

    @staticmethod
    def _stop(proc: subprocess.Popen[bytes], run: NodeRun) -> None:
        """SIGINT, as Ctrl-C or ``ros2 launch`` would send it; record how the node ended."""
        if proc.poll() is not None:
            run.leftovers = kill_group(proc)
            return
        start = time.monotonic()
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=STOP_S)
        except subprocess.TimeoutExpired:
            kill_group(proc)
            run.stop = "killed"
            return
        run.stop_s = time.monotonic() - start
        run.stop = "clean" if rc == 0 else f"exit {rc}"
        run.leftovers = kill_group(proc)


# --- the benchmark ----------------------------------------------------------------------------


@dataclass
class Options:
    """The command line, as the driver uses it."""

    small: Path
    large: Path
    repeats: int
    skip_nodes: bool
    skip_cold: bool
    timeout_s: float
    demo_laps: int


class Bench:
    """The temporary folder, the builds and the caches of one run."""

    def __init__(self, tmp: Path, opts: Options) -> None:
        self.tmp = tmp
        self.opts = opts
        self.builds: dict[str, Install] = {}
        self.shared_cache: Path | None = None  # --skip-cold: the cache every run shares
        self.tester: Tester | None = None
        self.install_cache_files = 0

    def fresh(self, stem: str) -> Path:
        """A new folder under the temporary folder."""
        path = self.tmp / f"{stem}-{uuid.uuid4().hex[:8]}"
        path.mkdir(parents=True)
        return path

    def prepare(self) -> None:
        """The colcon builds: one per cold variant, or one for ``--skip-cold``."""
        setup_s = 3 * self.opts.timeout_s
        if self.opts.skip_cold:
            build = colcon_build(self.tmp / "ws-warm", self.tmp / "cache-warm", setup_s)
            self.builds[WARM] = build
            self.shared_cache = build.cache_after
            prime = self.solve_cmd(build, self.opts.small)
            print("  priming the kernel cache (one h2o-solve, not reported)", file=sys.stderr)
            run_timed(prime, child_env(build.env, self.shared_cache), self.tmp,
                      self.opts.timeout_s, self.tmp / "prime.log")
            return
        # The empty-cache variant's runs never see its build's cache: no need to fill it.
        self.builds[EMPTY] = colcon_build(self.tmp / "ws-empty", self.tmp / "cache-build-empty",
                                          setup_s, skip_warmup=True)
        self.builds[WARM] = self.builds[EMPTY]
        self.builds[INSTALL] = colcon_build(self.tmp / "ws-install",
                                            self.tmp / "cache-build-install", setup_s)
        self.install_cache_files = kernel_files(files_under(self.builds[INSTALL].cache_after))

    def cache_for(self, variant: str) -> Path:
        """A kernel cache (``XDG_CACHE_HOME``) for a cold run of ``variant``."""
        path = self.fresh(f"cache-{variant}")
        if variant == INSTALL:
            shutil.copytree(self.builds[INSTALL].cache_after, path, dirs_exist_ok=True)
        return path

    def measure(self, launch: Callable[[Install, Path], Any]) -> dict[str, list[Any]]:
        """``launch(install, cache)`` cold in each variant and warm ``--repeats`` times."""
        runs: dict[str, list[Any]] = {}
        if self.opts.skip_cold:
            assert self.shared_cache is not None
            runs[WARM] = [launch(self.builds[WARM], self.shared_cache)
                          for _ in range(self.opts.repeats)]
            return runs
        for variant in COLD:
            build = self.builds[variant]
            build.reset()
            cache = self.cache_for(variant)
            runs[variant] = [launch(build, cache)]
            if variant == EMPTY:
                runs[WARM] = [launch(build, cache) for _ in range(self.opts.repeats)]
        return runs

    def _written(self, install: Install, cache: Path, before: set[Path],
                 tree_before: set[Path]) -> int:
        return kernel_files(files_under(cache) - before) + kernel_files(
            install.written() - tree_before)

    def solve_cmd(self, install: Install, graph: Path, report: Path | None = None) -> list[str]:
        """``h2o-solve GRAPH --mode exact --output TMP --quiet [--report R]``."""
        out = self.fresh("solve") / f"{graph.stem}.g2o"
        cmd = [str(install.exe("h2o-solve")), str(graph), "--mode", "exact", "--output",
               str(out), "--quiet"]
        return cmd + (["--report", str(report)] if report is not None else [])

    def process(self, install: Install, cache: Path, cmd: list[str], what: str) -> Run:
        """One whole process, with the kernel-cache files it wrote."""
        before, tree_before = files_under(cache), install.written()
        run = run_timed(cmd, child_env(install.env, cache), self.fresh("cwd"),
                        self.opts.timeout_s, self.fresh("log") / "out.log")
        run.written = self._written(install, cache, before, tree_before)
        run.detail = scrub(run.detail, self.tmp)
        print(f"  {what}: {run.status} {seconds(run.seconds)} s, "
              f"{run.written} kernel-cache files written", file=sys.stderr)
        return run

    def solve(self, graph: Path) -> Row:
        """``h2o-solve --mode exact`` on ``graph``."""
        def launch(install: Install, cache: Path) -> Run:
            report = self.fresh("report") / "report.json"
            run = self.process(install, cache, self.solve_cmd(install, graph, report),
                               f"h2o-solve {graph.stem}")
            try:
                run.solve_s = float(json.loads(report.read_text())["wall_s"])
            except (OSError, ValueError, KeyError, TypeError):
                pass
            return run

        return Row("`h2o-solve --mode exact`", graph.stem, self.measure(launch))

    def peer(self, graph: Path) -> Row:
        """The GTSAM peer on ``graph``: first run, then ``--repeats`` runs."""
        script = self.tmp / "gtsam_peer.py"
        if not script.exists():
            script.write_text(PEER)
        cmd = [sys.executable, str(script), str(graph), "3d" if graph_is_3d(graph) else "2d",
               repr(PRIOR_SIGMA), str(LM_MAX_ITERATIONS), repr(LM_RELATIVE_TOL),
               repr(LM_ABSOLUTE_TOL)]
        env = dds_env(dict(os.environ))

        def once() -> Run:
            log = self.fresh("log") / "out.log"
            run = run_timed(cmd, env, self.fresh("cwd"), self.opts.timeout_s, log)
            run.detail = scrub(run.detail, self.tmp)
            if run.status == "ok":
                try:
                    run.solve_s = float(json.loads(last_line(log))["solve_s"])
                except (ValueError, KeyError, TypeError):
                    pass
            print(f"  gtsam {graph.stem}: {run.status} {seconds(run.seconds)} s",
                  file=sys.stderr)
            return run

        runs = {} if self.opts.skip_cold else {EMPTY: [once()]}
        runs[WARM] = [once() for _ in range(self.opts.repeats)]
        return Row("GTSAM peer (`readG2o` + LM)", graph.stem, runs)

    def demo_bag(self) -> Path | str:
        """``h2o-demo --output DIR --laps N`` once: ``DIR/input``, or why there is none.
        Set-up, not timed: with the kernels the install compiled (a copy of that cache; with
        ``--skip-cold`` the shared one), as a user's first ``h2o-demo`` would have them."""
        if INSTALL in self.builds:
            install, cache = self.builds[INSTALL], self.cache_for(INSTALL)
        else:
            install = self.builds[WARM]
            cache = self.shared_cache if self.shared_cache is not None else self.fresh("cache")
        out = self.fresh("demo") / "demo"
        cmd = [str(install.exe("h2o-demo")), "--output", str(out), "--laps",
               str(self.opts.demo_laps), "--quiet"]
        print(f"  h2o-demo --laps {self.opts.demo_laps} (set-up)", file=sys.stderr)
        run = run_timed(cmd, child_env(install.env, cache), self.fresh("cwd"),
                        3 * self.opts.timeout_s, self.fresh("log") / "demo.log")
        if run.status != "ok" or not (out / "input").is_dir():
            return scrub(f"h2o-demo: {run.status} — {run.detail}".strip(" —"), self.tmp)
        return out / "input"

    def replay(self) -> Row:
        """``h2o-replay`` on the demo bag."""
        bag = self.demo_bag()
        if isinstance(bag, str):
            return Row("`h2o-replay`", "demo bag", note=bag)

        def launch(install: Install, cache: Path) -> Run:
            cmd = [str(install.exe("h2o-replay")), str(bag), "--output",
                   str(self.fresh("replay") / "out"), "--quiet"]
            return self.process(install, cache, cmd, "h2o-replay")

        return Row("`h2o-replay`", f"demo bag ({36 * self.opts.demo_laps} s)",
                   self.measure(launch))

    def node(self, spec: NodeSpec) -> Row:
        """An installed node: ready times and SIGINT stop."""
        if self.tester is None:
            self.tester = Tester()
        tester = self.tester

        def launch(install: Install, cache: Path) -> NodeRun:
            namespace = "/startup" + uuid.uuid4().hex[:10]
            params = install.prefix / "share" / PACKAGE / "config" / spec.params
            cmd = [str(install.exe(spec.name)), "--ros-args", "--params-file", str(params),
                   "-r", f"__ns:={namespace}", "-r", f"/diagnostics:={namespace}/diagnostics",
                   "-r", f"/tf:={namespace}/tf"]
            before, tree_before = files_under(cache), install.written()
            run = tester.start_node(cmd, namespace, spec, child_env(install.env, cache),
                                    self.fresh("cwd"), self.opts.timeout_s,
                                    self.fresh("log") / "node.log")
            run.written = self._written(install, cache, before, tree_before)
            run.detail = scrub(run.detail, self.tmp)
            print(f"  {spec.name}: {run.status}, matched {seconds(run.matched_s)} s, "
                  f"diagnostics {seconds(run.diag_s)} s, kernels loaded "
                  f"{seconds(run.loaded_s)} s, stop {run.stop} "
                  f"{seconds(run.stop_s)} s, {run.written} kernel-cache files written",
                  file=sys.stderr)
            return run

        return Row(spec.name, spec.input_topic, self.measure(launch))

    def close(self) -> None:
        """The tester's context."""
        if self.tester is not None:
            self.tester.close()


# --- tables ---------------------------------------------------------------------------------


def cold_cell(runs: list[Any] | None, value: Callable[[Any], float | None]) -> str:
    """One cold run: its value, or what happened instead."""
    if not runs:
        return "—"
    run = runs[0]
    got = value(run)
    if got is not None:
        return seconds(got)
    return run.status if run.status != "ok" else "not reached"


def warm_cell(runs: list[Any] | None, value: Callable[[Any], float | None]) -> str:
    """The median of the warm runs that gave a value, and how many did not."""
    if not runs:
        return "—"
    got = [value(r) for r in runs]
    failed = [r.status if r.status != "ok" else "not reached"
              for r, v in zip(runs, got, strict=True) if v is None]
    cell = seconds(median(got))
    done = [v for v in got if v is not None]
    if len(done) > 1:
        cell += f" ({seconds(min(done))}–{seconds(max(done))})"
    if failed:
        cell += f" ({len(failed)} of {len(runs)}: {', '.join(sorted(set(failed)))})"
    return cell


def written_cell(row: Row) -> str:
    """Kernel-cache files written: cold empty / cold after install / warm (largest)."""
    def one(variant: str) -> str:
        runs = row.runs.get(variant)
        return str(max(r.written for r in runs)) if runs else "—"
    return " / ".join(one(v) for v in (EMPTY, INSTALL, WARM))


def stop_cell(runs: list[NodeRun] | None) -> str:
    """How SIGINT ended the node: one run, or the warm runs together."""
    if not runs:
        return "—"
    left = ", processes left behind" if any(r.leftovers for r in runs) else ""
    if len(runs) == 1:
        r = runs[0]
        return (f"{r.stop} {seconds(r.stop_s)} s" if r.stop_s is not None else r.stop) + left
    clean = [r for r in runs if r.stop == "clean"]
    cell = f"{len(clean)} of {len(runs)} clean"
    if clean:
        cell += f", ≤ {seconds(max(r.stop_s or 0.0 for r in clean))} s"
    others = sorted({r.stop for r in runs if r.stop != "clean"})
    return cell + (f" ({', '.join(others)})" if others else "") + left


def solve_target(row: Row) -> str:
    """The small graph's targets: warm ≤ 1 s; the first solve after install compiles nothing."""
    warm = median([r.seconds for r in row.runs.get(WARM, [])])
    parts = [f"warm ≤ {TARGET_SOLVE_WARM_S:g} s: {verdict(warm, TARGET_SOLVE_WARM_S)}"]
    after = row.runs.get(INSTALL)
    if after:
        parts.append(f"after install compiles nothing: {first_solve_verdict(after[0])}")
    return "; ".join(parts)


def first_solve_verdict(run: Run) -> str:
    """Met when the first solve after install finished and wrote no kernel-cache file."""
    if run.status != "ok":
        return f"missed ({run.status})"
    return "met" if run.written == 0 else f"missed ({run.written} files)"


def ready_target(row: Row) -> str:
    """The node's target, ready ≤ 2 s, on each variant that ran."""
    parts = []
    for variant in (*COLD, WARM):
        runs = row.runs.get(variant)
        if runs:
            value = median([r.ready_s for r in runs]) if len(runs) > 1 else runs[0].ready_s
            name = "warm" if variant == WARM else COLUMN[variant].removeprefix("cold, ")
            parts.append(f"{name} {verdict(value, TARGET_READY_S)}")
    return f"≤ {TARGET_READY_S:g} s: " + ", ".join(parts)


def wall(run: Run) -> float | None:
    """A run's wall time (None when it did not finish)."""
    return run.seconds


def process_table(rows: list[Row], repeats: int) -> list[str]:
    """Whole processes: cold and warm wall times, the solve inside, files written, targets."""
    lines = table_head(f"| command | input | {COLUMN[EMPTY]} (s) | {COLUMN[INSTALL]} (s) "
                       f"| warm (s): median of {repeats} (range) | solve in it (s, warm) "
                       "| kernel-cache files written (cold empty / after install / warm) "
                       "| target |")
    for i, row in enumerate(rows):
        if row.note:
            lines.append(f"| {row.command} | {row.input} | not run: {row.note} | | | | | |")
            continue
        gtsam = row.command.startswith("GTSAM")
        cells = [cold_cell(row.runs.get(EMPTY), wall) + (" (first run)" if gtsam and
                                                         EMPTY in row.runs else ""),
                 "—" if gtsam else cold_cell(row.runs.get(INSTALL), wall),
                 warm_cell(row.runs.get(WARM), wall),
                 seconds(median([r.solve_s for r in row.runs.get(WARM, [])])),
                 "—" if gtsam else written_cell(row),
                 solve_target(row) if i == 0 and not gtsam else ""]
        lines.append("| " + " | ".join([row.command, row.input, *cells]) + " |")
    return lines


NODE_MEASURES: tuple[tuple[str, Callable[[NodeRun], float | None]], ...] = (
    ("input matched", lambda r: r.matched_s),
    ("first `/diagnostics`", lambda r: r.diag_s),
    ("ready (both)", lambda r: r.ready_s),
    ("kernels loaded", lambda r: r.loaded_s),
)


def node_table(rows: list[Row], repeats: int) -> list[str]:
    """Installed nodes: time to a matched input, to the first diagnostics, ready; stop."""
    lines = table_head(f"| node | until | {COLUMN[EMPTY]} (s) | {COLUMN[INSTALL]} (s) "
                       f"| warm (s): median of {repeats} (range) "
                       "| kernel-cache files written (cold empty / after install / warm) "
                       "| target |")
    for row in rows:
        for label, value in NODE_MEASURES:
            ready = label.startswith("ready")
            what = f"`{row.input}` matched" if label == "input matched" else label
            cells = [cold_cell(row.runs.get(EMPTY), value),
                     cold_cell(row.runs.get(INSTALL), value),
                     warm_cell(row.runs.get(WARM), value),
                     written_cell(row) if ready else "", ready_target(row) if ready else ""]
            lines.append("| " + " | ".join([row.command, what, *cells]) + " |")
        cells = [stop_cell(row.runs.get(v)) for v in (*COLD, WARM)]
        lines.append("| " + " | ".join([row.command, "SIGINT → exit", *cells, "", ""]) + " |")
    return lines


def target_lines(solves: list[Row], nodes: list[Row]) -> list[str]:
    """The targets, one line each, with the numbers behind them."""
    lines = []
    if solves and not solves[0].note:
        small = solves[0]
        warm = median([r.seconds for r in small.runs.get(WARM, [])])
        lines.append(f"- warm `h2o-solve` on {small.input} ≤ {TARGET_SOLVE_WARM_S:g} s: "
                     f"{verdict(warm, TARGET_SOLVE_WARM_S)} ({seconds(warm)} s)")
        after = small.runs.get(INSTALL)
        if after:
            run = after[0]
            lines.append(f"- the first solve after install compiles nothing: "
                         f"{first_solve_verdict(run)} ({run.written} kernel-cache files "
                         f"written, {seconds(run.seconds)} s)")
    for row in nodes:
        for variant in (WARM, *COLD):
            runs = row.runs.get(variant)
            if not runs:
                continue
            value = median([r.ready_s for r in runs])
            name = "warm" if variant == WARM else COLUMN[variant]
            got = f"{seconds(value)} s" if value is not None else runs[0].status
            lines.append(f"- installed {row.command} ready ≤ {TARGET_READY_S:g} s, {name}: "
                         f"{verdict(value, TARGET_READY_S)} ({got})")
    return lines


def failures(rows: list[Row]) -> list[str]:
    """Every run that did not finish (or stop) as it should, with its last output line;
    identical failures of one row and variant once, counted."""
    out = []
    for row in rows:
        for variant, runs in row.runs.items():
            seen: dict[str, int] = {}
            for r in runs:
                stop = getattr(r, "stop", "clean")
                if r.status != "ok" or stop not in ("clean", "—"):
                    what = r.status if r.status != "ok" else f"stop: {stop}"
                    line = (f"- {row.command} {row.input}, {variant}: {what}"
                            + (f" — `{r.detail}`" if r.detail else ""))
                    seen[line] = seen.get(line, 0) + 1
            out += [line + (f" ({n} of {len(runs)} runs)" if len(runs) > 1 else "")
                    for line, n in seen.items()]
    return out


NOTES = f"""\
Notes:

- Every process is the installed executable of a fresh `colcon build` (as
  `test/test_package_build.py`), run in the environment `source install/setup.bash` gives,
  with the loopback Fast DDS profile, `NUMBA_CACHE_DIR` unset and its own `XDG_CACHE_HOME`
  (the kernel cache is `$XDG_CACHE_HOME/h2o_slam/…`). Cold, empty cache: a fresh empty
  `XDG_CACHE_HOME` (that variant's build ran with `{SKIP_WARMUP}=1`: its cache is never
  used); cold, after install: a copy of the `XDG_CACHE_HOME` the colcon build ran with (what
  installing left in it). In both, the install tree is as the build left it. Warm: the same
  process again with the cache its empty-cache cold run left; the median.
- Wall time: from just before `Popen` to the exit. "solve in it": `wall_s` of
  `h2o-solve --report` (the exact solve alone), the GTSAM peer's own `optimize()` time.
- GTSAM peer: a script that reads the graph with `gtsam.readG2o`, holds its first pose
  with a prior (sigma {PRIOR_SIGMA:g}), runs `LevenbergMarquardtOptimizer` (max
  {LM_MAX_ITERATIONS} iterations, tolerances {LM_RELATIVE_TOL:g}) from the file's vertices (a
  graph without vertices: the edges composed from its first node), and exits. No kernel
  cache: its first run stands in the cold column.
- Nodes: started with the installed `config/*.yaml`, `-r __ns:=/startup…`, and
  `/diagnostics` and `/tf` remapped into that namespace. "input matched": this process's
  publisher on the node's `odom` counts a matched subscription; "first `/diagnostics`": the
  first message arrives here; ready = both. "kernels loaded": the first `/diagnostics`
  without `warming_up: true` (`h2o_node` says it while its kernels load beside the executor;
  `hybrid_vo_node` has no such value); the node runs until then (at most `--timeout`), so
  that the warm runs find in the cache every kernel it loads. Then SIGINT; clean = exit code
  0 within {STOP_S:g} s. Ready includes DDS discovery: the loopback profile has the
  participants announce every second (at Fast DDS's default of 3 s the tester matched a new
  node 3.6 s after its start in most runs, although its rclpy `Node` existed at ~1.0 s).
- Kernel-cache files written: files new in the run's `XDG_CACHE_HOME` (or new non-`.pyc` files
  in the install tree) after it ran; 0 = nothing was compiled.
- Targets: warm `h2o-solve` on the small graph ≤ {TARGET_SOLVE_WARM_S:g} s; an installed
  node ready ≤ {TARGET_READY_S:g} s warm and cold (answering while it warms up); the first
  solve after install compiles nothing. A run over `--timeout` is killed with its process
  group and reported as a timeout.
"""


def render_section(solves: list[Row], peers: list[Row], replays: list[Row], nodes: list[Row],
                   opts: Options, wall_s: float, notes: list[str],
                   load: tuple[float, float] | None = None) -> str:
    """The ``## Start-up`` section of RESULTS.md."""
    try:
        gtsam_version = metadata.version("gtsam")
    except metadata.PackageNotFoundError:
        gtsam_version = "not installed"
    try:
        numba_version = metadata.version("numba")
    except metadata.PackageNotFoundError:
        numba_version = "not installed"
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    bytecode = ("set (no `.pyc` is written: every process compiles the package's sources)"
                if os.environ.get("PYTHONDONTWRITEBYTECODE") else "not set")
    parts = [
        SECTION, "",
        f"Command (from the repo root): `{command(REPO)}`", "",
        f"Date: {when}. Machine: {platform.machine()}, nproc {os.cpu_count()}, Python "
        f"{platform.python_version()}, numba {numba_version}, gtsam {gtsam_version}, repo at "
        f"{revision(REPO)}. PYTHONDONTWRITEBYTECODE {bytecode}. Wall time {wall_s:.0f} s"
        + (f", 1-minute load average {load[0]:.1f} at the start and {load[1]:.1f} at the end"
           if load is not None else "") + ". Timings are indicative (shared machine).", "",
        f"Graphs: `{opts.small.stem}` (small) and `{opts.large.stem}` (large) of `--data`, the "
        "standard public pose graphs (as the SE-Sync project's `data/` folder distributes "
        "them, from Luca Carlone's and the g2o data sets; not in this repository). Bag: "
        f"`h2o-demo --laps {opts.demo_laps}`'s `input/` ({36 * opts.demo_laps} s of the "
        "simulated drive, stereo images at 10 Hz), written once, untimed, with the kernels the "
        "install compiled.", "",
        *process_table([*solves, *peers, *replays], opts.repeats),
    ]
    if nodes:
        parts += ["", *node_table(nodes, opts.repeats)]
    parts += ["", "Targets:", "", *target_lines(solves, nodes)]
    fails = failures([*solves, *peers, *replays, *nodes])
    if fails:
        parts += ["", "Runs that failed:", "", *fails]
    if notes:
        parts += ["", *notes]
    parts += ["", NOTES]
    return "\n".join(parts)


# --- driver ---------------------------------------------------------------------------------


def run(opts: Options, results: Path | None) -> int:
    """Benchmark; publish the section; return an exit code."""
    start = time.monotonic()
    load_start = os.getloadavg()[0]
    # rclpy in this process (the tester) uses the loopback profile as well.
    os.environ.update(dds_env(dict(os.environ)))
    for name in DISCOVERY_VARIABLES:
        os.environ.pop(name, None)
    with tempfile.TemporaryDirectory(prefix="h2o-startup-") as tmp:
        bench = Bench(Path(tmp), opts)
        try:
            print("startup.py: building", file=sys.stderr)
            try:
                bench.prepare()
            except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
                print(f"startup.py: {exc}", file=sys.stderr)
                return 1
            solves = [bench.solve(opts.small), bench.solve(opts.large)]
            peers = [bench.peer(opts.small), bench.peer(opts.large)]
            replays = [bench.replay()]
            nodes = [] if opts.skip_nodes else [bench.node(spec) for spec in NODES]
        finally:
            bench.close()
        notes = []
        if not opts.skip_cold:
            notes.append(f"The colcon build of the after-install variant left "
                         f"{bench.install_cache_files} kernel-cache files in its "
                         "`XDG_CACHE_HOME`.")
    section = render_section(solves, peers, replays, nodes, opts, time.monotonic() - start,
                             notes, (load_start, os.getloadavg()[0]))
    publish(section, results, SECTION)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments and run the benchmark."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_graph_arguments(parser)
    parser.add_argument("--no-write", dest="no_results", action="store_true",
                        help="print the section only (same as --no-results)")
    parser.add_argument("--small", default=DEFAULT_SMALL, metavar="NAME",
                        help=f"small graph, a file stem of --data (default {DEFAULT_SMALL})")
    parser.add_argument("--large", default=DEFAULT_LARGE, metavar="NAME",
                        help=f"large graph, a file stem of --data (default {DEFAULT_LARGE})")
    parser.add_argument("--repeats", type=int, default=DEFAULT_REPEATS, metavar="N",
                        help=f"warm runs per process (default {DEFAULT_REPEATS})")
    parser.add_argument("--skip-nodes", action="store_true", help="do not start the nodes")
    parser.add_argument("--skip-cold", action="store_true",
                        help="warm runs only (one build, one shared cache primed first)")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                        help=f"limit per process in seconds (default {DEFAULT_TIMEOUT_S:g}; "
                        "a cold compile takes over a minute on two cores)")
    parser.add_argument("--demo-laps", type=int, default=DEFAULT_DEMO_LAPS, metavar="N",
                        help=f"laps of the demo drive in the replayed bag (default "
                        f"{DEFAULT_DEMO_LAPS})")
    args = parser.parse_args(argv)
    if args.graphs:
        parser.error("--graphs: this benchmark times two graphs, --small NAME and --large NAME")
    if args.repeats < 1 or args.timeout <= 0 or args.demo_laps < 1:
        parser.error("--repeats and --demo-laps must be at least 1, --timeout positive")
    paths = select_graphs("startup.py", args.data, [args.small, args.large])
    if isinstance(paths, int):
        return paths
    opts = Options(paths[0], paths[1], args.repeats, args.skip_nodes, args.skip_cold,
                   args.timeout, args.demo_laps)
    return run(opts, results_path(args))


if __name__ == "__main__":
    sys.exit(main())
