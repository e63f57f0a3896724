"""``twomass bench TARGET``: performance figures; the targets live in :mod:`training.bench`."""

from __future__ import annotations

import argparse

from training.bench import TARGETS, run_target

HELP = f"performance figures (targets: {', '.join(sorted(TARGETS))})"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("target", nargs="?", help=f"one of: {', '.join(sorted(TARGETS))}")
    parser.add_argument("target_args", nargs=argparse.REMAINDER, help="options of the target (see TARGET --help)")


def run(args: argparse.Namespace) -> int:
    return run_target(args.target, args.target_args)
