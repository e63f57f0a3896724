"""The ``twomass`` console command: one subcommand per module, looked up in a dict.

Each subcommand lives in its own module (``training/commands/<name>.py``) that defines

    HELP: str                                # one line for ``twomass --help``
    def add_arguments(parser) -> None        # its argparse options
    def run(args) -> int                     # the work; returns the exit code

The modules import torch, numpy and the rooms inside ``run``, so that ``twomass --help`` stays fast.

Errors: the library raises its domain exceptions (:mod:`training.errors`, ``sim.RecordError``,
``som_torch.CheckpointError``: all ``ValueError``) and ``OSError``; :func:`main` alone turns them
into ``twomass <command>: error: <one line>`` on stderr and exit code 2. Anything else (a
``TypeError`` from a bug, an ``ImportError`` of a command module) is a traceback. Ctrl-C prints one
line and exits with 130, also during start-up.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from training.config import apply_process_defaults
from training.errors import one_line

COMMANDS: dict[str, str] = {
    "simulate": "training.commands.simulate",
    "identify": "training.commands.identify",
    "generate": "training.commands.generate",
    "train": "training.commands.train",
    "evaluate": "training.commands.evaluate",
    "commission": "training.commands.commission",
    "bench": "training.commands.bench",
    "demo": "training.commands.demo",
    "inspect": "training.commands.inspect",
}

#: Exit codes of :func:`main` besides a command's own: bad input, and Ctrl-C (128 + SIGINT).
EXIT_USAGE, EXIT_INTERRUPTED = 2, 130


def _command_modules() -> dict[str, ModuleType]:
    """Every module of :data:`COMMANDS`; one that fails to import raises (never dropped from ``--help``)."""
    return {name: importlib.import_module(path) for name, path in COMMANDS.items()}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twomass",
        description="Identify two-mass drive mechanics from one test run with self-organizing maps.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in _command_modules().items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def _run_command(args: argparse.Namespace) -> int:
    """The command's exit code; its domain and file errors as one line and :data:`EXIT_USAGE`."""
    try:
        return int(args._run(args) or 0)
    except (ValueError, OSError) as err:  # a TypeError is a bug: it stays a traceback
        print(f"twomass {args.command}: error: {one_line(err)}", file=sys.stderr)
        return EXIT_USAGE


def main(argv: Sequence[str] | None = None) -> int:
    prog = "twomass"
    try:  # all of it: Ctrl-C while torch loads is an interruption too
        apply_process_defaults()  # before the commands import numpy and torch
        parser = build_parser()
        args = parser.parse_args(argv)
        if getattr(args, "_run", None) is None:
            parser.print_help()
            return EXIT_USAGE
        prog = f"twomass {args.command}"
        return _run_command(args)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
