"""Progress bars of the subcommands: on stderr, only where someone watches.

Quiet with ``--no-progress`` and whenever stderr is not a terminal (a pipe, a log file, CI), so
that logs and captured output hold results, not bar frames.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any


def add_option(parser: argparse.ArgumentParser) -> None:
    """The ``--no-progress`` option, with its help."""
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar on stderr (there is none either when stderr is not a terminal)")


def wanted(args: argparse.Namespace) -> bool:
    """Whether to show progress: not with ``--no-progress``, only on a terminal."""
    return not getattr(args, "no_progress", False) and sys.stderr.isatty()


def bar(args: argparse.Namespace, *, show: bool | None = None, **kwargs: Any) -> Any:
    """A ``tqdm`` bar on stderr (``kwargs``: total, desc, unit, ...), shown where :func:`wanted`
    (``show``: that decision, made by the caller)."""
    from tqdm import tqdm

    return tqdm(file=sys.stderr, disable=not (wanted(args) if show is None else show), dynamic_ncols=True, **kwargs)
