"""Layering (doc/design.md, Layering): four packages that depend one way, and inside
h2o_slam the layers core < io < ros < app, with the baselines beside io on the core; imports
only run downward.

Between the packages:

* ``h2o_slam.core`` — the base every package may use (geometry, errors): no rclpy, no
  files, no plotting, nothing of the other packages.
* ``msg_adapters`` — message layouts, on ``h2o_slam.core`` alone.
* ``ros_node_base`` — the shell both nodes share (parameters from a configuration tree, the
  boundary, input counts, outputs, ``main``), on rclpy, ``msg_adapters`` and
  ``h2o_slam.core`` alone.
* ``hybrid_vo`` — the odometer, on ``h2o_slam.core`` and ``msg_adapters``; its node
  (``hybrid_vo.vo_node``) also on ``ros_node_base``. Nothing else of h2o_slam.
* ``h2o_slam.app`` — replay and the commands: the only place that joins the two nodes'
  packages (the only part of h2o_slam that may import ``hybrid_vo``).

Inside h2o_slam:

* ``h2o_slam.baselines`` — what the benchmarks compare against (TORO, covariance variants,
  other tools' χ²), over the core alone; only ``app`` (``h2o-solve``) imports it.
* ``h2o_slam.io`` — files and bags, over the core (rclpy only inside the bag writer).
* ``h2o_slam.ros`` — the node and its rclpy-free mapper and configuration tree, over io, core
  and ``ros_node_base``.

The simulator (``hybrid_vo.sim``) is a tool of the tests, the benchmarks and ``app``: no
other part of the packages imports it. Two checks: every import statement in the source
(also those inside functions), and what importing each module actually loads (which catches
indirect imports). ruff's banned-api rule (pyproject.toml) stops rclpy in a core file at
lint time. Within the core, no two modules import each other, directly or through others
(an import circle).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: The layers of h2o_slam, and those each may import (its own included).
MAY_IMPORT = {
    "core": ("core",),
    "baselines": ("core", "baselines"),
    "io": ("core", "io"),
    "ros": ("core", "io", "ros"),
    "app": ("core", "baselines", "io", "ros", "app"),
}
LAYERS = tuple(MAY_IMPORT)
#: Outside packages each part may import (beyond the standard library and numerical stack).
FORBIDDEN_EXTERNAL = {
    "core": ("rclpy", "rosbags", "matplotlib", "yaml", "msg_adapters", "hybrid_vo",
             "ros_node_base"),
    "baselines": ("rclpy", "rosbags", "matplotlib", "yaml", "msg_adapters", "hybrid_vo",
                  "ros_node_base"),
    "io": ("msg_adapters", "hybrid_vo", "ros_node_base"),
    "ros": ("hybrid_vo",),
    "app": (),
}
#: The simulator: only itself and h2o_slam's applications may import it.
SIMULATOR = "hybrid_vo.sim"
#: The packages of the repository.
PACKAGES = ("h2o_slam", "msg_adapters", "ros_node_base", "hybrid_vo")
#: What each package beside h2o_slam may import of the repository's packages (itself too).
SIBLING_ALLOWED = {
    "msg_adapters": ("msg_adapters", "h2o_slam.core"),
    "ros_node_base": ("ros_node_base", "msg_adapters", "h2o_slam.core"),
    "hybrid_vo": ("hybrid_vo", "msg_adapters", "ros_node_base", "h2o_slam.core"),
}
#: The one module of hybrid_vo that may use the node base: its node (the cores do not).
VO_NODE = "hybrid_vo.vo_node"


def _modules(package: str) -> list[tuple[str, Path]]:
    found = []
    for path in sorted((REPO / package).rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found.append((".".join(parts), path))
    return found


def _imports(source: str, module: str) -> list[str]:
    """Every module an import statement in ``source`` names (relative ones resolved)."""
    names = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = module.split(".")[: -node.level]
                base = ".".join(parent + ([base] if base else []))
            names += [base] + [f"{base}.{alias.name}" for alias in node.names]
    return names


def _within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "h2o_slam" and parts[1] in LAYERS else None


def violations(module: str, source: str) -> list[str]:
    """The imports of ``module`` (with ``source``) that run against the layering."""
    found = []
    top = module.split(".")[0]
    own = _layer(module)
    for name in _imports(source, module):
        root = name.split(".")[0]
        target = _layer(name)
        if own is not None:
            if target is not None and target not in MAY_IMPORT[own]:
                found.append(f"{module} ({own}) imports {name} ({target})")
            if root in FORBIDDEN_EXTERNAL[own]:
                found.append(f"{module} ({own}) imports {name}")
        elif top in SIBLING_ALLOWED and root in PACKAGES:
            if not any(_within(name, allowed) for allowed in SIBLING_ALLOWED[top]):
                found.append(f"{module} ({top}) imports {name}")
            elif root == "ros_node_base" and top == "hybrid_vo" and module != VO_NODE:
                found.append(f"{module} (the odometer's core) imports the node base ({name})")
        if _within(name, SIMULATOR) and not (_within(module, SIMULATOR) or own == "app"):
            found.append(f"{module} imports the simulator ({name})")
    return found


def test_every_h2o_slam_module_is_in_a_layer() -> None:
    loose = [m for m, _ in _modules("h2o_slam") if m != "h2o_slam" and _layer(m) is None]
    assert not loose, f"modules outside {'/'.join(LAYERS)}: {loose}"
    assert {_layer(m) for m, _ in _modules("h2o_slam")} >= set(LAYERS)


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_run_downward(package: str) -> None:
    found = [v for module, path in _modules(package)
             for v in violations(module, path.read_text(encoding="utf-8"))]
    assert not found, "\n".join(found)


@pytest.mark.parametrize(
    ("module", "source"),
    [
        ("h2o_slam.core.solver", "from h2o_slam.io.g2o import read_g2o"),
        ("h2o_slam.core.solver", "def f():\n    import rclpy"),
        ("h2o_slam.core.tree", "from h2o_slam import ros"),
        ("h2o_slam.core.graph", "from h2o_slam.baselines.chi2_metrics import all_chi2"),
        ("h2o_slam.core.modes", "def f():\n    from ..baselines import toro"),
        ("h2o_slam.baselines.toro", "from h2o_slam.io.g2o import read_g2o"),
        ("h2o_slam.io.g2o", "from h2o_slam.baselines import toro"),
        ("h2o_slam.io.g2o", "from ..ros import mapper"),
        ("h2o_slam.ros.mapper", "from hybrid_vo.sim import world"),
        ("msg_adapters.gps", "from h2o_slam.io.map_store import load_map"),
        ("hybrid_vo.frontend", "from h2o_slam.app.replay import replay"),
        ("hybrid_vo.odometer", "from hybrid_vo.sim.world import make_drive"),
        ("hybrid_vo.vo_node", "def f():\n    from .sim import messages"),
        ("msg_adapters.gps", "from hybrid_vo import sim"),
        # The packages depend one way: hybrid_vo and msg_adapters on h2o_slam.core alone,
        # the node base on neither node's package, the cores on no node base.
        ("hybrid_vo.vo_node", "from h2o_slam.ros.boundary import behind_boundary"),
        ("hybrid_vo.vo_node", "import h2o_slam.io.bags"),
        ("hybrid_vo.frontend", "from h2o_slam import ros"),
        ("hybrid_vo.frontend", "from ros_node_base.params import param_specs"),
        ("msg_adapters.gps", "from ros_node_base.node import NodeBase"),
        ("ros_node_base.node", "from h2o_slam.ros.mapper import Mapper"),
        ("ros_node_base.node", "from hybrid_vo.errors import HybridVOError"),
        ("ros_node_base.params", "def f():\n    import h2o_slam.app.replay"),
        ("h2o_slam.core.errors", "from ros_node_base.params import ParamSpec"),
        ("h2o_slam.io.g2o", "import ros_node_base"),
        ("h2o_slam.ros.h2o_node", "from hybrid_vo.node_config import VoNodeConfig"),
    ],
)
def test_an_upward_import_is_reported(module: str, source: str) -> None:
    assert violations(module, source), f"{source!r} in {module} passed"


def test_a_downward_import_passes() -> None:
    source = "from h2o_slam.core import geometry\nfrom ..io.g2o import read_g2o\nimport hybrid_vo"
    assert violations("h2o_slam.app.replay", source) == []
    assert violations("h2o_slam.app.cli.solve", "from h2o_slam.baselines import toro") == []
    assert violations("h2o_slam.baselines.toro", "from ..core.modes import tree_estimate") == []
    assert violations("h2o_slam.app.cli.demo", "from hybrid_vo.sim import world") == []
    assert violations("hybrid_vo.sim.messages", "from hybrid_vo.sim.world import Drive") == []
    assert violations("hybrid_vo.vo_node", "from ros_node_base.node import NodeBase\n"
                      "from h2o_slam.core.errors import InputError\nimport msg_adapters") == []
    assert violations("ros_node_base.node", "import msg_adapters as ma\n"
                      "from h2o_slam.core.errors import H2OError") == []
    assert violations("h2o_slam.ros.h2o_node", "from ros_node_base.node import NodeBase") == []


def import_circles(sources: dict[str, str]) -> list[list[str]]:
    """The import circles among the modules of ``sources`` (module name → source): each the
    sorted modules that reach one another through import statements (also those inside
    functions: a call that runs one still needs the other's module loaded)."""
    graph = {m: {n for n in _imports(src, m) if n in sources and n != m}
             for m, src in sources.items()}
    reach = {}
    for start in graph:
        seen: set[str] = set()
        todo = list(graph[start])
        while todo:
            name = todo.pop()
            if name not in seen:
                seen.add(name)
                todo += graph[name]
        reach[start] = seen
    circles = {tuple(sorted(n for n in reach[m] if m in reach[n])) for m in graph if m in reach[m]}
    return sorted(list(circle) for circle in circles)


def _core_sources() -> dict[str, str]:
    return {m: path.read_text(encoding="utf-8") for m, path in _modules("h2o_slam/core")}


def test_the_core_imports_without_a_circle() -> None:
    assert import_circles(_core_sources()) == []


@pytest.mark.parametrize(
    ("module", "planted", "other"),
    [
        # compiled.py's warm-up once imported the solver modules that import it.
        ("h2o_slam.core.compiled", "def warm():\n    from h2o_slam.core.solver import H2OSolver",
         "h2o_slam.core.solver"),
        ("h2o_slam.core.geometry", "from .online import OnlineH2O", "h2o_slam.core.online"),
    ],
)
def test_a_planted_import_circle_is_found(module: str, planted: str, other: str) -> None:
    sources = _core_sources()
    sources[module] += "\n\n" + planted + "\n"
    circles = import_circles(sources)
    assert any(module in circle and other in circle for circle in circles), circles


# Imports each module named on the command line in a fresh interpreter, in turn, and prints
# ``module loaded-name`` for the first forbidden name found in sys.modules afterwards.
_PROBE = """
import importlib, sys
forbidden = sys.argv[1].split(",")
for name in sys.argv[2:]:
    importlib.import_module(name)
    hit = [m for m in forbidden if m in sys.modules]
    if hit:
        print(name, hit[0])
        break
"""


def _loads_nothing_of(modules: list[str], forbidden: list[str]) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE, ",".join(forbidden), *modules],
        cwd=REPO, capture_output=True, text=True, timeout=180, check=False,
    )
    assert proc.returncode == 0, f"importing the modules failed:\n{proc.stderr}"
    assert not proc.stdout.strip(), f"importing {proc.stdout.strip()} (loaded)"


