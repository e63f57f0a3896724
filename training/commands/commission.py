"""``twomass commission``: the self-commissioning chain (SPEC 8) through a SPEC 8.1 drive, with a report.

The drive: the project's simulator (``--params`` / ``--population``: one :class:`sim.SimulatedDrive`
per plant, on the plant's drive keys in ``--params``, else the reference drive), a user's drive object
(``--drive MODULE:FACTORY``, the module found in the current folder as ``python -m`` finds it, or
``--drive path/file.py:FACTORY``; with ``--params`` / ``--population`` the factory is called with each
plant's parameters as a dict, for simulators and hardware-in-the-loop rigs that take one), or a folder
of files for a real drive and its scope (``--resume DIR``: :class:`training.commissioning.FileDrive`).

Limits are the user's (SPEC 8.2): a user's drive (``--drive``) gets no default limits,
``--w-limit`` and ``--travel-limit`` are required with it (``--resume``: the folder's
``drive.json``); only the simulator has the documented defaults. The first record that shows a
limit passed ends the experiments on that drive: one line on stderr says which, by how much, in
which experiment, nothing is delivered. Every drive call is bounded by ``--drive-timeout``.

Exit codes: 0 when every drive got a controller inside the limits (a refusal answered by the
fallback F1 included), and when an experiment waits for its recording (``--resume``);
:data:`EXIT_NOT_DELIVERED` (3) when a drive got no controller or an experiment passed a limit (the
report says why); 2 for bad input or a drive that fails (raises, does not answer in time, returns
a malformed record; one line).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from training._json import dumps
from training.commands import _progress
from training.errors import CommissioningError, ExperimentPending, OutputExistsError, UserError, error_text, one_line
from training.params_file import read_plants

if TYPE_CHECKING:  # the command imports these lazily, when it runs
    import sim
    from training.commissioning import CommissioningConfig, CommissioningReport, RecordIdentifier

#: Exit code when a drive got no controller, or an experiment passed a limit (the reports say which).
EXIT_NOT_DELIVERED = 3
#: The simulator's limits when none are given (``--params`` / ``--population`` without ``--drive``);
#: a user's drive has none: its limits are the user's to give.
DEFAULT_W_LIMIT, DEFAULT_TRAVEL_LIMIT = 100.0, 100.0
#: The longest a drive call may take [s] by default (``--drive-timeout``).
DEFAULT_DRIVE_TIMEOUT = 600.0
#: The longest the drive's ``close()`` is waited for after a fault of the drive [s].
CLOSE_AFTER_FAULT = 10.0

HELP = "run the self-commissioning chain (test signal, identify, validate, propose, tune) through a drive"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--params", type=Path, help="JSON file: one plant (object) or a list of plants; keys J_sigma, V_J, "
                     "f_e, d, backlash [rad, total 2s], M_FC, mu_F (or J_M, J_L, C_F, D_F), optional name; "
                     "optional drive keys per plant T_s, encoder_counts, T_Ei, K_M, M_N, M_max, current_noise_std "
                     "(default: the reference drive's; checked against the drive envelope of docs/contract.md)")
    src.add_argument("--population", type=int, metavar="N", help="draw N plants from the SPEC default population")
    src.add_argument("--resume", type=Path, metavar="DIR",
                     help="a file-based drive: DIR/drive.json (config, limits); the chain writes each experiment it "
                          "wants as DIR/NNN_request.json and stops; run again once DIR/NNN.csv + NNN.json are there "
                          "(the JSON may leave out what drive.json's config holds). A recording must be the experiment "
                          "requested (its torque level, its length; else exit 2); one that shows a limit passed ends "
                          "the run (exit 3). The folder's limits hold for its whole run: --w-limit, --travel-limit, "
                          "--M-max must equal them (else exit 2), --drive is refused")
    parser.add_argument("--drive", metavar="MODULE:FACTORY",
                        help="a SPEC 8.1 drive from FACTORY() in a module (found in the current folder, then on "
                             "PYTHONPATH) or a path/to/file.py (with --params/--population: FACTORY(plant_dict) per "
                             "plant); needs --w-limit and --travel-limit")
    parser.add_argument("--seed", type=int, default=0, help="population and noise seed (default 0)")
    parser.add_argument("--w-limit", type=float, default=None,
                        help=f"speed limit |w| [rad/s] for every experiment, at least 10 speed quanta of the drive's encoder; "
                             f"required with --drive (the simulator alone: default {DEFAULT_W_LIMIT:g})")
    parser.add_argument("--travel-limit", type=float, default=None,
                        help=f"travel limit |phi| [rad] from the start position of each experiment; required with --drive "
                             f"(the simulator alone: default {DEFAULT_TRAVEL_LIMIT:g})")
    parser.add_argument("--M-max", type=float, default=None,
                        help="torque limit [Nm] (default: the drive's M_max); the drive is handed min(this, its M_max)")
    parser.add_argument("--drive-timeout", type=float, default=DEFAULT_DRIVE_TIMEOUT, metavar="SECONDS",
                        help=f"longest a drive call (one experiment) may take (default {DEFAULT_DRIVE_TIMEOUT:g} s); past it "
                             f"the drive is a fault: one line, no further experiment, exit 2. The call cannot be killed: "
                             f"it runs in a background thread that is abandoned")
    parser.add_argument("--no-tune", action="store_true", help="no tuning: the proposal only (still run on the drive)")
    parser.add_argument("--tune-evaluations", type=int, default=30,
                        help="Nelder-Mead evaluations on the identified model (default 30)")
    parser.add_argument("--no-fallback", action="store_true",
                        help="after a refusal, end with it (no cautious fallback controller F1)")
    parser.add_argument("--max-map-distance", type=float, default=3.0,
                        help="refusal rule V4: largest map distance / training 99 %% quantile of a used map (default 3)")
    parser.add_argument("--validation", choices=("switching", "replay"), default="replay",
                        help="re-simulation mode of the validation (default replay: the recorded torque "
                             "reference open loop; switching: the test's switching law)")
    parser.add_argument("--no-measure", action="store_true",
                        help="no frequency-response experiment on the chosen loop and no redesign with it (faster)")
    parser.add_argument("--plots", type=Path, help="folder for one PNG page per drive: the test runs, the closed loop before and after "
                        "tuning (motor; load as the model estimates it), the delivered loop's Bode plot with its "
                        "margins; where the frequency response was measured also NAME_frf.png: measured beside the "
                        "model, with the coherence (needs matplotlib, the 'plot' extra)")
    parser.add_argument("--frf", type=Path, metavar="DIR",
                        help="folder for the frequency response measured on each drive as CSV, NAME_frf.csv: columns "
                             "f_Hz, magnitude_dB, phase_deg, coherence, model_magnitude_dB, model_phase_deg (torque "
                             "reference -> motor speed, both sample delays included); none for a drive not measured")
    parser.add_argument("--logdir", type=Path, help="TensorBoard log folder (scalars of the search)")
    parser.add_argument("--json", type=Path, help="write the reports (and the summary) as JSON to this file "
                        "(NaN and inf as null)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --json file, --plots page or --frf file")
    parser.add_argument("--checkpoints", type=Path, help="folder with the maps (default: the shipped checkpoints/)")
    parser.add_argument("--quiet", action="store_true", help="print only the summary (also for one drive), not the reports")
    parser.epilog = (f"safety: a drive of your own (--drive) needs --w-limit and --travel-limit; every experiment is handed "
                     f"concrete limits (M_max included); the first record that shows a limit passed (speed, travel, torque "
                     f"above the cap) ends all experiments on that drive and nothing is delivered. "
                     f"exit codes: 0 every drive got a controller inside the limits (or an experiment waits for its recording); "
                     f"{EXIT_NOT_DELIVERED} a drive got no controller or an experiment passed a limit (one line says which); "
                     f"2 bad input or a failing drive (it raises or exits, does not answer in time, returns a malformed "
                     f"or cut record)")
    _progress.add_option(parser)


def _plot(report: Any, folder: Path, overwrite: bool) -> None:
    """``folder/<name>.png``: the commissioning page (:func:`training.figures.commission_figure`);
    ``folder/<name>_frf.png`` where the frequency response was measured (its Bode page)."""
    from training.figures import commission_figure, frf_figure, save_png

    save_png(commission_figure(report), folder / f"{report.name}.png", overwrite=overwrite)
    if report.measured is not None:
        save_png(frf_figure(report), folder / f"{report.name}_frf.png", overwrite=overwrite)


def _refuse_existing(option: str, paths: list[Path], overwrite: bool) -> None:
    """Refuse an output of ``option`` (``--json``, ``--plots``) that exists, without ``--overwrite``."""
    if overwrite:
        return
    for path in paths:
        if path.exists():
            raise OutputExistsError(f"{option}: {str(path)!r} exists (pass --overwrite to replace it)")


def _import_module(name: str) -> Any:
    """The module ``name``, found as ``python -m`` finds it: in the current folder first (on
    ``sys.path`` while it imports), then on ``sys.path`` (``PYTHONPATH``, installed packages)."""
    cwd = os.getcwd()
    sys.path.insert(0, cwd)
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as err:
        if err.name is not None and name != err.name and not name.startswith(f"{err.name}."):
            raise UserError(f"--drive: importing {name} failed: {error_text(err)}") from None  # one of its imports
        raise UserError(f"--drive: cannot import {name!r}: no such module in the current folder {cwd} or on "
                        f"PYTHONPATH; give its file instead: --drive path/to/{name.replace('.', '/')}.py:FACTORY") from None
    except Exception as err:  # whatever the user's module raises: one line, not a traceback
        raise UserError(f"--drive: importing {name} failed: {error_text(err)}") from None
    finally:
        sys.path.remove(cwd)


def load_factory(spec: str) -> Any:
    """``MODULE:FACTORY`` (a module in the current folder or on ``sys.path``) or
    ``path/to/file.py:FACTORY`` -> the callable."""
    mod_name, sep, attr = spec.rpartition(":")
    if not sep or not mod_name or not attr:
        raise UserError(f"--drive: expected MODULE:FACTORY or path/to/file.py:FACTORY, received {spec!r}")
    if mod_name.endswith(".py"):
        path = Path(mod_name)
        if not path.is_file():
            raise UserError(f"--drive: {mod_name} is not a file")
        loader = importlib.util.spec_from_file_location(f"_twomass_drive_{path.stem}", path)
        module = importlib.util.module_from_spec(loader)
        sys.modules[loader.name] = module  # multiprocessing (spawn) finds the module's functions again
        folder = str(path.resolve().parent)
        sys.path.insert(0, folder)  # the file's sibling modules import while it loads
        try:
            loader.loader.exec_module(module)
        except Exception as err:  # whatever the user's file raises: one line, not a traceback
            del sys.modules[loader.name]
            raise UserError(f"--drive: importing {mod_name} failed: {error_text(err)}") from None
        finally:
            sys.path.remove(folder)
    else:
        module = _import_module(mod_name)
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise UserError(f"--drive: {mod_name} has no callable {attr!r}")
    return factory


def _plants(args: argparse.Namespace) -> tuple[list[dict[str, float]] | None, list[str], list[Any]]:
    """The plants' parameters, names and simulated drives (``sim.DriveConfig``), from ``--population``
    (the reference drive) or ``--params`` (each plant's drive keys; None: no plants)."""
    import sim

    if args.population is not None:
        if args.population < 1:
            raise UserError(f"--population: expected N >= 1, received {args.population}")
        return (sim.sample_population(args.population, args.seed).to_dicts(),
                [f"plant{i:03d}" for i in range(args.population)], [sim.DriveConfig()] * args.population)
    if args.params is not None:
        from training._checks import check_sim_cost

        plants = read_plants(args.params, "plant")  # a drive's noise checked at its rated torque M_N
        flat = plants.params.reshape(-1)
        for i, drive in enumerate(plants.drives):
            check_sim_cost(f"--params {args.params}", flat[i:i + 1], drive)
        return flat.to_dicts(), plants.names, plants.drives
    return None, [], []


def _same_limits(args: argparse.Namespace, stored: Any) -> None:
    """``--resume DIR``: the folder's drive and limits hold for its whole run; a ``--drive`` or a limit
    option that differs from ``DIR/drive.json`` is refused (the chain would plan with other limits)."""
    if args.drive is not None:
        raise UserError(f"--resume {args.resume} is the drive: --drive {args.drive} cannot be used with it")
    for opt, given, have in (("--w-limit", args.w_limit, stored.w_max), ("--travel-limit", args.travel_limit, stored.travel),
                             ("--M-max", args.M_max, stored.M_max)):
        if given is not None and not (have is not None and math.isclose(given, have, rel_tol=1e-12)):
            raise UserError(f"--resume {args.resume}: {opt} {given:g} differs from the folder's drive.json ({have}); its limits "
                            f"hold for the whole run: drop {opt}, or start a new folder with the new limits")


def _drives(args: argparse.Namespace, limits: Any) -> tuple[list[tuple[str, Any]], Any]:
    """``[(name, drive)]`` (built lazily: a factory is called per plant when its turn comes) and the limits."""
    import sim
    from training.commissioning import FileDrive

    if args.resume is not None:
        fd = FileDrive(args.resume)
        _same_limits(args, fd.limits)
        return [(fd.name, lambda: fd)], fd.limits
    plants, names, configs = _plants(args)
    if args.drive is not None:
        factory = load_factory(args.drive)
        if plants is None:
            return [("drive", factory)], limits
        return [(n, lambda p=p: factory(p)) for n, p in zip(names, plants)], limits
    if plants is None:
        raise UserError("give --params JSON, --population N, --drive MODULE:FACTORY or --resume DIR")
    return [(n, lambda p=p, c=c, i=i: sim.SimulatedDrive(p, c, seed=args.seed + 1000 * i))
            for i, (n, p, c) in enumerate(zip(names, plants, configs))], limits


def _check_options(args: argparse.Namespace) -> None:
    """Bad usage refused before any work: pages asked for and not drawable, a bad seed, a limit or
    bound that is not a finite number, a drive timeout not above 0, a drive of the user's own
    without its limits (before its module is even imported)."""
    from training._checks import finite_number, seed

    if args.plots is not None:
        from training.figures import require_plots

        require_plots("--plots")
    seed("--seed", args.seed)
    for name in ("--w-limit", "--travel-limit", "--M-max", "--max-map-distance", "--drive-timeout"):
        value = getattr(args, name[2:].replace("-", "_"))
        if value is not None:
            finite_number(name, value)
    if args.drive_timeout <= 0:
        raise UserError(f"--drive-timeout: expected seconds > 0, received {args.drive_timeout:g}")
    missing = [opt for opt, v in (("--w-limit", args.w_limit), ("--travel-limit", args.travel_limit)) if v is None]
    if args.drive is not None and args.resume is None and missing:
        raise UserError(f"--drive {args.drive}: {' and '.join(missing)} required: the limits of a drive of your own are yours "
                        f"to give (no defaults); e.g. --w-limit 20 --travel-limit 5 (rad/s, rad)")


def _settings(args: argparse.Namespace) -> CommissioningConfig:
    """The chain's settings (:class:`training.commissioning.CommissioningConfig`) from the options."""
    from training.commissioning import CommissioningConfig

    return CommissioningConfig(tune=not args.no_tune, max_map_distance_ratio=args.max_map_distance,
                               tune_evaluations=args.tune_evaluations, fallback=not args.no_fallback,
                               validation_mode=args.validation, drive_timeout=args.drive_timeout,
                               measure_response=not args.no_measure)


def _user_limits(args: argparse.Namespace) -> sim.DriveLimits:
    """The user's limits from the options (the simulator's defaults where none are given)."""
    import sim

    return sim.DriveLimits(w_max=DEFAULT_W_LIMIT if args.w_limit is None else args.w_limit,
                           travel=DEFAULT_TRAVEL_LIMIT if args.travel_limit is None else args.travel_limit, M_max=args.M_max)


def _identifier(args: argparse.Namespace) -> RecordIdentifier:
    """The identifier on the maps of ``--checkpoints`` (default: the shipped ones)."""
    from training.identification import Identifier

    if args.checkpoints is not None and not args.checkpoints.is_dir():
        raise UserError(f"--checkpoints: {args.checkpoints} is not a folder")
    return Identifier.load(args.checkpoints)


def _writer(args: argparse.Namespace) -> Any:
    """A TensorBoard writer on ``--logdir`` (None without it)."""
    if args.logdir is None:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(args.logdir))


