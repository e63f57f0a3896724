"""``twomass bench commission``: what the commissioning delivers against what the true plant allows.

Per plant of the SPEC population (``--seed``, never the development study set ``sample_population(50,
0)``) and per drive (the reference: SPEC's first-order current loop; and a second-order current
loop, damping 1/sqrt(2), same sum time constant, with one extra sample of delay), the chain
(:func:`training.commissioning.commission`, the shipped maps) runs on an independent plant in
another process (:mod:`training.bench._remote_plant`) under the user's limits ``--w-max``,
``--travel``. Then, on the drive's TRUE linear plant:

- the oracle's crossover (:func:`training.bench._oracle.oracle`: the largest first gain crossover of
  the law's structure at PM >= 45 deg, GM >= 6 dB, reference-to-load peak <= 6 dB, stable);
- the delivered law's true figures (:func:`training.bench._oracle.true_figures`) and the ratio of
  its crossover to the oracle's (0 where nothing was delivered or it has no crossover);
- a limit-cycle check of the delivered law on the NONLINEAR plant (backlash, friction), :func:`limit_cycle`;
- whether every experiment of the chain kept the limits on the plant's own true states.

The summary holds these against the targets of SPEC 8.2 (``TARGETS``).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from training.bench._remote_plant import SECOND_ORDER_DELAYED, PlantOptions, RemoteDrive
from training.bench._report import Table, machine_line, write_figures
from training.errors import UserError

HELP = ("commissioning: the delivered speed loop's true crossover and margins against the largest the true plant "
        "allows (the oracle), N population plants x 2 drives on an independent plant in another process")

#: The default population seed: plants the chain was never tuned on (0 is the development study set).
DEFAULT_SEED = 2611


@dataclass(frozen=True)
class BenchDrive:
    """One drive of the bench: its label and the plant's unmodelled effects."""

    label: str
    options: PlantOptions


#: The two drives per plant.
DRIVES = (BenchDrive("reference", PlantOptions()), BenchDrive("2nd-order+delay", SECOND_ORDER_DELAYED))


@dataclass(frozen=True)
class Targets:
    """SPEC 8.2's figures for the bench (each per drive, over the plants)."""

    median_ratio: float = 0.8
    """Delivered/oracle crossover, median over the plants."""
    class_median_ratio: float = 0.7
    """... median within each class."""
    ratio_floor: float = 0.5
    """Delivered/oracle at least this ..."""
    below_floor_allowed: int = 2
    """... on all but this many plants (of 24)."""
    fallback_allowed: int = 1
    """F1 on at most this many plants (of 24)."""
    min_phase_margin: float = 40.0
    """True phase margin [deg] of every delivered loop."""
    min_gain_margin_dB: float = 6.0
    """True gain margin [dB] of every delivered loop."""
    max_load_peak_dB: float = 20 * math.log10(2.0)
    """True reference-to-load peak [dB] of a loop that does not ring the load (the oracle's bound:
    a delivered loop above it may pass the oracle's crossover, its ratio above 1)."""


TARGETS = Targets()


@dataclass(frozen=True)
class LimitCycleCheck:
    """The limit-cycle criterion (:func:`limit_cycle`): per hold segment, the last quarter of the
    measured speed, a straight line removed (a slow loop's settling is not an oscillation), has an RMS
    above ``max(quanta` speed quanta, share x step)`` and at least ``sustain`` x the RMS of the
    quarter before (not decaying)."""

    quanta: float = 4.0
    """Speed quanta ``2 pi/(counts T_s)`` of RMS the encoder's dither may reach on its own."""
    share: float = 0.05
    """Share of the step's speed an oscillation must exceed to count."""
    sustain: float = 0.5
    """Last-quarter RMS over the previous quarter's: below it, the oscillation decays."""
    crossovers: float = 25.0
    """Each segment lasts this many ``1/w_c`` ..."""
    segment_s: tuple[float, float] = (0.25, 1.0)
    """... within these bounds [s] (the plant runs in another process: samples cost time)."""
    step_share: float = 0.1
    """The step is this share of the speed limit (and at most a quarter of the travel over two segments)."""
    disturbance_share: float = 0.5
    """The disturbance torque is this share of ``Kp`` x the step speed ..."""
    disturbance_cap: float = 0.2
    """... at most this share of the drive's nominal torque ``M_N``."""


