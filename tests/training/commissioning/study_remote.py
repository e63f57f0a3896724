"""The 50-plant study of issue 12 (not a test): the chain through the SPEC 8.1 interface on the
independent out-of-process plant (:mod:`remote_plant`), plain or with the variant, limits 20 rad/s
and 5 rad; limits checked on the plant's true states, the delivered loop on the true linear model.

    python tests/training/commissioning/study_remote.py N [--variant] [--only 7,9,23] [--no-measure] > out.txt

``--only``: run only these plants of the N (their names stay ``plantNNN``); ``--no-measure``: without
the frequency-response experiment and the redesign (stages ``measure``, ``redesign``).
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import remote_plant  # noqa: E402

import sim  # noqa: E402
from training.commissioning import CommissioningConfig, commission, summarize, summary_text  # noqa: E402
from training.identification import Identifier  # noqa: E402


def main() -> None:
    n, variant = int(sys.argv[1]), "--variant" in sys.argv
    only = {int(i) for i in sys.argv[sys.argv.index("--only") + 1].split(",")} if "--only" in sys.argv else set(range(n))
    limits = sim.DriveLimits(w_max=20.0, travel=5.0)
    config = CommissioningConfig(measure_response="--no-measure" not in sys.argv)
    ident = Identifier.load()
    reports, rows, t0 = [], [], time.perf_counter()
    for i, p in enumerate(sim.sample_population(n, 0).to_dicts()):
        if i not in only:
            continue
        drive = remote_plant.make_drive(p, variant=variant)
        try:
            rep = commission(drive, limits, identifier=ident, config=config, name=f"plant{i:03d}")
        finally:
            drive.close()
        reports.append(rep)
        peak = {k: max(e[k] for e in drive.experiments) for k in ("w_M", "w_L", "phi_M")}
        runs = rep.model_runs
        row = {"name": rep.name, "f_e": p["f_e"], "V_J": p["V_J"], "refused": rep.permission.rule,
               "fallback": rep.fallback_reason if rep.fallback is not None else None,
               "f1_w_c": rep.fallback.figures["w_c"] if rep.fallback is not None else None,
               "identified": rep.identified_structure,
               "w_c": rep.delivered.figures["w_c"] if rep.delivered is not None else None,
               "true_peaks": peak, "within_true": peak["w_M"] <= 20 and peak["phi_M"] <= 5,
               "true_pm": (rep.truth or {}).get("phase_margin"), "true_gm": (rep.truth or {}).get("gain_margin_dB"),
               "true_stable": (rep.truth or {}).get("stable"), "true_w_c": (rep.truth or {}).get("w_c"),
               "improvement": rep.improvement,
               "resonances_Hz": None if rep.measured is None else rep.measured.to_dict()["resonances_Hz"],
               "redesign": rep.redesign_reason or None,
               "not_worse": None if rep.delivered_run is None or rep.fallback is not None else
               bool(rep.delivered_run.usable and (not runs[0].usable  # an unsettled proposal is worse
                                                  or rep.delivered_run.cost <= runs[0].cost)),
               "seconds": rep.timings.get("total")}
        rows.append(row)
        print(json.dumps(row), flush=True)
    s = summarize(reports, time.perf_counter() - t0)
    print(summary_text(s))
    print(f"true states within 20 rad/s and 5 rad in every experiment: {sum(r['within_true'] for r in rows)}/{len(rows)}; "
          f"largest true |w_M| {max(r['true_peaks']['w_M'] for r in rows):.3g} rad/s, |w_L| "
          f"{max(r['true_peaks']['w_L'] for r in rows):.3g} rad/s, |phi_M| {max(r['true_peaks']['phi_M'] for r in rows):.3g} rad")
    pms = [r["true_pm"] for r in rows if r["true_pm"] is not None]
    gms = [r["true_gm"] for r in rows if r["true_gm"] is not None]
    print(f"delivered: true PM >= 35 deg and GM >= 5 dB: {sum(pm >= 35 and gm >= 5 for pm, gm in zip(pms, gms))}/{len(pms)}; "
          f"median true PM {statistics.median(pms):.1f} deg, min {min(pms):.1f}; min GM {min(gms):.1f} dB")
    print(f"not worse than the proposal of the same plan (measured cost, motor and estimated load): {sum(bool(r['not_worse']) for r in rows)}/"
          f"{sum(r['not_worse'] is not None for r in rows)}; seconds per plant: median "
          f"{statistics.median(r['seconds'] for r in rows):.1f}")


if __name__ == "__main__":
    main()
