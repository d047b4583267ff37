"""Benchmark: ``h2o-replay`` speed (× real time) and peak memory on a 10-minute drive.

    .venv/bin/python bench/replay.py [--laps N] [--seed N] [--output-dir DIR]
                                     [--results FILE] [--quick]

The drive of ``h2o-demo`` (the slip square of :mod:`hybrid_vo.sim.world`, 36 s a lap; 17 laps
≈ 10 minutes, ~6100 rendered stereo frames at 10 Hz, wheel odometry, GPS at 1 Hz, loop
closures, ground truth) is written once as an MCAP bag under ``--output-dir`` and reused by
later runs (rendering it takes minutes; the time is printed). The replay itself,
``h2o_slam.app.replay.replay(ReplayOptions(bag, output))`` with the defaults ``h2o-replay``
uses (hybrid VO odometry, every edge solved in full), runs in a fresh child process; its
peak resident set size is the child's ``ru_maxrss`` as ``os.wait4`` reports it. The table
goes to stdout and replaces the section ``## Replay (bench/replay.py)`` of
``bench/RESULTS.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from results_md import command, replace_section, revision

REPO = Path(__file__).resolve().parents[1]
DEFAULT_RESULTS = REPO / "bench" / "RESULTS.md"
DEFAULT_OUTPUT = Path(tempfile.gettempdir()) / "h2o-bench-replay"
SECTION = "## Replay (bench/replay.py)"
LAP_S = 36.0
DEFAULT_LAPS = 17  # 612 s: the 10-minute drive of issue 7
TARGET_X_REALTIME = 10.0


# --- the bag -----------------------------------------------------------------------------------


def record_bag(out_dir: Path, laps: int, seed: int) -> tuple[Path, dict[str, Any]]:
    """The drive's bag under ``out_dir``, written unless a complete one is there already.

    Returns the bag's folder and its record: frames, messages per topic, size, and
    ``record_s`` (the time it took to write it, when it was written by an earlier run too).
    """
    from h2o_slam.app.cli.demo import demo_drive
    from h2o_slam.io.bag_writer import write_bag
    from hybrid_vo.sim import world
    from hybrid_vo.sim.messages import drive_messages

    folder = out_dir / f"drive_{laps}laps_seed{seed}"
    bag, done = folder / "bag", folder / "record.json"
    if done.exists() and bag.exists():
        return bag, {**json.loads(done.read_text()), "cached": True}
    shutil.rmtree(folder, ignore_errors=True)  # a partial bag of an interrupted run
    folder.mkdir(parents=True)
    print(f"replay.py: rendering and writing {laps} laps ({laps * LAP_S:.0f} s) to {bag} "
          "(once; later runs reuse it) ...", file=sys.stderr, flush=True)
    start = time.perf_counter()
    drive = world.make_drive(demo_drive(seed, laps))
    counts = write_bag(bag, drive_messages(drive))
    record_s = time.perf_counter() - start
    size = sum(p.stat().st_size for p in bag.rglob("*") if p.is_file())
    record = {"laps": laps, "seed": seed, "frames": len(drive), "messages": counts,
              "bytes": size, "record_s": record_s}
    done.write_text(json.dumps(record, indent=1))
    print(f"replay.py: recorded {len(drive)} frames in {record_s:.0f} s", file=sys.stderr)
    return bag, {**record, "cached": False}


# --- the replay (child process) --------------------------------------------------------------


def replay_child(bag: Path, output: Path, result: Path) -> int:
    """Replay ``bag`` into ``output``; write the summary and this process's RSS to ``result``."""
    start = time.perf_counter()
    from h2o_slam.app.cli.demo import WORLD_DATUM
    from h2o_slam.app.replay import ReplayOptions, replay

    imported_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    imports_s = time.perf_counter() - start
    summary = replay(ReplayOptions(bag=bag, output=output, h2o_params={"datum": WORLD_DATUM},
                                   progress=False))
    result.write_text(json.dumps({"summary": summary, "rss_after_imports_kb": imported_kb,
                                  "imports_s": imports_s,
                                  "child_s": time.perf_counter() - start}, default=str))
    return 0


