"""The console entry points of the two nodes (``ros2 run h2o_slam h2o_node``).

A node's imports take a second or two (rclpy, numpy, scipy, numba); a Ctrl-C in that time
used to end it with a KeyboardInterrupt traceback from whichever import it hit. Importing
the node inside ``main`` makes a Ctrl-C at any instant of the start a quiet, normal stop.
"""

from __future__ import annotations

import importlib


def _run(module: str) -> int:
    try:
        return int(importlib.import_module(module).main())
    except KeyboardInterrupt:  # Ctrl-C before rclpy's handler is installed
        return 0


def h2o_node() -> int:
    """``h2o_node``: :func:`h2o_slam.ros.h2o_node.main`."""
    return _run("h2o_slam.ros.h2o_node")


def hybrid_vo_node() -> int:
    """``hybrid_vo_node``: :func:`hybrid_vo.vo_node.main`."""
    return _run("hybrid_vo.vo_node")
