"""h2o-replay's command line on small wheel-odometry bags: argument errors, damaged bags
(declared against read counts, --salvage), a summary after every failure; h2o-solve's
output paths checked before solving."""

from __future__ import annotations

import json
import math
import random
import shutil
import sqlite3
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from nav_msgs.msg import Odometry

import msg_adapters as ma
from h2o_slam.app.cli import replay as replay_cli
from h2o_slam.app.cli import solve as solve_cli
from h2o_slam.io.bag_writer import write_bag

T0 = 1_700_000_000 * 10**9
COUNT = 400


@dataclass
class _Message:
    topic: str
    type_name: str
    stamp_ns: int
    msg: Any


def wheel_stream(count: int = COUNT, bad: Callable[[int], bool] = lambda i: False
                 ) -> Iterator[_Message]:
    """Wheel odometry around a circle at 100 Hz (``bad(i)``: message i carries x = NaN)."""
    for i in range(count):
        stamp = T0 + i * 10**7
        sample = ma.planar_odometry_sample(stamp, "odom", "base_link", 3.0 * math.sin(i / 80),
                                           3.0 * (1 - math.cos(i / 80)), i / 80,
                                           ma.planar_covariance(0.01, 0.01, 0.01))
        msg = ma.fill_odometry(Odometry, sample)
        if bad(i):
            msg.pose.pose.position.x = math.nan
        yield _Message("/wheel/odom", "nav_msgs/msg/Odometry", stamp, msg)


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("wheel_bags")
    out = {}
    for storage in ("mcap", "sqlite3"):
        out[storage] = root / storage
        write_bag(out[storage], wheel_stream(), storage)
    return out


def storage_file(bag: Path) -> Path:
    return next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    try:
        code = replay_cli.main(argv)
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    return code, capsys.readouterr().err.strip().splitlines()


def summary(out: Path) -> dict[str, Any]:
    return dict(json.loads((out / "summary.json").read_text()))


# --- arguments -------------------------------------------------------------------------------