LIMIT_CYCLE = LimitCycleCheck()


@dataclass
class BenchRow:
    """One plant on one drive. ``delivered``: ``model``, ``F1`` or ``none``; ``refusal``: the refusal
    rule's code (None: none); ``ratio``: delivered true ``w_c`` / oracle's (0: nothing delivered);
    ``limit_cycle``: None where not checked (nothing delivered); ``within_limits``: every experiment of
    the chain kept ``|w_M| <= w_max`` and ``|phi_M| <= travel`` on the plant's true states."""

    plant: int
    drive: str
    structure: str
    f_e: float
    V_J: float
    backlash: float
    oracle_w_c: float
    oracle_notches: int
    delivered: str
    refusal: str | None
    fallback_reason: str | None
    stated_w_c: float | None
    w_c: float | None
    ratio: float
    phase_margin: float | None
    gain_margin_dB: float | None
    load_peak_dB: float | None
    stable: bool | None
    limit_cycle: bool | None
    within_limits: bool
    true_peaks: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--plants", type=int, default=24, help="population plants (default 24)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED,
                        help=f"population seed (default {DEFAULT_SEED}; 0 is the development study set)")
    parser.add_argument("--w-max", type=float, default=20.0, help="the user's speed limit [rad/s] (default 20)")
    parser.add_argument("--travel", type=float, default=5.0, help="the user's travel limit [rad] (default 5)")
    parser.add_argument("--only", default=None, help="run only these plants of the N, e.g. 3,7 (names stay)")
    parser.add_argument("--json", dest="json_out", default=None, help="also write the rows and the summary to this JSON file")


def _selection(args: argparse.Namespace) -> list[int]:
    """The plant indices to run; UserError for a bad option."""
    if args.plants < 1:
        raise UserError(f"--plants: expected a positive integer, received {args.plants}")
    for name in ("w_max", "travel"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise UserError(f"--{name.replace('_', '-')}: expected a finite number > 0, received {value}")
    if args.only is None:
        return list(range(args.plants))
    try:
        only = sorted({int(i) for i in args.only.split(",")})
    except ValueError:
        raise UserError(f"--only: expected plant numbers separated by commas, received {args.only!r}") from None
    if not all(0 <= i < args.plants for i in only):
        raise UserError(f"--only: expected plant numbers 0..{args.plants - 1}, received {args.only!r}")
    return only


def limit_cycle_scenario(w_c: float, Kp: float, limits: Any, config: Any, check: LimitCycleCheck = LIMIT_CYCLE):
    """Four hold segments from rest: step to ``w_s``; a disturbance torque ``M_d`` on; back to 0 with it;
    0 without it. Returns the :class:`sim.Scenario`, the segment length [samples] and ``w_s``."""
    import sim

    lo, hi = check.segment_s
    seg_s = min(max(check.crossovers / w_c, lo), hi) if math.isfinite(w_c) and w_c > 0 else hi
    n = max(8, round(seg_s / config.T_s))
    w_s = min(check.step_share * limits.w_max, limits.travel / (4 * seg_s))
    M_d = min(check.disturbance_share * Kp * w_s, check.disturbance_cap * config.M_N)
    w_ref = np.concatenate([np.full(2 * n, w_s), np.zeros(2 * n)])
    M_dist = np.concatenate([np.zeros(n), np.full(2 * n, M_d), np.zeros(n)])
    return sim.Scenario(w_ref=w_ref, M_dist=M_dist), n, w_s


def oscillates(speed: np.ndarray, n: int, w_s: float, q_w: float, check: LimitCycleCheck = LIMIT_CYCLE) -> bool:
    """The criterion of :class:`LimitCycleCheck` on the measured ``speed`` of segments of ``n`` samples."""
    threshold = max(check.quanta * q_w, check.share * w_s)
    q = n // 4
    t = np.arange(q, dtype=float)

    def rms(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean((x - np.polyval(np.polyfit(t, x, 1), t)) ** 2))) if len(x) == q else 0.0

    for start in range(0, len(speed) - n + 1, n):
        last, before = rms(speed[start + n - q:start + n]), rms(speed[start + n - 2 * q:start + n - q])
        if last > threshold and last >= check.sustain * before:
            return True
    return False


