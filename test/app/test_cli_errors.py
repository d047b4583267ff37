"""The error convention the three commands share (h2o_slam.app.cli.common): usage errors exit 2,
input errors 1, one line naming the argument or file, no empty folders left behind; and
h2o-demo's and h2o-replay's help."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from h2o_slam.app.cli import demo as demo_cli
from h2o_slam.app.cli import replay as replay_cli
from h2o_slam.app.cli import solve as solve_cli
from h2o_slam.app.cli.common import missing_folders, remove_if_empty, unusable_folder

Main = Callable[[list[str] | None], int]


def run(main: Main, argv: list[str], capsys: pytest.CaptureFixture[str]
        ) -> tuple[int, list[str], str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse: --help, bad values
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.err.strip().splitlines(), captured.out


def test_replay_missing_bag_is_exit_1_and_creates_nothing(tmp_path, capsys):
    out = tmp_path / "deep" / "out"
    code, err, _ = run(replay_cli.main, [str(tmp_path / "nope"), "--output", str(out)], capsys)
    assert code == 1 and err == [f"h2o-replay: {tmp_path / 'nope'}: no such file or folder"]
    assert not (tmp_path / "deep").exists()


def test_replay_empty_bag_folder_names_its_metadata(tmp_path, capsys):
    bag = tmp_path / "bag"
    bag.mkdir()
    out = tmp_path / "out"
    code, err, _ = run(replay_cli.main, [str(bag), "--output", str(out), "--quiet"], capsys)
    assert code == 1 and len(err) == 1
    assert err[0].startswith(f"h2o-replay: {bag / 'metadata.yaml'}: no such file"), err
    assert not out.exists()


@pytest.mark.parametrize("main, prog", [(replay_cli.main, "h2o-replay"),
                                        (demo_cli.main, "h2o-demo")])
def test_output_that_cannot_be_a_folder_is_exit_2(main, prog, tmp_path, capsys):
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("{}")
    a_file = tmp_path / "file"
    a_file.write_text("x")
    full = tmp_path / "full"
    full.mkdir()
    (full / "mine").write_text("keep")
    head = [str(bag)] if main is replay_cli.main else []
    for output, reason in ((a_file, "is a file"), (a_file / "sub", "is a file"),
                           (full, "not empty")):
        code, err, _ = run(main, [*head, "--output", str(output)], capsys)
        assert code == 2 and len(err) == 1, err
        assert err[0].startswith(f"{prog}: --output {output}: ") and reason in err[0], err
    assert [p.name for p in full.iterdir()] == ["mine"]


def test_replay_failure_removes_the_folders_it_created(tmp_path, capsys, monkeypatch):
    bag = tmp_path / "bag"
    bag.mkdir()
    # An MCAP file's start: a storage file the reader is left to try (and fails here).
    (bag / "bag.mcap").write_bytes(b"\x89MCAP0\r\n")

    def fail(options):
        options.output.mkdir(parents=True)
        raise OSError(5, "disk gone", str(options.output))

    monkeypatch.setattr(replay_cli, "replay", fail)
    code, err, _ = run(replay_cli.main, [str(bag), "--output", str(tmp_path / "a" / "b")],
                       capsys)
    assert code == 1 and len(err) == 1 and "disk gone" in err[0]
    assert not (tmp_path / "a").exists()


def test_demo_failure_removes_the_folders_it_created(tmp_path, capsys, monkeypatch):
    def fail(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(demo_cli, "run", fail)
    out = tmp_path / "x" / "demo"
    code, err, _ = run(demo_cli.main, ["--output", str(out), "--quiet"], capsys)
    assert code == 1 and err == ["h2o-demo: [Errno 28] No space left on device"]
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("args", [["--laps", "0"], ["--laps", "x"], ["--storage", "zip"],
                                  ["--seed", "1.5"]])
def test_demo_bad_arguments_are_one_line_exit_2(args, capsys):
    code, err, _ = run(demo_cli.main, args, capsys)
    assert code == 2 and len(err) == 1 and err[0].startswith("h2o-demo: error: argument "), err


def test_demo_help_is_plain_and_points_to_the_ground_truth(capsys):
    code, _, out = run(demo_cli.main, ["--help"], capsys)
    assert code == 0
    for markup in (":mod:", "``", ":func:"):
        assert markup not in out
    assert "replay/ground_truth.tum" in out
    options = out[out.index("options:"):]
    assert "storage plugin" in options[options.index("--storage"):options.index("--quiet")]


def test_replay_storage_has_help(capsys):
    code, _, out = run(replay_cli.main, ["--help"], capsys)
    assert code == 0 and "storage plugin of the output bag" in out


def test_solve_input_errors_are_exit_1(tmp_path, capsys):
    bad = tmp_path / "bad.g2o"
    bad.write_text("EDGE_SE2 0 1 nan 0 0 1 0 0 1 0 1\n")
    code, err, _ = run(solve_cli.main, [str(bad), "-o", str(tmp_path / "o.g2o")], capsys)
    assert code == 1 and len(err) == 1 and err[0].startswith(f"h2o-solve: {bad}:1:"), err


def test_folder_helpers(tmp_path):
    target = tmp_path / "a" / "b" / "c"
    created = missing_folders(target)
    assert created == [target, target.parent, tmp_path / "a"]
    target.mkdir(parents=True)
    (target.parent / "keep").write_text("x")
    remove_if_empty(created)
    assert not target.exists() and (tmp_path / "a" / "b" / "keep").exists()
    assert unusable_folder("--output", None) is None
    assert unusable_folder("--output", tmp_path / "new" / "deeper") is None