@dataclass(frozen=True)
class _Session:
    """What every drive of one command shares: the options, the chain's settings, the user's
    limits, the identifier, the TensorBoard writer (or None) and where progress goes."""

    args: argparse.Namespace
    settings: CommissioningConfig
    limits: sim.DriveLimits
    identifier: RecordIdentifier
    writer: Any
    say: Callable[[str], None]


def _build(session: _Session, name: str, make: Callable[[], Any]) -> Any:
    """The drive ``name`` from its factory; what a user's factory raises is one line naming it."""
    try:
        return make()
    except (ExperimentPending, UserError):
        raise
    except Exception as err:  # the user's factory: one line naming it
        raise UserError(f"--drive {session.args.drive}: building drive {name!r} failed: {error_text(err)}") from None


def _commission_drive(session: _Session, name: str, drive: Any) -> CommissioningReport:
    """The chain on one drive, the drive closed after it; a fault of the drive is one line naming it."""
    from training.commissioning import commission

    timeout = session.settings.drive_timeout
    try:
        report = commission(drive, session.limits, identifier=session.identifier, config=session.settings,
                            writer=session.writer, progress=session.say, name=name)
    except CommissioningError as err:
        _close(drive, name, timeout, quiet=True)  # the first fault is the story
        raise CommissioningError(f"drive {name!r}: {one_line(err)}") from None
    except BaseException:
        _close(drive, name, timeout, quiet=True)
        raise
    _close(drive, name, timeout)
    return report


