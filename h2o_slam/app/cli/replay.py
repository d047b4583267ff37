"""``h2o-replay``: replay a recording through both nodes in-process, or publish it.

    h2o-replay BAG --output DIR [--topics FILE] [--topic ROLE=TOPIC ...]
               [--odometry auto|hybrid|wheel] [--budget-ms X] [--no-gps]
               [--storage mcap|sqlite3] [--graph-period S] [--quiet] [--salvage]
    h2o-replay BAG --realtime [--rate R] [--delay S] [--topics FILE] [--topic ROLE=TOPIC ...]

The work is :mod:`h2o_slam.app.replay`; this module parses arguments, prints, and maps errors to
one line and a non-zero exit code (2: the command line, an output folder that cannot be
used; 1: the bag, the topic map or an incomplete replay; see :mod:`h2o_slam.app.cli.common`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from h2o_slam.app.cli.common import (
    EXIT_INPUT,
    OneLineParser,
    missing_folders,
    number,
    remove_if_empty,
    unusable_folder,
    usage_error,
)
from h2o_slam.app.replay import ReplayOptions, format_summary, publish_realtime, replay
from h2o_slam.core.errors import H2OError
from h2o_slam.io.bag_reader import bag_problem
from h2o_slam.io.topic_map import topic_map
from h2o_slam.ros.node_config import H2ONodeConfig
from ros_node_base.params import spec_named

PROG = "h2o-replay"


def _node_range(parameter: str) -> tuple[float, float]:
    spec = spec_named(H2ONodeConfig, parameter)
    assert spec.low is not None and spec.high is not None
    return spec.low, spec.high


#: The node's own range of ``budget_ms``: a replay accepts what a robot would.
BUDGET_RANGE_MS = _node_range("budget_ms")


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = OneLineParser(prog=PROG, description=(
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
    p.add_argument("--budget-ms", type=number(*BUDGET_RANGE_MS), default=None,
                   help="h2o_node's per-callback budget in ms as on a robot, "
                        f"{BUDGET_RANGE_MS[0]:g} to {BUDGET_RANGE_MS[1]:g} (outputs then "
                        "depend on timing); default or 0: every edge solved in full, "
                        "deterministic")
    p.add_argument("--no-gps", action="store_true", help="do not feed GPS to the back end")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="storage plugin of the output bag in DIR/outputs (default: mcap)")
    p.add_argument("--graph-period", type=number(0.0, 1e6, low_open=True), default=10.0,
                   help="bag seconds between graph outputs and chi2 samples")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.add_argument("--salvage", action="store_true",
                   help="accept a partial replay (a damaged bag, fewer messages than the bag "
                        "declares, an empty graph): warnings on stderr, exit 0")
    p.add_argument("--verbose", action="store_true",
                   help="the nodes log every rejected message (the summary counts them)")
    p.add_argument("--realtime", action="store_true",
                   help="publish the bag's mapped topics on the ROS graph at the recorded "
                        "pace instead (for external nodes); no outputs are written")
    p.add_argument("--rate", type=number(0.0, 1e6, low_open=True), default=1.0,
                   help="--realtime speed factor")
    p.add_argument("--delay", type=number(0.0, 3600.0), default=1.0,
                   help="--realtime: seconds between creating the publishers and the first "
                        "message, for subscribers to match them")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    cli = parser()
    args = cli.parse_args(argv)
    if not args.realtime:
        if args.output is None:
            cli.error("--output is required (or --realtime)")
        problem = unusable_folder("--output", args.output)
        if problem is not None:
            return usage_error(PROG, problem)
    problem = bag_problem(args.bag)
    if problem is not None:
        print(f"{PROG}: {problem}", file=sys.stderr)
        return EXIT_INPUT
    created = [] if args.realtime else missing_folders(args.output)
    try:
        topics = topic_map(args.topics, args.topic)
        if args.realtime:
            return publish_realtime(args.bag, topics, args.rate, args.delay)
        options = ReplayOptions(
            bag=args.bag, output=args.output, topics=topics, odometry=args.odometry,
            budget_ms=args.budget_ms or None, use_gps=not args.no_gps, storage=args.storage,
            graph_period_s=args.graph_period, progress=not args.quiet, verbose=args.verbose,
            salvage=args.salvage)
        summary = replay(options)
    except (H2OError, OSError) as exc:
        remove_if_empty(created)
        where = ""
        if args.output is not None and (args.output / "summary.json").exists():
            where = f" [outputs and summary.json in {args.output}]"
        print(f"{PROG}: {exc}{where}", file=sys.stderr)
        return EXIT_INPUT
    for problem in summary.get("problems", []):
        print(f"{PROG}: warning: {args.bag}: {problem} (accepted by --salvage)",
              file=sys.stderr)
    if not args.quiet:
        print(format_summary(summary))
        print(f"outputs in {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
