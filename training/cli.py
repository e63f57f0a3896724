"""The ``twomass`` console command: one subcommand per module, looked up in a dict.

Each subcommand lives in its own module (``training/commands/<name>.py``) that defines

    HELP: str                                # one line for ``twomass --help``
    def add_arguments(parser) -> None        # its argparse options
    def run(args) -> int                     # the work; returns the exit code

The modules import torch, numpy and the rooms inside ``run``, so that ``twomass --help`` stays fast.

Errors: the library raises its domain exceptions (:mod:`training.errors`, ``sim.RecordError``,
``som_torch.CheckpointError``: all ``ValueError``) and ``OSError``; :func:`main` alone turns them
into ``twomass <command>: error: <one line>`` on stderr and exit code 2. Anything else (a
``TypeError`` from a bug, an ``ImportError`` of a command module) is a traceback.

Signals: Ctrl-C (SIGINT) and SIGTERM (``kill``, ``timeout``, systemd, ``docker stop``) interrupt the
command the same way, also during start-up: SIGTERM raises :class:`Terminated`, a
``KeyboardInterrupt``, so every cleanup of Ctrl-C runs (temporary files removed, worker pools
ended); one line on stderr and exit code 130 (SIGINT) or 143 (SIGTERM). A signal ignored when
``twomass`` starts (``nohup``, a background job of a script) stays ignored; a second signal does not
cut the cleanup of the first short (SIGKILL does, leaving what it leaves). Processes forked while a
command runs (the pool workers of ``identify``) leave both signals to the command: SIGINT ignored,
SIGTERM (what ending a pool sends) its default action, so they end at once and quietly.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from types import FrameType, ModuleType
from typing import Any

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
    "calibrate": "training.commands.calibrate",
}

#: Exit codes of :func:`main` besides a command's own: bad input, Ctrl-C (128 + SIGINT) and
#: SIGTERM (128 + SIGTERM).
EXIT_USAGE, EXIT_INTERRUPTED, EXIT_TERMINATED = 2, 128 + signal.SIGINT, 128 + signal.SIGTERM


class Terminated(KeyboardInterrupt):
    """SIGTERM received: an interruption like Ctrl-C (a ``KeyboardInterrupt``, so that the same
    cleanup runs), told apart by its exit code :data:`EXIT_TERMINATED`."""


#: The process whose signals :func:`_interruptions` turns into exceptions (None: none is), and
#: whether one did: the signals after the first are ignored, so that they cannot cut its cleanup short
#: (``timeout`` sends SIGTERM to the command and again to its process group).
_handling_pid: int | None = None
_interrupted = False


def _raise_interruption(signum: int, frame: FrameType | None) -> None:
    global _interrupted
    if _interrupted:
        return
    _interrupted = True
    raise Terminated("SIGTERM") if signum == signal.SIGTERM else KeyboardInterrupt


def _forked_child_signals() -> None:
    """In a process forked while a command runs (a pool worker): SIGINT ignored (Ctrl-C reaches the
    whole process group; the command ends its workers itself), SIGTERM back to its default action
    (a worker ends at once when its pool is ended, without running Python cleanup or a traceback)."""
    if _handling_pid is not None and os.getpid() != _handling_pid:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


if hasattr(os, "register_at_fork"):  # POSIX; it acts only while a command runs
    os.register_at_fork(after_in_child=_forked_child_signals)


@contextlib.contextmanager
def _interruptions() -> Iterator[None]:
    """Inside the block SIGINT raises ``KeyboardInterrupt`` and SIGTERM :class:`Terminated` (each
    unless ignored when the block starts); the previous handlers come back after it. Outside the
    main thread (where Python cannot set handlers) nothing changes."""
    global _handling_pid, _interrupted
    if threading.current_thread() is not threading.main_thread() or _handling_pid is not None:
        yield
        return
    previous: dict[int, Any] = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            previous[signum] = signal.signal(signum, _raise_interruption)
    _handling_pid, _interrupted = os.getpid(), False
    try:
        yield
    finally:
        _handling_pid, _interrupted = None, False
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)  # None: set outside Python


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
    with _interruptions():  # until the last line is printed: a second signal cannot cut it short
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
    prog = "twomass"
    try:  # all of it: Ctrl-C or SIGTERM while torch loads is an interruption too
        apply_process_defaults()  # before the commands import numpy and torch
        parser = build_parser()
        args = parser.parse_args(argv)
        if getattr(args, "_run", None) is None:
            parser.print_help()
            return EXIT_USAGE
        prog = f"twomass {args.command}"
        return _run_command(args)
    except Terminated:
        print(f"{prog}: terminated (SIGTERM)", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
