"""``h2o-demo``: the whole system on built-in data.

    h2o-demo [--output DIR] [--seed N] [--laps N] [--storage mcap|sqlite3]

Simulates a drive with :mod:`hybrid_vo.sim.world` (stereo camera, wheel odometry with slip and
hallucinated turns, GPS with dropouts, loop closures, ground truth), writes it as a bag,
replays it with ``h2o-replay``'s machinery twice — with and without GPS — and prints ATE
and final error of wheel odometry, hybrid VO, H₂O without GPS and H₂O with GPS. DIR
(a new temporary folder when not given) receives the input bag (``input/``), everything
the replay with GPS writes (``replay/``, ``ground_truth.tum`` among it), the replay
without GPS (``no_gps/``), and the three plots of both runs together (:data:`PLOTS`).

Exit codes as every command of the package (:mod:`h2o_slam.app.cli.common`): 2 for the command
line (an output folder that is a file or not empty), 1 when the run fails.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from h2o_slam.app.cli.common import (
    EXIT_INPUT,
    OneLineParser,
    integer,
    missing_folders,
    remove_if_empty,
    unusable_folder,
    usage_error,
)
from h2o_slam.app.replay import Replay, ReplayOptions
from h2o_slam.core.errors import H2OError
from h2o_slam.core.graph import EdgeKind
from h2o_slam.io.bag_writer import write_bag
from h2o_slam.io.bags import DATUM_KEY, Storage
from h2o_slam.io.g2o import read_g2o
from h2o_slam.io.plots import plot_callback_times, plot_chi2, plot_trajectories
from h2o_slam.io.replay_outputs import read_tum
from hybrid_vo.sim import world
from hybrid_vo.sim.messages import drive_messages

PROG = "h2o-demo"

#: What ``h2o-demo --help`` says it does (the module docstring, without its markup).
DESCRIPTION = (
    "Simulate a drive (stereo camera, wheel odometry with slip and hallucinated turns, GPS "
    "with dropouts, loop closures, ground truth), record it as a bag, replay it through "
    "hybrid_vo_node and h2o_node twice (with and without GPS), and print the ATE and final "
    "error of wheel odometry, hybrid VO, H2O without GPS and H2O with GPS. The output folder "
    "receives the input bag in input/, the replay with GPS in replay/ (its outputs bag, TUM "
    "trajectories with replay/ground_truth.tum, graph, plots and summary.json), the "
    "replay without GPS in no_gps/, and plots of both runs: trajectories.png, chi2.png and "
    "callback_times.png."
)

#: The pictures ``h2o-demo`` writes into DIR, both runs together (``make doc-images``
#: copies them into doc/images for the README).
PLOTS = ("trajectories.png", "chi2.png", "callback_times.png")

#: Bag seconds between χ² samples (and graph outputs) of the demo's replays: the drive is
#: short, so finer than h2o-replay's default.
GRAPH_PERIOD_S = 1.0

#: Where hybrid_vo.sim.world puts the origin of its ENU frame (lat, lon, alt): the demo's
#: surveyed datum, stated in its bag, so that the map frame and the ground truth share their
#: origin.
WORLD_DATUM = list(world.GPS_DATUM)


def demo_drive(seed: int, laps: int) -> world.DriveConfig:
    """The slip-heavy drive of the benchmarks, ``laps`` times round, with a GPS receiver of
    5 cm σ (RTK grade)."""
    base = world.scenario("slip", seed=seed)
    lap = base.segments[: len(base.segments) // 2]
    turns = tuple((t + k * 36.0, yaw, dur) for k in range(laps)
                  for t, yaw, dur in base.slip.hallucinated_turns if t < 36.0)
    slip = replace(base.slip, hallucinated_turns=turns,
                   drift_windows_s=tuple((a + k * 36.0, b + k * 36.0) for k in range(laps)
                                         for a, b in ((4.0, 14.0), (22.0, 30.0))))
    return replace(base, name="demo", segments=lap * laps, slip=slip, gps_sigma_m=0.05)


def run(output: Path, seed: int, laps: int, storage: Storage, progress: bool) -> dict[str, Any]:
    """Simulate, record, replay twice; returns ``{"rows": ..., "summaries": ...}``."""
    drive = world.make_drive(demo_drive(seed, laps))
    bag = output / "input"
    start = time.perf_counter()
    record(drive, bag, storage)
    record_s = time.perf_counter() - start
    runs = {name: Replay(replay_options(bag, output / folder, gps, progress))
            for name, folder, gps in (("with GPS", "replay", True),
                                      ("without GPS", "no_gps", False))}
    with_gps, without = (r.run() for r in runs.values())
    write_plots(output, runs)
    acc, acc_no = with_gps["accuracy"], without["accuracy"]
    rows = [("wheel odometry", acc.get("wheel")), ("hybrid VO", acc.get("hybrid_vo")),
            ("H2O without GPS", acc_no.get("h2o")), ("H2O with GPS", acc.get("h2o"))]
    return {"rows": rows, "record_s": record_s, "frames": len(drive),
            "summaries": {"with_gps": with_gps, "without_gps": without}}


def record(drive: world.Drive, bag: Path, storage: Storage, with_images: bool = True) -> None:
    """Write ``drive`` as the demo's input bag, stating the world's datum in its metadata so
    that any replay of it (``h2o-replay`` too) maps in the ground truth's frame
    (``with_images=False``: the back end's inputs alone, a quick bag for tests)."""
    write_bag(bag, drive_messages(drive, with_images=with_images), storage,
              custom_data={DATUM_KEY: json.dumps(WORLD_DATUM)})


def replay_options(bag: Path, output: Path, gps: bool, progress: bool) -> ReplayOptions:
    """How the demo replays its bag (``gps``: feed GPS to the back end): as ``h2o-replay``
    does, the datum from the bag, with χ² sampled more often."""
    return ReplayOptions(bag=bag, output=output, use_gps=gps, progress=progress,
                         graph_period_s=GRAPH_PERIOD_S)


def write_plots(output: Path, runs: dict[str, Replay]) -> None:
    """The demo's three pictures in ``output`` (:data:`PLOTS`): the table's trajectories
    with the GPS fixes and the ground truth, χ² of both runs, and the callback times of the
    run with GPS."""
    with_gps, without = runs["with GPS"].options.output, runs["without GPS"].options.output

    tracks = {label: read_tum(path) for label, path in (
        ("wheel odometry", with_gps / "wheel.tum"), ("hybrid VO", with_gps / "hybrid_vo.tum"),
        ("H₂O without GPS", without / "h2o.tum"), ("H₂O with GPS", with_gps / "h2o.tum"),
        ("ground truth", with_gps / "ground_truth.tum"))}
    graph = read_g2o(with_gps / "graph.g2o")
    plot_trajectories(output / PLOTS[0], {k: v[1] for k, v in tracks.items()},
                      gps_enu=graph.meas_t[graph.kind == EdgeKind.POSITION],
                      title="h2o-demo: the simulated drive (final graphs)",
                      stamps_ns={k: v[0] for k, v in tracks.items()})
    plot_chi2(output / PLOTS[1], {f"H₂O {name}": run.chi2_samples()
                                  for name, run in runs.items() if run.chi2_trace},
              title="h2o-demo: χ² per degree of freedom of each graph over bag time")
    plot_callback_times(output / PLOTS[2], runs["with GPS"].callback_panels(),
                        title="h2o-demo: time per callback (replay with GPS, one process)")


def table(rows: list[tuple[str, dict[str, float] | None]]) -> str:
    """The accuracy table as text."""
    lines = [f"{'trajectory':<18} {'ATE (m)':>9} {'final error (m)':>16}"]
    for name, acc in rows:
        ate = acc["ate_m"] if acc else math.nan
        final = acc["final_error_m"] if acc else math.nan
        lines.append(f"{name:<18} {ate:>9.3f} {final:>16.3f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    p = OneLineParser(prog=PROG, description=DESCRIPTION)
    p.add_argument("--output", type=Path, metavar="DIR",
                   help="folder for everything, new or empty (default: a new temporary "
                        "folder)")
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated drive (default 1)")
    p.add_argument("--laps", type=integer(1), default=3,
                   help="laps of the 36 s square (default 3)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="storage plugin of the bags written (default: mcap)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    args = p.parse_args(argv)
    problem = unusable_folder("--output", args.output)
    if problem is not None:
        return usage_error(PROG, problem)
    output = args.output or Path(tempfile.mkdtemp(prefix="h2o-demo-"))
    created = missing_folders(output) if args.output else [output]
    try:
        output.mkdir(parents=True, exist_ok=True)
        result = run(output, args.seed, args.laps, args.storage, not args.quiet)
    except (H2OError, OSError) as exc:
        remove_if_empty(created)
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_INPUT
    summary = result["summaries"]["with_gps"]
    print(f"simulated {result['frames']} stereo frames ({summary['bag_duration_s']:.0f} s), "
          f"recorded in {result['record_s']:.1f} s, replayed at "
          f"{summary['speed_x_realtime']:.1f}x real time")
    print(table(result["rows"]))
    print(f"everything is in {output} (input bag in input/, replay outputs in replay/ and "
          "no_gps/; ground truth in replay/ground_truth.tum; plots "
          f"{', '.join(PLOTS)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
