"""``ros2 launch h2o_slam h2o_slam.launch.py``: the same as ``h2o_slam.launch.xml`` (both
nodes, their parameter files, remappings; ``rviz:=true`` adds RViz), for those who launch
Python files. Arguments are passed through to the XML file, which holds the description.

The ``launch`` packages are imported only when the file is launched: they are part of a ROS
installation, not of the package's Python dependencies.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

#: The description this file includes, next to it in ``share/h2o_slam/launch``.
XML = Path(__file__).with_name("h2o_slam.launch.xml")


def generate_launch_description() -> Any:
    """The launch description: ``h2o_slam.launch.xml`` included, its arguments forwarded."""
    from launch import LaunchDescription
    from launch.actions import IncludeLaunchDescription
    from launch.launch_description_sources import AnyLaunchDescriptionSource

    return LaunchDescription([IncludeLaunchDescription(AnyLaunchDescriptionSource(str(XML)))])
