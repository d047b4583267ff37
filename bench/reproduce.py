"""Re-run the seeds' tables and figures beside today's peers; writes bench/REPRODUCTION.md.

    .venv/bin/python bench/reproduce.py            # everything (an hour or more)
    .venv/bin/python bench/reproduce.py --quick    # a few-minute subset
    .venv/bin/python bench/reproduce.py --only thesis_energy carlone_table1

The public pose graphs come from ``--data DIR`` (default ``$H2O_POSEGRAPHS``; without either,
an experiment that reads them is not run and the script exits 2), the KITTI stereo clip of
``hybrid_vo`` from ``--kitti DIR`` (left out without it); ``bench/README.md`` says where
both come from.

Each experiment lives in ``bench/repro/<name>.py`` (see ``bench/repro/__init__.py``); a
section whose module is missing or fails is written as such, and the others still run.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import platform
import sys
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from repro.context import Context  # noqa: E402
from results_md import command, default_data, no_data, replace_section, revision  # noqa: E402

#: In the order of issue 15's list.
EXPERIMENTS = ("thesis_energy", "thesis_dmax", "thesis_noise", "hybrid_vo", "carlone_table1",
               "hybrid_hessians")
#: The experiments that run without the public pose graphs.
WITHOUT_GRAPHS = ("hybrid_vo",)


def run_one(name: str, ctx: Context) -> tuple[str, str]:
    """``(heading, body)`` of one experiment; a failure becomes its section's text."""
    try:
        module = importlib.import_module(f"repro.{name}")
    except ModuleNotFoundError as exc:
        if exc.name != f"repro.{name}":
            raise
        return f"## {name}", f"Not written yet (no `bench/repro/{name}.py`).\n"
    begin = time.perf_counter()
    try:
        body = module.run(ctx)
    except Exception:  # one broken experiment must not lose the others' results
        body = "Failed:\n\n```\n" + traceback.format_exc() + "```\n"
    elapsed = time.perf_counter() - begin
    subset = " (quick subset)" if ctx.quick else ""
    return f"## {module.TITLE}", (f"{body.rstrip()}\n\n_Ran in {elapsed:.0f} s{subset}, {_now()}, "
                                  f"repo at {revision(REPO)}: `{command(REPO)}`._\n")


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")


def header() -> str:
    return (
        "# Reproducing the seeds\n\n"
        "Written by `bench/reproduce.py` (`--quick` for a few-minute subset, `--only NAME` "
        "to re-run one experiment); each section ends with when, at which revision and by "
        f"which command it was made. Machine: {platform.machine()}, "
        f"Python {platform.python_version()}. The public pose graphs are read from "
        "`--data DIR` or `$H2O_POSEGRAPHS`, the KITTI clip from `--kitti DIR` "
        "(`bench/README.md` says where they come from).\n\n"
        "Each section: the seed's numbers and ours side by side, the protocol differences, "
        "figures, and a verdict.\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few-minute subset")
    parser.add_argument("--only", nargs="+", choices=EXPERIMENTS, metavar="NAME",
                        help=f"run these experiments only ({', '.join(EXPERIMENTS)})")
    parser.add_argument("--data", type=Path, default=default_data(), metavar="DIR",
                        help="folder of the public pose graphs as .g2o files (default: "
                        "$H2O_POSEGRAPHS; see bench/README.md)")
    parser.add_argument("--kitti", type=Path, default=None, metavar="DIR",
                        help="a KITTI odometry stereo sequence for hybrid_vo (calib.txt, "
                        "poses.txt and the image pairs; left out without it)")
    parser.add_argument("--output", type=Path, default=REPO / "bench/REPRODUCTION.md",
                        help="markdown written (sections of experiments not run are kept)")
    args = parser.parse_args(argv)
    if args.data is None and set(args.only or EXPERIMENTS) - set(WITHOUT_GRAPHS):
        return no_data("reproduce.py")
    plots = args.output.parent / "repro_plots"
    plots.mkdir(parents=True, exist_ok=True)
    ctx = Context(quick=args.quick, data=args.data, plots=plots, repo=REPO, kitti=args.kitti)
    if not args.output.exists() or args.only is None:
        args.output.write_text(header())
    for name in args.only or EXPERIMENTS:
        heading, body = run_one(name, ctx)
        replace_section(args.output, heading, f"{heading}\n\n{body}")
        print(f"{heading[3:]}: done", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
