"""``h2o-replay``: replay a recording through both nodes in-process, or publish it.

    h2o-replay BAG --output DIR [--topics FILE] [--topic ROLE=TOPIC ...]
               [--odometry auto|hybrid|wheel] [--budget-ms X] [--no-gps]
               [--storage mcap|sqlite3] [--graph-period S] [--quiet]
    h2o-replay BAG --realtime [--rate R] [--delay S] [--topics FILE] [--topic ROLE=TOPIC ...]

The work is :mod:`h2o_slam.replay`; this module parses arguments, prints, and maps errors to
one line and a non-zero exit code (1: the bag or the output, 2: the command line).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from h2o_slam.errors import H2OError
from h2o_slam.replay import ReplayOptions, format_summary, publish_realtime, replay
from h2o_slam.replay_io import ReplayError, topic_map

PROG = "h2o-replay"


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(prog=PROG, description=(
        "Replay a rosbag2 (sqlite3 or mcap) or ROS 1 bag through hybrid_vo_node and h2o_node "
        "in-process, in bag-time order, and write their outputs, TUM trajectories, the graph, "
        "plots and a summary."))
    p.add_argument("bag", type=Path, help="rosbag2 folder, .mcap/.db3 file or ROS 1 .bag")
    p.add_argument("--output", type=Path, help="folder for the outputs (new or empty)")
    p.add_argument("--topics", type=Path, help="YAML topic map (see config/replay_topics.yaml)")
    p.add_argument("--topic", action="append", default=[], metavar="ROLE=TOPIC",
                   help="map one role to a topic (repeatable; ROLE= turns a role off)")
    p.add_argument("--odometry", choices=("auto", "hybrid", "wheel"), default="auto",
                   help="back-end odometry: hybrid VO (needs images), wheel, or auto")
    p.add_argument("--budget-ms", type=float, default=None,
                   help="h2o_node's per-callback budget as on a robot (outputs then depend "
                        "on timing); default: every edge solved in full, deterministic")
    p.add_argument("--no-gps", action="store_true", help="do not feed GPS to the back end")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="storage of the output bag")
    p.add_argument("--graph-period", type=float, default=10.0,
                   help="bag seconds between graph outputs and chi2 samples")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.add_argument("--verbose", action="store_true",
                   help="the nodes log every rejected message (the summary counts them)")
    p.add_argument("--realtime", action="store_true",
                   help="publish the bag's mapped topics on the ROS graph at the recorded "
                        "pace instead (for external nodes); no outputs are written")
    p.add_argument("--rate", type=float, default=1.0, help="--realtime speed factor")
    p.add_argument("--delay", type=float, default=1.0,
                   help="--realtime: seconds between creating the publishers and the first "
                        "message, for subscribers to match them")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = parser().parse_args(argv)
    try:
        topics = topic_map(args.topics, args.topic)
        if args.realtime:
            return publish_realtime(args.bag, topics, args.rate, args.delay)
        if args.output is None:
            parser().error("--output is required (or --realtime)")
        options = ReplayOptions(
            bag=args.bag, output=args.output, topics=topics, odometry=args.odometry,
            budget_ms=args.budget_ms, use_gps=not args.no_gps, storage=args.storage,
            graph_period_s=args.graph_period, progress=not args.quiet, verbose=args.verbose)
        summary = replay(options)
    except (H2OError, OSError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        if isinstance(exc, ReplayError) and args.output is not None and \
                (args.output / "summary.json").exists():
            print(f"{PROG}: what was replayed before the error is in {args.output}",
                  file=sys.stderr)
        return 1
    if not args.quiet:
        print(format_summary(summary))
        print(f"outputs in {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
