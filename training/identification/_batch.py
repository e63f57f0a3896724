"""Identifying many records: each record's failure isolated to its own outcome; chunks of records
read, analysed, recalled and refined in forked worker processes, one per core."""

from __future__ import annotations

import gc
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol

from sim import Record, read_record
from training._distributed import process_group
from training.config import blas_threads
from training.errors import one_line
from training.identification._analysis import Analysis, analyze
from training.identification._result import IdentificationFailure, Outcome

#: Records analysed before one batched recall + refinement (a worker's unit of work): the
#: refinement packs the models of a batch's records into the simulator's blocks of 32, which
#: 8 records filled poorly (identify of 1000 records: 47 s with 32, 63 s with 8, 48 s with 64 or 128).
CHUNK = 32


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
        except Exception as err:  # noqa: BLE001 - a bug in the reader must not cost the other records their answer
            return IdentificationFailure(f"{path}: unexpected {type(err).__name__} reading the record: "
                                         f"{one_line(err)}", path)
        return analysis_outcome(record, path)


def default_jobs(n_records: int) -> int:
    """Worker processes for ``n_records``: one for a few records, else one per CPU this process may
    use (under torchrun its share of them), at most one per batch of :data:`CHUNK`."""
    return 1 if n_records < 2 * CHUNK else min(process_group().cpus(), -(-n_records // CHUNK))


@dataclass(frozen=True)
class ReadRecord:
    """One record file read and analysed: its ``name`` (the path as given) and its ``outcome``
    (the analysis, or the failure to read or analyse it)."""

    name: str
    outcome: Analysis | IdentificationFailure


class ChunkIdentifier(Protocol):
    """What answers a chunk of read records (:meth:`training.identification.Identifier.identify_read`):
    one final outcome per record, in order."""

    def identify_read(self, chunk: Sequence[ReadRecord]) -> list[Outcome]: ...


#: In a forked worker: the parent's identifier, handed over by the fork (:func:`_start_worker`), not pickled.
_worker_identifier: ChunkIdentifier | None = None


def _start_worker(identifier: ChunkIdentifier) -> None:
    """Pool initializer: keeps the identifier; one thread for BLAS, torch and the simulator kernel
    (one worker per core)."""
    global _worker_identifier
    import torch
    from threadpoolctl import threadpool_limits

    _worker_identifier = identifier
    os.environ["TWOMASS_SIM_THREADS"] = "1"
    torch.set_num_threads(1)
    threadpool_limits(limits=1)


def _read(paths: Sequence[str]) -> list[ReadRecord]:
    return [ReadRecord(path, file_outcome(path)) for path in paths]


def _answer_chunk(paths: list[str]) -> list[Outcome]:
    """A worker's task: read, analyse and identify one chunk of files."""
    if _worker_identifier is None:
        raise RuntimeError("_answer_chunk runs in a worker started by answered_files only")
    return _worker_identifier.identify_read(_read(paths))


def _answered_here(chunks: list[list[str]], identifier: ChunkIdentifier,
                   tick: Callable[[int], object]) -> Iterator[Outcome]:
    """:func:`answered_files` in this process: each record counted as it is read."""
    for chunk in chunks:
        items = []
        for path in chunk:
            items.append(ReadRecord(path, file_outcome(path)))
            tick(1)
        yield from identifier.identify_read(items)


def answered_files(paths: Sequence[str], jobs: int | None, identifier: ChunkIdentifier,
                   progress: Callable[[int], object] | None = None) -> Iterator[Outcome]:
    """One outcome per path, in order: the records read and analysed (:func:`file_outcome`) in
    chunks of :data:`CHUNK`, each chunk then answered by ``identifier`` (the maps' recall and the
    refinement). With ``jobs > 1`` (``None``: :func:`default_jobs`) whole chunks go to ``jobs``
    forked workers, so every stage runs on every core; the outcomes are the same as with one
    (each chunk is the same batch). ``progress`` gets the number of records done as they are.

    The workers are forked: they inherit the loaded maps and modules (no start-up cost) and run
    torch and the simulator kernel on one thread each, which is also what keeps them safe in a
    parent whose thread pools have already run."""
    if jobs is None:
        jobs = default_jobs(len(paths))
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs: expected an integer >= 1 or None, received {jobs!r}")
    tick = progress or (lambda _n: None)
    chunks = [list(paths[i:i + CHUNK]) for i in range(0, len(paths), CHUNK)]
    if jobs == 1 or len(chunks) < 2 or "fork" not in multiprocessing.get_all_start_methods():
        yield from _answered_here(chunks, identifier, tick)
        return
    # the parent's objects (modules, maps) out of the collector's sight before the fork: the workers'
    # collections then neither walk them nor copy the memory pages they share with the parent
    # (a caller that froze objects itself keeps its own policy)
    freeze = gc.get_freeze_count() == 0
    if freeze:
        gc.freeze()
    try:
        with multiprocessing.get_context("fork").Pool(min(jobs, len(chunks)), _start_worker, (identifier,)) as pool:
            for outcomes in pool.imap(_answer_chunk, chunks):
                tick(len(outcomes))
                yield from outcomes
    finally:
        if freeze:
            gc.unfreeze()
