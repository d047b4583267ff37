"""h2o-replay and h2o-demo on real bag files written by the simulator."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

import msg_adapters as ma
from h2o_slam.app.cli import demo as demo_cli
from h2o_slam.app.cli import replay as replay_cli
from h2o_slam.app.cli.demo import PLOTS
from h2o_slam.app.cli.demo import run as run_demo
from h2o_slam.app.replay import Replay, ReplayOptions, replay
from h2o_slam.io.bag_reader import BagReader
from h2o_slam.io.bag_writer import write_bag
from h2o_slam.io.replay_outputs import read_tum
from hybrid_vo.sim import world
from hybrid_vo.sim.messages import drive_messages

pytestmark = pytest.mark.slow

TURN = (math.pi / 2) / 3.0
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def short_drive() -> world.Drive:
    """Half a lap of the slip drive (18 s): images, slip, GPS, a closure where it revisits."""
    cfg = world.scenario("slip", seed=3, segments=((6.0, 1.3, 0.0), (3.0, 1.0, TURN)) * 2
                         + ((6.0, 1.3, 0.0), (3.0, 1.0, -TURN), (4.0, 1.3, -TURN)),
                         loop_min_gap_s=5.0, loop_radius_m=3.0)
    return world.make_drive(cfg)


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    drive = short_drive()
    out = {}
    for storage in ("mcap", "sqlite3"):
        out[storage] = root / storage
        write_bag(out[storage], drive_messages(drive), storage)
    return out


@pytest.fixture(scope="module")
def replays(bags: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("replays")
    out = {}
    for storage, bag in bags.items():
        out[storage] = root / storage
        replay(ReplayOptions(bag=bag, output=out[storage], progress=False))
    return out


def test_both_storage_formats_give_identical_outputs(replays: dict[str, Path]) -> None:
    mcap, sqlite = replays["mcap"], replays["sqlite3"]
    for name in ("wheel.tum", "hybrid_vo.tum", "h2o.tum", "ground_truth.tum", "graph.g2o"):
        assert (mcap / name).read_bytes() == (sqlite / name).read_bytes(), name
    summary = json.loads((mcap / "summary.json").read_text())
    assert summary["odometry"] == "hybrid_vo" and summary["deterministic"]
    assert summary["graph"]["nodes"] > 10 and summary["accepted"]["gps"] > 5
    assert summary["accuracy"]["hybrid_vo"]["ate_m"] < summary["accuracy"]["wheel"]["ate_m"]


def test_tum_files_load_with_evo(replays: dict[str, Path]) -> None:
    from evo.tools import file_interface

    for name in ("wheel", "hybrid_vo", "h2o", "ground_truth"):
        path = replays["mcap"] / f"{name}.tum"
        traj = file_interface.read_tum_trajectory_file(str(path))
        stamps, xyz, _ = read_tum(path)
        assert traj.num_poses == len(stamps) > 10
        np.testing.assert_array_equal(traj.positions_xyz, xyz)


def test_output_bag_holds_what_the_nodes_published(replays: dict[str, Path]) -> None:
    topics = {"wheel_odom": "/odometry/hybrid", "gps": None, "loop_closure": None}
    with BagReader(replays["mcap"] / "outputs", topics, required=("wheel_odom",)) as reader:
        count = sum(1 for _ in reader.messages())
        present = set(reader.stats.topics)
    assert count > 100
    assert {"/h2o_node/pose", "/h2o_node/graph/poses", "/diagnostics", "/tf"} <= present


def test_truncated_bag_ends_with_one_line_and_a_readable_partial_output(
        bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = tmp_path / "cut"
    cut.mkdir()
    source = next(bags["mcap"].glob("*.mcap"))
    data = source.read_bytes()
    (cut / source.name).write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    code = replay_cli.main([str(cut / source.name), "--output", str(out), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert err[0].startswith("h2o-replay: ") and "cut" in err[0]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["error"] and summary["graph"]["nodes"] > 0
    stamps, _, _ = read_tum(out / "h2o.tum")
    assert len(stamps) == summary["graph"]["nodes"]
    with BagReader(out / "outputs", {"wheel_odom": "/odometry/hybrid"},
                   required=("wheel_odom",)) as reader:
        assert sum(1 for _ in reader.messages()) > 10


def test_missing_topics_are_named(bags: dict[str, Path], tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    code = replay_cli.main([str(bags["mcap"]), "--output", str(tmp_path / "o"), "--quiet",
                            "--topic", "wheel_odom=/no/such/odom"])
    err = capsys.readouterr().err
    assert code == 1 and "/no/such/odom" in err and err.count("\n") == 1


def test_demo_h2o_with_gps_beats_hybrid_vo_which_beats_wheels(tmp_path: Path) -> None:
    result = run_demo(tmp_path, seed=4, laps=2, storage="mcap", progress=False)
    ate = {name: acc["ate_m"] for name, acc in result["rows"]}
    assert ate["H2O with GPS"] < ate["hybrid VO"] < ate["wheel odometry"]
    assert (tmp_path / "replay" / "ground_truth.tum").is_file()
    assert (tmp_path / "input").is_dir() and (tmp_path / "no_gps" / "h2o.tum").is_file()
    for folder in (tmp_path, tmp_path / "replay", tmp_path / "no_gps"):
        for name in PLOTS:  # the demo's own three, of both runs; each replay's three
            blob = (folder / name).read_bytes()
            assert blob[:8] == PNG_MAGIC and len(blob) > 20_000, folder / name


def test_h2o_replay_of_the_demo_bag_gives_the_demos_numbers(tmp_path: Path) -> None:
    """h2o-replay of the bag the demo records reproduces the demo's own replay of it: the
    map frame is the same (the datum the drive's GPS and ground truth are about)."""
    bag = tmp_path / "input"
    demo_cli.record(short_drive(), bag, "mcap", with_images=False)
    demo = Replay(demo_cli.replay_options(bag, tmp_path / "demo", gps=True, progress=False))
    ours = demo.run()
    assert replay_cli.main([str(bag), "--output", str(tmp_path / "cli"), "--quiet"]) == 0
    theirs = json.loads((tmp_path / "cli" / "summary.json").read_text())
    assert ours["accepted"]["gps"] > 5
    for track in ("h2o", "h2o_online"):
        assert theirs["accuracy"][track] == ours["accuracy"][track], track
    assert (tmp_path / "cli" / "h2o.tum").read_bytes() == \
        (tmp_path / "demo" / "h2o.tum").read_bytes()


def test_chi2_samples_carry_each_graphs_degrees_of_freedom(bags: dict[str, Path],
                                                           tmp_path: Path) -> None:
    run = Replay(ReplayOptions(bag=bags["mcap"], output=tmp_path / "out", progress=False))
    summary = run.run()
    samples = run.chi2_samples()  # what chi2.png draws: χ² per degree of freedom
    assert len(samples.stamps_s) == len(samples.chi2) == len(samples.dof) >= 3
    assert samples.chi2[-1] == summary["graph"]["chi2"]
    # The odometry chain is a tree (no DOF); each closure adds 3, each GPS fix (x, y) 2, less
    # the map's pose (3), which the fixes pin.
    held = run.h2o.mapper.decisions() if run.h2o else {}
    fixes = held["gps_fixes in"] + held["gps_fixes down-weighted"]
    closures = held["loop_closures in"] + held["loop_closures down-weighted"]
    assert fixes > 10 and samples.dof[-1] == 2 * fixes + 3 * closures - 3
    assert samples.holds.startswith("odometry, ")
    assert samples.holds.endswith(f", {held['gps_fixes in']} GPS fixes")


def test_realtime_publishes_the_bag_on_the_ros_graph(bags: dict[str, Path]) -> None:
    import threading

    from nav_msgs.msg import Odometry
    from node_harness import Harness

    from h2o_slam.app.replay import publish_realtime

    topics = {"wheel_odom": "/wheel/odom", "gps": None, "loop_closure": None,
              "ground_truth": None, "left_image": None, "right_image": None,
              "left_info": None, "right_info": None}
    with BagReader(bags["mcap"], topics, required=("wheel_odom",)) as reader:
        recorded = [ma.stamp_ns(m.msg.header) for m in reader.messages()]
    harness = Harness()
    try:
        got = harness.subscribe(Odometry, "/wheel/odom")
        # The delay covers discovery, so every recorded message must arrive.
        worker = threading.Thread(target=publish_realtime,
                                  args=(bags["mcap"], topics, 20.0, 3.0))
        start = time.monotonic()
        worker.start()
        harness.spin_until(lambda: not worker.is_alive() and len(got) >= len(recorded), 60.0,
                           f"the bag's {len(recorded)} odometry messages")
        elapsed = time.monotonic() - start
    finally:
        harness.close()
    assert [ma.stamp_ns(m.header) for m in got] == recorded
    # 3 s of delay, then 18 s of bag at 20x: paced, not dumped at once.
    assert elapsed > 3.0 + 0.8
