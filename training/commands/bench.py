"""``twomass bench TARGET``: performance figures; the targets live in :mod:`training.bench`."""

from __future__ import annotations

import argparse
import importlib

from training.bench import TARGETS
from training.errors import UserError

HELP = f"performance figures (targets: {', '.join(sorted(TARGETS))})"



def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("target", nargs="?", help=f"one of: {', '.join(sorted(TARGETS))}")
    parser.add_argument("target_args", nargs=argparse.REMAINDER, help="options of the target (see TARGET --help)")


def run(args: argparse.Namespace) -> int:
    valid = ", ".join(sorted(TARGETS))
    if args.target is None:
        raise UserError(f"no bench target given; valid targets: {valid}")
    if args.target not in TARGETS:
        raise UserError(f"unknown bench target '{args.target}'; valid targets: {valid}")
    module = importlib.import_module(TARGETS[args.target])
    sub = argparse.ArgumentParser(prog=f"twomass bench {args.target}", description=getattr(module, "HELP", None))
    module.add_arguments(sub)
    return int(module.run(sub.parse_args(args.target_args)) or 0)
