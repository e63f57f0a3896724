"""``twomass identify FILE...``: identify test-run records with the shipped maps (SPEC section 9).

Writes JSON Lines: one object per record, in the order given, each with ``record`` (the path as
given) and either ``error`` (one line) or ``structure``, ``parameters``, ``quality`` and
``warnings`` (see :class:`training.identification._identifier.Identifier`). Non-finite numbers are written as
``null``. A record may be named ``NAME.csv``, ``NAME.json`` or ``NAME``; when several arguments
name the same record (``runs/*`` lists both files of each record) only the first is answered.

Exit codes: 0 every record identified; 1 some records have an ``error`` (the others are
answered); 2 bad usage (no files, unusable checkpoints, ``--out`` exists, ...).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import re
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, TextIO

from training.errors import UserError

HELP = "identify records (NAME.csv + NAME.json) with the shipped maps; JSON Lines out, one object per record"

EXIT_OK, EXIT_SOME_ERRORS = 0, 1
CHUNK = 8  # records analysed before one batched recall + refinement (overlaps the analysis workers)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = ("exit status: 0 all records identified, 1 some records have an 'error' (the others are "
                     "answered), 2 bad usage (no files, unusable checkpoints, --out exists)")
    parser.add_argument("files", nargs="*", metavar="FILE",
                        help="record as NAME.csv, NAME.json or NAME (CSV with t, speed, current|torque; "
                             "metadata NAME.json beside it)")
    parser.add_argument("--out", type=Path, metavar="PATH", help="write JSON Lines here (atomically) instead of stdout")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    parser.add_argument("--checkpoints", type=Path, metavar="DIR",
                        help="folder with the maps and manifest.json (default: the shipped checkpoints/, "
                             "or $TWOMASS_CHECKPOINTS)")
    parser.add_argument("--jobs", type=int, metavar="N", help="worker processes for the analysis (default: 1 for "
                        "fewer than 8 records, else 2 where 2 CPUs are available)")
    parser.add_argument("--no-refine", action="store_true",
                        help="the maps' answer alone, without the model-based refinement (faster, coarser)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def json_safe(x: Any) -> Any:
    """``x`` with numpy scalars as Python numbers, tuples as lists and NaN/inf as ``None``."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x
    if hasattr(x, "item") and callable(x.item) and getattr(x, "ndim", 0) == 0:  # numpy / torch scalar
        return json_safe(x.item())
    if isinstance(x, int):
        return x
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    return str(x)


def _record_key(path: str) -> str:
    """The record a path names: its absolute path without ``.csv`` / ``.json``."""
    p = Path(path)
    if p.suffix in (".csv", ".json"):
        p = p.with_suffix("")
    return os.path.abspath(p)


def _one_line(err: BaseException) -> str:
    lines = str(err).strip().splitlines()
    return lines[0] if lines else type(err).__name__


def analyze_path(path: str) -> Any:
    """Read and analyse one record: an ``Analysis``, or the one-line reason it cannot be identified."""
    from sim import read_record
    from training.identification._analysis import analyze

    try:
        return analyze(read_record(path))
    except (ValueError, OSError) as err:  # RecordError, plausibility, sections, fit
        return _one_line(err)
    except Exception as err:  # a bug in the analysis must not cost the other records their answer
        return f"unexpected {type(err).__name__} in the analysis: {_one_line(err)}"


def _analyses(paths: Sequence[str], jobs: int) -> Iterator[Any]:
    """``analyze_path`` over ``paths`` in order; in ``jobs`` forked workers when ``jobs > 1``."""
    if jobs <= 1 or len(paths) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        yield from map(analyze_path, paths)
        return
    # fork: the workers inherit the imported modules (no start-up cost); they run numpy/scipy only,
    # never torch ops (not fork-safe once torch's thread pool has started in the parent)
    # the child's OpenBLAS re-initialises after fork with its default thread count: set it again
    with multiprocessing.get_context("fork").Pool(min(jobs, len(paths))) as pool:
        yield from pool.imap(analyze_path, paths, chunksize=2)


