"""``twomass demo``: the main job on built-in defaults.

Simulates the SPEC test run on the reference drive for two plants (the default elastic plant and
one with clear backlash), identifies both records with the shipped maps exactly as
``twomass identify`` would, and prints identified against true values side by side, with the
quality figures (each explained in one line) and warnings. ``--params`` replaces the plants;
``--seed`` the noise. ``--json``: the JSON lines ``twomass identify`` would write for the records
(the README's example is the first of them).

How well the one test run determines each parameter is the 90 % interval of each value (SPEC 4.1)
where the maps carry a calibration (``twomass calibrate``), with the calibrated probability of the
class and of the whole answer; without one a line says so. Warnings (what to act on) are printed
apart from the notes (the codes of the uncertainty remarks the intervals already carry).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any, TextIO

from training.commands import _progress


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
    ("M_FC", "Nm", 1.0), ("mu_F", "Nm*s/rad", 1.0), ("M_L0", "Nm", 1.0), ("M_FCM", "Nm", 1.0),
    ("mu_FM", "Nm*s/rad", 1.0),
)


#: What each printed figure means: one line each, printed under the tables.
EXPLAINED: tuple[tuple[str, str], ...] = (
    ("s_N", "normalized backlash s*C_F/M_N: above 0.1 the backlash shapes the response"),
    ("r_osc", "oscillation-to-resolution ratio V_J*M*/(J_sigma*w_0*q_w): below 1 the encoder cannot see the "
              "elastic mode"),
    ("90 % interval", "where the maps carry a calibration: the truth lies inside for 9 of 10 answers (held-out "
                      "simulated records); +-x %: within x % of the value either side"),
    ("P(class)", "the calibrated probability of the identified class (next: the runner-up class)"),
    ("P(right)", "the calibrated probability that the answer is right: class right, f_e, V_J and J_sigma within "
                 "30 %"),
    ("warnings", "what to act on or distrust (a likely wrong answer, a record outside the envelope, a fault)"),
    ("notes", "the codes of the uncertainty remarks (docs/identification.md) that the intervals already carry"),
    ("map distance", "each map's recall distance over the 99 % quantile of held-out training records "
                     "(above 1: unlike the training data)"),
    ("oscillation", "rms of the oscillation in speed quanta of the encoder (below 1: elastic values uncertain)"),
    ("one-mass residual", "rms error of the rigid one-mass fit over the speed's rms (large: not rigid, or not the "
                          "test signal)"),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0, help="current-noise seed (default 0)")
    parser.add_argument("--params", metavar="JSON",
                        help="plants instead of the built-in two: a JSON object or list of objects (text or a file "
                             "path) with J_sigma, V_J, f_e, d, backlash [rad, total], M_FC, mu_F (or J_M, J_L, C_F, "
                             "D_F), optional name")
    parser.add_argument("--checkpoints", type=Path, metavar="DIR",
                        help="maps folder (default: the shipped maps, or $TWOMASS_CHECKPOINTS)")
    parser.add_argument("--json", action="store_true",
                        help="print the JSON lines `twomass identify` writes for the simulated records (SI units), "
                             "instead of the tables")
    _progress.add_option(parser)


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


def _interval_cell(name: str, value: float | None, true: float, intervals: Any, k: float) -> str:
    """The 90 % interval of ``name`` as :func:`training.identification.interval_text` writes it (in
    the shown unit, ``k`` x SI), marked where the true value ``true`` [SI] lies outside."""
    from training.identification import interval_text

    low, high = intervals[name]
    text = interval_text(name, value, (low, high), scale=k)
    return text if low <= true <= high else f"{text}  (true value outside)"


def _quality_line(res: Any) -> str:
    """The calibrated probabilities (class, runner-up, answer right; the structure map's, marked
    uncalibrated, where the maps carry no calibration) and the quality figures."""
    q = res.quality
    probs = q.structure_probabilities
    runner_up = max((c for c in probs if c != res.structure), key=probs.__getitem__, default=None)
    line = f"  quality: P({res.structure}) {probs[res.structure]:.2f}"
    if q.answer_probability is None:
        line += " uncalibrated"
    if runner_up is not None:
        line += f" (next: {runner_up} {probs[runner_up]:.2f})"
    if q.answer_probability is not None:
        line += f"; P(right) {q.answer_probability:.2f}"
    dist = ", ".join(f"{n} {_num(v)}" for n, v in q.map_distance_ratio.items())
    return (line + f"; map distance / training 99 % quantile: {dist}; oscillation {q.osc_quanta:.3g} speed quanta "
            f"rms; one-mass residual {100.0 * q.one_mass_rel_residual:.2g} %")


def print_result(label: str, truth: dict[str, Any], res: Any, n_samples: int, T_s: float, out: TextIO) -> None:
    """One plant: true vs identified table with each value's 90 % interval (where ``res.intervals``
    is given: the maps carry a calibration; else one line says there is none), the probabilities
    and quality line, the warnings, and the notes' codes (``res``: an ``IdentificationResult`` or
    ``IdentificationFailure``)."""
    print(f"\n{label}: record {n_samples} samples ({n_samples * T_s:.2f} s), true class {truth['structure']}, "
          f"s_N {truth['s_N']:.3g}, r_osc {truth['r_osc']:.3g}", file=out)
    if not res.ok:
        print(f"  identification failed: {res.error}", file=out)
        return
    intervals = res.intervals
    head = f"  {'':10} {'unit':>9} {'true':>16} {'identified':>16} {'error':>9}"
    print(head + ("" if intervals is None else "   90 % interval"), file=out)
    ok = "ok" if res.structure == truth["structure"] else "WRONG"
    print(f"  {'structure':10} {'-':>9} {truth['structure']:>16} {res.structure:>16} {ok:>9}", file=out)
    for name, unit, k in _ROWS:
        t = float(truth[name]) * k
        v = getattr(res.parameters, name)
        v = None if v is None else float(v) * k
        row = f"  {name:10} {unit:>9} {_num(t):>16} {_num(v):>16} {_rel(v, t):>9}"
        if intervals is not None:
            si = getattr(res.parameters, name)
            row += "   " + _interval_cell(name, None if si is None else float(si), float(truth[name]), intervals, k)
        print(row, file=out)
    if intervals is None:
        print("  90 % intervals: none (the maps carry no calibration; `twomass calibrate` makes one)", file=out)
    print(_quality_line(res), file=out)
    if res.quality.stiff_mode_note is not None:
        print(f"  note: {res.quality.stiff_mode_note}", file=out)
    print("  warnings: " + ("; ".join(w.text for w in res.warnings) or "none"), file=out)
    if res.notes:
        print("  notes: " + ", ".join(dict.fromkeys(w.code for w in res.notes)), file=out)


def _explain(out: TextIO) -> None:
    print("\nthe figures:", file=out)
    for name, text in EXPLAINED:
        print(f"  {name:18} {text}", file=out)


def run(args: argparse.Namespace) -> int:
    from sim import DriveConfig, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test
    from training._json import dumps
    from training.commands.identify import load_identifier
    from training._checks import check_sim_cost, seed
    from training.params_file import read_params_file

    seed("--seed", args.seed)
    drive, signal = DriveConfig(), TestSignalConfig()
    if args.params is None:
        labels = [label for label, _ in DEFAULT_PLANTS]
        params = TwoMassParams.from_dicts([dict(p) for _, p in DEFAULT_PLANTS])
    else:
        params, labels = read_params_file(args.params, name_prefix="plant")
        check_sim_cost("--params", params, drive)
    n = len(labels)
    steps = 1 + n
    with _progress.bar(args, total=steps, desc="demo", unit="step") as bar:
        bar.set_postfix_str("loading the maps")
        ident = load_identifier(args.checkpoints)
        bar.update(1)
        bar.set_postfix_str(f"simulating {n} test run(s)")
        resp = simulate_test(params, drive, signal, seed=args.seed)
        records = responses_to_records(resp, params, drive, signal, names=[f"demo{i}" for i in range(n)])
        results = []
        for i, rec in enumerate(records):
            bar.set_postfix_str(f"identifying {labels[i]}")
            results.append(replace(ident.identify_records([rec])[0], record=labels[i]))
            bar.update(1)
        if args.json:
            for res in results:
                print(dumps(res))
            return 1 if any(not r.ok for r in results) else 0
    out = sys.stdout
    print(f"twomass demo: reference drive (M_max {drive.M_max:g} Nm, K_M {drive.K_M:g} Nm/A, T_Ei "
          f"{drive.T_Ei * 1e3:g} ms, T_s {drive.T_s * 1e6:g} us, {round(math.log2(drive.encoder_counts))}-bit "
          f"encoder); test signal M* {signal.M_star:g} Nm, w_max {signal.w_max:g} rad/s; "
          "identified with the shipped maps", file=out)
    for label, rec, res in zip(labels, records, results):
        print_result(label, rec.meta["truth"], res, len(rec), drive.T_s, out)
    _explain(out)
    failed = sum(not r.ok for r in results)
    return 1 if failed else 0