@pytest.mark.parametrize("args", [
    ["--budget-ms", "-5"], ["--budget-ms", "nan"], ["--budget-ms", "5000"],
    ["--budget-ms", "inf"], ["--budget-ms", "fast"], ["--graph-period", "-1"],
    ["--graph-period", "0"], ["--graph-period", "nan"], ["--rate", "0"], ["--delay", "-1"],
    ["--odometry", "lidar"], [],
])
def test_bad_arguments_are_one_line_and_exit_2(args: list[str], tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    output = [] if not args else ["--output", str(tmp_path / "out")]
    code, err = run([str(tmp_path / "bag"), *output, *args], capsys)
    assert code == 2 and len(err) == 1 and err[0].startswith("h2o-replay: error: "), err
    assert not (tmp_path / "out").exists()


# --- complete and damaged bags -----------------------------------------------------------------


def test_a_whole_bag_is_complete(bags: dict[str, Path], tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    for storage, bag in bags.items():
        out = tmp_path / storage
        code, err = run([str(bag), "--output", str(out), "--quiet", "--budget-ms", "0"], capsys)
        assert code == 0 and err == [], err
        s = summary(out)
        assert s["complete"] and s["problems"] == [] and s["deterministic"]
        assert s["declared_messages"] == s["read_messages"] == {"/wheel/odom": COUNT}
        assert s["graph"]["nodes"] > 10 and (out / "graph.json").is_file()


def _garble(bag: Path, dst: Path) -> Path:
    shutil.copytree(bag, dst)
    data = bytearray(storage_file(dst).read_bytes())
    rng = random.Random(5)
    mid = len(data) // 2
    data[mid:mid + 4096] = bytes(rng.getrandbits(8) for _ in range(4096))
    storage_file(dst).write_bytes(bytes(data))
    return dst


def _delete_rows(bag: Path, dst: Path, where: str) -> Path:
    shutil.copytree(bag, dst)
    with sqlite3.connect(storage_file(dst)) as db:
        db.execute(f"DELETE FROM messages WHERE {where}")
    return dst


def _raw_db3_without_odometry(bag: Path, dst: Path) -> Path:
    folder = _delete_rows(bag, dst.with_name(dst.name + "_folder"), "1")
    return storage_file(folder)


def _declare_more(bag: Path, dst: Path) -> Path:
    shutil.copytree(bag, dst)
    meta_path = dst / "metadata.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    info = meta["rosbag2_bagfile_information"]
    info["topics_with_message_count"][0]["message_count"] += 7
    info["message_count"] += 7
    meta_path.write_text(yaml.safe_dump(meta))
    return dst


def _truncate(bag: Path, dst: Path) -> Path:
    shutil.copytree(bag, dst)
    data = storage_file(dst).read_bytes()
    storage_file(dst).write_bytes(data[: len(data) // 2])
    return dst


def _wrong_type(bag: Path, dst: Path) -> Path:
    from sensor_msgs.msg import NavSatFix

    fix = NavSatFix()
    write_bag(dst, [_Message("/wheel/odom", "sensor_msgs/msg/NavSatFix", T0, fix)])
    return dst


def _poisoned(bag: Path, dst: Path) -> Path:
    write_bag(dst, wheel_stream(bad=lambda i: True))  # every message refused by the node
    return dst


#: name: (storage, damage, what the one line and the summary's first problem say)
DAMAGED: dict[str, tuple[str, Callable[[Path, Path], Path], str]] = {
    "mcap 4 KiB garble in a chunk": ("mcap", _garble, r"stopped after \d+ messages|read \d+ of"),
    "mcap cut in half": ("mcap", _truncate, r"stopped after \d+ messages|read \d+ of"),
    "db3 odometry rows deleted": ("sqlite3", lambda b, d: _delete_rows(b, d, "1"),
                                  r"read 0 of the 400 messages"),
    "db3 half the rows deleted": ("sqlite3", lambda b, d: _delete_rows(b, d, "id % 2 = 0"),
                                  r"read 200 of the 400 messages the bag declares on "
                                  r"/wheel/odom"),
    "raw db3 without odometry": ("sqlite3", _raw_db3_without_odometry,
                                 r"no message on /wheel/odom"),
    "metadata declares more": ("mcap", _declare_more, r"read 400 of the 407 messages"),
    "odometry of the wrong type": ("mcap", _wrong_type, r"has type sensor_msgs/msg/NavSatFix"),
    "every odometry message poisoned": ("mcap", _poisoned, r"the graph is empty"),
}
# A bag that does not exist (or an empty folder) is refused before DIR is created, so it
# leaves no folder and no summary: test_cli_errors.py; so is a folder that is no bag:


def _folder_with(name: str, content: bytes) -> Callable[[Path, Path], Path]:
    def make(bag: Path, dst: Path) -> Path:
        dst.mkdir()
        (dst / name).write_bytes(content)
        return dst
    return make


def _without_storage(bag: Path, dst: Path) -> Path:
    shutil.copytree(bag, dst)
    storage_file(dst).unlink()
    return dst


def _garbage_storage(bag: Path, dst: Path) -> Path:
    shutil.copytree(bag, dst)
    storage_file(dst).write_bytes(random.Random(4).randbytes(4096))
    return dst


def _a_text_file(bag: Path, dst: Path) -> Path:
    dst.mkdir()
    (dst / "notes.txt").write_text("hello")
    return dst / "notes.txt"


#: name: (make the path from a good bag, where the line starts, what it says)
NO_BAG: dict[str, tuple[Callable[[Path, Path], Path], str, str]] = {
    "a random file": (_folder_with("data.bin", random.Random(3).randbytes(300)), "",
                      r"not a bag \(no metadata\.yaml and no \.mcap or \.db3 file\)"),
    "a .txt file": (_folder_with("notes.txt", b"hello"), "", r"not a bag \(no metadata\.yaml"),
    "metadata.yaml not YAML": (_folder_with("metadata.yaml", b"{{{: [\n"), "/metadata.yaml",
                               r"not YAML \(line \d+: .*\), and no \.mcap or \.db3 file"),
    "metadata.yaml not a bag's": (_folder_with("metadata.yaml", b"{}"), "/metadata.yaml",
                                  r"not rosbag2 metadata \(no rosbag2_bagfile_information\)"),
    "metadata.yaml without its storage": (_without_storage, "/metadata.yaml",
                                          r"lists mcap\.mcap, which is missing"),
    "a text file as the bag": (_a_text_file, "", r"not a bag \(expected a rosbag2 folder"),
    "storage garbled from its first byte": (_garbage_storage, "/mcap.mcap",
                                            r"not an MCAP file \(it does not start as one"),
}


@pytest.mark.parametrize("name", sorted(NO_BAG))
def test_no_bag_is_one_line_exit_1_and_creates_nothing(
        name: str, bags: dict[str, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    import re

    make, tail, reason = NO_BAG[name]
    bag = make(bags["mcap"], tmp_path / "bag")
    out = tmp_path / "deep" / "out"
    code, err = run([str(bag), "--output", str(out), "--quiet"], capsys)
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"h2o-replay: {bag}{tail}: ") and re.search(reason, err[0]), err
    assert "Error)" not in err[0], err  # the reason is ours, not an exception's text
    assert not (tmp_path / "deep").exists()


def replay_damaged(name: str, bags: dict[str, Path], tmp_path: Path,
                   capsys: pytest.CaptureFixture[str], *flags: str
                   ) -> tuple[Path, Path, int, list[str]]:
    """Damage a recorded bag as ``DAMAGED[name]`` says and replay it quietly:
    ``(bag, output folder, exit code, stderr lines)``."""
    storage, damage, _ = DAMAGED[name]
    bag = damage(bags[storage], tmp_path / "bag")
    out = tmp_path / "out"
    code, err = run([str(bag), "--output", str(out), "--quiet", *flags], capsys)
    return bag, out, code, err


@pytest.mark.parametrize("name", sorted(DAMAGED))
def test_a_damaged_bag_is_one_line_exit_1_and_a_summary(
        name: str, bags: dict[str, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    import re

    reason = DAMAGED[name][2]
    bag, out, code, err = replay_damaged(name, bags, tmp_path, capsys)
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"h2o-replay: {bag}: ") and re.search(reason, err[0]), err
    s = summary(out)  # every failure writes the summary
    assert not s["complete"] and re.search(reason, s["problems"][0]), s


@pytest.mark.parametrize("name", ["mcap 4 KiB garble in a chunk", "db3 half the rows deleted",
                                  "metadata declares more"])
def test_salvage_accepts_a_partial_replay_and_says_so(
        name: str, bags: dict[str, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    _, out, code, err = replay_damaged(name, bags, tmp_path, capsys, "--salvage")
    s = summary(out)
    assert code == 0 and s["salvage"] and not s["complete"]
    assert len(err) == len(s["problems"]) >= 1
    assert all(line.startswith("h2o-replay: warning: ") and line.endswith(
        "(accepted by --salvage)") for line in err), err
    lost = s["lost_messages"]["/wheel/odom"]
    assert lost == s["declared_messages"]["/wheel/odom"] - s["read_messages"]["/wheel/odom"]
    assert lost != 0


def test_output_folder_in_use_is_refused_without_touching_it(
        bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    code, err = run([str(bags["mcap"]), "--output", str(out), "--quiet"], capsys)
    assert code == 2 and len(err) == 1 and "not empty" in err[0]
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]


# --- h2o-solve's outputs ---------------------------------------------------------------------

GRAPH = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"


@pytest.mark.parametrize("option", ["--output", "--report", "--trace"])
def test_solve_checks_its_output_paths_before_solving(
        option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    graph = tmp_path / "in.g2o"
    graph.write_text(GRAPH)
    monkeypatch.setattr(solve_cli, "solve_file", lambda *a, **k: pytest.fail("solved"))
    paths = {"--output": tmp_path / "out.g2o"}
    paths[option] = tmp_path / "missing" / "x.json"
    argv = [str(graph)] + [str(v) for item in paths.items() for v in item]
    assert solve_cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"h2o-solve: {option} {paths[option]}: folder {tmp_path / 'missing'} "
                   "does not exist"]
    paths[option] = tmp_path  # a folder where a file is expected
    argv = [str(graph)] + [str(v) for item in paths.items() for v in item]
    assert solve_cli.main(argv) == 2
    assert "is a folder" in capsys.readouterr().err


def test_an_exception_no_check_foresaw_still_writes_the_summary(
        bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    from h2o_slam.ros.h2o_node import H2ONode

    calls = []

    def explode(self: Any, msg: Any) -> None:
        calls.append(msg)
        if len(calls) == 50:
            raise RuntimeError("adversarial message")

    monkeypatch.setattr(H2ONode, "on_odom", explode)
    out = tmp_path / "out"
    code, err = run([str(bags["mcap"]), "--output", str(out), "--quiet"], capsys)
    assert code == 1 and len(err) == 1, err
    assert "stopped after 50 messages: adversarial message (RuntimeError)" in err[0]
    s = summary(out)
    assert s["error"] and not s["complete"] and s["read_messages"]["/wheel/odom"] == 50
