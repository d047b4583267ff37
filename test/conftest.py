"""Keeps every test's DDS traffic on loopback, also when pytest is run without ``make``, and
gives node tests their rclpy context."""

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

PROFILE = Path(__file__).resolve().parents[1] / "config" / "fastdds_localhost.xml"

os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(PROFILE))
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


@pytest.fixture(scope="module")
def context() -> Iterator[object]:
    """An rclpy context of its own for a test module's nodes, shut down after it."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


@pytest.fixture()
def harness() -> Iterator[object]:
    """An in-process executor with its own context (``node_harness.Harness``), closed after
    the test."""
    from node_harness import Harness  # rclpy on use: most tests never start a node

    h = Harness()
    yield h
    h.close()
