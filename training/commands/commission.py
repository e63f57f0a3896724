"""``twomass commission``: the self-commissioning chain (SPEC 8) on simulated plants, with a report.

Per plant: adapt the test signal within the limits, identify with the shipped maps, validate by
re-simulation, refuse (with the reason) or propose a PI speed controller, fine-tune it and check
the result on the plant. A refusal is a normal outcome: it is printed clearly and the exit code
stays 0. ``--population N`` adds a summary over the plants.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from training.errors import UserError
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
    parser.add_argument("--json", type=Path, help="write the reports (and the summary) as JSON to this file")
    parser.add_argument("--checkpoints", type=Path, help="folder with the maps (default: the shipped checkpoints/)")
    parser.add_argument("--quiet", action="store_true", help="print only the summary with --population")
    parser.add_argument("--no-progress", action="store_true")


def _check_positive(name: str, v: float | None) -> None:
    if v is not None and not (math.isfinite(v) and v > 0):
        raise UserError(f"{name}: expected a finite number > 0, received {v}")


def summarize(reports: list[Any], wall_s: float) -> dict[str, Any]:
    """Figures over many plants: refusals by rule, limit checks, stability over the plants that end
    with a controller (model-based or fallback), improvement over the model-based proposals
    (improvement = 1 - tuned/proposal cost on the plant; a fallback starts from a loop too slow to
    settle in the test window, so its 'improvement' says little)."""
    acc = [r for r in reports if r.controller is not None]
    refused = [r for r in reports if r.refused]
    by_rule: dict[str, int] = {}
    for r in refused:
        rule = r.permission.reason.split(" ", 1)[0]
        by_rule[rule] = by_rule.get(rule, 0) + 1
    imps = [(r.improvement, r.name) for r in acc if r.improvement is not None and not r.fallback]
    worst = min(imps) if imps else (None, None)
    return {
        "plants": len(reports),
        "with_controller": len(acc),
        "model_based": sum(1 for r in acc if not r.fallback),
        "fallback": sum(1 for r in acc if r.fallback),
        "refused": len(refused),
        "refused_by_rule": by_rule,
        "within_limits": sum(bool(r.checks.get("within_limits")) for r in reports),
        "stable": sum(bool(r.checks.get("stable")) for r in acc),
        "tuned_not_worse": sum(bool(r.checks.get("tuned_not_worse")) for r in acc),
        "median_improvement": statistics.median(i for i, _ in imps) if imps else None,
        "worst_improvement": worst[0],
        "worst_plant": worst[1],
        "best_improvement": max(i for i, _ in imps) if imps else None,
        "structure_correct": sum(r.identification.get("structure") == r.truth.get("structure") for r in reports),
        "wall_s": wall_s,
    }


def summary_text(s: dict[str, Any]) -> str:
    def pct(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"
    rules = ", ".join(f"{k} {v}" for k, v in sorted(s["refused_by_rule"].items())) or "none"
    return "\n".join([
        f"== summary over {s['plants']} plants ==",
        f"limits kept in every test run: {s['within_limits']}/{s['plants']}",
        f"identified structure = true class: {s['structure_correct']}/{s['plants']}",
        f"refused for a model-based controller: {s['refused']}/{s['plants']} ({rules}); "
        f"ended with a controller: {s['with_controller']}/{s['plants']} "
        f"({s['model_based']} model-based, {s['fallback']} cautious fallback F1 tuned on the plant)",
        f"over those: stable closed loop {s['stable']}/{s['with_controller']}, "
        f"tuned cost <= proposal cost on the plant {s['tuned_not_worse']}/{s['with_controller']}",
        f"cost improvement of the model-based proposals on the plant (1 - tuned/proposal): "
        f"median {pct(s['median_improvement'])}, "
        f"worst {pct(s['worst_improvement'])} ({s['worst_plant']}), best {pct(s['best_improvement'])}",
        f"wall time {s['wall_s']:.0f} s",
    ])


def _plot(report: Any, folder: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UserError("--plots needs matplotlib: pip install -e '.[plot]'") from None
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
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
    tmp = folder / f".{report.name}.png.tmp"
    fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
    os.replace(tmp, folder / f"{report.name}.png")


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)


def run(args: argparse.Namespace) -> int:
    import sim
    from training.commissioning._chain import commission
    from training.commissioning._excitation import ExcitationLimits
    from training.identification._identifier import Identifier

    for name in ("--w-limit", "--travel-limit", "--M-star-max", "--max-map-distance"):
        _check_positive(name, getattr(args, name[2:].replace("-", "_")))
    if args.tune_evaluations < 1 or args.plant_evaluations < 0 or args.fallback_evaluations < 0:
        raise UserError(f"--tune-evaluations >= 1, --plant-evaluations >= 0 and --fallback-evaluations >= 0 expected, "
                        f"received {args.tune_evaluations}, {args.plant_evaluations}, {args.fallback_evaluations}")
    drive = sim.DriveConfig()
    if args.population is not None:
        if args.population < 1:
            raise UserError(f"--population: expected N >= 1, received {args.population}")
        params = sim.sample_population(args.population, args.seed)
        names = [f"plant{i:03d}" for i in range(args.population)]
    elif args.params is not None:
        params, names = read_params_file(args.params, "plant")
    else:
        raise UserError("give --params JSON or --population N")
    if args.checkpoints is not None and not args.checkpoints.is_dir():
        raise UserError(f"--checkpoints: {args.checkpoints} is not a folder")
    limits = ExcitationLimits(w_limit=args.w_limit, travel_limit=args.travel_limit, M_star_max=args.M_star_max)
    identifier = Identifier.load(args.checkpoints)
    writer = None
    if args.logdir is not None:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(args.logdir))
    if args.plots is not None:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            raise UserError("--plots needs matplotlib: pip install -e '.[plot]'") from None
    flat = params.reshape(-1)
    n = flat.J_sigma.numel()
    say = (lambda msg: None) if args.no_progress else (lambda msg: print(msg, file=sys.stderr, flush=True))
    reports = []
    t0 = time.perf_counter()
    for i in range(n):
        say(f"[{i + 1}/{n}] {names[i]}")
        rep = commission(flat[i], drive, limits, identifier=identifier, seed=args.seed + 1000 * i, tune=not args.no_tune,
                         writer=writer, progress=say, max_map_distance_ratio=args.max_map_distance,
                         tune_evaluations=args.tune_evaluations, plant_evaluations=args.plant_evaluations,
                         name=names[i], validation_mode=args.validation,
                         fallback_evaluations=args.fallback_evaluations)
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
    wall = time.perf_counter() - t0
    summary = summarize(reports, wall) if n > 1 or args.population is not None else None
    if summary is not None:
        print(summary_text(summary), flush=True)
    if writer is not None:
        writer.close()
    if args.json is not None:
        _write_json(args.json, {"reports": [r.to_dict() for r in reports], "summary": summary})
    return 0
