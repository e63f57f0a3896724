"""``twomass simulate``: parameters in (JSON or a seeded population), records out (CSV + JSON)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from training.commands import _progress
from training.errors import OutputExistsError, UserError
from training.params_file import read_params_file

HELP = "simulate the SPEC test run for given or sampled systems and write records (CSV + JSON)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--params", type=Path, help="JSON file: one system (object) or a list of systems; keys "
                     "J_sigma, V_J, f_e, d, backlash [rad, total], M_FC, mu_F (or J_M, J_L, C_F, D_F), optional name")
    src.add_argument("--population", type=int, metavar="N", help="draw N systems from the SPEC default population")
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


def run(args: argparse.Namespace) -> int:
    import torch

    from sim import DriveConfig, TestSignalConfig, iter_records, sample_population, write_record

    drive = DriveConfig()
    signal = TestSignalConfig(M_star=args.M_star, w_max=args.w_max, timeout=args.timeout)
    if args.params is not None:
        params, names = read_params_file(args.params, "sys")
    else:
        if args.population < 1:
            raise UserError(f"--population: expected N >= 1, received {args.population}")
        params, names = sample_population(args.population, args.seed), None
    n = params.J_sigma.numel()
    _refuse_existing(args.out, names or [f"sys{i:05d}" for i in range(n)], args.overwrite)
    dtype = torch.float64 if args.float64 else torch.float32
    bar = _progress.bar(args, total=n, desc="simulate", unit="sys")
    written = 0
    if args.method == "reference":
        from sim import responses_to_records, simulate_test

        resp = simulate_test(params, drive, signal, method="reference", seed=args.seed)
        records = responses_to_records(resp, params, drive, signal, names=names)
        bar.update(n)
    else:
        records = iter_records(params, drive, signal, seed=args.seed, dtype=dtype)
    for rec in records:
        if names is not None and args.method == "fast":
            rec.name = names[int(rec.name[3:])]
        write_record(args.out / rec.name, rec, overwrite=args.overwrite)
        written += 1
        if args.method == "fast":
            bar.update(1)
    bar.close()
    print(f"wrote {written} record(s) to {args.out}", file=sys.stderr)
    return 0
