"""``h2o-solve`` on real files it writes and reads."""

from __future__ import annotations

import io
import json
import time

import numpy as np
import pytest

from h2o_slam.app.cli.common import ProgressLine
from h2o_slam.app.cli.solve import main
from h2o_slam.baselines.chi2_metrics import METRICS, all_chi2
from h2o_slam.core.graph import chi2, edge_errors
from h2o_slam.io.g2o import read_g2o, write_g2o
from h2o_slam.io.synthetic import add_gps, grid3d, manhattan


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
    for key in ("nodes", "edges", "chi2_initial", "chi2_final", "chi2_per_pass", "wall_s",
                "load_s"):
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
    assert code == 2 and len(err.splitlines()) == 1 and "--period-ms" in err
    assert not out.exists()


def test_paced_online_run_reports_its_period_and_idle_steps(planar_file, tmp_path):
    out, report = tmp_path / "o.g2o", tmp_path / "r.json"
    assert main([str(planar_file), "--output", str(out), "--mode", "online", "--budget-ms", "1",
                 "--period-ms", "3", "--idle-s", "0", "--report", str(report)]) == 0
    data = json.loads(report.read_text())
    assert data["period_ms"] == 3.0
    assert data["idle_steps_between"] > 0
    assert 0 < data["updates"]


