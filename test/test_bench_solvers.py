"""bench/solvers.py: graph selection (public stems and generated names), the χ² ratios to the
best of every run, the starts-and-targets table, and one whole run on a tiny generated graph
(every solver, through ``h2o-solve`` and GTSAM) when gtsam is installed."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

from h2o_slam.io import synthetic

_BENCH = Path(__file__).resolve().parent.parent / "bench"
if str(_BENCH) not in sys.path:
    sys.path.insert(0, str(_BENCH))
solvers = importlib.import_module("solvers")


def _h2o(chi2: float, wall_s: float, init: str = "tree", robust: bool = True,
         status: str = "ok") -> object:
    return solvers.H2ORun("exact", status, init, robust, chi2=chi2, wall_s=wall_s)


def _lm(chi2: float, optimize_s: float, init: str = "input", init_s: float = 0.0) -> object:
    return solvers.LMRun("ok", chi2=chi2, optimize_s=optimize_s, init=init, init_s=init_s)


def _result(planar: bool = False, **runs: object) -> object:
    g = "lago" if planar else "chordal"
    base = dict(exact=_h2o(10.0, 2.0), offline=solvers.H2ORun("offline", "timeout"),
                lm=_lm(30.0, 0.5), exact_global=_h2o(10.005, 1.0, g),
                exact_global_ls=_h2o(10.0, 0.4, g, robust=False),
                lm_global=_lm(10.002, 0.3, g, 0.2))
    return solvers.GraphResult("g", 5, 7, planar, 99.0, **(base | runs))


def test_generated_graphs_are_spheres_and_grids_at_every_noise_level():
    names = list(solvers.GENERATED)
    assert names == [f"{kind}_sigma{s:g}" for kind in ("sphere", "grid3d")
                     for s in synthetic.LARGE_NOISE_SIGMAS_RAD]
    assert "sphere_sigma0.3" in names and "grid3d_sigma0.05" in names


def test_graphs_by_name_need_no_data_when_all_are_generated(tmp_path: Path):
    paths = solvers.choose_graphs(None, ["sphere_sigma0.1", "grid3d_sigma0.2"])
    assert paths == [solvers.GENERATED_DIR / "sphere_sigma0.1.g2o",
                     solvers.GENERATED_DIR / "grid3d_sigma0.2.g2o"]
    (tmp_path / "intel.g2o").write_text("")
    mixed = solvers.choose_graphs(tmp_path, ["sphere_sigma0.3", "intel"])
    assert mixed == [tmp_path / "intel.g2o", solvers.GENERATED_DIR / "sphere_sigma0.3.g2o"]
    every = solvers.choose_graphs(tmp_path, None)
    assert isinstance(every, list) and every[0] == tmp_path / "intel.g2o"
    assert len(every) == 1 + len(solvers.GENERATED)


def test_graph_selection_errors(tmp_path: Path, capsys: pytest.CaptureFixture):
    assert solvers.choose_graphs(None, None) == 2  # public graphs asked for, no folder
    assert "no pose graphs given" in capsys.readouterr().err
    assert solvers.choose_graphs(None, ["intel", "sphere_sigma0.1"]) == 2
    assert solvers.choose_graphs(tmp_path, ["nosuch"]) == 2
    assert "no such graph" in capsys.readouterr().err


def test_ratios_are_to_the_best_of_every_run():
    r = _result()
    assert r.optimum == 10.0
    # The best χ² may come from any run, GTSAM's initialization + LM included.
    assert _result(lm_global=_lm(9.0, 0.3, "chordal", 0.2)).optimum == 9.0
    failed = _h2o(1.0, 1.0, "chordal", status="failed: boom")
    assert _result(exact_global=failed).optimum == 10.0  # a failed run does not count
    assert solvers.meets_chi2(r.exact_global, r.optimum)  # 1.0005 ≤ 1.001
    assert not solvers.meets_chi2(_h2o(10.02, 1.0), 10.0)
    assert not solvers.meets_chi2(failed, 10.0)


def test_times_compare_with_gtsam_initialization_plus_lm():
    r = _result()
    assert r.lm_global.time_s == pytest.approx(0.5)  # initialization + optimize()
    assert not solvers.meets_time(r.exact_global, r.lm_global)  # 1.0 s > 0.5 s
    assert solvers.meets_time(r.exact_global_ls, r.lm_global)  # 0.4 s
    assert not solvers.meets_time(r.exact, solvers.LMRun("timeout"))


def test_best_start_is_the_lower_chi2_and_on_a_tie_the_faster():
    assert solvers.best_start(_result()) == "tree"  # 10.0 < 10.005
    tie = _result(exact_global=_h2o(10.0, 1.0, "chordal"))
    assert solvers.best_start(tie) == "chordal"  # same χ², 1 s < 2 s
    assert solvers.best_start(_result(True, exact=_h2o(11.0, 0.1))) == "lago"
    assert solvers.global_init(True) == "lago" and solvers.global_init(False) == "chordal"


def test_tables_have_every_run_and_the_targets():
    rows = [_result(), _result(True)]
    text = solvers.format_tables(rows)
    main = text.splitlines()[0]
    for column in ("| exact χ²/opt |", "| offline χ²/opt |", "| LM χ²/opt |",
                   "| exact --init G χ²/opt |", "| GTSAM G + LM χ²/opt |",
                   "| GTSAM G + LM s |", "| exact --init G / GTSAM G + LM time |"):
        assert column in main
    lines = text.splitlines()
    # Every table row has as many cells as its header.
    for block in text.split("\n\n"):
        table = [line for line in block.splitlines() if line.startswith("|")]
        if table:
            assert {line.count("|") for line in table} == {table[0].count("|")}
    assert any("| g | SE(3) | chordal | 1.000000 | 1.000500 | tree |" in line for line in lines)
    assert "SE(2) (1 graphs, G = lago): exact from tree: χ² target 1/1" in text
    assert "exact from chordal --robust off: χ² target 1/1, time target 1/1, both 1/1." in text
    assert "timeout" in text  # the offline run's status stands in its cells


def test_failures_are_listed_by_solver():
    text = solvers.format_tables([_result(exact_global_ls=_h2o(
        1.0, 1.0, "chordal", robust=False, status="failed (exit 1): bad"))])
    assert "- g, H₂O exact --init chordal --robust off: failed (exit 1): bad" in text


def test_a_tiny_generated_graph_through_every_solver(tmp_path: Path, monkeypatch):
    pytest.importorskip("gtsam")
    monkeypatch.setitem(solvers.GENERATED, "sphere_tiny",
                        lambda: synthetic.sphere(4, 6, 0, sigma_rot_rad=0.1))
    result = solvers.bench_graph(solvers.GENERATED_DIR / "sphere_tiny.g2o", tmp_path, 120.0)
    assert (tmp_path / "sphere_tiny.g2o").is_file() and result.generated
    assert [run.status for run in result.runs] == ["ok"] * 6
    assert result.exact_global.init == "chordal" and result.lm_global.init == "chordal"
    assert not result.exact_global_ls.robust
    assert result.lm_global.init_s > 0.0
    for run in (result.exact, result.exact_global, result.exact_global_ls, result.lm_global):
        assert run.chi2 <= 1.001 * result.optimum
    section = solvers.render_section([result], [])
    assert section.startswith(solvers.SECTION) and "| sphere_tiny | 24 |" in section


def test_repeated_runs_are_timed_by_the_median():
    times = iter([3.0, 1.0, 2.0])
    run = solvers.repeated(lambda: _h2o(5.0, next(times)), 3)
    assert run.times_s == [3.0, 1.0, 2.0] and run.time_s == 2.0 and run.wall_s == 3.0
    lm_times = iter([(0.1, 0.5), (0.2, 0.2)])

    def lm() -> object:
        init_s, optimize_s = next(lm_times)
        return _lm(5.0, optimize_s, "chordal", init_s)

    assert solvers.repeated(lm, 2).time_s == pytest.approx(0.5)  # median of 0.6 and 0.4
    once = solvers.repeated(lambda: _h2o(5.0, 7.0), 1)
    assert once.times_s == [] and once.time_s == 7.0
    calls = []
    failed = solvers.repeated(lambda: calls.append(1) or _h2o(1.0, 1.0, status="timeout"), 3)
    assert failed.status == "timeout" and len(calls) == 1  # not repeated
    assert "| 3, 1, 2 |" in solvers.format_tables([_result(exact_global_ls=run)])
    # Each graph's row shows its own repeats, not the last graph's.
    other = solvers.repeated(lambda: _h2o(5.0, 9.0), 2)
    text = solvers.format_tables([_result(exact_global_ls=run), _result(exact_global_ls=other)])
    assert "| 3, 1, 2 |" in text and "| 9, 9 |" in text
