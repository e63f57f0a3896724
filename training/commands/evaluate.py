"""``twomass evaluate``: SOM vs IV4 on the paper's grid and a random population (SPEC section 7)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from training.commands import _progress

HELP = "evaluate the SOM identification against IV4 on the paper's grid and a random set (tables + figures)"

DEFAULT_OUT = Path("docs/results")
DEFAULT_CACHE = Path("data/evaluate-cache")

#: Largest grid backlash width accepted by ``--backlash`` [degrees]: 10 x the default population's
#: widest (1 degree); wider is no gear backlash the test run or the maps are meant for.
MAX_BACKLASH_DEG = 10.0


def _floats(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, received {text!r}") from None
    if not vals:
        raise argparse.ArgumentTypeError(f"expected at least one number, received {text!r}")
    return vals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options (no heavy import here: ``--help`` stays fast; the grid defaults are filled in by :func:`run`)."""
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT,
                        help=f"report folder (default {DEFAULT_OUT}, relative to the working folder)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace report files already in --out (without it nothing is computed when any exists)")
    parser.add_argument("--seed", type=int, default=5,
                        help="seed of the grid draw; the random set uses seed + 1 (default 5)")
    parser.add_argument("--per-cell", type=int, default=20, help="systems per grid cell (default 20; 0 = no grid)")
    parser.add_argument("--population", type=int, default=1000, metavar="N",
                        help="systems of the random set from the default population (default 1000; 0 = none)")
    parser.add_argument("--f-e", type=_floats, default=None, metavar="LIST",
                        help="grid eigenfrequencies [Hz], comma-separated (default: the paper's 10,20,30,50,80,120)")
    parser.add_argument("--backlash", type=_floats, default=None, metavar="DEG_LIST",
                        help="grid backlash widths in DEGREES (total width 2s, as in the paper; parameter files "
                             f"and the JSON output use rad), 0 to {MAX_BACKLASH_DEG:g}, comma-separated (default: the "
                             "paper's 0,0.2,0.5)")
    parser.add_argument("--checkpoints", type=Path, default=None, help="map folder (default: the shipped maps)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                        help=f"cache of per-system results, keyed by config (default {DEFAULT_CACHE})")
    parser.add_argument("--no-cache", action="store_true", help="neither read nor write the cache")
    parser.add_argument("--workers", type=int, default=None,
                        help="analysis processes (default: CPU count, under torchrun each process's share; "
                             "0 = in this process)")
    only = parser.add_mutually_exclusive_group()
    only.add_argument("--no-iv4", action="store_true", help="SOM only (with and without the refinement)")
    only.add_argument("--no-som", action="store_true", help="IV4 only (e.g. while the maps are being retrained)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    parser.add_argument("--drives", type=int, default=None, metavar="N",
                        help="instead: the study on the matrix of six drives across the drive envelope (docs/contract.md), "
                             "N systems per drive (seed --seed), written to OUT/drives.md and OUT/drives.json; the "
                             "answers' confidence (interval coverage, calibration, warnings) to OUT/confidence.md, "
                             "OUT/confidence.json and OUT/fig_reliability.png")
    parser.add_argument("--envelope-drives", type=int, default=None, metavar="K",
                        help="with --drives N: instead of the matrix, K drives and tests drawn at random over the "
                             "drive envelope (seed --seed; drives no matrix chose), N systems each, and all together; "
                             "written to OUT/drives_envelope.md and OUT/drives_envelope.json (the confidence to "
                             "OUT/confidence_envelope.md, .json and OUT/fig_reliability_envelope.png)")
    parser.add_argument("--real-axis", nargs="?", const="both", default=None, metavar="EFFECT",
                        help="with --drives N (the matrix): the drives' populations with SPEC 1.1's load torque and "
                             "motor friction (docs/simulator.md): EFFECT both (the default: SPEC 1.1's population), "
                             "load (the load torque M_L0 alone) or motor (the motor friction M_FCM, mu_FM alone); the "
                             "figures gain M_L0 within 5 %%, M_FC and M_FCM within 1 %% of M*; written to "
                             "OUT/drives_real_axis.md, .json and OUT/confidence_real_axis.md, .json, "
                             "OUT/fig_reliability_real_axis.png (with load or motor: drives_real_axis_load.md etc.)")
    parser.add_argument("--drive-names", default=None, metavar="LIST",
                        help="with --drives N (the matrix): only these drives, comma-separated, each NAME or NAME=K "
                             "(K systems instead of N), e.g. reference=200,servo_200w,low_res_1ms (default: all six)")
    _progress.add_option(parser)


def command_line(args: argparse.Namespace) -> str:
    """The command that reproduces this run (every option that changes the results)."""
    parts = ["twomass evaluate", f"--out {args.out}", f"--seed {args.seed}", f"--per-cell {args.per_cell}",
             f"--population {args.population}", "--f-e " + ",".join(f"{v:g}" for v in args.f_e),
             "--backlash " + ",".join(f"{v:g}" for v in args.backlash)]
    if args.checkpoints is not None:
        parts.append(f"--checkpoints {args.checkpoints}")
    if args.no_iv4:
        parts.append("--no-iv4")
    if args.no_som:
        parts.append("--no-som")
    return " ".join(parts)


def _drive_study(args: argparse.Namespace) -> tuple[bool, str]:
    """Whether ``--drives`` runs on envelope drives, and its files' suffix (``""``, ``"_envelope"``,
    ``"_real_axis"``, ``"_real_axis_<effect>"`` but for ``both``); bad values raise ``ValueError`` (one line)."""
    from training.evaluation import real_axis_effect

    if args.drives < 1:
        raise ValueError(f"--drives: expected N >= 1 systems per drive, received {args.drives}")
    envelope = args.envelope_drives is not None
    if envelope and args.envelope_drives < 1:
        raise ValueError(f"--envelope-drives: expected K >= 1 drives, received {args.envelope_drives}")
    for option, value in (("--real-axis", args.real_axis), ("--drive-names", args.drive_names)):
        if value is not None and envelope:
            raise ValueError(f"{option}: the matrix's study only, not with --envelope-drives")
    if args.real_axis is None:
        return envelope, "_envelope" if envelope else ""
    try:
        real_axis_effect(args.real_axis)
    except ValueError as err:
        raise ValueError(f"--real-axis: {err}") from None
    return False, "_real_axis" + ("" if args.real_axis == "both" else f"_{args.real_axis}")


def _drive_counts(args: argparse.Namespace) -> dict[str, int]:
    """``--drive-names``: drive name of :data:`training.evaluation.DRIVES` -> systems (``NAME=K``, else
    ``--drives``), in the order given; without it every drive with ``--drives``. Bad values: ``ValueError``."""
    from training.evaluation import DRIVES

    if args.drive_names is None:
        return {name: args.drives for name in DRIVES}
    counts: dict[str, int] = {}
    for item in (v.strip() for v in args.drive_names.split(",") if v.strip()):
        name, _, k = item.partition("=")
        if name not in DRIVES:
            raise ValueError(f"--drive-names: expected drives of {', '.join(DRIVES)}, received {name!r}")
        if name in counts:
            raise ValueError(f"--drive-names: drive {name!r} given twice")
        if k and not (k.isdigit() and int(k) >= 1):
            raise ValueError(f"--drive-names: expected NAME=K with K >= 1 systems, received {item!r}")
        counts[name] = int(k) if k else args.drives
    if not counts:
        raise ValueError(f"--drive-names: expected at least one drive, received {args.drive_names!r}")
    return counts


def _run_drives(args: argparse.Namespace) -> int:
    """``--drives N``: per drive of :data:`training.evaluation.DRIVES` (with ``--envelope-drives K``: of K
    drives drawn over the envelope, and of all of them together), N systems identified and scored."""
    import json

    from som_torch import atomic_write
    from training._json import dumps
    from training.figures import refuse_existing
    from training.evaluation import (DRIVES, confidence_files, confidence_report, drive_figures, drive_rows,
                                     drives_markdown, envelope_rows, real_axis_effect, write_confidence)
    from training.identification import Identifier

    envelope, suffix = _drive_study(args)
    counts = _drive_counts(args)
    md, js = args.out / f"drives{suffix}.md", args.out / f"drives{suffix}.json"
    confidence_stem = f"confidence{suffix}"
    refuse_existing([md, js, *confidence_files(args.out, confidence_stem, plots=not args.no_plots)], args.overwrite)
    identifier = Identifier.load(args.checkpoints)
    command = _drives_command(args, envelope, counts)
    real_axis = args.real_axis is not None
    ranges = real_axis_effect(args.real_axis) if real_axis else False
    if envelope:
        runs = envelope_rows(args.envelope_drives, args.drives, args.seed, identifier)
        title = f"Identification on {args.envelope_drives} drives drawn at random over the drive envelope"
    else:
        runs = ((name, DRIVES[name].description,
                 drive_rows(DRIVES[name], k, args.seed, identifier, real_axis=ranges)) for name, k in counts.items())
        title = "Identification on a matrix of drives" + _real_axis_words(args.real_axis)
    figures, descriptions, by_drive = {}, {}, {}
    for name, words, rows in runs:  # a drive at a time: its figures as soon as they are known
        figures[name], descriptions[name], by_drive[name] = drive_figures(rows, real_axis), words, rows
        print(f"{name}: {json.dumps(figures[name])}", file=sys.stderr)
    if envelope:
        every = [r for rows in by_drive.values() for r in rows]
        figures["all"], descriptions["all"] = drive_figures(every), f"the {args.envelope_drives} drives together"
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(md, lambda f: f.write(drives_markdown(figures, command, descriptions, title)), text=True)
    atomic_write(js, lambda f: f.write(dumps({"command": command, "drives": figures, "descriptions": descriptions})
                                        + "\n"), text=True)
    confidence = write_confidence(confidence_report(by_drive), args.out, confidence_stem, command,
                                  {k: v for k, v in descriptions.items() if k in by_drive},
                                  f"Confidence of the answers: {title[0].lower()}{title[1:]}", plots=not args.no_plots)
    print(f"wrote {md}, {js} and " + ", ".join(str(p) for p in confidence))
    return 0


def _drives_command(args: argparse.Namespace, envelope: bool, counts: dict[str, int]) -> str:
    """The command that reproduces a ``--drives`` run (``counts``: :func:`_drive_counts`)."""
    real_axis = "" if args.real_axis is None else " --real-axis" + ("" if args.real_axis == "both"
                                                                     else f" {args.real_axis}")
    names = "" if args.drive_names is None else " --drive-names " + ",".join(f"{n}={k}" for n, k in counts.items())
    return (f"twomass evaluate --drives {args.drives}"
            + (f" --envelope-drives {args.envelope_drives}" if envelope else "") + real_axis + names
            + f" --seed {args.seed} --out {args.out}"
            + (f" --checkpoints {args.checkpoints}" if args.checkpoints is not None else ""))


def _real_axis_words(effect: str | None) -> str:
    """The real-axis effect (``--real-axis``) in a title: nothing without one."""
    if effect is None:
        return ""
    return " with real axes (SPEC 1.1)" + ("" if effect == "both" else f": the {effect} part alone")


def _check_grid(f_e: tuple[float, ...], backlash_deg: tuple[float, ...]) -> None:
    """Grid values the study can simulate: finite ``f_e`` > 0 at a bounded cost, backlash 0 ..
    :data:`MAX_BACKLASH_DEG`; else a :class:`UserError` naming the option."""
    from sim import DriveConfig, TwoMassParams
    from training._checks import check_sim_cost, finite_number
    from training.errors import UserError

    for f in f_e:
        finite_number("--f-e", f)
    check_sim_cost("--f-e", TwoMassParams.from_dicts([{"J_sigma": 0.05, "V_J": 1.0, "f_e": f} for f in f_e]),
                   DriveConfig())
    for b in backlash_deg:
        if not 0.0 <= b <= MAX_BACKLASH_DEG:  # NaN too
            raise UserError(f"--backlash: expected widths 0 .. {MAX_BACKLASH_DEG:g} degrees, received {b:g}")


def run(args: argparse.Namespace) -> int:
    from training._checks import seed

    seed("--seed", args.seed)
    if args.drives is not None:
        return _run_drives(args)
    if args.envelope_drives is not None:
        raise ValueError("--envelope-drives K: give the systems per drive with --drives N")
    from training._distributed import process_group
    from training.evaluation import (GRID_BACKLASH_DEG, GRID_F_E, grid_set, population_set, report_files, run_study,
                                     write_report)
    from training.figures import refuse_existing

    t0 = time.perf_counter()
    args.f_e = GRID_F_E if args.f_e is None else args.f_e
    args.backlash = GRID_BACKLASH_DEG if args.backlash is None else args.backlash
    _check_grid(args.f_e, args.backlash)
    group = process_group()  # under torchrun: the systems are split, rank 0 writes the report
    if args.per_cell < 0 or args.population < 0:
        raise ValueError(f"--per-cell and --population: expected >= 0, received {args.per_cell}, {args.population}")
    if args.per_cell == 0 and args.population == 0:
        raise ValueError("--per-cell and --population: expected at least one > 0, received both 0")
    workers = group.cpus() if args.workers is None else args.workers
    if workers < 0:
        raise ValueError(f"--workers: expected >= 0, received {workers}")
    methods = ("som", "maps") if args.no_iv4 else ("iv4",) if args.no_som else ("som", "maps", "iv4")
    sets = {}
    if args.per_cell:
        sets["grid"] = grid_set(args.per_cell, args.seed, f_e=args.f_e, backlash_deg=args.backlash)
    if args.population:
        sets["population"] = population_set(args.population, args.seed + 1)
    refuse_existing(report_files(args.out, list(sets), plots=not args.no_plots), args.overwrite)  # before the work
    with _progress.bar(args, show=_progress.wanted(args) and group.main, total=sum(s.size for s in sets.values()),
                       unit="sys", desc="evaluate") as bar:
        summary, rows_by_set = run_study(sets, methods=methods, checkpoints=args.checkpoints,
                                         cache_dir=None if args.no_cache else args.cache, workers=workers,
                                         progress=bar.update)
    if not group.main:
        return 0
    written = write_report(summary, rows_by_set, args.out, command=command_line(args), plots=not args.no_plots)
    _print_summary(summary, written)
    print(f"wrote {args.out / 'report.md'} and {len(written['files']) - 1} more files in "
          f"{time.perf_counter() - t0:.0f} s (the command's start-up not counted)")
    return 0


def _print_summary(summary: dict[str, Any], written: dict[str, Any]) -> None:
    if written["note"]:
        print(written["note"])
    for name, s in summary["sets"].items():
        rates = "; ".join(f"{m.upper()} E_30 {_fmt(s['overall'][m]['E_30'])} %, E_50 {_fmt(s['overall'][m]['E_50'])} %"
                          for m in summary["methods"])
        print(f"{name}: {s['n']} systems: {rates}")
    for c in summary["checks"]:
        print(f"check {'PASS' if c['passed'] else 'FAIL' if c['passed'] is False else 'n/a'}: {c['name']} ({c['detail']})")


def _fmt(x: float | None) -> str:
    return "–" if x is None else f"{x:.0f}"
