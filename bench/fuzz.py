"""Fuzz campaign: both nodes fed hostile input through every callback, timer and service.

    .venv/bin/python bench/fuzz.py --examples N [--nodes h2o vo] [--seed S]
                                   [--results FILE | --no-results]

The strategies and the driver are those of ``test/test_fuzz_nodes.py``
(``test/node_fuzz.py``); CI runs a few dozen examples, this runs as many as asked. Per
node, ``N`` hypothesis examples (sequences of 1–40 operations each: messages, timer ticks,
service calls) each against a fresh node; every operation is one input. A run counts the
exceptions that escaped a callback, non-finite values published or held, and rejections
the nodes' boundary counted as *unexpected* (a bug caught rather than bad input refused);
the target is zero of each. The table also says how deep the inputs reached (keyframes,
accepted loop closures and fixes, frames tracked by vision) and replaces the section
``## Fuzz (bench/fuzz.py)`` of ``bench/RESULTS.md``. DDS is not used (callbacks are called
as the executor would), so the loopback profile is only needed for ``rclpy.init``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import platform
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "test"))
sys.path.insert(0, str(REPO / "bench"))

import rclpy  # noqa: E402
from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from hypothesis import seed as hypothesis_seed  # noqa: E402
from node_fuzz import (  # noqa: E402
    H2O_OPS,
    VO_OPS,
    NodeDriver,
    Outcome,
    make_h2o_node,
    make_vo_node,
    run_h2o,
    run_vo,
)
from rclpy.context import Context  # noqa: E402
from results_md import command, replace_section, revision  # noqa: E402

DEFAULT_RESULTS = REPO / "bench" / "RESULTS.md"
SECTION = "## Fuzz (bench/fuzz.py)"


@dataclass
class Campaign:
    """One node's campaign: the merged outcome, depth reached, failing examples, time."""

    node: str
    examples: int = 0
    outcome: Outcome = field(default_factory=Outcome)
    depth: Counter[str] = field(default_factory=Counter)
    rejected: int = 0
    failures: list[str] = field(default_factory=list)
    wall_s: float = 0.0


def run_campaign(node_kind: str, examples: int, seed: int, context: Context,
                 map_dir: Path) -> Campaign:
    """Run ``examples`` hypothesis examples against fresh nodes of one kind."""
    campaign = Campaign(node_kind)
    strategy = H2O_OPS if node_kind == "h2o" else VO_OPS

    @hypothesis_seed(seed)
    # Generation only: a failure is recorded with its input, not shrunk (which would take
    # longer than the campaign).
    @settings(max_examples=examples, deadline=None, database=None, phases=[Phase.generate],
              suppress_health_check=list(HealthCheck))
    @given(ops=strategy)
    def one(ops: list[tuple[Any, ...]]) -> None:
        node = make_h2o_node(context, map_dir) if node_kind == "h2o" else make_vo_node(context)
        try:
            driver = NodeDriver(node)
            if node_kind == "h2o":
                run_h2o(driver, ops)
                mapper = node.mapper
                campaign.depth.update({"keyframes": mapper.num_nodes,
                                       "loop closures accepted": mapper.accepted["loop_closure"],
                                       "fixes accepted": mapper.accepted["gps"]})
                campaign.rejected += sum((node.rejected + mapper.rejected).values())
            else:
                run_vo(driver, ops)
                stats = node.frontend.stats
                campaign.depth.update({"frames": stats.frames,
                                       "frames tracked by vision": stats.vision_frames,
                                       "calibrations": stats.calibrations})
                campaign.rejected += sum(stats.rejected.values())
        finally:
            node.destroy_node()
        out = driver.outcome
        if (out.escaped or out.non_finite or out.unexpected) and len(campaign.failures) < 5:
            campaign.failures.append(
                f"{out.escaped[:1]} {out.non_finite[:1]} {dict(out.unexpected)} <- "
                f"{repr(ops)[:400]}")
        campaign.outcome.merge(out)
        campaign.examples += 1
        if campaign.examples % 100 == 0:
            print(f"{node_kind}: {campaign.examples} examples, {campaign.outcome.inputs} inputs",
                  file=sys.stderr)

    start = time.perf_counter()
    one()
    campaign.wall_s = time.perf_counter() - start
    return campaign


def table(campaigns: list[Campaign]) -> str:
    """The results as a markdown table."""
    rows = ["| node | examples | inputs | escaped | non-finite published/held | unexpected "
            "| rejected (by reason) | published | depth reached | wall s |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for c in campaigns:
        out = c.outcome
        depth = ", ".join(f"{k} {v}" for k, v in c.depth.items())
        rows.append(f"| {c.node} | {c.examples} | {out.inputs} | {len(out.escaped)} | "
                    f"{len(out.non_finite)} | {sum(out.unexpected.values())} | {c.rejected} | "
                    f"{out.published} | {depth} | {c.wall_s:.0f} |")
    return "\n".join(rows)


def section(campaigns: list[Campaign], seed: int) -> str:
    """The ``## Fuzz`` section of RESULTS.md."""
    lines = [
        SECTION, "",
        f"`{command(REPO)}` — {dt.date.today().isoformat()}, revision {revision(REPO)}, "
        f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, "
        f"hypothesis seed {seed}.", "",
        "Each example is a fresh node fed 1–40 operations (messages on every subscription, "
        "timer ticks, service calls and, for h2o_node, parameter changes), nine in ten values "
        "those of a driving robot and one in ten hostile (NaN, ±inf, 1e200, ±1.7e308, "
        "subnormals, the 1e8 m bound and just beyond, malformed strings, sizes and image "
        "headers, 32000² PNGs). Escaped: exceptions out of a callback (each would have ended "
        "the node). Non-finite: NaN/inf in any float of any published message, or in the "
        "poses, track and keyframes the node holds, checked after every input. Unexpected: "
        "rejections the boundary counted as `unexpected <Type>` (bugs, not bad input). "
        "Target: zero in all three.", "",
        table(campaigns), "",
    ]
    for c in campaigns:
        for failure in c.failures:
            lines.append(f"- {c.node} failure: `{failure}`")
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the campaigns, print the table, write the section."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=200,
                        help="hypothesis examples per node (each 1-40 inputs)")
    parser.add_argument("--nodes", nargs="+", choices=["h2o", "vo"], default=["h2o", "vo"])
    parser.add_argument("--seed", type=int, default=13)
    parser.add_argument("--results", type=Path, default=DEFAULT_RESULTS)
    parser.add_argument("--no-results", action="store_true",
                        help="print the table only; RESULTS.md is left alone")
    args = parser.parse_args(argv)
    if args.examples < 1:
        parser.error("--examples must be >= 1")
    context = Context()
    rclpy.init(context=context)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            campaigns = [run_campaign(kind, args.examples, args.seed, context, Path(tmp))
                         for kind in args.nodes]
    finally:
        rclpy.shutdown(context=context)
    print(table(campaigns))
    for c in campaigns:
        for failure in c.failures:
            print(f"{c.node} failure: {failure}", file=sys.stderr)
    if not args.no_results:
        replace_section(args.results, SECTION, section(campaigns, args.seed))
        print(f"wrote {SECTION!r} to {args.results}", file=sys.stderr)
    bad = any(c.outcome.escaped or c.outcome.non_finite or c.outcome.unexpected
              for c in campaigns)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