def test_unbudgeted_online_run_counts_an_update_for_every_new_edge(planar_file, tmp_path):
    out, report = tmp_path / "o.g2o", tmp_path / "r.json"
    assert main([str(planar_file), "--output", str(out), "--mode", "online", "--idle-s", "0",
                 "--report", str(report)]) == 0
    data = json.loads(report.read_text())
    # Each arrival's edges are relaxed in its callback, all but its own tree edge (which
    # starts satisfied).
    assert data["updates"] >= data["edges"] - (data["nodes"] - 1) > 0


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str], str]:
    """Exit code, stderr lines and stdout of ``h2o-solve argv`` (argparse's exits too)."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.err.strip().splitlines(), captured.out


def test_default_is_exact_to_convergence_from_the_tree(planar_file, tmp_path, capsys):
    out, report = tmp_path / "o.g2o", tmp_path / "r.json"
    code, err, _ = run([str(planar_file), "-o", str(out), "--report", str(report), "-q"],
                       capsys)
    data = json.loads(report.read_text())
    # The one line on stderr is the certificate's.
    assert code == 0 and err == [f"h2o-solve: {data['certificate']['message']}"]
    assert data["certificate"]["certified"] is True
    assert (data["mode"], data["converged"]) == ("exact", True)
    # The robust default runs from the odometry's tree and from LAGO and names the start kept.
    assert data["init"] in ("tree", "lago") and data["robust"]["dropped"] == 0
    # passes is what ran, not the cap.
    assert data["passes"] == data["iterations"] == len(data["chi2_per_pass"]) < 100
    assert data["max_iterations"] == 100 and data["tolerance"] == 1e-10
    graph = read_g2o(planar_file)
    offline = tmp_path / "off.json"
    assert main([str(planar_file), "-o", str(tmp_path / "off.g2o"), "--mode", "offline",
                 "--report", str(offline), "-q"]) == 0
    assert data["chi2_final"] <= json.loads(offline.read_text())["chi2_final"]
    solved = read_g2o(out)
    assert chi2(graph, solved.R, solved.t) == pytest.approx(data["chi2_final"], rel=1e-9)


def test_exact_at_its_cap_says_so(planar_file, tmp_path, capsys):
    report = tmp_path / "r.json"
    code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--passes", "1",
                        "--report", str(report), "-q", "--certify", "off"], capsys)
    data = json.loads(report.read_text())
    assert code == 0 and data["converged"] is False
    assert data["passes"] == data["iterations"] == 1
    assert len(err) == 1 and err[0].startswith("h2o-solve: warning: exact mode stopped at its "
                                               "cap of 1 iterations"), err


def test_a_loose_tolerance_stops_sooner(planar_file, tmp_path, capsys):
    reports = []
    for tol in ("1e-10", "0.5"):
        report = tmp_path / f"r{tol}.json"
        assert main([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--tolerance", tol,
                     "--report", str(report), "-q"]) == 0
        reports.append(json.loads(report.read_text()))
    assert reports[1]["converged"] and reports[1]["tolerance"] == 0.5
    assert reports[1]["iterations"] < reports[0]["iterations"]


def test_lago_report_names_no_start(planar_file, tmp_path, capsys):
    report = tmp_path / "r.json"
    assert main([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--solver", "lago",
                 "--report", str(report), "-q"]) == 0
    data = json.loads(report.read_text())
    assert (data["mode"], data["init"], data["passes"]) == ("lago", None, 0)
    assert data["iterations"] is None and data["load_s"] == 0.0  # no kernel to load


@pytest.mark.parametrize("metric", METRICS)
def test_metric_sets_the_reported_chi2_and_all_three_are_reported(planar_file, tmp_path,
                                                                  metric, capsys):
    cube = tmp_path / "cube.g2o"
    write_g2o(cube, grid3d(20, seed=4).graph)
    out, report = tmp_path / "o.g2o", tmp_path / "r.json"
    assert main([str(cube), "-o", str(out), "--init", "input", "--metric", metric,
                 "--report", str(report), "-q"]) == 0
    data = json.loads(report.read_text())
    graph, solved = read_g2o(cube), read_g2o(out)
    assert data["metric"] == metric
    assert data["chi2_metrics"]["initial"] == pytest.approx(all_chi2(graph))
    assert data["chi2_metrics"]["final"] == pytest.approx(all_chi2(graph, solved.R, solved.t),
                                                          rel=1e-9)
    assert data["chi2_initial"] == data["chi2_metrics"]["initial"][metric]
    assert data["chi2_final"] == data["chi2_metrics"]["final"][metric]
    assert data["chi2_per_pass"][-1] == data["chi2_final"]


@pytest.mark.parametrize("args, named", [
    (["--passes", "-1"], "--passes"), (["--passes", "two"], "--passes"),
    (["--tolerance", "2"], "--tolerance"), (["--tolerance", "nan"], "--tolerance"),
    (["--d-max", "0"], "--d-max"), (["--budget-ms", "-1"], "--budget-ms"),
    (["--budget-ms", "5"], "--budget-ms"), (["--gps-batch-size", "0"], "--gps-batch-size"),
    (["--idle-s", "inf"], "--idle-s"), (["--samples", "-2"], "--samples"),
    (["--metric", "ceres"], "--metric"), (["--mode", "fast"], "--mode"),
])
def test_usage_errors_exit_2_naming_the_argument(planar_file, tmp_path, args, named, capsys):
    out = tmp_path / "o.g2o"
    code, err, _ = run([str(planar_file), "-o", str(out), *args], capsys)
    assert code == 2 and len(err) == 1 and err[0].startswith("h2o-solve: ") and named in err[0]
    assert not out.exists()


def test_progress_line_after_a_second_and_quiet(planar_file, tmp_path, capsys):
    stream = io.StringIO()
    with ProgressLine("h2o-solve", period_s=0.05, stream=stream) as line:
        line.status = "offline: pass 3, chi2 12.5"
        time.sleep(0.2)
    lines = stream.getvalue().splitlines()
    assert lines and all(x.startswith("h2o-solve: offline: pass 3, chi2 12.5 (") for x in lines)
    stream = io.StringIO()
    with ProgressLine("h2o-solve", period_s=0.05, stream=stream, enabled=False):
        time.sleep(0.15)
    assert stream.getvalue() == ""
    # Started ahead of the work, the line waits for the block: nothing before it is entered,
    # its clock from the entry; closed without entering, its thread ends.
    stream = io.StringIO()
    line = ProgressLine("h2o-solve", period_s=0.05, stream=stream).start()
    time.sleep(0.15)
    assert stream.getvalue() == ""
    with line:
        time.sleep(0.12)
    assert stream.getvalue().splitlines()[0] == "h2o-solve: working (0 s)"
    unused = ProgressLine("h2o-solve", period_s=0.05, stream=io.StringIO()).start()
    unused.close()
    assert not unused._thread.is_alive()
    # A solve shorter than the period prints nothing (the certificate's line is no progress).
    code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--certify", "off"],
                       capsys)
    assert code == 0 and err == []


def test_a_solve_longer_than_a_second_prints_progress(planar_file, tmp_path, capsys,
                                                      monkeypatch):
    import h2o_slam.app.cli.solve as solve_cli

    real = solve_cli._solve

    def slow(graph, opt, passes, progress):
        progress(1, 123.0)
        time.sleep(1.3)
        return real(graph, opt, passes, progress)

    monkeypatch.setattr(solve_cli, "_solve", slow)
    argv = [str(planar_file), "-o", str(tmp_path / "o.g2o"), "--mode", "offline"]
    code, err, _ = run(argv, capsys)
    assert code == 0 and err and err[0].startswith("h2o-solve: offline: pass 1, chi2 123 ("), err
    code, err, _ = run([*argv, "--quiet"], capsys)
    assert code == 0 and err == []


def test_default_exact_solve_drops_planted_false_closures(tmp_path, capsys):
    """A file with false loop closures: the default (robust) solve names and drops them and
    reaches the outlier-free optimum; ``--robust off`` is bent by them."""
    from h2o_slam.io.outliers import plant_outliers

    clean = manhattan(120, seed=2).graph
    planted = plant_outliers(clean, "random", 5, seed=1)
    path = tmp_path / "planted.g2o"
    write_g2o(path, planted.graph)
    out, report = tmp_path / "o.g2o", tmp_path / "r.json"
    code, err, _ = run([str(path), "-o", str(out), "--report", str(report), "-q"], capsys)
    data = json.loads(report.read_text())["robust"]
    assert code == 0
    assert err[0] == (f"h2o-solve: robust: dropped 5 of {data['weighed']} loop closures and "
                      "fixes as outliers (listed in the report's robust.dropped_edges)")
    # The certificate speaks of the edges kept: the outlier-free problem's optimum.
    certificate = json.loads(report.read_text())["certificate"]
    assert err[1:] == [f"h2o-solve: {certificate['message']}"] and certificate["certified"]
    assert certificate["edges"] == planted.graph.num_edges - 5
    assert data["dropped_edges"] == np.flatnonzero(planted.outlier).tolist()
    solved = read_g2o(out)
    best = chi2(clean, *_exact(clean))
    assert chi2(clean, solved.R, solved.t) == pytest.approx(best, rel=1e-6)
    assert data["chi2_accepted"] == pytest.approx(best, rel=1e-6)
    plain = tmp_path / "plain.json"
    code, err, _ = run([str(path), "-o", str(tmp_path / "p.g2o"), "--robust", "off",
                        "--report", str(plain), "-q", "--certify", "off"], capsys)
    assert code == 0 and err == [] and json.loads(plain.read_text())["robust"] is None
    bent = read_g2o(tmp_path / "p.g2o")
    assert chi2(clean, bent.R, bent.t) > 10 * best


def _exact(graph):
    from h2o_slam.core.modes import solve_exact

    result = solve_exact(graph)
    return result.R, result.t


def test_robust_gnc_needs_exact_mode(planar_file, tmp_path, capsys):
    code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--mode", "offline",
                        "--robust", "gnc"], capsys)
    assert code == 2
    assert err == ["h2o-solve: --robust gnc applies to --mode exact with --solver h2o only"]


def test_budget_inf_is_no_limit(planar_file, tmp_path, capsys):
    """``--budget-ms inf`` is accepted and solves as no budget does (the default)."""
    reports = []
    for extra in ([], ["--budget-ms", "inf"]):
        report = tmp_path / f"r{len(extra)}.json"
        code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--mode", "online",
                            "--idle-s", "0", "--report", str(report), "-q", *extra], capsys)
        assert code == 0 and err == []
        # Strict JSON: no budget is null, not Infinity.
        reports.append(json.loads(report.read_text(), parse_constant=pytest.fail))
    assert reports[1]["budget_ms"] is None and reports[1]["overruns"] is None
    assert reports[1]["chi2_final"] == reports[0]["chi2_final"]
    # Only the budget may be infinite: inf elsewhere still names the finite range.
    code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--idle-s", "inf"],
                       capsys)
    assert code == 2 and len(err) == 1 and "[0, inf)" in err[0], err


def test_indefinite_information_exits_1_naming_file_and_line(tmp_path, capsys):
    bad = tmp_path / "indefinite.g2o"
    bad.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
                   "EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n")
    out = tmp_path / "o.g2o"
    code, err, _ = run([str(bad), "-o", str(out), "-q"], capsys)
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"h2o-solve: {bad}:4: ") and "indefinite" in err[0]
    assert not out.exists()


@pytest.mark.parametrize("solver", ["h2o", "lago"])
def test_a_fast_solve_of_a_slowly_read_file_prints_no_progress(planar_file, tmp_path, capsys,
                                                               monkeypatch, solver):
    """Reading the file (and writing the result) is not the solve: a fast solve after a slow
    read prints no progress line."""
    import h2o_slam.app.cli.solve as solve_cli

    real = solve_cli.read_g2o

    def slow_read(path):
        time.sleep(1.3)
        return real(path)

    monkeypatch.setattr(solve_cli, "read_g2o", slow_read)
    code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--solver", solver,
                        "--certify", "off"], capsys)
    assert code == 0 and err == [], err


def test_init_chordal_starts_a_3d_graph_near_the_optimum(tmp_path, capsys):
    """``--init chordal``: rotations first, no guess; a planar file is refused in one line."""
    graph = grid3d(60, seed=2, sigma_rot_rad=0.1).graph
    src, out, report = tmp_path / "g.g2o", tmp_path / "o.g2o", tmp_path / "r.json"
    write_g2o(src, graph)
    assert main([str(src), "-o", str(out), "--init", "chordal", "--report", str(report),
                 "--robust", "off"]) == 0
    data = json.loads(report.read_text())
    assert data["init"] == "chordal"
    assert data["chi2_initial"] < 3.0 * data["chi2_final"]  # the start is near the optimum
    planar = tmp_path / "p.g2o"
    write_g2o(planar, manhattan(30, seed=1).graph)
    assert main([str(planar), "-o", str(out), "--init", "chordal"]) == 1
    assert "chordal initialization is for 3-D graphs" in capsys.readouterr().err


def test_a_file_whose_closures_agree_far_better_than_stated_says_so(tmp_path, capsys):
    """Information the identity on centimetre edges: the console and the report say how
    much tighter the closures agree than stated and how the thresholds were scaled."""
    from h2o_slam.core.graph import make_graph

    walk = manhattan(400, seed=0, sigma_xy_m=0.01, sigma_yaw_rad=0.002).graph
    loose = make_graph(walk.planar, walk.ids, walk.R, walk.t, walk.kind, walk.a, walk.b,
                       walk.meas_R, walk.meas_t,
                       np.broadcast_to(np.eye(6), walk.info.shape).copy())
    path, report = tmp_path / "loose.g2o", tmp_path / "r.json"
    write_g2o(path, loose)
    code, err, _ = run([str(path), "-o", str(tmp_path / "o.g2o"), "--report", str(report),
                        "-q", "--certify", "off"], capsys)
    data = json.loads(report.read_text())["robust"]
    assert code == 0 and data["dropped"] == 0
    assert data["closure_noise_scale"] < 1e-3
    assert data["closure_threshold_scale"] == pytest.approx(100 * data["closure_noise_scale"])
    assert err == [f"h2o-solve: robust: the loop closures agree "
                   f"{1 / data['closure_noise_scale']:.3g} times better than their information "
                   "says (variance); their outlier thresholds are scaled by "
                   f"{data['closure_threshold_scale']:.3g}"]


def test_certificate_of_a_3d_solution_read_back(tmp_path, capsys):
    """The report's certificate speaks of the solution written: its χ² is the written
    vertices', the refined point's no lower on the χ² than h2o's optimum by much."""
    src, out, report = tmp_path / "g.g2o", tmp_path / "o.g2o", tmp_path / "r.json"
    write_g2o(src, grid3d(40, seed=4).graph)
    code, err, _ = run([str(src), "-o", str(out), "--report", str(report), "-q"], capsys)
    cert = json.loads(report.read_text())["certificate"]
    assert code == 0 and err == [f"h2o-solve: {cert['message']}"]
    assert err[0].startswith("h2o-solve: certified globally optimal (λ_min = ")
    assert cert["certified"] is True and cert["eig_converged"] and cert["refine_converged"]
    assert -cert["tolerance"] <= cert["lambda_min"] and cert["tolerance"] > 0.0
    graph, solved = read_g2o(src), read_g2o(out)
    assert (cert["nodes"], cert["edges"]) == (graph.num_nodes, graph.num_edges)
    assert cert["chi2_solution"] == pytest.approx(chi2(graph, solved.R, solved.t), rel=1e-9)
    assert cert["sesync_cost"] <= cert["cost_at_solution"]
    assert 0.0 < cert["max_rotation_moved_rad"] < 0.1 and cert["seconds"] > 0.0


