"""Training data: simulate a population, analyse each record, store features and truth in shards.

A dataset is a folder::

    dataset.json          config (n, seed, shard size, population ranges, drive, test signal,
                          feature version) -- written first, checked on resume
    shard_00000.npz ...   per shard: features (S x F), truth columns (S), STEP-2 estimates (S),
                          ok (S; False where the analysis failed), written atomically
    shard_00000.rejected.json ...   per shard with rejected systems: why the analysis refused
                          each (outside the shards and their sha256: the reasons are words)

Generation is resumable: an interrupted run continues with the missing shards; a folder made
with another config is refused rather than mixed or overwritten. Under ``torchrun`` the ranks
share the shards and rank 0 writes them (see :func:`generate`).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sim import (DERIVED_NAMES, PARAM_NAMES, STRUCTURE_CLASSES, DriveConfig, EnvelopeRanges, EnvelopeSample,
                 PopulationRanges, TestSignalConfig, TwoMassParams, default_substeps, iter_records, sample_envelope,
                 sample_population)
from som_torch import atomic_write
from training._distributed import process_group
from training._pool import worker_pool
from training._json import dumps
from training.errors import UserError, one_line
from training.identification import FEATURE_NAMES, FEATURE_VERSION, analyze

#: The drive and test run of each system (its record's metadata): the test's ``M_star`` [Nm] and
#: ``w_max`` [rad/s], the drive's ``M_N`` [Nm], ``T_s``, ``T_Ei`` [s], ``encoder_counts`` and the
#: measured current's noise std over ``M*/K_M``.
DRIVE_TRUTH_NAMES: tuple[str, ...] = ("M_star", "w_max", "M_N", "T_s", "T_Ei", "encoder_counts", "current_noise")
#: Truth columns stored per system (SI units; ``structure`` as index into STRUCTURE_CLASSES).
TRUTH_NAMES: tuple[str, ...] = (PARAM_NAMES + DERIVED_NAMES + ("s_N", "r_osc", "w_e_T_Ei", "structure")
                                + DRIVE_TRUTH_NAMES)
#: STEP-2 estimates and context figures stored per system.
ESTIMATE_NAMES: tuple[str, ...] = ("J_sigma", "M_FC", "mu_F", "M_0", "M_star", "osc_quanta", "rel_residual")


@dataclass(frozen=True)
class GenerateConfig:
    """What a dataset is made of. Equal configs make equal datasets.

    Without ``envelope``: the population of ``ranges`` on one ``drive`` with one test ``signal``.
    With ``envelope``: drives, test runs and mechanics drawn over SPEC 3.1's envelope
    (:func:`sim.sample_envelope`; ``ranges`` and ``drive`` are then unused, and of ``signal`` only
    its ``timeout`` and ``tail``)."""

    n: int
    seed: int
    shard_size: int = 500
    ranges: PopulationRanges = field(default_factory=PopulationRanges)
    drive: DriveConfig = field(default_factory=DriveConfig)
    signal: TestSignalConfig = field(default_factory=TestSignalConfig)
    envelope: EnvelopeRanges | None = None

    def __post_init__(self) -> None:
        if self.n < 1 or self.shard_size < 1:
            raise ValueError(f"GenerateConfig: expected n >= 1 and shard_size >= 1, received {self.n}, {self.shard_size}")

    def to_dict(self) -> dict[str, Any]:
        return {"n": self.n, "seed": self.seed, "shard_size": self.shard_size, "ranges": asdict(self.ranges),
                "drive": asdict(self.drive), "signal": asdict(self.signal),
                "envelope": None if self.envelope is None else asdict(self.envelope), "feature_version": FEATURE_VERSION,
                "feature_names": list(FEATURE_NAMES)}

    @property
    def n_shards(self) -> int:
        return -(-self.n // self.shard_size)


@dataclass
class Dataset:
    """A loaded dataset: ``features`` (N x F), ``truth``/``estimate`` dicts of (N,) arrays, ``ok`` (N,)."""

    features: np.ndarray
    truth: dict[str, np.ndarray]
    estimate: dict[str, np.ndarray]
    ok: np.ndarray
    config: dict[str, Any]
    sha256: str

    def __len__(self) -> int:
        return int(self.ok.shape[0])


def _analyze_one(record: Any) -> tuple[np.ndarray, np.ndarray] | str:
    """The features and STEP 2's estimates of ``record``, or why the analysis refused it."""
    try:
        a = analyze(record)
    except ValueError as err:
        return one_line(err)
    f = a.fit
    est = np.array([f.J_sigma, f.M_FC, f.mu_F, f.M_0, a.M_star, a.osc_quanta, f.rel_residual])
    return a.features, est


