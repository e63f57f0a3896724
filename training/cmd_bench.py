"""``twomass bench TARGET``: performance figures; each target is a module ``training.bench_<name>``."""

from __future__ import annotations

import argparse
import importlib

from training.errors import UserError

HELP = "performance figures (targets: see TARGETS)"

# target name -> module exposing add_arguments(parser) and run(args) -> int. Add new ones here.
TARGETS: dict[str, str] = {
    "identify": "training.bench_identify",
    "sim": "training.bench_sim",
    "som": "training.bench_som",
}


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