# A ring of six poses whose measured turns add up to 2π + 0.34 rad (0.6 rad of noise a
# step), started winding once more than the odometry: Gauss-Newton ends in a local minimum
# at χ² 589 (the global one is 1.9; test/core/test_certificate.py checks it is a minimum).
RING = """VERTEX_SE2 0 1.000000 0.000000 0.000000
VERTEX_SE2 1 -0.563847 0.825879 2.169833
VERTEX_SE2 2 -0.503309 -0.864107 -2.098220
VERTEX_SE2 3 0.928505 0.371319 0.380429
VERTEX_SE2 4 -0.823168 0.567798 2.537764
VERTEX_SE2 5 -0.390921 -0.920424 -1.972428
EDGE_SE2 0 1 1.000000 0.130400 1.122636 10 0 0 10 0 100
EDGE_SE2 1 2 1.000000 0.094708 0.967935 10 0 0 10 0 100
EDGE_SE2 2 3 1.000000 -0.070374 1.431451 10 0 0 10 0 100
EDGE_SE2 3 4 1.000000 -0.126542 1.110138 10 0 0 10 0 100
EDGE_SE2 4 5 1.000000 -0.062327 0.725796 10 0 0 10 0 100
EDGE_SE2 5 0 1.000000 0.004133 1.264155 10 0 0 10 0 100
"""