def _truth_row(truth: dict[str, Any], drive: DriveConfig, signal: TestSignalConfig) -> np.ndarray:
    row = dict(truth, M_star=signal.M_star, w_max=signal.w_max, M_N=drive.M_N, T_s=drive.T_s, T_Ei=drive.T_Ei,
               encoder_counts=drive.encoder_counts, current_noise=drive.current_noise(signal.M_star))
    row["w_e_T_Ei"] = truth["w_e"] * drive.T_Ei
    row["structure"] = STRUCTURE_CLASSES.index(truth["structure"])
    return np.array([float(row[k]) for k in TRUTH_NAMES])


def _prepare(out: Path, config: GenerateConfig) -> tuple[bool, list[int]]:
    """Check (or write) ``out/dataset.json``; whether this call wrote it, and the shards still missing."""
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "dataset.json"
    want = json.loads(dumps(config.to_dict()))  # as it reads back (tuples become lists)
    new = not cfg_path.exists()
    if not new:
        have = json.loads(cfg_path.read_text())
        if have != want:
            raise UserError(f"{out} holds a dataset of another config (n/seed/ranges/features differ); "
                            "choose a new folder or remove it")
    else:
        strays = sorted(p.name for p in out.glob("shard_*.npz"))
        if strays:  # shards no dataset.json vouches for: of another config, or not ours at all
            more = f" and {len(strays) - 1} more" if len(strays) > 1 else ""
            raise UserError(f"{out} holds shard files ({strays[0]}{more}) but no dataset.json that says what made "
                            "them; choose a new folder or remove them")
        atomic_write(cfg_path, lambda f: f.write(dumps(want, indent=1)), text=True)
    return new, [k for k in range(config.n_shards) if not (out / f"shard_{k:05d}.npz").exists()]


def _bounds(config: GenerateConfig, k: int) -> tuple[int, int]:
    """Systems ``[lo, hi)`` of shard ``k``."""
    return k * config.shard_size, min(config.n, (k + 1) * config.shard_size)


#: Systems per worker task: a worker simulates and analyses them (parameters in, features out; a
#: record never crosses a process boundary).
TASK_SYSTEMS = 16


def _task(fields: dict[str, np.ndarray], drive: DriveConfig, signal: TestSignalConfig, substeps: int,
          seed: int) -> tuple[dict[str, np.ndarray], dict[int, str]]:
    """Features, estimates, truth and ok of the systems ``TwoMassParams(**fields)`` (flat ``m``)
    tested with ``signal`` on ``drive``, simulated with ``substeps`` and current noise seeded
    ``seed + i`` for system ``i``; and why the analysis refused a system (by its index). The parameters come as numpy arrays: torch would hand a tensor
    to the worker as a shared-memory file descriptor, through a thread of this process that prints
    a traceback when the worker is ended during the hand-over (an interrupted run)."""
    sub = TwoMassParams(**fields)
    records = sorted(iter_records(sub, drive, signal, seed=seed, substeps=substeps),
                     key=lambda r: int(r.name[3:]))  # iter_records yields duration-sorted groups
    m = len(records)
    out = {"features": np.zeros((m, len(FEATURE_NAMES))), "estimate": np.full((m, len(ESTIMATE_NAMES)), np.nan),
           "truth": np.stack([_truth_row(r.meta["truth"], drive, signal) for r in records]),
           "ok": np.zeros(m, dtype=bool)}
    rejected: dict[int, str] = {}
    for i, record in enumerate(records):
        res = _analyze_one(record)
        if isinstance(res, str):
            rejected[i] = res
        else:
            out["features"][i], out["estimate"][i], out["ok"][i] = res[0], res[1], True
    return out, rejected


