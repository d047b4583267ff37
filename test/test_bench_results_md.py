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


def test_run_graphs_skips_a_graph_that_cannot_be_read_and_keeps_the_others(tmp_path):
    from h2o_slam.io.g2o import read_g2o

    good, bad = tmp_path / "a.g2o", tmp_path / "b.g2o"
    good.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
                    "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    bad.write_text("EDGE_SE2 0 1 not a number\n")
    out = tmp_path / "out"
    rows, skipped = results_md.run_graphs(
        "x.py", [good, bad], out, lambda path, folder: (path.stem, folder,
                                                          read_g2o(path).num_edges))
    assert rows == [("a", out, 1)]
    assert len(skipped) == 1 and skipped[0].startswith("b: ") and "b.g2o" in skipped[0]


def test_table_head_rules_every_column():
    assert results_md.table_head("| a | b | c |") == ["| a | b | c |", "| --- | --- | --- |"]