def test_a_local_minimum_is_not_certified(tmp_path, capsys):
    src, report = tmp_path / "ring.g2o", tmp_path / "r.json"
    src.write_text(RING)
    code, err, _ = run([str(src), "-o", str(tmp_path / "o.g2o"), "--init", "input",
                        "--robust", "off", "--report", str(report), "-q",
                        "--staircase", "off"], capsys)
    data = json.loads(report.read_text())
    cert = data["certificate"]
    assert code == 0 and data["chi2_final"] > 500 and data["staircase"] is None
    assert err == [f"h2o-solve: could not certify: λ_min = {cert['lambda_min']:.3g} < "
                   f"-{cert['tolerance']:.3g}"]
    assert cert["certified"] is False and cert["lambda_min"] < -1.0
    # from the tree start the same file reaches the global minimum, certified
    code, err, _ = run([str(src), "-o", str(tmp_path / "o.g2o"), "--robust", "off",
                        "--report", str(report), "-q"], capsys)
    data = json.loads(report.read_text())
    assert data["chi2_final"] < 2.0 and data["certificate"]["certified"] is True


def test_the_staircase_leads_out_of_a_local_minimum(tmp_path, capsys):
    """By default an uncertified solution is solved again from SE-Sync's staircase: the ring
    started in its local minimum ends at the global one, certified, and the time reported
    is the written answer's (the certificate and the climb included)."""
    src, out, report = tmp_path / "ring.g2o", tmp_path / "o.g2o", tmp_path / "r.json"
    src.write_text(RING)
    code, err, _ = run([str(src), "-o", str(out), "--init", "input", "--robust", "off",
                        "--report", str(report), "-q"], capsys)
    data = json.loads(report.read_text())
    stair, cert = data["staircase"], data["certificate"]
    assert code == 0 and stair["adopted"] and stair["relaxation_solved"]
    assert stair["chi2_before"] > 500 and stair["chi2_after"] < 2.0
    assert err == [f"h2o-solve: not certified; SE-Sync's Riemannian staircase (rank "
                   f"{stair['rank']}) and exact mode from its rounded point: chi2 "
                   f"{stair['chi2_before']:.6g} -> {stair['chi2_after']:.6g}, written",
                   f"h2o-solve: {cert['message']}"]
    assert cert["certified"] is True
    graph, solved = read_g2o(src), read_g2o(out)
    assert data["chi2_final"] == pytest.approx(chi2(graph, solved.R, solved.t), rel=1e-9)
    assert data["chi2_final"] == pytest.approx(stair["chi2_after"], rel=1e-12)
    assert data["wall_s"] > stair["seconds"] > stair["climb_s"] > 0.0