def limit_cycle(drive: RemoteDrive, law: Any, w_c: float, Kp: float, limits: Any) -> bool:
    """Run ``law`` on the drive's nonlinear plant (:func:`limit_cycle_scenario`) and apply :func:`oscillates`
    (a run stopped at a limit counts as one)."""
    config = drive.config
    scenario, n, w_s = limit_cycle_scenario(w_c, Kp, limits, config)
    record = drive.run_closed_loop(law, scenario, limits)
    if record.meta.get("aborted"):
        return True
    q_w = 2 * math.pi / (config.encoder_counts * config.T_s)
    return oscillates(np.asarray(record.speed, dtype=float), n, w_s, q_w)


def _true_plant(p: dict[str, float], options: PlantOptions, config: Any):
    from training.commissioning import linear_plant, mechanics_from

    mech = mechanics_from(p)
    return mech, linear_plant(mech, config, current_loop_damping=options.current_loop_damping,
                              extra_delay=options.extra_delay)


def run_one(index: int, p: dict[str, float], bench_drive: BenchDrive, limits: Any, identifier: Any) -> BenchRow:
    """The chain, the oracle and the checks on plant ``index`` (parameters ``p``) on ``bench_drive``."""
    from training.bench._oracle import oracle, true_figures
    from training.commissioning import commission

    t0 = time.perf_counter()
    drive = RemoteDrive(p, options=bench_drive.options)
    try:
        rep = commission(drive, limits, identifier=identifier, name=f"plant{index:03d}")
        chain_runs = list(drive.experiments)
        mech, plant = _true_plant(p, bench_drive.options, drive.config)
        ref = oracle(plant, mech)
        d = rep.delivered
        figs = true_figures(plant, d.Kp, d.Ti, d.T_f, d.notch) if d is not None else None
        cycle = None if d is None else limit_cycle(drive, d.law(drive.config), figs.w_c, d.Kp, limits)
    finally:
        drive.close()
    peaks = {k: max((e[k] for e in chain_runs), default=0.0) for k in ("w_M", "w_L", "phi_M")}
    w_c = figs.w_c if figs is not None and math.isfinite(figs.w_c) else None
    return BenchRow(
        plant=index, drive=bench_drive.label, structure=(rep.truth or {}).get("structure", "-"), f_e=p["f_e"],
        V_J=p["V_J"], backlash=p["backlash"], oracle_w_c=ref.w_c, oracle_notches=len(ref.notches),
        delivered="none" if d is None else ("F1" if rep.fallback is not None else "model"),
        refusal=rep.permission.rule if rep.permission is not None else None,
        fallback_reason=rep.fallback_reason if rep.fallback is not None else None,
        stated_w_c=None if d is None else d.figures.get("w_c"), w_c=w_c,
        ratio=(w_c / ref.w_c) if w_c is not None and ref.w_c > 0 else 0.0,
        phase_margin=None if figs is None else figs.phase_margin,
        gain_margin_dB=None if figs is None else figs.gain_margin_dB,
        load_peak_dB=None if figs is None else figs.load_peak_dB, stable=None if figs is None else figs.stable,
        limit_cycle=cycle, within_limits=peaks["w_M"] <= limits.w_max and peaks["phi_M"] <= limits.travel,
        true_peaks=peaks, seconds=time.perf_counter() - t0)


