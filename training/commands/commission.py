"""``twomass commission``: the self-commissioning chain (SPEC 8) on simulated plants, with a report.

Per plant: adapt the test signal within the limits, identify with the shipped maps, validate by
re-simulation, refuse (with the reason) or propose a PI speed controller, fine-tune it and check
the result on the plant. A refusal is a normal outcome: it is printed clearly and the exit code
stays 0. ``--population N`` adds a summary over the plants.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from som_torch import atomic_write
from training._json import dumps
from training.errors import OutputExistsError, UserError
from training.params_file import read_params_file

HELP = "run the self-commissioning chain (test signal, identify, validate, propose, tune) on simulated plants"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--params", type=Path, help="JSON file: one plant (object) or a list of plants; keys J_sigma, V_J, "
                     "f_e, d, backlash [rad, total 2s], M_FC, mu_F (or J_M, J_L, C_F, D_F), optional name")
    src.add_argument("--population", type=int, metavar="N", help="draw N plants from the SPEC default population")
    parser.add_argument("--seed", type=int, default=0, help="population and noise seed (default 0)")
    parser.add_argument("--w-limit", type=float, default=100.0, help="speed limit |w| [rad/s] for the test runs (default 100)")
    parser.add_argument("--travel-limit", type=float, default=100.0,
                        help="travel limit |phi| [rad] from the start position (default 100)")
    parser.add_argument("--M-star-max", type=float, default=None, help="torque cap for the test [Nm] (default: drive M_max)")
    parser.add_argument("--no-tune", action="store_true", help="stop after the proposal (still evaluated on the plant)")
    parser.add_argument("--tune-evaluations", type=int, default=30,
                        help="Nelder-Mead evaluations on the identified linear model (default 30)")
    parser.add_argument("--plant-evaluations", type=int, default=0,
                        help="extra Nelder-Mead evaluations on the plant after the pre-tune (default 0)")
    parser.add_argument("--fallback-evaluations", type=int, default=20,
                        help="after a refusal: Nelder-Mead evaluations on the plant for the cautious fallback "
                             "controller F1 (default 20; 0: end with the refusal)")
    parser.add_argument("--max-map-distance", type=float, default=3.0,
                        help="refusal rule V4: largest map distance / training 99 %% quantile of a used map (default 3)")
    parser.add_argument("--validation", choices=("switching", "replay"), default="replay",
                        help="re-simulation mode of the validation (default replay: the recorded torque "
                             "reference open loop; switching: the test's switching law)")
    parser.add_argument("--plots", type=Path, help="folder for PNG plots (needs matplotlib, the 'plot' extra)")
    parser.add_argument("--logdir", type=Path, help="TensorBoard log folder (scalars of the search)")
    parser.add_argument("--json", type=Path, help="write the reports (and the summary) as JSON to this file "
                        "(NaN and inf as null)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    parser.add_argument("--checkpoints", type=Path, help="folder with the maps (default: the shipped checkpoints/)")
    parser.add_argument("--quiet", action="store_true", help="print only the summary with --population")
    parser.add_argument("--no-progress", action="store_true")


def _check_positive(name: str, v: float | None) -> None:
    if v is not None and not (math.isfinite(v) and v > 0):
        raise UserError(f"{name}: expected a finite number > 0, received {v}")


def _pyplot() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UserError("--plots needs matplotlib: pip install -e '.[plot]'") from None
    return plt


def _plot(report: Any, folder: Path) -> None:
    """The test record against its re-simulation and the closed-loop runs before/after tuning, as
    ``folder/<name>.png``."""
    import numpy as np

    plt = _pyplot()
    T_s = float(report.drive.T_s)
    fig, axes = plt.subplots(3 if report.responses else 1, 1, figsize=(8, 9 if report.responses else 3.5), squeeze=False)
    ax = axes[0, 0]
    if report.validation is not None:
        v = report.validation
        t = np.arange(len(v.measured)) * T_s
        ax.plot(t, v.measured, label="measured")
        ax.plot(t, v.simulated, "--", label="identified model")
        ax.set_title(f"{report.name}: test record vs re-simulation ({v.reason})", fontsize=9)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("w_M [rad/s]")
    ax.legend(fontsize=8)
    if report.responses:
        sc = report.responses["scenario"]
        t = np.arange(sc.n_segment) * T_s * 1e3
        for j, (title, ax) in enumerate((("speed step", axes[1, 0]), (f"load {sc.M_L:g} Nm", axes[2, 0]))):
            ax.plot(t, report.responses["before"][j], label="proposal")
            ax.plot(t, report.responses["after"][j], label="tuned")
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("t [ms]")
            ax.set_ylabel("w_M [rad/s]")
            ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        atomic_write(folder / f"{report.name}.png", lambda f: fig.savefig(f, format="png", dpi=90))
    finally:
        plt.close(fig)


def _refuse_existing(path: Path | None, overwrite: bool) -> None:
    if path is not None and path.exists() and not overwrite:
        raise OutputExistsError(f"--json: {str(path)!r} exists (pass --overwrite to replace it)")


def _plants(args: argparse.Namespace) -> tuple[Any, list[str]]:
    """The plants (``TwoMassParams``) and their names, from ``--population`` or ``--params``."""
    import sim

    if args.population is not None:
        if args.population < 1:
            raise UserError(f"--population: expected N >= 1, received {args.population}")
        return sim.sample_population(args.population, args.seed), [f"plant{i:03d}" for i in range(args.population)]
    if args.params is not None:
        return read_params_file(args.params, "plant")
    raise UserError("give --params JSON or --population N")


def run(args: argparse.Namespace) -> int:
    import sim
    from training.commissioning import CommissioningConfig, ExcitationLimits, commission, summarize, summary_text
    from training.identification import Identifier

    for name in ("--w-limit", "--travel-limit", "--M-star-max", "--max-map-distance"):
        _check_positive(name, getattr(args, name[2:].replace("-", "_")))
    config = CommissioningConfig(tune=not args.no_tune, max_map_distance_ratio=args.max_map_distance,
                                 tune_evaluations=args.tune_evaluations, plant_evaluations=args.plant_evaluations,
                                 fallback_evaluations=args.fallback_evaluations, validation_mode=args.validation)
    _refuse_existing(args.json, args.overwrite)
    drive = sim.DriveConfig()
    params, names = _plants(args)
    if args.checkpoints is not None and not args.checkpoints.is_dir():
        raise UserError(f"--checkpoints: {args.checkpoints} is not a folder")
    limits = ExcitationLimits(w_limit=args.w_limit, travel_limit=args.travel_limit, M_star_max=args.M_star_max)
    identifier = Identifier.load(args.checkpoints)
    writer = None
    if args.logdir is not None:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(args.logdir))
    if args.plots is not None:
        _pyplot()
    flat = params.reshape(-1)
    n = flat.J_sigma.numel()
    say = (lambda msg: None) if args.no_progress else (lambda msg: print(msg, file=sys.stderr, flush=True))
    reports = []
    t0 = time.perf_counter()
    for i in range(n):
        say(f"[{i + 1}/{n}] {names[i]}")
        rep = commission(flat[i], drive, limits, identifier=identifier, config=replace(config, seed=args.seed + 1000 * i),
                         writer=writer, progress=say, name=names[i])
        reports.append(rep)
        if writer is not None:
            for k, v in (("cost_proposal", rep.plant_costs.get("proposal")), ("cost_tuned", rep.plant_costs.get("tuned")),
                         ("improvement", rep.improvement), ("refused", float(rep.refused))):
                if v is not None:
                    writer.add_scalar(f"commission/{k}", v, i)
        if args.plots is not None:
            _plot(rep, args.plots)
        if not (args.quiet and args.population is not None):
            print(rep.to_text(), flush=True)
            print(flush=True)
    summary = summarize(reports, time.perf_counter() - t0) if n > 1 or args.population is not None else None
    if summary is not None:
        print(summary_text(summary), flush=True)
    if writer is not None:
        writer.close()
    if args.json is not None:
        _refuse_existing(args.json, args.overwrite)  # it may have appeared while we worked
        text = dumps({"reports": [r.to_dict() for r in reports], "summary": summary}, indent=1)
        atomic_write(args.json, lambda f: f.write(text), text=True)
    return 0
