"""``h2o-solve`` on real files it writes and reads."""

from __future__ import annotations

import json

import numpy as np
import pytest

from h2o_slam.cli.solve import main
from h2o_slam.g2o import read_g2o, write_g2o
from h2o_slam.graph import chi2
from h2o_slam.synthetic import grid3d, manhattan


@pytest.fixture(scope="module")
def planar_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("g") / "city.g2o"
    write_g2o(path, manhattan(120, seed=2).graph)
    return path


@pytest.mark.parametrize("mode", ["offline", "online", "exact"])
def test_solves_and_reports(planar_file, tmp_path, mode, capsys):
    out, report = tmp_path / "out.g2o", tmp_path / "report.json"
    code = main([str(planar_file), "--output", str(out), "--mode", mode,
                 "--passes", "3", "--report", str(report)])
    assert code == 0
    data = json.loads(report.read_text())
    assert json.loads(capsys.readouterr().out) == data
    for key in ("nodes", "edges", "chi2_initial", "chi2_final", "chi2_per_pass", "wall_s"):
        assert key in data
    graph = read_g2o(planar_file)
    solved = read_g2o(out)
    assert np.array_equal(solved.ids, graph.ids)
    assert solved.num_edges == graph.num_edges == data["edges"]
    # The written vertices are the solution, at round-trip precision.
    assert chi2(graph, solved.R, solved.t) == pytest.approx(data["chi2_final"], rel=1e-9)
    assert data["chi2_final"] < data["chi2_initial"]
    if mode == "online":
        assert set(data["per_callback_ms"]) == {"mean", "p99", "max"}
        assert data["per_callback_ms"]["max"] >= data["per_callback_ms"]["p99"] > 0
    else:
        assert data["per_callback_ms"] is None


def test_three_dimensional_exact_solve(tmp_path):
    src = tmp_path / "cube.g2o"
    write_g2o(src, grid3d(40, seed=4).graph)
    out = tmp_path / "cube_out.g2o"
    assert main([str(src), "-o", str(out), "--mode", "exact", "--init", "input"]) == 0
    graph = read_g2o(src)
    solved = read_g2o(out)
    assert chi2(graph, solved.R, solved.t) < 0.5 * chi2(graph)


def test_bad_file_gives_one_line_naming_file_and_line(tmp_path, capsys):
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 zero 1 0 0 1 0 1\n")
    code = main([str(bad), "--output", str(tmp_path / "o.g2o")])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1
    assert f"{bad}:3:" in err
    assert not (tmp_path / "o.g2o").exists()


def test_missing_file_is_one_line(tmp_path, capsys):
    code = main([str(tmp_path / "nope.g2o"), "--output", str(tmp_path / "o.g2o")])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1 and "nope.g2o" in err


def test_period_needs_an_online_budget(planar_file, tmp_path, capsys):
    out = tmp_path / "o.g2o"
    code = main([str(planar_file), "--output", str(out), "--mode", "online", "--period-ms", "5"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1 and "--period-ms" in err
    assert not out.exists()


def test_paced_online_run_reports_its_period_and_idle_steps(planar_file, tmp_path):
    out, report = tmp_path / "o.g2o", tmp_path / "r.json"
    assert main([str(planar_file), "--output", str(out), "--mode", "online", "--budget-ms", "1",
                 "--period-ms", "3", "--idle-s", "0", "--report", str(report)]) == 0
    data = json.loads(report.read_text())
    assert data["period_ms"] == 3.0
    assert data["idle_steps_between"] > 0
