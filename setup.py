"""Build script of the h2o_slam ament_python package (colcon and pip both use it)."""

from glob import glob

from setuptools import find_packages, setup

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
            "h2o_node = h2o_slam.ros.h2o_node:main",
            "hybrid_vo_node = hybrid_vo.vo_node:main",
            "h2o-replay = h2o_slam.app.cli.replay:main",
            "h2o-demo = h2o_slam.app.cli.demo:main",
        ],
    },
)
