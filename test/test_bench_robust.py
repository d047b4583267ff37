"""The pure pieces of bench/robust.py (no solver run): which rows meet issue 23's targets and
how the summary counts them."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

_BENCH = Path(__file__).resolve().parent.parent / "bench"
if str(_BENCH) not in sys.path:
    sys.path.insert(0, str(_BENCH))
robust = importlib.import_module("robust")


def _row(solver: str, status: str = "ok", **scores: float) -> object:
    fields = dict(ate_m=0.0, chi2_ratio=1.0, p99_ms=4.0, max_ms=9.0) | scores
    return robust.Row("g", "random", 10, solver, status, **fields)


def test_a_row_meets_the_target_on_its_map_and_a_node_row_on_its_callbacks_too():
    assert robust.target(_row("h2o", max_ms=50.0)) == "met"
    assert robust.target(_row("node")) == "met"
    assert robust.target(_row("node", max_ms=10.5)).startswith("missed: callbacks")
    assert robust.target(_row("h2o", ate_m=0.06)) == "missed: ATE 0.06 m"
    assert robust.target(_row("h2o", "timeout (300 s)")) == "missed (timeout (300 s))"
    assert robust.target(_row("gnc", ate_m=9.0)) == ""


def test_the_summary_leaves_out_rows_skipped_by_design():
    rows = [_row("h2o"), _row("node", "skipped: 3-D (the node is planar)"), _row("lm")]
    assert robust.target(rows[1]) == ""
    assert robust.target_summary(rows).endswith("met on 1 of 1 rows.")
