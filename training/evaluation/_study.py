"""The study's runs (SPEC 7): simulate every system of a set once, run the SOM identifier and IV4
on the *same* record (in a spawned process pool, one BLAS thread per worker) and keep one row per
system: ``truth`` (true parameters, ``s_N``, ``r_osc``, ``w_e_T_Ei``, class), and per method its
estimates (SI units). Per-method results are cached on disk (:mod:`._cache`).
:func:`run_study` runs several sets and summarizes them (:mod:`._summary`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait
from functools import partial
from pathlib import Path
from typing import Any

import torch

from sim import DriveConfig, Record, TestSignalConfig, iter_records
from training._distributed import process_group
from training._pool import worker_pool
from training.config import checkpoints_folder
from training.errors import error_text
from training.evaluation._cache import load_cached, method_config, save_cached
from training.evaluation._iv4 import identify_iv4
from training.evaluation._metrics import finite_or_none as _num
from training.evaluation._sets import METHOD_PARAMS, METHODS, TRUTH_KEYS, EvalSet
from training.evaluation._summary import summarize

# ----------------------------------------------------------------------------- per record


_IDENTIFIERS: dict[tuple[str, bool], Any] = {}


def _identifier(checkpoints: str, refine: bool = True) -> Any:
    """The loaded maps of ``checkpoints`` (with or without the refinement), once per process."""
    if (checkpoints, refine) not in _IDENTIFIERS:
        from training.identification import Identifier, RefineConfig

        _IDENTIFIERS[checkpoints, refine] = Identifier.load(checkpoints, refine=RefineConfig() if refine else None)
    return _IDENTIFIERS[checkpoints, refine]


def som_result(record: Record, checkpoints: str, refine: bool = True) -> dict[str, Any]:
    """SOM identification of one record (``refine=False``: the maps' answer alone), reduced to
    what the evaluation needs (JSON-able).

    Keys: ``structure`` (class name or ``None``), ``J_sigma``, ``V_J``, ``f_e`` [Hz], ``d``,
    ``backlash`` [rad], ``M_FC`` [Nm], ``mu_F`` [Nm s/rad] (``None`` where not identified),
    ``osc_quanta``, ``outside_training``, ``n_warnings`` and ``error`` (one line or ``None``).
    Any exception of the analysis is caught and reported as ``error`` (it is a miss).
    """
    out: dict[str, Any] = dict.fromkeys(METHOD_PARAMS["som"])
    out.update(structure=None, osc_quanta=None, outside_training=None, n_warnings=0, error=None)
    try:
        outcome = _identifier(checkpoints, refine).identify_records([record])[0]
    except Exception as err:  # noqa: BLE001 - one bad record must not end a long run; it is reported
        out["error"] = error_text(err)
        return out
    if not outcome.ok:
        out["error"] = outcome.error
        return out
    parameters = outcome.parameters.to_dict()
    out.update({k: _num(parameters[k]) for k in METHOD_PARAMS["som"]})
    out.update(structure=outcome.structure, osc_quanta=_num(outcome.quality.osc_quanta),
               outside_training=bool(outcome.quality.outside_training), n_warnings=len(outcome.warnings))
    return out


def iv4_result(record: Any) -> dict[str, Any]:
    """IV4 (``training.evaluation._iv4.identify_iv4`` with its defaults) on one record (JSON-able).

    Keys: ``J_sigma``, ``V_J``, ``f_e`` [Hz], ``d`` (``None`` where NaN), ``valid``, ``reason``,
    ``converged``, ``iterations``. Input: ``K_M * current`` (or ``torque``) and the measured speed.
    """
    out: dict[str, Any] = dict.fromkeys(METHOD_PARAMS["iv4"])
    out.update(valid=False, reason="", converged=False, iterations=0)
    try:
        res = identify_iv4(record.motor_torque, record.speed, record.T_s, T_Ei=float(record.info.T_Ei))
    except Exception as err:  # noqa: BLE001 - reported as an invalid result (a miss)
        out["reason"] = error_text(err)
        return out
    estimate = res.estimate
    out.update({k: _num(getattr(estimate, k)) for k in METHOD_PARAMS["iv4"]})
    out.update(valid=bool(estimate.valid), reason=str(estimate.reason), converged=bool(res.converged),
               iterations=int(res.iterations))
    return out


def _process(record: Any, checkpoints: str, methods: tuple[str, ...]) -> tuple[int, dict[str, dict[str, Any]]]:
    """Worker job: ``(system index, {method: result})`` for one record."""
    index = int(record.name[3:])
    out: dict[str, dict[str, Any]] = {}
    if "som" in methods:
        out["som"] = som_result(record, checkpoints)
    if "maps" in methods:
        out["maps"] = som_result(record, checkpoints, refine=False)
    if "iv4" in methods:
        out["iv4"] = iv4_result(record)
    return index, out


def _imap_bounded(pool: Executor, fn: Callable[[Any], Any], items: Iterable[Any], limit: int) -> Iterator[Any]:
    """``fn`` over ``items`` in ``pool``, results in completion order, at most ``limit`` in flight
    (the records are simulated lazily, so memory stays bounded)."""
    pending: set[Future[Any]] = set()
    for item in items:
        pending.add(pool.submit(fn, item))
        if len(pending) >= limit:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                yield f.result()
    while pending:
        done, pending = wait(pending, return_when=FIRST_COMPLETED)
        for f in done:
            yield f.result()


# ----------------------------------------------------------------------------- runs


def truth_rows(eval_set: EvalSet, drive: DriveConfig, signal: TestSignalConfig) -> list[dict[str, Any]]:
    """Per system: ``set``, ``index``, ``cell_f_e``/``cell_backlash_deg`` (grid) and ``truth``
    (:data:`TRUTH_KEYS`; ``backlash`` [rad], ``structure`` a class name)."""
    truths = eval_set.params().truth(drive, signal.M_star)
    rows = []
    for i, t in enumerate(truths):
        cell = eval_set.cell_of(i)
        t = dict(t, w_e_T_Ei=t["w_e"] * drive.T_Ei)
        rows.append({"set": eval_set.name, "index": i, "cell_f_e": cell[0] if cell else None,
                     "cell_backlash_deg": cell[1] if cell else None,
                     "truth": {k: t[k] for k in TRUTH_KEYS}})
    return rows




def _compute(eval_set: EvalSet, methods: tuple[str, ...], drive: DriveConfig, signal: TestSignalConfig,
             checkpoints: str, workers: int, progress: Callable[[int], None] | None) -> dict[str, list[Any]]:
    """Per method, the result of every system of ``eval_set`` (simulated once, lazily), in order.

    Under torchrun each rank simulates and runs its block of the systems (with the substeps and
    noise seeds of the whole set: the records one process makes) and every rank gets all results."""
    from sim._integrate_fast import default_substeps

    group = process_group()
    params = eval_set.params()
    share = group.block(eval_set.size)
    n = len(share)
    fresh: dict[str, list[Any]] = {m: [None] * n for m in methods}
    records = iter_records(params[torch.arange(share.start, share.stop)], drive, signal,
                           seed=eval_set.noise_seed + share.start, group=64, substeps=default_substeps(params, drive))
    job = partial(_process, checkpoints=checkpoints, methods=methods)

    def keep(done: Iterable[tuple[int, dict[str, Any]]]) -> None:
        for index, res in done:
            for m in methods:
                fresh[m][index] = res[m]
            if progress:
                progress(1)

    if workers == 0:
        keep(map(job, records))
    else:
        with worker_pool(workers) as pool:
            keep(_imap_bounded(pool, job, records, 4 * workers))
    missing = [m for m in methods if any(r is None for r in fresh[m])]
    if missing:
        raise RuntimeError(f"run_set: expected {n} results per method, some missing for {missing}")
    parts = group.all_gather(fresh)
    if progress and group.main:
        progress(eval_set.size - n)  # the other ranks' systems
    return {m: [r for part in parts for r in part[m]] for m in methods}


def run_set(eval_set: EvalSet, *, methods: Sequence[str] = METHODS, drive: DriveConfig | None = None,
            signal: TestSignalConfig | None = None, checkpoints: str | os.PathLike[str] | None = None,
            cache_dir: str | os.PathLike[str] | None = None, workers: int = 2,
            progress: Callable[[int], None] | None = None) -> tuple[list[dict[str, Any]], dict[str, dict[str, Any]]]:
    """Simulate ``eval_set`` once and run every method of ``methods`` on the same records.

    Args:
        methods: subset of :data:`METHODS`.
        checkpoints: map folder for the SOM (default: :func:`training.config.checkpoints_folder`).
        cache_dir: folder for per-method result caches (``None``: no cache).
        workers: processes of the spawn pool (1 BLAS thread each); ``0`` runs in this process
            (slow unless ``OPENBLAS_NUM_THREADS=1`` was set before numpy was imported).
        progress: called with the number of systems finished since the last call.

    Returns:
        ``(rows, info)``: one row per system (see :func:`truth_rows`, plus one key per method)
        and, per method, ``cached`` (bool) and how its results were computed: ``compute_s``
        (wall time of simulation + all methods computed together), ``workers``, ``loadavg``
        (1-minute load average before and after; the machine may be shared).
    """
    methods = _checked_methods(methods, workers)
    drive = drive or DriveConfig()
    signal = signal or TestSignalConfig()
    ckpt = str(Path(checkpoints) if checkpoints is not None else checkpoints_folder())
    cfgs = {m: method_config(m, eval_set, drive, signal, ckpt) for m in methods}
    if "som" in methods or "maps" in methods:
        _identifier(ckpt)  # fail fast (one line) on maps that do not fit this toolkit, cached or not
    cache = Path(cache_dir) if cache_dir is not None else None
    results, info = _cached_results(cache, cfgs, eval_set.size)
    todo = tuple(m for m in methods if m not in results)
    if todo:
        fresh, meta = _timed_compute(eval_set, todo, drive, signal, ckpt, workers, progress)
        for m in todo:
            results[m], info[m] = fresh[m], {"cached": False, **meta}
        if cache is not None and process_group().main:
            for m in todo:
                save_cached(cache, cfgs[m], fresh[m], meta)
    elif progress:
        progress(eval_set.size)
    rows = truth_rows(eval_set, drive, signal)
    for m in methods:
        for row, res in zip(rows, results[m]):
            row[m] = res
    return rows, {m: info[m] for m in methods}


def _timed_compute(eval_set: EvalSet, methods: tuple[str, ...], drive: DriveConfig, signal: TestSignalConfig,
                   checkpoints: str, workers: int,
                   progress: Callable[[int], None] | None) -> tuple[dict[str, list[Any]], dict[str, Any]]:
    """:func:`_compute`'s results and how they were computed: ``compute_s``, ``workers``,
    ``methods_together``, ``loadavg`` (before and after), ``date``."""
    t0, load0 = time.perf_counter(), _loadavg()
    fresh = _compute(eval_set, methods, drive, signal, checkpoints, workers, progress)
    meta = {"compute_s": time.perf_counter() - t0, "workers": workers, "methods_together": list(methods),
            "loadavg": [load0, _loadavg()], "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    return fresh, meta


def _checked_methods(methods: Sequence[str], workers: int) -> tuple[str, ...]:
    """``methods`` in the order of :data:`METHODS`; a ``ValueError`` naming ``methods`` or ``workers``."""
    if not methods or any(m not in METHODS for m in methods):
        raise ValueError(f"methods: expected a non-empty subset of {METHODS}, received {list(methods)}")
    if workers < 0:
        raise ValueError(f"workers: expected >= 0, received {workers}")
    return tuple(m for m in METHODS if m in methods)


def _cached_results(cache: Path | None, cfgs: dict[str, dict[str, Any]],
                    size: int) -> tuple[dict[str, list[Any]], dict[str, dict[str, Any]]]:
    """Per method of ``cfgs`` whose results ``cache`` holds: the results and how they were computed
    (under torchrun rank 0 reads the cache)."""
    results: dict[str, list[Any]] = {}
    info: dict[str, dict[str, Any]] = {}
    if cache is None:
        return results, info
    group = process_group()
    for m, cfg in cfgs.items():
        hit = group.on_main(partial(load_cached, cache, cfg, size))
        if hit is not None:
            results[m], info[m] = hit[0], {"cached": True, **hit[1]}
    return results, info


def _loadavg() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


# ----------------------------------------------------------------------------- study


def run_study(sets: Mapping[str, EvalSet], *, methods: Sequence[str] = METHODS, drive: DriveConfig | None = None,
              signal: TestSignalConfig | None = None, checkpoints: str | os.PathLike[str] | None = None,
              cache_dir: str | os.PathLike[str] | None = None, workers: int = 2,
              progress: Callable[[int], None] | None = None
              ) -> tuple[dict[str, Any], dict[str, list[dict[str, Any]]]]:
    """:func:`run_set` over ``sets`` (by name) and their :func:`summarize` (JSON-able).

    Returns ``(summary, rows_by_set)``; the summary adds to :func:`summarize`'s tables each set's
    ``config``, the ``workers`` and the ``timing`` (``total_s``, per set ``s``, ``n`` and how
    each method's results were computed, see :func:`run_set`).
    """
    t0 = time.perf_counter()
    rows_by_set: dict[str, list[dict[str, Any]]] = {}
    timing: dict[str, Any] = {}
    for name, s in sets.items():
        t = time.perf_counter()
        rows_by_set[name], info = run_set(s, methods=methods, drive=drive, signal=signal, checkpoints=checkpoints,
                                          cache_dir=cache_dir, workers=workers, progress=progress)
        timing[name] = {"s": time.perf_counter() - t, "n": s.size, "methods": info}
    summary = {**summarize(rows_by_set, sets, methods), "config": {name: s.to_dict() for name, s in sets.items()},
               "workers": workers, "timing": {"total_s": time.perf_counter() - t0, "sets": timing}}
    return summary, rows_by_set
