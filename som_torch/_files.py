"""Atomic file writes: a reader never sees a half-written file, and a failed write leaves none."""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def _create_temp(path: Path) -> tuple[int, Path]:
    """A new file beside ``path``, opened for writing with mode ``0o666`` less the umask (as any
    new file; ``tempfile.mkstemp`` would give 0600)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(16):  # a name clash is as good as impossible; retry anyway
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
        try:
            return os.open(tmp, flags, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path}: no free temporary name beside it")


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[Any]], object], *, text: bool = False) -> None:
    """Call ``write(fileobj)`` on a temporary file beside ``path`` (binary, or text with
    ``text=True``), fsync, then ``os.replace`` it onto ``path``; on any failure the temporary file
    is removed and ``path`` is left as it was. Creates missing parent folders. A new file gets the
    usual permissions (``0o666`` less the umask); a replaced file keeps its mode."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        old_mode: int | None = stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        old_mode = None
    fd, tmp = _create_temp(path)
    try:
        with os.fdopen(fd, "w" if text else "wb", **({"encoding": "utf-8", "newline": "\n"} if text else {})) as f:
            if old_mode is not None and os.chmod in os.supports_fd:
                os.chmod(f.fileno(), old_mode)
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