def _show(session: _Session, index: int, report: CommissioningReport) -> None:
    """One drive's report: a passed limit's line on stderr, its TensorBoard scalars, its page and its text."""
    args, writer = session.args, session.writer
    if report.breach is not None:
        print(f"twomass commission: drive {report.name!r}: {report.breach.text()}", file=sys.stderr, flush=True)
    if writer is not None:
        for key, value in (("improvement", report.improvement), ("refused", float(report.refused)),
                           ("delivered", float(report.delivered is not None))):
            if value is not None:
                writer.add_scalar(f"commission/{key}", value, index)
    if args.plots is not None:
        _plot(report, args.plots, args.overwrite)
    if args.frf is not None and report.measured is not None:
        report.measured.to_csv(args.frf / f"{report.name}_frf.csv")
    if not args.quiet:
        print(report.to_text(), flush=True)
        print(flush=True)


def _write_json(args: argparse.Namespace, reports: list[CommissioningReport], summary: dict[str, Any] | None) -> None:
    """``--json``: the reports and the summary, written at once (refused where it appeared meanwhile)."""
    from som_torch import atomic_write

    _refuse_existing("--json", [args.json], args.overwrite)  # it may have appeared while we worked
    text = dumps({"reports": [r.to_dict() for r in reports], "summary": summary}, indent=1)
    atomic_write(args.json, lambda f: f.write(text), text=True)