@dataclass(frozen=True)
class DriveSummary:
    """One drive over the plants, against :data:`TARGETS`."""

    drive: str
    plants: int
    median_ratio: float
    class_median_ratio: dict[str, float]
    at_least_floor: int
    fallback: int
    delivered: int
    min_phase_margin: float | None
    min_gain_margin_dB: float | None
    unstable: int
    ringing: int
    limit_cycles: int
    limit_cycles_backlash: int
    within_limits: int
    median_seconds: float

    @property
    def verdicts(self) -> dict[str, bool]:
        """Each target: kept (scaled to this many plants where it is a count of 24)."""
        t, n = TARGETS, self.plants
        return {
            f"median ratio >= {t.median_ratio}": self.median_ratio >= t.median_ratio,
            f"per-class median >= {t.class_median_ratio}": all(v >= t.class_median_ratio for v in self.class_median_ratio.values()),
            f"ratio >= {t.ratio_floor} on all but {t.below_floor_allowed} of 24": n - self.at_least_floor <= t.below_floor_allowed * n / 24,
            f"F1 on at most {t.fallback_allowed} of 24": self.fallback <= t.fallback_allowed * n / 24,
            f"true PM >= {t.min_phase_margin:g} deg, GM >= {t.min_gain_margin_dB:g} dB, stable": self.unstable == 0 and (
                self.min_phase_margin is None or (self.min_phase_margin >= t.min_phase_margin
                                                  and self.min_gain_margin_dB >= t.min_gain_margin_dB)),
            f"load peak <= {t.max_load_peak_dB:.0f} dB": self.ringing == 0,
            "no limit cycle on backlash plants": self.limit_cycles_backlash == 0,
            "every experiment inside the limits": self.within_limits == n,
        }


def _median(values: Sequence[float]) -> float:
    return statistics.median(values) if values else math.nan


def _worst_margins(delivered: Sequence[BenchRow]) -> tuple[float | None, float | None]:
    """The smallest true phase margin [deg] and gain margin [dB] of the delivered loops (None: none)."""
    pms = [r.phase_margin for r in delivered if r.phase_margin is not None]
    gms = [r.gain_margin_dB for r in delivered if r.gain_margin_dB is not None]
    return min(pms, default=None), min(gms, default=None)


def summarize_rows(rows: Sequence[BenchRow], drive: str) -> DriveSummary:
    """:class:`DriveSummary` of the ``rows`` of ``drive``."""
    mine = [r for r in rows if r.drive == drive]
    delivered = [r for r in mine if r.delivered != "none"]
    min_pm, min_gm = _worst_margins(delivered)
    cycles = [r for r in mine if r.limit_cycle]
    return DriveSummary(
        drive=drive, plants=len(mine), median_ratio=_median([r.ratio for r in mine]),
        class_median_ratio={c: _median([r.ratio for r in mine if r.structure == c]) for c in sorted({r.structure for r in mine})},
        at_least_floor=sum(r.ratio >= TARGETS.ratio_floor for r in mine),
        fallback=sum(r.delivered == "F1" for r in mine), delivered=len(delivered),
        min_phase_margin=min_pm, min_gain_margin_dB=min_gm,
        unstable=sum(r.stable is False for r in delivered),
        ringing=sum(r.load_peak_dB is not None and r.load_peak_dB > TARGETS.max_load_peak_dB for r in delivered),
        limit_cycles=len(cycles),
        limit_cycles_backlash=sum(r.backlash > 0 for r in cycles), within_limits=sum(r.within_limits for r in mine),
        median_seconds=_median([r.seconds for r in mine]))


