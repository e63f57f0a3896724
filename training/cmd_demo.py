"""``twomass demo``: simulate the reference drive with a default elastic plant and summarize the record."""

from __future__ import annotations

import argparse
import math
import sys

HELP = "simulate the reference drive with a default elastic plant and print a summary (no arguments needed)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--f-e", type=float, default=30.0, help="eigenfrequency [Hz] (default 30)")
    parser.add_argument("--backlash-deg", type=float, default=0.1, help="total backlash [degree] (default 0.1)")
    parser.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from sim import DriveConfig, TestSignalConfig, TwoMassParams, responses_to_records, simulate_test
    from sim.test_signal import SECTION_NAMES

    drive, signal = DriveConfig(), TestSignalConfig()
    params = TwoMassParams(J_sigma=0.05, V_J=1.0, f_e=args.f_e, d=0.02, backlash=math.radians(args.backlash_deg),
                           M_FC=0.2, mu_F=0.001)
    resp = simulate_test(params, drive, signal, seed=args.seed)
    rec = responses_to_records(resp, params.reshape(1), drive, signal, names=["demo"])[0]
    truth = rec.meta["truth"]
    out = sys.stdout
    print("twomass demo: reference drive (M_max 20 Nm, T_Ei 0.5 ms, T_s 250 us, 20-bit encoder)", file=out)
    print(f"plant: J_sigma {truth['J_sigma']:.3g} kg m^2, V_J {truth['V_J']:.3g}, f_e {truth['f_e']:.3g} Hz, "
          f"d {truth['d']:.3g}, backlash {math.degrees(truth['backlash']):.3g} deg, M_FC {truth['M_FC']:.3g} Nm, "
          f"mu_F {truth['mu_F']:.3g} Nm s/rad", file=out)
    print(f"derived: C_F {truth['C_F']:.4g} Nm/rad, s_N {truth['s_N']:.3g}, w_e*T_Ei {2 * math.pi * truth['f_e'] * drive.T_Ei:.3g}, "
          f"r_osc {truth['r_osc']:.3g} -> class {truth['structure']}", file=out)
    print(f"test: M* {signal.M_star} Nm, w_max {signal.w_max} rad/s; record {len(rec)} samples, "
          f"{len(rec) * drive.T_s:.3f} s", file=out)
    for q, name in enumerate(SECTION_NAMES, start=1):
        n = int(np.sum(rec.section == q))
        flag = "  (timed out)" if rec.meta["timed_out"][q - 1] else ""
        print(f"  section {name:>3}: {n * drive.T_s * 1e3:8.1f} ms{flag}", file=out)
    print(f"  tail     : {np.sum(rec.section == 0) * drive.T_s * 1e3:8.1f} ms", file=out)
    print(f"speed range {rec.speed.min():.2f} .. {rec.speed.max():.2f} rad/s, final speed {rec.speed[-1]:.3f} rad/s, "
          f"current range {rec.current.min():.2f} .. {rec.current.max():.2f} A", file=out)
    return 0