def run_replay(bag: Path, out_dir: Path) -> dict[str, Any]:
    """Replay in a fresh child process; returns its result plus ``peak_rss_kb`` and
    ``process_s`` (from spawn to exit), or ``{"error": ...}``."""
    output, result = out_dir / "replay_output", out_dir / "replay_result.json"
    shutil.rmtree(output, ignore_errors=True)
    result.unlink(missing_ok=True)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--role", "replay", "--bag",
           str(bag), "--replay-output", str(output), "--result", str(result)]
    load = os.getloadavg()[0]
    start = time.perf_counter()
    with (out_dir / "replay_child.log").open("w") as log:
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    process_s = time.perf_counter() - start
    if proc.returncode != 0 or not result.exists():
        return {"error": f"replay exited with {proc.returncode} (log: "
                         f"{out_dir / 'replay_child.log'})"}
    data = json.loads(result.read_text())
    # ru_maxrss is in KiB on Linux.
    return {**data, "peak_rss_kb": usage.ru_maxrss, "process_s": process_s,
            "load": (load, os.getloadavg()[0])}


# --- report ------------------------------------------------------------------------------------


def _callbacks(stats: dict[str, float] | None) -> tuple[str, float]:
    """``"mean / p99 / max (count)"`` and the total seconds of a callback summary."""
    if not stats:
        return "—", 0.0
    text = (f"{stats['mean']:.2f} / {stats['p99']:.2f} / {stats['max']:.1f} "
            f"({stats['count']})")
    return text, stats["mean"] * stats["count"] * 1e-3


def format_table(record: dict[str, Any], res: dict[str, Any]) -> str:
    """The Markdown table of one replay."""
    head = ["bag s", "frames", "bag MB", "record s", "replay wall s", "× real time",
            "child process s", "peak RSS MB", "RSS after imports MB",
            "VO image ms mean / p99 / max (n)", "H₂O ms mean / p99 / max (n)",
            "VO / H₂O / rest s", "load 1-min"]
    s = res["summary"]
    vo_text, vo_s = _callbacks(s.get("vo_callback_ms"))
    h2o_text, h2o_s = _callbacks(s.get("h2o_callback_ms"))
    wall = float(s["wall_time_s"])
    rec = f"{record['record_s']:.0f}" + (" (cached)" if record.get("cached") else "")
    row = [f"{s['bag_duration_s']:.0f}", str(record["frames"]), f"{record['bytes'] / 1e6:.0f}",
           rec, f"{wall:.1f}", f"{s['speed_x_realtime']:.1f}", f"{res['process_s']:.1f}",
           f"{res['peak_rss_kb'] / 1024:.0f}", f"{res['rss_after_imports_kb'] / 1024:.0f}",
           vo_text, h2o_text, f"{vo_s:.1f} / {h2o_s:.1f} / {wall - vo_s - h2o_s:.1f}",
           f"{res['load'][0]:.2f} → {res['load'][1]:.2f}"]
    return "\n".join(["| " + " | ".join(head) + " |", "|" + " --- |" * len(head),
                      "| " + " | ".join(row) + " |"])


def verdict(res: dict[str, Any]) -> str:
    """The target of issue 7, judged."""
    x = float(res["summary"]["speed_x_realtime"])
    met = "met" if x >= TARGET_X_REALTIME else "NOT met"
    return (f"Target (issue 7): replay ≥ {TARGET_X_REALTIME:g}× real time: {met} ({x:.1f}×); "
            f"peak RSS {res['peak_rss_kb'] / 1024:.0f} MB (no target).")


