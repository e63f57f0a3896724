"""Analysing many records: each record's failure isolated to its own outcome, optionally in
forked worker processes (the analysis is the slow, record-by-record part of the identification)."""

from __future__ import annotations

import multiprocessing
from collections.abc import Iterator, Sequence

from sim import Record, read_record
from training._distributed import process_group
from training.config import blas_threads
from training.errors import one_line
from training.identification._analysis import Analysis, analyze
from training.identification._result import IdentificationFailure

#: Records analysed before one batched recall + refinement (overlaps the analysis workers).
CHUNK = 8


def analysis_outcome(record: Record, name: str | None = None) -> Analysis | IdentificationFailure:
    """:func:`analyze` of ``record``, or an :class:`IdentificationFailure` (``record`` = ``name``)
    with the one-line reason, which starts with ``name`` where given (as the reading errors do);
    an exception that is no ``ValueError`` is named as unexpected."""
    try:
        return analyze(record)
    except ValueError as err:  # IdentificationError: the record cannot be identified
        return IdentificationFailure(one_line(err) if name is None else f"{name}: {one_line(err)}", name)
    except Exception as err:  # noqa: BLE001 - a bug in the analysis must not cost the other records their answer
        return IdentificationFailure(f"unexpected {type(err).__name__} in the analysis: {one_line(err)}", name)


def file_outcome(path: str) -> Analysis | IdentificationFailure:
    """Read and analyse the record ``path`` names (one BLAS thread): see :func:`analysis_outcome`."""
    with blas_threads():
        try:
            record = read_record(path)
        except (ValueError, OSError) as err:  # RecordError, missing files
            return IdentificationFailure(one_line(err), path)
        return analysis_outcome(record, path)


def default_jobs(n_records: int) -> int:
    """Worker processes for ``n_records``: one for a few records, else up to 2 (the CPUs we may use;
    under torchrun this process's share of them)."""
    return 1 if n_records < 8 else min(2, process_group().cpus())


def file_outcomes(paths: Sequence[str], jobs: int | None) -> Iterator[Analysis | IdentificationFailure]:
    """:func:`file_outcome` over ``paths`` in order; in ``jobs`` forked workers when ``jobs > 1``
    (``None``: :func:`default_jobs`)."""
    if jobs is None:
        jobs = default_jobs(len(paths))
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs: expected an integer >= 1 or None, received {jobs!r}")
    if jobs == 1 or len(paths) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        yield from map(file_outcome, paths)
        return
    # fork: the workers inherit the imported modules (no start-up cost); they run numpy/scipy only,
    # never torch ops (not fork-safe once torch's thread pool has started in the parent); each
    # sets its BLAS threads again (a forked OpenBLAS starts with its default thread count)
    with multiprocessing.get_context("fork").Pool(min(jobs, len(paths))) as pool:
        yield from pool.imap(file_outcome, paths, chunksize=2)
