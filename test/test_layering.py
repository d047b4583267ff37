"""Layering (DESIGN §1): the cores run as plain libraries, without rclpy.

ruff's banned-api rule (pyproject.toml) stops a core module from importing rclpy itself;
this test also catches the indirect case, a core module that imports something that
imports rclpy. Node modules (``*node*.py``) and bag replay (``h2o_slam/replay*.py``) are
the shells allowed to use it.
"""

from __future__ import annotations

import subprocess
import sys
from fnmatch import fnmatch
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CORE_PACKAGES = {"h2o_slam": ["*node*.py", "replay*.py"], "hybrid_vo": ["*node*.py"]}

# Imports each module named on the command line in turn and prints the first one after
# whose import rclpy is loaded, or nothing.
_PROBE = """
import importlib, sys
for name in sys.argv[1:]:
    importlib.import_module(name)
    if "rclpy" in sys.modules:
        print(name)
        break
"""


def _core_modules() -> list[str]:
    names = []
    for package, allowed in CORE_PACKAGES.items():
        for path in sorted((REPO / package).rglob("*.py")):
            if any(fnmatch(path.name, pattern) for pattern in allowed):
                continue
            parts = path.relative_to(REPO).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            names.append(".".join(parts))
    return names


def test_core_modules_are_found() -> None:
    modules = _core_modules()
    assert "h2o_slam" in modules
    assert "hybrid_vo" in modules


def test_core_modules_do_not_load_rclpy() -> None:
    modules = _core_modules()
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE, *modules],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, f"importing the core modules failed:\n{proc.stderr}"
    culprit = proc.stdout.strip()
    assert not culprit, f"importing {culprit} loads rclpy; cores must not depend on it"