@pytest.mark.parametrize("layer", ["core", "baselines"])
def test_the_core_and_the_baselines_load_no_rclpy_files_or_plotting(layer: str) -> None:
    modules = [m for m, _ in _modules("h2o_slam") if _layer(m) == layer]
    above = [f"h2o_slam.{other}" for other in LAYERS if other not in MAY_IMPORT[layer]]
    _loads_nothing_of(modules, ["rclpy", "rosbags", "matplotlib", *above, "msg_adapters",
                                "hybrid_vo"])


def test_io_and_the_rclpy_free_cores_load_no_rclpy() -> None:
    io = [m for m, _ in _modules("h2o_slam") if _layer(m) == "io"]
    vo_core = [m for m, _ in _modules("hybrid_vo") if m != VO_NODE]
    trees = ["h2o_slam.ros.mapper", "h2o_slam.ros.node_config", "ros_node_base.params",
             "ros_node_base.documents"]
    _loads_nothing_of(io + vo_core + trees, ["rclpy", "h2o_slam.app", "ros_node_base.node"])


def test_the_packages_beside_h2o_slam_load_nothing_of_it_but_the_core() -> None:
    """Also through indirect imports: hybrid_vo, msg_adapters and the node base stand on
    h2o_slam.core alone, so that only h2o_slam.app joins the two nodes' packages."""
    modules = [m for package in SIBLING_ALLOWED for m, _ in _modules(package)]
    _loads_nothing_of(modules, [f"h2o_slam.{layer}" for layer in LAYERS if layer != "core"])


def test_only_the_simulator_loads_the_simulator() -> None:
    modules = [m for package in ("hybrid_vo", "msg_adapters") for m, _ in _modules(package)
               if not _within(m, SIMULATOR)]
    _loads_nothing_of(modules, [SIMULATOR])
