"""Build script of the h2o_slam ament_python package (colcon and pip both use it)."""

import os
import subprocess
import sys
from glob import glob

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py


class BuildAndWarm(build_py):
    """``build_py``, then the solver's compiled kernels loaded or compiled into the user's
    cache (``python -m h2o_slam.core.warmup`` on the built package): a node of a fresh
    ``colcon build`` then starts without compiling. The cache is keyed by the kernel
    sources, not the install path, so this takes a second when they did not change.
    ``H2O_SLAM_SKIP_WARMUP=1`` skips it; a failure only warns (the node compiles on first
    start instead)."""

    def run(self):
        super().run()
        if os.environ.get("H2O_SLAM_SKIP_WARMUP") or self.dry_run:
            return
        built = os.path.abspath(self.build_lib)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            p for p in (built, os.environ.get("PYTHONPATH")) if p))
        # From the built copy (``-m`` puts the working folder first on the path): the
        # source tree stays untouched.
        done = subprocess.run([sys.executable, "-m", "h2o_slam.core.warmup"], env=env,
                              cwd=built, check=False)
        if done.returncode:
            print("warning: the h2o_slam kernels were not compiled at build time; the "
                  "first node start will compile them", file=sys.stderr)


PACKAGE_NAME = "h2o_slam"

setup(
    name=PACKAGE_NAME,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "bench", "bench.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE_NAME]),
        ("share/" + PACKAGE_NAME, ["package.xml"]),
        ("share/" + PACKAGE_NAME + "/config", sorted(glob("config/*"))),
        # ros2 launch h2o_slam h2o_slam.launch.xml (or .launch.py), and RViz's view of it.
        ("share/" + PACKAGE_NAME + "/launch", sorted(glob("launch/*.launch.*"))),
        ("share/" + PACKAGE_NAME + "/rviz", sorted(glob("rviz/*.rviz"))),
    ],
    cmdclass={"build_py": BuildAndWarm},
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="h2o_slam maintainers",
    maintainer_email="h2o-slam@example.com",
    description=(
        "Flexible-cost pose-graph SLAM: hybrid wheel/visual odometry, the H2O "
        "hybrid-Hessian solver, and LAGO."
    ),
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "h2o-solve = h2o_slam.app.cli.solve:main",
            "h2o_node = h2o_slam.app.cli.nodes:h2o_node",
            "hybrid_vo_node = h2o_slam.app.cli.nodes:hybrid_vo_node",
            "h2o-replay = h2o_slam.app.cli.replay:main",
            "h2o-demo = h2o_slam.app.cli.demo:main",
        ],
    },
)
