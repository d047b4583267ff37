"""colcon builds the package as a robot would, and `ros2 run` finds its executables.

The `ros2` command itself is not on PyPI, so the lookup it performs is reproduced here:
``ament_index_python.packages.get_package_prefix(pkg)`` through ``AMENT_PREFIX_PATH``, then
the executable files under ``<prefix>/lib/<pkg>`` (ros2run's ``get_executable_path``). The
executable is then run in the environment that ``source install/setup.bash`` produces.

Everything colcon writes goes to a temporary directory; the source tree must stay untouched.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "h2o_slam"
EXECUTABLES = ["h2o-solve", "h2o-replay", "h2o-demo"]
NODES = ["h2o_node", "hybrid_vo_node"]
BUILD_TIMEOUT_S = 300
RUN_TIMEOUT_S = 60

pytestmark = pytest.mark.slow


def _git_status() -> set[str] | None:
    """Untracked and ignored entries of the source tree, or None outside a git checkout."""
    if not (REPO / ".git").exists() or shutil.which("git") is None:
        return None
    out = subprocess.run(
        ["git", "status", "--porcelain", "--ignored"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return set(out.splitlines())


def _run(
    cmd: list[str], *, cwd: Path, env: dict[str, str], timeout: float
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        cmd, cwd=cwd, env=env, timeout=timeout, capture_output=True, text=True, check=False
    )


class ColconBuild:
    """Paths and outcome of one ``colcon build`` into a temporary workspace."""

    def __init__(self, root: Path, status_before: set[str] | None) -> None:
        self.root = root
        self.install = root / "install"
        self.prefix = self.install / PACKAGE
        self.status_before = status_before
        self.status_after = _git_status()


@pytest.fixture(scope="module")
def colcon_build(tmp_path_factory: pytest.TempPathFactory) -> ColconBuild:
    root = tmp_path_factory.mktemp("colcon_ws")
    env = dict(os.environ)
    # No user-level colcon defaults (e.g. a global --symlink-install) leak into the build.
    env["COLCON_HOME"] = str(root / "colcon_home")
    status_before = _git_status()
    cmd = [
        sys.executable,
        "-m",
        "colcon",
        "--log-base",
        str(root / "log"),
        "build",
        "--base-paths",
        str(REPO),
        "--build-base",
        str(root / "build"),
        "--install-base",
        str(root / "install"),
        "--event-handlers",
        "desktop_notification-",
        "status-",
    ]
    proc = _run(cmd, cwd=root, env=env, timeout=BUILD_TIMEOUT_S)
    if proc.returncode != 0:
        pytest.fail(
            f"colcon build failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}",
            pytrace=False,
        )
    return ColconBuild(root, status_before)


@pytest.fixture(scope="module")
def sourced_env(colcon_build: ColconBuild) -> dict[str, str]:
    """The environment after ``source install/setup.bash``, as a user's shell has it."""
    if shutil.which("bash") is None:
        pytest.fail("bash is needed to source the colcon install space", pytrace=False)
    proc = subprocess.run(
        ["bash", "-c", 'source "$1/setup.bash" && env -0', "_", str(colcon_build.install)],
        capture_output=True,
        env=dict(os.environ),
        timeout=RUN_TIMEOUT_S,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr.decode(errors="replace")
    env = {}
    for entry in proc.stdout.split(b"\0"):
        if b"=" in entry:
            key, _, value = entry.decode(errors="surrogateescape").partition("=")
            env[key] = value
    return env


def _ros2_run_lookup(package: str, executable: str) -> Path:
    """Resolve an executable as ``ros2 run`` does (ros2run.api.get_executable_path)."""
    from ament_index_python.packages import get_package_prefix

    base = Path(get_package_prefix(package)) / "lib" / package
    matches = [
        Path(dirpath) / name
        for dirpath, _dirs, names in os.walk(base)
        for name in names
        if name == executable and os.access(Path(dirpath) / name, os.X_OK)
    ]
    assert len(matches) == 1, f"{executable} under {base}: {matches}"
    return matches[0]


def test_build_leaves_source_tree_untouched(colcon_build: ColconBuild) -> None:
    if colcon_build.status_before is None or colcon_build.status_after is None:
        pytest.skip("source tree is not a git checkout")
    new = colcon_build.status_after - colcon_build.status_before
    assert not new, f"colcon build wrote into the source tree: {sorted(new)}"


def test_install_space_layout(colcon_build: ColconBuild) -> None:
    prefix = colcon_build.prefix
    assert (prefix / "share/ament_index/resource_index/packages" / PACKAGE).is_file()
    assert (prefix / "share" / PACKAGE / "package.xml").is_file()
    for config in ("fastdds_localhost.xml", "h2o.yaml", "hybrid_vo.yaml"):
        assert (prefix / "share" / PACKAGE / "config" / config).is_file(), config
    # What `ros2 launch h2o_slam <file>` and `rviz2 -d` look for under share/h2o_slam.
    for installed in ("launch/h2o_slam.launch.xml", "launch/h2o_slam_replay.launch.xml",
                      "launch/h2o_slam.launch.py", "rviz/h2o_slam.rviz"):
        path = prefix / "share" / PACKAGE / installed
        assert path.is_file() and path.read_bytes() == (REPO / installed).read_bytes(), path
    for name in EXECUTABLES + NODES:
        exe = prefix / "lib" / PACKAGE / name
        assert exe.is_file() and os.access(exe, os.X_OK), exe


def test_sourced_install_space_imports_installed_copy(
    colcon_build: ColconBuild, sourced_env: dict[str, str]
) -> None:
    assert str(colcon_build.prefix) in sourced_env["AMENT_PREFIX_PATH"].split(os.pathsep)
    proc = _run(
        [
            sys.executable,
            "-c",
            "import h2o_slam, hybrid_vo, msg_adapters, ros_node_base; print(h2o_slam.__file__)",
        ],
        env=sourced_env,
        cwd=colcon_build.root,
        timeout=RUN_TIMEOUT_S,
    )
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()).is_relative_to(colcon_build.prefix), proc.stdout