def test_a_failing_staircase_leaves_the_solution_written(tmp_path, capsys, monkeypatch):
    """The staircase is a second opinion: when it fails (here its eigensolver), the solve's
    answer is written as it stands, and the report and console say why."""
    import h2o_slam.core.staircase as staircase

    def broken(*args, **kwargs):
        raise ArithmeticError("not positive definite")

    monkeypatch.setattr(staircase, "staircase_start", broken)
    src, out, report = tmp_path / "ring.g2o", tmp_path / "o.g2o", tmp_path / "r.json"
    src.write_text(RING)
    code, err, _ = run([str(src), "-o", str(out), "--init", "input", "--robust", "off",
                        "--report", str(report), "-q"], capsys)
    data = json.loads(report.read_text())
    stair = data["staircase"]
    assert code == 0 and not stair["adopted"]
    assert stair["error"] == "ArithmeticError: not positive definite"
    assert err[0] == ("h2o-solve: not certified; SE-Sync's Riemannian staircase failed "
                      "(ArithmeticError: not positive definite); the solution stands")
    graph, solved = read_g2o(src), read_g2o(out)
    assert chi2(graph, solved.R, solved.t) == pytest.approx(stair["chi2_before"], rel=1e-12)
    assert stair["chi2_before"] > 500  # the local minimum, written