def _exit_code(reports: list[CommissioningReport]) -> int:
    """0 when every drive got a controller inside the limits; :data:`EXIT_NOT_DELIVERED` otherwise
    (the drives without one named on stderr)."""
    failed = [r.name for r in reports if r.breach is None and (r.delivered is None or not r.checks.get("within_limits", False))]
    if failed:
        print(f"twomass commission: no controller or a limit passed for: {', '.join(failed)} (exit {EXIT_NOT_DELIVERED})",
              file=sys.stderr)
        return EXIT_NOT_DELIVERED
    return EXIT_NOT_DELIVERED if any(r.breach is not None for r in reports) else 0


def run(args: argparse.Namespace) -> int:
    """The options checked, the outputs refused where they exist, then the chain on each drive in
    turn (its report shown as it ends), the summary, ``--json``; the exit code (module docstring)."""
    from training.commissioning import summarize, summary_text

    _check_options(args)
    settings = _settings(args)
    _refuse_existing("--json", [] if args.json is None else [args.json], args.overwrite)
    drives, limits = _drives(args, _user_limits(args))
    _refuse_existing("--plots", [] if args.plots is None else [args.plots / f"{name}{end}" for name, _ in drives
                                                                for end in (".png", "_frf.png")],
                     args.overwrite)  # before any experiment
    _refuse_existing("--frf", [] if args.frf is None else [args.frf / f"{name}_frf.csv" for name, _ in drives], args.overwrite)
    session = _Session(args, settings, limits, _identifier(args), _writer(args), _progress_line(args))
    reports = []
    started = time.perf_counter()
    try:
        for i, (name, make) in enumerate(drives):
            session.say(f"[{i + 1}/{len(drives)}] {name}")
            reports.append(_commission_drive(session, name, _build(session, name, make)))
            _show(session, i, reports[-1])
    except ExperimentPending as pending:
        print(str(pending), flush=True)
        return 0
    finally:
        if session.writer is not None:
            session.writer.close()
    summary = summarize(reports, time.perf_counter() - started) if len(drives) > 1 or args.quiet else None
    if summary is not None:
        print(summary_text(summary), flush=True)
    if args.json is not None:
        _write_json(args, reports, summary)
    return _exit_code(reports)


def _progress_line(args: argparse.Namespace) -> Callable[[str], None]:
    """Where progress goes: one line each on stderr where wanted (:func:`_progress.wanted`), else nowhere."""
    if _progress.wanted(args):
        return lambda msg: print(msg, file=sys.stderr, flush=True)
    return lambda msg: None


def _close(drive: Any, name: str, timeout: float, quiet: bool = False) -> None:
    """The drive's ``close()``, bounded by the drive timeout; a fault of it is the drive's fault
    (one line, exit 2). ``quiet``: an earlier fault is being reported: close within
    :data:`CLOSE_AFTER_FAULT` seconds at most, and say nothing of its own fault."""
    from training.commissioning import close_drive

    try:
        close_drive(drive, min(timeout, CLOSE_AFTER_FAULT) if quiet else timeout)
    except ValueError as err:  # CommissioningError, UserError
        if not quiet:
            raise CommissioningError(f"drive {name!r}: {one_line(err)}") from None
