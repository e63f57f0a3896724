"""``twomass bench TARGET``: performance figures; the targets live in :mod:`training.bench`."""

from __future__ import annotations

import argparse

from training.bench import TARGETS, run_target

HELP = f"performance figures (targets: {', '.join(sorted(TARGETS))}; `twomass bench TARGET --help` for each)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    targets = ", ".join(sorted(TARGETS))
    parser.add_argument("target", nargs="?", metavar="TARGET",
                        help=f"what to measure, one of: {targets} (sim: simulator throughput; som: SOM training "
                             "against MiniSom; identify: wall time of `twomass identify` on N records)")
    parser.add_argument("target_args", nargs=argparse.REMAINDER, metavar="...",
                        help="the target's own options; `twomass bench TARGET --help` lists them")


def run(args: argparse.Namespace) -> int:
    return run_target(args.target, args.target_args)