def _population(config: GenerateConfig) -> EnvelopeSample:
    """The systems, each on one of the drives and test runs ``cases`` (one case without an envelope)."""
    if config.envelope is None:
        return EnvelopeSample(sample_population(config.n, config.seed, config.ranges),
                              torch.zeros(config.n, dtype=torch.int64), ((config.drive, config.signal),))
    s = sample_envelope(config.n, config.seed, config.envelope)
    t = config.signal  # the envelope draws M* and w_max; timeout and tail are the config's
    return replace(s, cases=tuple((drive, TestSignalConfig(sig.M_star, sig.w_max, t.timeout, t.tail))
                                  for drive, sig in s.cases))


def _shard(k: int, population: EnvelopeSample, config: GenerateConfig, pool: Any,
           progress: Callable[[int], None] | None) -> tuple[dict[str, np.ndarray], dict[int, str]]:
    """The arrays of shard ``k``: a function of ``config`` and ``k`` alone (substeps per case within
    the shard, noise seeded per system), whatever the workers and their tasks; and why the analysis
    refused a system (by its index in the dataset)."""
    params, case, cases = population.params, population.cell.tolist(), population.cases
    lo, hi = _bounds(config, k)
    seed = config.seed * 1_000_003 + lo
    tasks: list[tuple[dict[str, np.ndarray], DriveConfig, TestSignalConfig, int, int]] = []
    cuts = [lo] + [i for i in range(lo + 1, hi) if case[i] != case[i - 1]] + [hi]
    for a, b in zip(cuts[:-1], cuts[1:]):  # runs of systems on one drive and test
        drive, signal = cases[case[a]]
        run = params[torch.arange(a, b)]
        substeps = default_substeps(run, drive)
        for j in range(0, b - a, TASK_SYSTEMS):
            sub = run[torch.arange(j, min(j + TASK_SYSTEMS, b - a))]
            fields = {k: getattr(sub, k).numpy() for k in PARAM_NAMES}
            tasks.append((fields, drive, signal, substeps, seed + a - lo + j))
    parts, rejected, start = [], {}, lo
    for part, refused in pool.map(_task, *zip(*tasks)):
        parts.append(part)
        rejected.update({start + i: reason for i, reason in refused.items()})
        start += len(part["ok"])
        if progress:
            progress(len(part["ok"]))
    return {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}, rejected


