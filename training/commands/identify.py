"""``twomass identify FILE...``: identify test-run records with the shipped maps (SPEC section 9).

Writes JSON Lines: one object per record, in the order given, each with ``record`` (the path as
given) and either ``error`` (one line) or ``structure``, ``parameters``, ``quality`` and
``warnings`` (:meth:`training.identification.Identifier.iter_files` does the work: the same path
as ``Identifier.identify_files``). Non-finite numbers are written as ``null``. A record may be
named ``NAME.csv``, ``NAME.json`` or ``NAME``; when several arguments name the same record
(``runs/*`` lists both files of each record) only the first is answered.

Exit codes: 0 every record identified; 1 some records have an ``error`` (the others are
answered); 2 bad usage (no files, unusable checkpoints, ``--out`` exists, ...).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, TextIO

from training._json import dumps
from training.commands import _progress
from training.errors import OutputExistsError, UserError, one_line

HELP = "identify records (NAME.csv + NAME.json) with the shipped maps; JSON Lines out, one object per record"

EXIT_OK, EXIT_SOME_ERRORS = 0, 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = ("output: one JSON object per line, numbers in SI units: J_sigma, J_M, J_L [kg m^2], V_J [-], "
                     "f_e [Hz], C_F [Nm/rad], d [-], backlash [rad, total width 2s], M_FC, mu_F [Nm, Nm s/rad] of "
                     "the load, M_L0 [Nm] the constant load torque, M_FCM, mu_FM [Nm, Nm s/rad] of the motor; "
                     "exit status: 0 all records identified, 1 some records have an 'error' (the others are "
                     "answered), 2 bad usage (no files, unusable checkpoints, --out exists)")
    parser.add_argument("files", nargs="*", metavar="FILE",
                        help="record as NAME.csv, NAME.json or NAME (CSV with t, speed, current|torque; "
                             "metadata NAME.json beside it)")
    parser.add_argument("--out", type=Path, metavar="PATH", help="write JSON Lines here (atomically) instead of stdout")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out file (and existing pages "
                        "in --plot DIR)")
    parser.add_argument("--plot", type=Path, metavar="DIR", help="write one PNG page per record into DIR: NAME.png "
                        "(speed and the identified model's replay, w_osc, spectrum, current, results) and "
                        "NAME_maps.png (the record on the maps); needs the plot extra (docs/figures.md)")
    parser.add_argument("--checkpoints", type=Path, metavar="DIR",
                        help="folder with the maps and manifest.json (default: the shipped checkpoints/, "
                             "or $TWOMASS_CHECKPOINTS)")
    parser.add_argument("--jobs", type=int, metavar="N", help="worker processes, each reading, analysing and "
                        "refining whole batches of 32 records (default: 1 for fewer than 64 records, else one per "
                        "CPU)")
    parser.add_argument("--no-refine", action="store_true",
                        help="the maps' answer alone, without the model-based refinement (faster, coarser)")
    _progress.add_option(parser)


def load_identifier(folder: Path | None, refine: bool = True) -> Any:
    """The maps of ``folder`` (default: :func:`training.config.checkpoints_folder`); a folder that is
    missing or whose maps cannot be used is a :class:`UserError` (one line)."""
    from training.config import checkpoints_folder
    from training.identification import Identifier, RefineConfig

    where = folder if folder is not None else checkpoints_folder()
    if not Path(where).is_dir():
        raise UserError(f"--checkpoints: expected a folder with the trained maps, received {str(where)!r} (not found; "
                        "give --checkpoints DIR or set TWOMASS_CHECKPOINTS)")
    try:
        return Identifier.load(where, refine=RefineConfig() if refine else None)
    except (ValueError, OSError) as err:  # CheckpointError, unreadable or foreign files: one line, exit 2
        raise UserError(f"cannot load the maps from {where}: {one_line(err)}") from None


def _distinct_records(files: list[str]) -> list[str]:
    """``files`` without those naming a record already named (``NAME``, ``NAME.csv``, ``NAME.json``)."""
    seen: set[str] = set()
    out = []
    for f in files:
        p = Path(f)
        key = os.path.abspath(p.with_suffix("") if p.suffix in (".csv", ".json") else p)
        if key not in seen:
            seen.add(key)
            out.append(f)
    return out


def _refuse_existing(out: Path | None, overwrite: bool) -> None:
    if out is not None and out.exists() and not overwrite:
        raise OutputExistsError(f"--out: {str(out)!r} exists (pass --overwrite to replace it)")


def _check_out(out: Path | None, overwrite: bool) -> None:
    if out is None:
        return
    if out.is_dir():
        raise UserError(f"--out: expected a file path, received a folder {str(out)!r}")
    _refuse_existing(out, overwrite)
    if not out.parent.is_dir():
        raise UserError(f"--out: folder {str(out.parent)!r} does not exist")


def _write_lines(outcomes: Iterable[Any], f: TextIO) -> tuple[int, int]:
    """One JSON line per outcome; returns (lines, failures)."""
    n = errors = 0
    for res in outcomes:
        f.write(dumps(res) + "\n")
        n += 1
        errors += not res.ok
    return n, errors


def _page_writer(folder: Path | None, paths: list[str], maps: Any, overwrite: bool) -> Any:
    """The writer of ``--plot`` pages (``training.figures.PageWriter``), or None without ``--plot``."""
    if folder is None:
        return None
    from training.figures import PageWriter

    return PageWriter(folder, paths, maps, overwrite=overwrite,
                      report=lambda line: print(f"twomass identify: --plot: {line}", file=sys.stderr))


def run(args: argparse.Namespace) -> int:
    from som_torch import atomic_write
    from training._distributed import process_group
    from training.identification import CHUNK

    if args.plot is not None:  # before any work: pages asked for and not drawable is bad usage
        from training.figures import require_plots

        require_plots("--plot")
    group = process_group()  # under torchrun: the records are split, rank 0 writes them in input order
    if not args.files:
        raise UserError("expected at least one record FILE (NAME.csv, NAME.json or NAME), received none")
    group.on_main(lambda: _check_out(args.out, args.overwrite))
    paths = _distinct_records(args.files)
    if len(paths) < len(args.files) and group.main:
        print(f"twomass identify: {len(args.files) - len(paths)} argument(s) name a record already given; "
              "answered once", file=sys.stderr)
    if args.jobs is not None and args.jobs < 1:
        raise UserError(f"--jobs: expected N >= 1, received {args.jobs}")
    bar = _progress.bar(args, show=_progress.wanted(args) and group.main, total=len(paths), desc="identify",
                        unit="rec")
    bar.set_postfix_str("loading the maps")
    ident = load_identifier(args.checkpoints, refine=not args.no_refine)
    pages = _page_writer(args.plot, paths, ident.maps, args.overwrite) if group.main else None
    counts = (0, 0)
    analysed = 0

    def on_analysed(k: int) -> None:  # a record is answered after the maps' recall and the refinement
        nonlocal analysed
        analysed += k
        bar.set_postfix_str(f"analysed {analysed}/{len(paths)}" + ("; maps and refinement" if analysed > bar.n else ""))

    def outcomes() -> Iterator[Any]:
        if not group.distributed:
            for res in ident.iter_files(paths, jobs=args.jobs, progress=on_analysed):
                bar.update(1)
                yield res
            return
        for res in group.ordered(paths, lambda share: ident.iter_files(share, jobs=args.jobs), granule=CHUNK):
            bar.update(1)
            yield res

    def write(f: TextIO) -> None:
        nonlocal counts
        with contextlib.closing(outcomes()) as answers:  # closed on an interruption too: its worker pool ends now
            counts = _write_lines(answers if pages is None else map(pages, answers), f)
        _refuse_existing(args.out, args.overwrite)  # it may have appeared while we worked

    try:
        if not group.main:
            list(outcomes())  # this rank's share, sent to rank 0
        elif args.out is None:
            write(sys.stdout)
            sys.stdout.flush()
        else:
            atomic_write(args.out, write, text=True)
    finally:
        bar.close()
    n, errors = group.on_main(lambda: counts)  # every rank exits with rank 0's status
    if not group.main:
        return EXIT_SOME_ERRORS if errors else EXIT_OK
    where = f" to {args.out}" if args.out is not None else ""
    print(f"twomass identify: {n - errors} of {n} record(s) identified{where}"
          + (f"; {errors} with an error" if errors else ""), file=sys.stderr)
    return EXIT_SOME_ERRORS if errors else EXIT_OK
