"""``twomass demo``: the main job on built-in defaults.

Simulates the SPEC test run on the reference drive for two plants (the default elastic plant and
one with clear backlash), identifies both records with the shipped maps exactly as
``twomass identify`` would, and prints identified against true values side by side, with the
quality figures and warnings. ``--params`` replaces the plants; ``--seed`` the noise.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any, TextIO


HELP = ("simulate two default plants, identify them with the shipped maps, print identified vs true "
        "(no arguments needed)")

#: The built-in plants: (label, parameters; backlash = total width 2s [rad]).
DEFAULT_PLANTS: tuple[tuple[str, dict[str, float]], ...] = (
    ("elastic plant", dict(J_sigma=0.05, V_J=1.0, f_e=30.0, d=0.02, backlash=math.radians(0.1), M_FC=0.2, mu_F=0.001)),
    ("plant with backlash", dict(J_sigma=0.05, V_J=1.0, f_e=40.0, d=0.02, backlash=math.radians(0.5), M_FC=0.2,
                                 mu_F=0.001)),
)

#: Rows of the table: parameter, unit, factor from SI to the shown unit.
_ROWS: tuple[tuple[str, str, float], ...] = (
    ("J_sigma", "kg*m^2", 1.0), ("V_J", "-", 1.0), ("J_M", "kg*m^2", 1.0), ("J_L", "kg*m^2", 1.0),
    ("f_e", "Hz", 1.0), ("C_F", "Nm/rad", 1.0), ("d", "-", 1.0), ("backlash", "deg", 180.0 / math.pi),
    ("M_FC", "Nm", 1.0), ("mu_F", "Nm*s/rad", 1.0),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0, help="current-noise seed (default 0)")
    parser.add_argument("--params", metavar="JSON",
                        help="plants instead of the built-in two: a JSON object or list of objects (text or a file "
                             "path) with J_sigma, V_J, f_e, d, backlash [rad, total], M_FC, mu_F (or J_M, J_L, C_F, "
                             "D_F), optional name")
    parser.add_argument("--checkpoints", type=Path, metavar="DIR",
                        help="maps folder (default: the shipped checkpoints/)")


def _num(x: float | None) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.4g}"


def _rel(ident: float | None, true: float) -> str:
    if ident is None:
        return "n/a"
    if true == 0:
        return "exact" if ident == 0 else "-"
    return f"{100.0 * (ident - true) / abs(true):+.1f} %"


def print_result(label: str, truth: dict[str, Any], res: Any, n_samples: int, T_s: float, out: TextIO) -> None:
    """One plant: true vs identified table, quality line, warnings (``res``: an
    ``IdentificationResult`` or ``IdentificationFailure``)."""
    print(f"\n{label}: record {n_samples} samples ({n_samples * T_s:.2f} s), true class {truth['structure']}, "
          f"s_N {truth['s_N']:.3g}, r_osc {truth['r_osc']:.3g}", file=out)
    if not res.ok:
        print(f"  identification failed: {res.error}", file=out)
        return
    print(f"  {'':10} {'unit':>9} {'true':>16} {'identified':>16} {'error':>9}", file=out)
    ok = "ok" if res.structure == truth["structure"] else "WRONG"
    print(f"  {'structure':10} {'-':>9} {truth['structure']:>16} {res.structure:>16} {ok:>9}", file=out)
    for name, unit, k in _ROWS:
        t = float(truth[name]) * k
        v = getattr(res.parameters, name)
        v = None if v is None else float(v) * k
        print(f"  {name:10} {unit:>9} {_num(t):>16} {_num(v):>16} {_rel(v, t):>9}", file=out)
    q = res.quality
    dist = ", ".join(f"{n} {_num(v)}" for n, v in q.map_distance_ratio.items())
    print(f"  quality: P({res.structure}) {q.structure_probabilities[res.structure]:.2f}; "
          f"map distance / training 99 % quantile: {dist}; oscillation {q.osc_quanta:.3g} speed quanta rms; "
          f"one-mass residual {100.0 * q.one_mass_rel_residual:.2g} %", file=out)
    print("  warnings: " + ("; ".join(w.text for w in res.warnings) or "none"), file=out)


def run(args: argparse.Namespace) -> int:
    from sim import DriveConfig, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test
    from training.commands.identify import load_identifier
    from training.params_file import read_params_file

    if args.params is None:
        labels = [label for label, _ in DEFAULT_PLANTS]
        params = TwoMassParams.from_dicts([dict(p) for _, p in DEFAULT_PLANTS])
    else:
        params, labels = read_params_file(args.params, name_prefix="plant")
    drive, signal = DriveConfig(), TestSignalConfig()
    ident = load_identifier(args.checkpoints)
    resp = simulate_test(params, drive, signal, seed=args.seed)
    records = responses_to_records(resp, params, drive, signal, names=[f"demo{i}" for i in range(len(labels))])
    results = ident.identify_records(records)
    out = sys.stdout
    print(f"twomass demo: reference drive (M_max {drive.M_max:g} Nm, K_M {drive.K_M:g} Nm/A, T_Ei "
          f"{drive.T_Ei * 1e3:g} ms, T_s {drive.T_s * 1e6:g} us, {round(math.log2(drive.encoder_counts))}-bit "
          f"encoder); test signal M* {signal.M_star:g} Nm, w_max {signal.w_max:g} rad/s; "
          "identified with the shipped maps", file=out)
    for label, rec, res in zip(labels, records, results):
        print_result(label, rec.meta["truth"], res, len(rec), drive.T_s, out)
    failed = sum(not r.ok for r in results)
    return 1 if failed else 0