def generate(out_dir: str | os.PathLike[str], config: GenerateConfig, *, workers: int | None = None,
             progress: Callable[[int], None] | None = None) -> Path:
    """Make (or complete) the dataset of ``config`` in ``out_dir``; returns the folder.

    ``progress(k)`` is called with the number of systems finished since the last call.
    ``workers``: analysis processes (default: this process's share of the CPUs).

    Under ``torchrun`` the missing shards are dealt out to the ranks, one per rank and round; rank
    0 checks the folder and writes every shard (the same bytes a process alone writes) and is the
    only one to call ``progress``.
    """
    out = Path(out_dir)
    group = process_group()
    population = _population(config)  # before dataset.json: a config that cannot be drawn leaves nothing behind
    new, missing = group.on_main(lambda: _prepare(out, config))
    own = progress if group.main else None
    if own:
        own(config.n - sum(hi - lo for lo, hi in (_bounds(config, k) for k in missing)))
    written = False
    try:
        with worker_pool(workers or group.cpus()) as pool:
            for r in range(0, len(missing), group.world):
                deal = missing[r:r + group.world]  # shard deal[i] goes to rank i
                mine = _shard(deal[group.rank], population, config, pool, own) if group.rank < len(deal) else None
                for i, (k, (arrays, rejected)) in enumerate(zip(deal, group.gather(mine) or [])):
                    if rejected:  # before the shard: a shard on disk is done and never rewritten
                        rows = [{"system": j, "reason": why} for j, why in sorted(rejected.items())]
                        atomic_write(out / _rejected_name(k), lambda f: f.write(dumps({"rejected": rows})), text=True)
                    atomic_write(out / f"shard_{k:05d}.npz", lambda f: np.savez(f, **arrays))
                    written = True
                    if own and i != group.rank:
                        own(len(arrays["ok"]))
    except BaseException:
        if new and not written and group.main:  # nothing to resume: no dataset.json without a shard
            (out / "dataset.json").unlink(missing_ok=True)
        raise
    return out


def _rejected_name(k: int) -> str:
    return f"shard_{k:05d}.rejected.json"


def rejection_reasons(folder: str | os.PathLike[str]) -> dict[int, str]:
    """Why the analysis refused systems of the dataset in ``folder``: system index -> one line
    (from the shards' ``.rejected.json`` files; a shard written without one has none listed)."""
    reasons: dict[int, str] = {}
    for path in sorted(Path(folder).glob("shard_*.rejected.json")):
        try:
            reasons.update({int(row["system"]): str(row["reason"]) for row in json.loads(path.read_text())["rejected"]})
        except (ValueError, OSError, KeyError, TypeError, RecursionError):  # words only: an unreadable list is no error
            continue
    return reasons


def load_dataset(folder: str | os.PathLike[str]) -> Dataset:
    """Read a complete dataset folder (all shards present, feature version current)."""
    folder = Path(folder)
    cfg_path = folder / "dataset.json"
    if not cfg_path.exists():
        raise UserError(f"{folder}: no dataset.json; make one with `twomass generate`")
    config = json.loads(cfg_path.read_text())
    if config.get("feature_version") != FEATURE_VERSION:
        raise UserError(f"{folder}: features of version {config.get('feature_version')!r}, "
                        f"this toolkit computes {FEATURE_VERSION!r}; generate the data anew")
    n_shards = -(-int(config["n"]) // int(config["shard_size"]))
    paths = [folder / f"shard_{k:05d}.npz" for k in range(n_shards)]
    missing = [p.name for p in paths if not p.exists()]
    if missing:
        raise UserError(f"{folder}: {len(missing)} of {n_shards} shards missing (first {missing[0]}); "
                        "rerun the same `twomass generate` command to complete it")
    h = hashlib.sha256()
    parts: dict[str, list[np.ndarray]] = {"features": [], "estimate": [], "truth": [], "ok": []}
    for p in paths:
        data = p.read_bytes()
        h.update(data)
        try:
            z = np.load(io.BytesIO(data))
            if not isinstance(z, np.lib.npyio.NpzFile):  # a lone .npy array
                raise ValueError("a single array, not an .npz archive")
            with z:
                for key in parts:
                    parts[key].append(z[key])
        except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as err:  # not a shard generate wrote
            raise UserError(f"{p}: not a readable dataset shard ({one_line(err)}); "
                            "rerun `twomass generate` into a new folder") from None
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    truth = {n: cat["truth"][:, i] for i, n in enumerate(TRUTH_NAMES)}
    truth["structure"] = truth["structure"].astype(int)
    estimate = {n: cat["estimate"][:, i] for i, n in enumerate(ESTIMATE_NAMES)}
    return Dataset(cat["features"], truth, estimate, cat["ok"], config, h.hexdigest())
