"""The ``main`` every node executable shares: spin until Ctrl-C or SIGTERM; a node that
cannot start (bad parameter, unreadable map) ends with one line and exit code 1."""

from __future__ import annotations

import sys
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


def run_node(make: Callable[[], Node], name: str,
             start_errors: tuple[type[BaseException], ...],
             args: list[str] | None = None) -> int:
    """Initialize rclpy, build the node with ``make`` and spin it; returns the exit code."""
    rclpy.init(args=args)
    try:
        try:
            node = make()
        except start_errors as exc:
            print(f"{name}: {exc}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:  # Ctrl-C while starting: a normal stop, no traceback
            return 0
        except Exception:
            # Ctrl-C or SIGTERM after rclpy.init shuts the context down under the node being
            # built, which then fails with "the given context is not valid": a normal stop.
            if rclpy.ok():
                raise
            return 0
        try:
            rclpy.spin(node)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass  # Ctrl-C or SIGTERM: a normal stop
        except Exception:
            # SIGTERM shuts the context down from the signal handler; a callback publishing
            # at that moment fails with "context is invalid". Only that is a normal stop.
            if rclpy.ok():
                raise
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return 0
