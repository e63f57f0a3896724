"""Atomic file writes: a reader never sees a half-written file, and a failed or interrupted write
leaves none (its temporary file is removed on any exception, ``KeyboardInterrupt`` included)."""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def _create_temp(path: Path, made: list[Path]) -> int:
    """A new file beside ``path``, opened for writing with mode ``0o666`` less the umask (as any
    new file; ``tempfile.mkstemp`` would give 0600). Its name goes into ``made`` before it is
    created, so that a caller interrupted at any point after the creation can remove it."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(16):  # a name clash is as good as impossible; retry anyway
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
        try:
            made.append(tmp)
            return os.open(tmp, flags, 0o666)
        except FileExistsError:
            made.remove(tmp)  # someone else's file: not ours to remove
            continue
        except OSError as err:  # a read-only folder: the user's path, not our temporary name
            made.remove(tmp)
            raise _naming(err, path, tmp) from None
    raise FileExistsError(f"{path}: no free temporary name beside it")


def _naming(err: OSError, path: Path, tmp: Path) -> OSError:
    """``err`` as the user sees it: a system error about the temporary file ``tmp`` (or about no file:
    a full disk) names ``path`` instead, the temporary name being ours, not the user's; any other
    ``err`` (one with no errno, about another file) as it is."""
    if err.errno is None or (err.filename is not None and os.fspath(err.filename) != os.fspath(tmp)):
        return err
    return type(err)(err.errno, err.strerror or os.strerror(err.errno), os.fspath(path))


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[Any]], object], *, text: bool = False) -> None:
    """Call ``write(fileobj)`` on a temporary file beside ``path`` (binary, or text with
    ``text=True``), fsync, then ``os.replace`` it onto ``path``; on any failure or interruption the
    temporary file is removed and ``path`` is left as it was. Creates missing parent folders. A new
    file gets the usual permissions (``0o666`` less the umask); a replaced file keeps its mode. An
    ``OSError`` of the temporary file (a read-only folder, a full disk) names ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        old_mode: int | None = stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        old_mode = None
    made: list[Path] = []  # the temporary file, once named: removed on any failure or interruption
    try:
        fd = _create_temp(path, made)
        tmp = made[-1]
        with os.fdopen(fd, "w" if text else "wb", **({"encoding": "utf-8", "newline": "\n"} if text else {})) as f:
            if old_mode is not None and os.chmod in os.supports_fd:
                os.chmod(f.fileno(), old_mode)
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as err:
        for tmp in made:
            tmp.unlink(missing_ok=True)
        raise err if not made else _naming(err, path, made[-1]) from None
    except BaseException:
        for tmp in made:
            tmp.unlink(missing_ok=True)
        raise
