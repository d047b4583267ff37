"""The ``main`` every node executable shares: spin until Ctrl-C or SIGTERM; a node that
cannot start (bad parameter, unreadable map) ends with one line and exit code 1."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import TypeAlias

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

_Hook: TypeAlias = "Callable[[sys.UnraisableHookArgs], object]"  # the class is typeshed's only


def _quiet_half_built_logger(then: _Hook) -> _Hook:
    """A Ctrl-C inside ``RcutilsLogger.__init__`` leaves a logger without the attribute its
    ``__del__`` reads (rclpy 7.1); Python then prints "Exception ignored ... AttributeError"
    with a traceback at what is a normal stop. Only that one message is silenced; every
    other goes on to the hook that was installed before (``then``)."""

    def hook(unraisable: sys.UnraisableHookArgs) -> object:
        where = getattr(unraisable.object, "__qualname__", "")
        if not (where == "RcutilsLogger.__del__" and unraisable.exc_type is AttributeError):
            then(unraisable)
        return None

    hook.quiets_half_built_logger = True  # type: ignore[attr-defined]
    return hook


def run_node(make: Callable[[], Node], name: str,
             start_errors: tuple[type[BaseException], ...],
             args: list[str] | None = None) -> int:
    """Initialize rclpy, build the node with ``make`` and spin it; returns the exit code."""
    if not getattr(sys.unraisablehook, "quiets_half_built_logger", False):
        sys.unraisablehook = _quiet_half_built_logger(sys.unraisablehook)
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
