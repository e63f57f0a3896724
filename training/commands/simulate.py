"""``twomass simulate``: parameters in (JSON or a seeded population), records out (CSV + JSON).

Each system of ``--params`` runs on the reference drive or on the drive its keys give (``T_s``,
``encoder_counts``, ``T_Ei``, ``K_M``, ``M_N``, ``M_max``, ``current_noise_std``: checked against
SPEC 3.1's envelope, :mod:`training.params_file`); its record's metadata carries that drive.
A system may be a real axis (SPEC 1.1: keys ``M_L0``, ``M_FCM``, ``mu_FM``; ``--real-axis`` draws
them for ``--population``): it is held at rest by ``M_hold = M_L0`` before the test, whose levels
run around it (metadata ``M_hold``) unless ``--plain-levels``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from training.commands import _progress
from training.errors import OutputExistsError, UserError
from training.params_file import read_plants

HELP = "simulate the SPEC test run for given or sampled systems and write records (CSV + JSON)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--params", type=Path, help="JSON file: one system (object) or a list of systems; keys "
                     "J_sigma, V_J, f_e, d, backlash [rad, total], M_FC, mu_F (or J_M, J_L, C_F, D_F), optional name; "
                     "optional real-axis keys M_L0 [Nm, constant load torque, any sign], M_FCM [Nm, motor Coulomb "
                     "friction], mu_FM [Nm s/rad, motor viscous friction] (default 0); "
                     "optional drive keys per system T_s, encoder_counts, T_Ei, K_M, M_N, M_max, current_noise_std "
                     "(default: the reference drive's; checked against the drive envelope of docs/contract.md)")
    src.add_argument("--population", type=int, metavar="N", help="draw N systems from the SPEC default population")
    parser.add_argument("--real-axis", action="store_true",
                        help="with --population: add SPEC 1.1's real-axis parts (M_L0 in +-0.15 M* for half of the "
                             "systems, M_FCM 0..0.03 M* for half, mu_FM 0..0.002 Nm s/rad; on the reference test)")
    parser.add_argument("--plain-levels", action="store_true",
                        help="run the test's levels plain on an axis with a load torque M_L0 (held only before the "
                             "test; default: around the holding torque M_hold = M_L0, which the metadata records)")
    parser.add_argument("--seed", type=int, default=0, help="population and noise seed (default 0)")
    parser.add_argument("--out", type=Path, required=True, help="folder for NAME.csv + NAME.json")
    parser.add_argument("--M-star", type=float, default=10.0, help="test torque M* [Nm] (default 10)")
    parser.add_argument("--w-max", type=float, default=100.0, help="test speed limit w_max [rad/s] (default 100)")
    parser.add_argument("--timeout", type=float, default=10.0, help="safety timeout per section [s] (default 10)")
    parser.add_argument("--method", choices=("fast", "reference"), default="fast",
                        help="fast: fixed-step RK4 in the fused C kernel (the torch twin without it); reference: "
                             "adaptive dopri5 (torchdiffeq) in float64, slow, for checking (default fast)")
    parser.add_argument("--float64", action="store_true", help="integrate in float64 (default float32)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace existing records (without it nothing is written when any record exists)")
    _progress.add_option(parser)


def _refuse_existing(folder: Path, names: list[str], overwrite: bool) -> None:
    """Before anything is written: an :class:`OutputExistsError` naming the records of ``names``
    already in ``folder`` (unless ``overwrite``), so that a batch is written whole or not at all."""
    taken = [n for n in names if any((folder / f"{n}{ext}").exists() for ext in (".csv", ".json"))]
    if taken and not overwrite:
        shown = ", ".join(taken[:3]) + (f" and {len(taken) - 3} more" if len(taken) > 3 else "")
        raise OutputExistsError(f"--out {folder}: {len(taken)} of the {len(names)} records exist ({shown}); "
                                "nothing written (pass --overwrite to replace them)")


def _memory_estimate(params: Any, drive: Any, signal: Any, method: str, itemsize: int) -> float:
    """Bytes the simulation of ``params`` holds at once: the fast path one group of systems (``sim.iter_records``:
    512) at a time, the reference method all of them; each with its record's samples (as long as
    ``sim`` expects the test to run, at most every section timing out)."""
    from training._checks import BYTES_PER_SYSTEM

    n = params.J_sigma.numel()
    expected = float(signal.expected_duration(params.J_sigma.reshape(-1)).max()) / drive.T_s
    samples = min(signal.max_samples(drive), 1.25 * expected + 2048)
    per_sample = 2 * (3 * itemsize + 1) if method == "fast" else 64  # growing buffers are copied once
    at_once = min(n, 512) if method == "fast" else n
    return n * BYTES_PER_SYSTEM + at_once * samples * per_sample + 48 * samples  # + one record in float64


#: Bytes of a record's CSV row (t 17 digits, speed 12, current and torque_ref 7, section; 46 measured
#: on the default population) and of its JSON metadata (about 900 measured), for :func:`_disk_estimate`.
CSV_ROW_BYTES, META_BYTES = 48, 1024


def _disk_estimate(params: Any, drive: Any, signal: Any) -> float:
    """Bytes the records of ``params`` take on disk: each record's samples (1.5 x the duration
    ``sim`` expects: 1.47 measured; at most every section timing out) in CSV rows, and its metadata."""
    expected = signal.expected_duration(params.J_sigma.reshape(-1)) / drive.T_s
    samples = (1.5 * expected).clamp(max=signal.max_samples(drive))
    return float(samples.sum()) * CSV_ROW_BYTES + params.J_sigma.numel() * META_BYTES


def _signal(args: argparse.Namespace, drives: list[Any]) -> Any:
    """The test signal of the options: finite levels, ``M*`` within each drive's ``M_max`` (SPEC 3.1)."""
    from sim import TestSignalConfig
    from training._checks import finite_number

    for option, value in (("--M-star", args.M_star), ("--w-max", args.w_max), ("--timeout", args.timeout)):
        finite_number(option, value)
    M_max = min(d.M_max for d in drives)
    if args.M_star > M_max:
        raise UserError(f"--M-star: expected at most the drive's M_max {M_max:g} Nm (SPEC 3.1), "
                        f"received {args.M_star:g}")
    return TestSignalConfig(M_star=args.M_star, w_max=args.w_max, timeout=args.timeout)


