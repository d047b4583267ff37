"""The benchmarks' RESULTS.md section writer, on real files."""

from __future__ import annotations

import importlib.util
from pathlib import Path

_PATH = Path(__file__).resolve().parent.parent / "bench" / "results_md.py"
_spec = importlib.util.spec_from_file_location("results_md", _PATH)
assert _spec is not None and _spec.loader is not None
results_md = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(results_md)


def test_replaces_only_its_own_section(tmp_path):
    path = tmp_path / "RESULTS.md"
    path.write_text("# Benchmark results\n\n## A\n\nold a\n\n## B\n\nkeep b\n")
    results_md.replace_section(path, "## A", "## A\n\nnew a\n")
    assert path.read_text() == "# Benchmark results\n\n## A\n\nnew a\n\n## B\n\nkeep b\n"
    results_md.replace_section(path, "## B", "## B\n\nnew b\n")
    assert path.read_text() == "# Benchmark results\n\n## A\n\nnew a\n\n## B\n\nnew b\n"


def test_appends_a_missing_section_and_creates_the_file(tmp_path):
    path = tmp_path / "RESULTS.md"
    results_md.replace_section(path, "## A", "## A\n\nfirst\n")
    assert path.read_text() == "# Benchmark results\n\n## A\n\nfirst\n"
    results_md.replace_section(path, "## C", "## C\n\nthird\n")
    assert path.read_text().endswith("## A\n\nfirst\n\n## C\n\nthird\n")