def identify_paths(ident: Any, paths: Sequence[str], progress: Any = None, jobs: int = 1) -> Iterator[dict[str, Any]]:
    """``{"record": path, ...}`` per path, in order; analysed one by one (or in ``jobs`` worker
    processes), recalled in chunks of :data:`CHUNK`. ``progress``: called with 1 per record."""
    from training.identification._analysis import Analysis

    items: list[tuple[str, Any]] = []

    def recall(good: list[Any]) -> list[dict[str, Any]]:
        try:
            return ident.identify_analyses(good)  # one batched recall per map
        except Exception:  # isolate the record that breaks the batch
            out = []
            for a in good:
                try:
                    out.append(ident.identify_analyses([a])[0])
                except Exception as err:
                    out.append({"error": f"recall failed: {type(err).__name__}: {_one_line(err)}"})
            return out

    def flush() -> Iterator[dict[str, Any]]:
        results = iter(recall([a for _, a in items if isinstance(a, Analysis)]))
        for p, a in items:
            yield {"record": p, **(next(results) if isinstance(a, Analysis) else {"error": a})}
        items.clear()

    for p, a in zip(paths, _analyses(paths, jobs)):
        items.append((p, a))
        if progress is not None:
            progress(1)
        if len(items) >= CHUNK:
            yield from flush()
    yield from flush()


def default_jobs(n_records: int) -> int:
    """Worker processes for ``n_records``: one for a few records, else up to 2 (the CPUs we may use)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return 1 if n_records < 8 else max(1, min(2, cpus))


def _load_identifier(folder: Path | None, refine: bool = True) -> Any:
    from training.identification._identifier import DEFAULT_CHECKPOINTS, Identifier
    from training.identification._refine import RefineConfig

    where = folder if folder is not None else DEFAULT_CHECKPOINTS
    if not Path(where).is_dir():
        raise UserError(f"--checkpoints: expected a folder with the trained maps, received {str(where)!r} (not found)")
    try:
        return Identifier.load(where, refine=RefineConfig() if refine else None)
    except Exception as err:  # CheckpointError, unreadable or foreign files: one line, exit 2
        raise UserError(f"cannot load the maps from {where}: {_one_line(err)}") from None


def _check_out(out: Path | None, overwrite: bool) -> None:
    if out is None:
        return
    if out.is_dir():
        raise UserError(f"--out: expected a file path, received a folder {str(out)!r}")
    if out.exists() and not overwrite:
        raise UserError(f"--out: {str(out)!r} exists (pass --overwrite to replace it)")
    if not out.parent.is_dir():
        raise UserError(f"--out: folder {str(out.parent)!r} does not exist")


def _write_lines(results: Iterator[dict[str, Any]], f: TextIO) -> tuple[int, int]:
    n = errors = 0
    for res in results:
        f.write(json.dumps(json_safe(res), allow_nan=False) + "\n")
        n += 1
        errors += "error" in res
    return n, errors


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    if not args.files:
        raise UserError("expected at least one record FILE (NAME.csv, NAME.json or NAME), received none")
    _check_out(args.out, args.overwrite)
    seen: set[str] = set()
    paths: list[str] = []
    for p in args.files:
        key = _record_key(p)
        if key not in seen:
            seen.add(key)
            paths.append(p)
    if len(paths) < len(args.files):
        print(f"twomass identify: {len(args.files) - len(paths)} argument(s) name a record already given; "
              "answered once", file=sys.stderr)
    if args.jobs is not None and args.jobs < 1:
        raise UserError(f"--jobs: expected N >= 1, received {args.jobs}")
    jobs = args.jobs if args.jobs is not None else default_jobs(len(paths))
    ident = _load_identifier(args.checkpoints, refine=not args.no_refine)
    bar = tqdm(total=len(paths), desc="identify", unit="rec", file=sys.stderr,
               disable=args.no_progress or len(paths) < 2)
    try:
        results = identify_paths(ident, paths, progress=bar.update, jobs=jobs)
        if args.out is None:
            n, errors = _write_lines(results, sys.stdout)
            sys.stdout.flush()
        else:
            fd, tmp = tempfile.mkstemp(dir=args.out.parent, prefix=f".{args.out.name}.", suffix=".tmp")
            try:
                with os.fdopen(fd, "w") as f:
                    n, errors = _write_lines(results, f)
                if args.out.exists() and not args.overwrite:  # appeared while we worked
                    raise UserError(f"--out: {str(args.out)!r} exists (pass --overwrite to replace it)")
                os.replace(tmp, args.out)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
    finally:
        bar.close()
    where = f" to {args.out}" if args.out is not None else ""
    print(f"twomass identify: {n - errors} of {n} record(s) identified{where}"
          + (f"; {errors} with an error" if errors else ""), file=sys.stderr)
    return EXIT_SOME_ERRORS if errors else EXIT_OK