def _runs(drives: list[Any]) -> list[tuple[int, int]]:
    """``(start, stop)`` of each run of consecutive systems on one drive (the simulator runs one drive
    per batch; each system's noise stays seeded by its index in the whole batch)."""
    starts = [i for i in range(len(drives)) if i == 0 or (drives[i] is not drives[i - 1] and drives[i] != drives[i - 1])]
    return list(zip(starts, starts[1:] + [len(drives)]))


def _params_text(truth: dict[str, Any]) -> str:
    from sim import ALL_PARAM_NAMES

    return ", ".join(f"{k} {truth[k]:.3g}" for k in ALL_PARAM_NAMES if k in truth)


def _plants(args: argparse.Namespace) -> tuple[Any, list[str] | None, list[Any]]:
    """The systems to simulate, their names (``None``: numbered) and drives: from ``--params``, else
    ``--population`` systems of the default (``--real-axis``: the real-axis) population."""
    from sim import DriveConfig, sample_population
    from training._checks import BYTES_PER_SYSTEM, check_memory

    if args.real_axis and args.params is not None:
        raise UserError("--real-axis: only with --population (give M_L0, M_FCM, mu_FM in the --params file instead)")
    if args.params is not None:
        plants = read_plants(args.params, "sys", M_star=args.M_star)
        return plants.params, plants.names, plants.drives
    if args.population < 1:
        raise UserError(f"--population: expected N >= 1, received {args.population}")
    check_memory(f"--population {args.population}", args.population * BYTES_PER_SYSTEM)
    return sample_population(args.population, args.seed, real_axis=args.real_axis), None, [DriveConfig()] * args.population


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from sim import RecordError, iter_records, write_record
    from training._checks import check_disk, check_memory, check_sim_cost, finite_number, seed

    finite_number("--M-star", args.M_star)  # the drives' noise is checked at it
    seed("--seed", args.seed)
    params, names, drives = _plants(args)
    signal = _signal(args, drives)
    n = params.J_sigma.numel()
    flat = params.reshape(-1)
    runs = _runs(drives)
    source = f"--params {args.params}" if args.params is not None else "--population"
    for start, stop in runs:
        check_sim_cost(source, flat[start:stop], drives[start])
    what = f"simulate ({n} systems, --timeout {args.timeout:g}, --w-max {args.w_max:g})"
    itemsize = 8 if args.float64 else 4
    check_memory(what, max(_memory_estimate(flat[start:stop], drives[start], signal, args.method, itemsize)
                           for start, stop in runs))
    check_disk(what, args.out, sum(_disk_estimate(flat[start:stop], drives[start], signal) for start, stop in runs))
    _refuse_existing(args.out, names or [f"sys{i:05d}" for i in range(n)], args.overwrite)
    dtype = torch.float64 if args.float64 else torch.float32
    bar = _progress.bar(args, total=n, desc="simulate", unit="sys")
    written = 0

    def records(start: int, stop: int) -> Iterator[Any]:
        """The records of systems ``start:stop`` (one drive), named by their index in the whole batch."""
        part, drive, part_seed = flat[start:stop], drives[start], args.seed + start
        if args.method == "reference":
            from sim import responses_to_records, simulate_test

            resp = simulate_test(part, drive, signal, method="reference", seed=part_seed,
                                 around_hold=not args.plain_levels)
            part_names = names[start:stop] if names is not None else [f"sys{i:05d}" for i in range(start, stop)]
            yield from responses_to_records(resp, part, drive, signal, names=part_names)
            bar.update(stop - start)
            return
        for rec in iter_records(part, drive, signal, seed=part_seed, dtype=dtype, around_hold=not args.plain_levels):
            i = start + int(rec.name[3:])
            rec.name = names[i] if names is not None else f"sys{i:05d}"
            yield rec

    for rec in (rec for start, stop in runs for rec in records(start, stop)):
        try:
            write_record(args.out / rec.name, rec, overwrite=args.overwrite)  # refuses NaN/inf, writing nothing
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM between its CSV and its JSON: no half record stays
            for ext in (".csv", ".json"):
                (args.out / f"{rec.name}{ext}").unlink(missing_ok=True)
            raise
        except RecordError:
            if np.isfinite(rec.speed).all() and np.isfinite(rec.current).all():
                raise
            raise UserError(f"{rec.name}: the simulation diverged (non-finite speed or current; {written} record(s) "
                            f"written before it): its parameters lie far outside what the simulator resolves "
                            f"({_params_text(rec.meta['truth'])})") from None
        written += 1
        if args.method == "fast":
            bar.update(1)
    bar.close()
    print(f"wrote {written} record(s) to {args.out}", file=sys.stderr)
    return 0