def _fmt(v: float | None, spec: str = ".3g") -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def rows_table(rows: Sequence[BenchRow]) -> str:
    """The per-plant table (markdown)."""
    table = Table(["plant", "drive", "class", "f_e Hz", "V_J", "oracle w_c", "delivered", "true w_c", "ratio",
                   "PM deg", "GM dB", "load pk dB", "limit cycle", "limits kept", "s"])
    for r in rows:
        how = r.delivered + (f" ({r.refusal})" if r.refusal else "") + (f" [{r.fallback_reason}]" if r.fallback_reason else "")
        table.add(r.plant, r.drive, r.structure, _fmt(r.f_e), _fmt(r.V_J, ".2f"), _fmt(r.oracle_w_c),
                  how, _fmt(r.w_c), _fmt(r.ratio, ".2f"), _fmt(r.phase_margin, ".1f"), _fmt(r.gain_margin_dB, ".1f"),
                  _fmt(r.load_peak_dB, ".1f"), "-" if r.limit_cycle is None else ("YES" if r.limit_cycle else "no"),
                  "yes" if r.within_limits else "NO", f"{r.seconds:.0f}")
    return table.render()


def summary_lines(s: DriveSummary) -> list[str]:
    """The summary of one drive as lines, each target marked kept or missed."""
    classes = ", ".join(f"{c} {v:.2f}" for c, v in s.class_median_ratio.items())
    lines = [f"== {s.drive}: {s.plants} plants ==",
             f"delivered/oracle true crossover: median {s.median_ratio:.2f} (per class: {classes}); "
             f">= {TARGETS.ratio_floor}: {s.at_least_floor}/{s.plants}",
             f"delivered {s.delivered}/{s.plants} ({s.delivered - s.fallback} model-based, {s.fallback} F1); "
             f"true PM min {_fmt(s.min_phase_margin, '.1f')} deg, GM min {_fmt(s.min_gain_margin_dB, '.1f')} dB, "
             f"unstable {s.unstable}; load peak above {TARGETS.max_load_peak_dB:.0f} dB (rings the load, the "
             f"oracle's bound): {s.ringing}",
             f"limit cycles: {s.limit_cycles} ({s.limit_cycles_backlash} on backlash plants); experiments inside the "
             f"limits: {s.within_limits}/{s.plants}; seconds per plant: median {s.median_seconds:.0f}"]
    lines += [f"  target {name}: {'kept' if ok else 'MISSED'}" for name, ok in s.verdicts.items()]
    return lines


def run(args: argparse.Namespace) -> int:
    import sim
    from training.identification import Identifier

    chosen = _selection(args)
    limits = sim.DriveLimits(w_max=args.w_max, travel=args.travel)
    params = sim.sample_population(args.plants, args.seed).to_dicts()
    identifier = Identifier.load()
    print(machine_line())
    print(f"plants {len(chosen)} of sample_population({args.plants}, {args.seed}); limits {args.w_max:g} rad/s, "
          f"{args.travel:g} rad; drives: " + ", ".join(d.label for d in DRIVES))
    rows: list[BenchRow] = []
    t0, cpu0 = time.perf_counter(), time.process_time()
    for i in chosen:
        for bench_drive in DRIVES:
            row = run_one(i, params[i], bench_drive, limits, identifier)
            rows.append(row)
            print(f"plant {i:3d} {bench_drive.label:16s} {row.structure:10s} oracle {row.oracle_w_c:8.3g} rad/s, "
                  f"delivered {row.delivered} {_fmt(row.w_c)} rad/s, ratio {row.ratio:.2f}, {row.seconds:.0f} s",
                  file=sys.stderr, flush=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    print(rows_table(rows))
    summaries = [summarize_rows(rows, d.label) for d in DRIVES]
    for s in summaries:
        print("\n".join(summary_lines(s)))
    print(f"wall {wall:.0f} s, CPU of this process {cpu:.0f} s (the plant processes apart); load average "
          f"{os.getloadavg()[0]:.2f}")
    print(f"reproduce: {args.command_line}")
    if args.json_out:
        write_figures(args.json_out, {"command": args.command_line, "rows": [asdict(r) for r in rows],
                                      "summary": [{**asdict(s), "verdicts": s.verdicts} for s in summaries],
                                      "wall_s": wall, "cpu_s": cpu})
    return 0
