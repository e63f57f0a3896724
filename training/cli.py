"""The ``twomass`` console command: one subcommand per module, looked up in a dict.

Each subcommand lives in its own module (``training/cmd_<name>.py``) that defines

    HELP: str                                # one line for ``twomass --help``
    def add_arguments(parser) -> None        # its argparse options
    def run(args) -> int                     # the work; returns the exit code

Bad input raises :class:`training.errors.UserError` (or ``ValueError``/``OSError`` from the
library); :func:`main` turns it into a one-line message on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from training.errors import UserError

COMMANDS: dict[str, str] = {
    "simulate": "training.commands.simulate",
    "identify": "training.commands.identify",
    "generate": "training.commands.generate",
    "train": "training.commands.train",
    "evaluate": "training.commands.evaluate",
    "commission": "training.commands.commission",
    "bench": "training.commands.bench",
    "demo": "training.commands.demo",
}


def _available() -> dict[str, object]:
    """Import the subcommand modules that exist (a missing one is simply not offered yet)."""
    modules = {}
    for name, path in COMMANDS.items():
        try:
            modules[name] = importlib.import_module(path)
        except ModuleNotFoundError as err:
            if err.name != path:  # the module exists but one of its imports is missing: a real bug
                raise
    return modules


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twomass",
        description="Identify two-mass drive mechanics from one test run with self-organizing maps.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module in _available().items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    # The work is many small least-squares and FFT problems: several BLAS threads per process on a
    # few cores thrash (measured 10x slower under load). Set before numpy loads; a user's value wins.
    for var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # not OMP: the simulator kernel uses OpenMP
        os.environ.setdefault(var, "1")
    # OpenMP threads that spin after each of the many short kernel calls take the cores from the
    # analysis workers (identify of 100 records: 9.2-9.7 s passive against 9.6-10.2 s spinning)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "_run", None) is None:
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except (UserError, ValueError, TypeError, OSError) as err:
        print(f"twomass {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"twomass {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
