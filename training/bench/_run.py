"""Running one ``twomass bench`` target by name, with its own options."""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from training._json import dumps
from training.errors import UserError

#: target name -> module (imported only when the target runs)
TARGETS: dict[str, str] = {
    "identify": "training.bench._identify",
    "sim": "training.bench._sim",
    "som": "training.bench._som",
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
    return int(module.run(parser.parse_args(list(argv))) or 0)


def write_figures(path: str | Path, figures: Mapping[str, Any]) -> None:
    """A target's figures as JSON at ``path`` (atomically)."""
    from som_torch import atomic_write  # here: `twomass --help` lists the targets without torch

    text = dumps(figures, indent=1)
    atomic_write(path, lambda f: f.write(text), text=True)