def test_certify_option(planar_file, tmp_path, capsys):
    report = tmp_path / "r.json"
    for args in (["--certify", "off"], ["--mode", "offline"], ["--solver", "lago"]):
        code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--report",
                            str(report), "-q", *args], capsys)
        assert code == 0 and err == [] and json.loads(report.read_text())["certificate"] is None
    code, err, _ = run([str(planar_file), "-o", str(tmp_path / "o.g2o"), "--mode", "offline",
                        "--certify", "on"], capsys)
    assert code == 2 and err == ["h2o-solve: --certify on applies to --mode exact with "
                                 "--solver h2o only"]


def test_conditioned_information_is_counted_and_warned_about(tmp_path, capsys):
    """An edge whose x and y information are perfectly correlated (singular) is conditioned;
    the report and a warning say how much that changes χ² at the solution."""
    src, out, report = tmp_path / "singular.g2o", tmp_path / "o.g2o", tmp_path / "r.json"
    src.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 2 1 1 1.5\n"
                   "EDGE_SE2 0 1 1 0 0 10 0 0 10 0 10\n"
                   "EDGE_SE2 1 2 0 1.1 1.6 10 0 0 10 0 10\n"
                   "EDGE_SE2 0 2 1.1 0.9 1.5 4 4 0 4 0 10\n")
    code, err, _ = run([str(src), "-o", str(out), "--report", str(report), "-q",
                        "--robust", "off", "--certify", "off"], capsys)
    data = json.loads(report.read_text())
    cond = data["conditioned"]
    assert code == 0 and cond["edges"] == 1 and cond["clamped_edges"] == [2]
    # as written, by hand: the singular matrix weighs the solution's error of edge 2
    graph, solved = read_g2o(src), read_g2o(out)
    e = edge_errors(graph, solved.R, solved.t)[:, [0, 1, 5]]
    singular = np.array([[4.0, 4.0, 0.0], [4.0, 4.0, 0.0], [0.0, 0.0, 10.0]])
    written = sum(e[k] @ graph.info[k][np.ix_([0, 1, 5], [0, 1, 5])] @ e[k] for k in (0, 1))
    written += e[2] @ singular @ e[2]
    assert cond["chi2_as_written"] == pytest.approx(written, rel=1e-6)
    assert cond["chi2_conditioned"] == pytest.approx(data["chi2_final"], rel=1e-9)
    assert cond["chi2_difference"] == pytest.approx(
        cond["chi2_conditioned"] - cond["chi2_as_written"], rel=1e-9)
    assert len(err) == 1 and err[0].startswith(
        "h2o-solve: warning: 1 singular or nearly singular information matrices were "
        "conditioned"), err
    assert f"{cond['chi2_as_written']:.9g} as written" in err[0]
    # a file without such matrices reports none
    write_g2o(src, manhattan(20, seed=1).graph)
    assert main([str(src), "-o", str(out), "--report", str(report), "-q"]) == 0
    assert json.loads(report.read_text())["conditioned"] is None


@pytest.mark.parametrize(("planar", "gps", "expected"),
                         [(False, False, "chordal"), (False, True, "tree"), (True, False, "tree")])
def test_the_default_start_is_chordal_for_3d_graphs_of_relative_edges(
        tmp_path, planar, gps, expected):
    """``--init auto`` (the default): rotations first where it applies, the tree elsewhere;
    the report names the start used."""
    graph = manhattan(40, seed=1).graph if planar else grid3d(27, seed=2).graph
    src, out, report = tmp_path / "g.g2o", tmp_path / "o.g2o", tmp_path / "r.json"
    if gps:
        graph = add_gps(graph, graph.t, 5, 1.0)
    write_g2o(src, graph)
    assert main([str(src), "-o", str(out), "--report", str(report), "--robust", "off",
                 "--certify", "off"]) == 0
    assert json.loads(report.read_text())["init"] == expected