NOTES = """\
Notes:

- Drive: `h2o-demo`'s (`h2o_slam.app.cli.demo.demo_drive(seed, laps)`: the slip square,
  36 s a lap, stereo 160×120 at 10 Hz, wheel odometry at the frame rate with slip and
  hallucinated turns, GPS σ 5 cm at 1 Hz with NO_FIX dropouts, loop closures, ground
  truth), written by `h2o_slam.io.bag_writer.write_bag(drive_messages(drive))` as MCAP. "record
  s" is simulating, rendering and writing it, done once and cached under `--output-dir`.
- Replay: `h2o_slam.app.replay.replay(ReplayOptions(bag, output, h2o_params={"datum": …}))` —
  `h2o-replay`'s defaults: hybrid VO odometry into h2o_node, `budget_ms` 0 (every edge in
  full, deterministic), all outputs (MCAP of the outputs, TUM, g2o, plots, summary) — in a
  fresh child process. "replay wall s" and "× real time" are the summary's `wall_time_s`
  and `speed_x_realtime` (bag duration / wall time from opening the bag to the end of the
  last message, before the output files are written); "child process s" is spawn to exit
  (imports, replay, writing the outputs).
- Memory: peak RSS is the child's `ru_maxrss` from `os.wait4` (everything it ever had
  resident: Python, numpy, OpenCV, rclpy, matplotlib and the replay); "RSS after imports"
  is its `ru_maxrss` before the replay starts.
- Breakdown: VO is the summed time of hybrid_vo_node's image callbacks, H₂O the summed
  time of h2o_node's input callbacks (the summary's `vo_callback_ms` and
  `h2o_callback_ms`); the rest is reading and deserializing the bag, camera info, periodic
  outputs (graph, map→odom, diagnostics) and writing the output bag.
"""


def render_section(record: dict[str, Any], res: dict[str, Any], laps: int, seed: int) -> str:
    """The ``## Replay`` section of RESULTS.md."""
    when = dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    machine = (f"{platform.machine()}, nproc {os.cpu_count()}, Python "
               f"{platform.python_version()}, repo at {revision(REPO)}")
    caption = (f"One replay of {laps} laps of the demo drive (seed {seed}) with images, in a "
               "child process; load average (1 min) before → after the replay in the last "
               "column, on 2 cores.")
    return (f"{SECTION}\n\nCommand (from the repo root): `{command(REPO)}`\n\n"
            f"Date: {when}. Machine: {machine}; shared with other work, timings "
            f"indicative.\n\n{caption}\n\n{format_table(record, res)}\n\n{verdict(res)}\n\n"
            f"{NOTES}")


# --- entry point -------------------------------------------------------------------------------


def run(laps: int, seed: int, out_dir: Path, results: Path | None) -> int:
    """Record (or reuse) the bag, replay it, print and write the section."""
    out_dir.mkdir(parents=True, exist_ok=True)
    bag, record = record_bag(out_dir, laps, seed)
    print(f"replay.py: replaying {bag} (load {os.getloadavg()[0]:.2f}) ...", file=sys.stderr,
          flush=True)
    res = run_replay(bag, out_dir)
    if "error" in res:
        print(f"replay.py: {res['error']}", file=sys.stderr)
        return 1
    section = render_section(record, res, laps, seed)
    print(section)
    if results is not None:
        replace_section(results, SECTION, section)
        print(f"written to {results}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse arguments; run the benchmark or its replay child."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--laps", type=int, default=DEFAULT_LAPS,
                        help=f"laps of the 36 s demo square (default {DEFAULT_LAPS}, "
                        f"{DEFAULT_LAPS * LAP_S:.0f} s)")
    parser.add_argument("--seed", type=int, default=1, help="seed of the drive (default 1)")
    parser.add_argument("--output-dir", type=Path, default=DEFAULT_OUTPUT,
                        help="the cached bag and the replay's outputs (default "
                        f"{DEFAULT_OUTPUT})")
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS,
                        help=f"markdown file to update (default {DEFAULT_RESULTS})")
    parser.add_argument("--no-results", action="store_true", help="only print the table")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 1 lap (36 s); prints, writes nothing")
    parser.add_argument("--role", choices=("replay",), help=argparse.SUPPRESS)
    parser.add_argument("--bag", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--replay-output", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.role == "replay":
        return replay_child(args.bag, args.replay_output, args.result)
    if args.laps < 1:
        parser.error("--laps must be >= 1")
    if args.quick:
        args.laps, args.no_results = 1, True
    results = None if args.no_results else args.results
    return run(args.laps, args.seed, args.output_dir, results)


if __name__ == "__main__":
    sys.exit(main())
