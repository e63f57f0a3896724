"""``twomass bench TARGET``: performance figures; the targets live in :mod:`training.bench`."""

from __future__ import annotations

import argparse

from training.bench import TARGETS, run_target

HELP = f"performance figures (targets: {', '.join(sorted(TARGETS))}; `twomass bench TARGET --help` for each)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    targets = ", ".join(sorted(TARGETS))
    parser.add_argument("target", nargs="?", metavar="TARGET",
                        help=f"what to measure, one of: {targets} (commission: the delivered speed loop's true crossover "
                             "against the largest the true plant allows, population plants on an independent plant; sim: C kernel vs vectorized numpy RK4; som: "
                             "som_torch vs MiniSom/XPySom with QE and TE; identify: `twomass identify` on 1 and N "
                             "records; train: `twomass generate` + `train` of N systems; wall, CPU, peak memory)")
    parser.add_argument("target_args", nargs=argparse.REMAINDER, metavar="...",
                        help="the target's own options; `twomass bench TARGET --help` lists them")


def run(args: argparse.Namespace) -> int:
    return run_target(args.target, args.target_args)
