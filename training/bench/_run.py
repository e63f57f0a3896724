"""Running one ``twomass bench`` target by name, with its own options."""

from __future__ import annotations

import argparse
import importlib
import shlex
from collections.abc import Sequence

from training.errors import UserError

#: target name -> module (imported only when the target runs)
TARGETS: dict[str, str] = {
    "commission": "training.bench._commission",
    "identify": "training.bench._identify",
    "sim": "training.bench._sim",
    "som": "training.bench._som",
    "train": "training.bench._train",
}


def run_target(target: str | None, argv: Sequence[str]) -> int:
    """Parse ``argv`` with the options of ``target`` (one of :data:`TARGETS`) and run it; its exit code."""
    valid = ", ".join(sorted(TARGETS))
    if target is None:
        raise UserError(f"no bench target given; valid targets: {valid}")
    if target not in TARGETS:
        raise UserError(f"unknown bench target '{target}'; valid targets: {valid}")
    module = importlib.import_module(TARGETS[target])
    parser = argparse.ArgumentParser(prog=f"twomass bench {target}", description=module.HELP)
    module.add_arguments(parser)
    args = parser.parse_args(list(argv))
    args.command_line = shlex.join(["twomass", "bench", target, *argv])  # printed by the target: reproduces it
    return int(module.run(args) or 0)