def test_installed_copy_has_every_sub_package(
    colcon_build: ColconBuild, sourced_env: dict[str, str]
) -> None:
    """setup.py's ``find_packages`` installs every folder with an ``__init__.py``, a new
    sub-package too: each imports from the install space, not from the source tree."""
    packages = sorted(".".join(init.parent.relative_to(REPO).parts)
                      for top in ("h2o_slam", "hybrid_vo", "msg_adapters", "ros_node_base")
                      for init in (REPO / top).rglob("__init__.py"))
    code = ("import importlib, sys\n"
            "for name in sys.argv[1:]:\n"
            "    print(importlib.import_module(name).__file__)")
    proc = _run([sys.executable, "-c", code, *packages], env=sourced_env,
                cwd=colcon_build.root, timeout=RUN_TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr
    outside = [f for f in proc.stdout.split() if not Path(f).is_relative_to(colcon_build.prefix)]
    assert len(proc.stdout.split()) == len(packages) and not outside, proc.stdout


@pytest.mark.parametrize("executable", EXECUTABLES)
def test_ros2_run_finds_and_runs_executable(
    colcon_build: ColconBuild,
    sourced_env: dict[str, str],
    monkeypatch: pytest.MonkeyPatch,
    executable: str,
) -> None:
    monkeypatch.setenv("AMENT_PREFIX_PATH", sourced_env["AMENT_PREFIX_PATH"])
    exe = _ros2_run_lookup(PACKAGE, executable)
    assert exe == colcon_build.prefix / "lib" / PACKAGE / executable

    proc = _run(
        [str(exe), "--help"], env=sourced_env, cwd=colcon_build.root, timeout=RUN_TIMEOUT_S
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    assert proc.stdout.lstrip().startswith("usage:"), proc.stdout
    assert executable in proc.stdout


def test_installed_h2o_node_answers_over_loopback_dds(
    colcon_build: ColconBuild, sourced_env: dict[str, str], monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    """The installed h2o_node, resolved as ``ros2 run`` does and started with the installed
    config/h2o.yaml, takes odometry over DDS and answers on its topics and services."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Odometry
    from node_harness import Harness
    from std_srvs.srv import Trigger

    import msg_adapters as ma

    monkeypatch.setenv("AMENT_PREFIX_PATH", sourced_env["AMENT_PREFIX_PATH"])
    exe = _ros2_run_lookup(PACKAGE, "h2o_node")
    params = colcon_build.prefix / "share" / PACKAGE / "config" / "h2o.yaml"
    harness = Harness()
    map_file = tmp_path / "graph.g2o"
    env = dict(sourced_env)
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(REPO / "config" / "fastdds_localhost.xml")
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    proc = subprocess.Popen(
        [str(exe), "--ros-args", "--params-file", str(params), "-r",
         f"__ns:={harness.namespace}", "-p", f"map_file:={map_file}"],
        env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        poses = harness.subscribe(PoseStamped, "h2o_node/pose")
        harness.wait_for_subscribers(Odometry, "odom", timeout_s=RUN_TIMEOUT_S)
        t0 = 1_700_000_000 * 10**9
        for i in range(40):
            sample = ma.planar_odometry_sample(t0 + i * 10**8, "odom", "base_link", 0.1 * i,
                                               0.0, 0.0, ma.planar_covariance(0.01, 0.01, 0.01))
            harness.publish(Odometry, "odom", ma.fill_odometry(Odometry, sample))
            harness.spin_for(0.02)
        # Inputs that came while the kernels loaded are held, then handled in a burst: wait
        # for the pose of the last odometry sent.
        harness.spin_until(lambda: any(abs(p.pose.position.x - 3.9) < 1e-6 for p in poses),
                           RUN_TIMEOUT_S, "the last odometry's pose from h2o_node")
        assert len(poses) >= 30
        assert poses[-1].header.frame_id == "map"
        answer = harness.call(Trigger, "h2o_node/save_map", Trigger.Request())
        assert answer.success, answer.message
        assert map_file.is_file() and map_file.with_suffix(".json").is_file()
    finally:
        proc.terminate()
        try:
            output = proc.communicate(timeout=RUN_TIMEOUT_S)[0]
        finally:
            harness.close()
    assert proc.returncode in (0, -15), output
