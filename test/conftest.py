"""Keeps every test's DDS traffic on loopback, also when pytest is run without ``make``."""

import os
from pathlib import Path

PROFILE = Path(__file__).resolve().parents[1] / "config" / "fastdds_localhost.xml"

os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(PROFILE))
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
