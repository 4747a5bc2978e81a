"""``scg-jax reproduce``: the paper's results (``scg_experiments``): data, plots and a report of every claim."""

from __future__ import annotations

import argparse
from pathlib import Path

from scg_cli.common import UsageError, check_output, positive_int
from scg_cli.progress import add_progress_argument, console_progress


def add_reproduce_parser(subparsers) -> argparse.ArgumentParser:
    from scg_experiments import RESULTS
    from scg_experiments.common import PROFILES

    parser = subparsers.add_parser(
        "reproduce",
        help="reproduce the paper's results: train what is needed, evaluate, write data, plots and report.md",
        description=(
            "Run the named results (all when none is named): " + ", ".join(RESULTS) + ". Trained policies and GPs "
            "are cached in DIR/cache by a hash of their config, so a rerun only evaluates. Each result writes its "
            "data (CSV/JSON) and a PNG to DIR/NAME; DIR/report.md lists every claim of the paper with the measured "
            "numbers and holds / does not hold / method not available, and each result's wall time."
        ),
    )
    parser.add_argument("names", nargs="*", metavar="NAME", help=f"results to run ({', '.join(RESULTS)}; default all)")
    parser.add_argument(
        "--profile",
        choices=PROFILES,
        default="quick",
        help="budgets: quick (everything in about 15 min on 2 CPU cores), paper (the paper's budgets), tiny (tests)",
    )
    parser.add_argument("--seeds", type=positive_int, default=None, help="seeds (default: 1, paper profile 3)")
    parser.add_argument("--out", type=Path, default=Path("results/reproduce"), metavar="DIR", help="output folder")
    add_progress_argument(parser)
    return parser


def run_reproduce(args: argparse.Namespace, console) -> int:
    from scg_experiments import RESULTS, reproduce

    unknown = [name for name in args.names if name not in RESULTS]
    if unknown:
        raise UsageError(f"argument NAME: unknown result {unknown[0]!r}; allowed values are {', '.join(RESULTS)}")
    check_output(args.out, "dir")
    seeds = args.seeds if args.seeds is not None else (3 if args.profile == "paper" else 1)
    reproduce(args.names, args.out, args.profile, seeds, console_progress(console, args.progress_interval))
    console.print(f"wrote {args.out}/report.md")
    return 0
