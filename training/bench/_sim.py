"""``twomass bench sim``: simulator throughput, the solve_ivp baseline, and records for a population."""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
import torch

from training.bench._run import write_figures

HELP = "simulator throughput (system-substeps/s) vs batch size, solve_ivp baseline, population records time"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", default="1,4,16,64,256,1024,4096,16384", help="batch sizes (comma list)")
    parser.add_argument("--work", type=float, default=4e7, help="system-substeps per batch size (default 4e7)")
    parser.add_argument("--float64", action="store_true", help="bench float64 instead of the default float32")
    parser.add_argument("--baseline-systems", type=int, default=2, help="systems for the solve_ivp baseline")
    parser.add_argument("--baseline-samples", type=int, default=2000, help="samples per baseline system")
    parser.add_argument("--records", type=int, default=1800, help="population size for the records timing")
    parser.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")


def _throughput(B: int, work: float, dtype: torch.dtype) -> tuple[float, int, int]:
    from sim import DriveConfig, TestSignalConfig, sample_population
    from sim._integrate_fast import FastParams, FastState, SignalState, default_substeps, new_test_buffers, run_test_chunk
    from sim._kernel import load_kernel

    drive = DriveConfig()
    # w_max out of reach: every system stays active (section I) for the whole measurement
    signal = TestSignalConfig(w_max=1e9, timeout=1e3)
    params = sample_population(B, 1)
    S = default_substeps(params, drive)
    lib = load_kernel()
    if lib is None:
        raise OSError("the fused C kernel is unavailable (no C compiler); nothing to bench")
    nk = int(max(64, min(200_000, work / (B * S))))
    fp = FastParams.build(params, drive, S, dtype)
    x, c = FastState.zeros(B, dtype), SignalState.start(B)
    buf = new_test_buffers(B, nk, dtype)
    warm = min(nk, 32)
    run_test_chunk(lib, x, fp, c, drive, signal.levels(drive), signal.n_timeout(drive), signal.n_tail(drive), 0, warm, buf)
    t0 = time.perf_counter()
    run_test_chunk(lib, x, fp, c, drive, signal.levels(drive), signal.n_timeout(drive), signal.n_tail(drive), warm,
                   nk - warm, buf)
    el = time.perf_counter() - t0
    return B * (nk - warm) * S / el, S, nk - warm


def _solve_ivp_test(p: dict, n_samples: int) -> tuple[float, int]:
    """What a user would write: solve_ivp (RK45) per sample interval, the switching controller in Python."""
    from scipy.integrate import solve_ivp

    from sim import SECTION_LEVELS, SPEED_RETURN, DriveConfig, TestSignalConfig

    drive, sig = DriveConfig(), TestSignalConfig()
    J_M, J_L, C_F, D_F, s, M_FC, mu_F = (p[k] for k in ("J_M", "J_L", "C_F", "D_F", "s", "M_FC", "mu_F"))

    def rhs(_t, y, M_ref):
        w_M, w_L, dphi, M_M, _phi = y
        e = dphi - min(max(dphi, -s), s)
        M_S = C_F * e + (D_F * (w_M - w_L) if e != 0 else 0.0)
        return [(M_M - M_S) / J_M, (M_S - M_FC * np.sign(w_L) - mu_F * w_L) / J_L, w_M - w_L,
                (M_ref - M_M) / drive.T_Ei, w_M]

    y = np.zeros(5)
    sec, cnt, nI, nIV, M_ref, M_next = 1, 0, 0, 0, 0.0, 0.0
    scale = drive.encoder_counts / (2 * math.pi)
    c_prev = 0.0
    t0 = time.perf_counter()
    k = 0
    for k in range(n_samples):
        c = math.floor(y[4] * scale)
        w = (c - c_prev) * drive.q_w
        c_prev = c
        cnt += 1
        end = {1: w >= sig.w_max, 2: cnt >= nI or w <= SPEED_RETURN * sig.w_max, 3: w <= 0, 4: w <= -sig.w_max,
               5: cnt >= nIV or w >= -SPEED_RETURN * sig.w_max, 6: w >= 0}.get(sec, cnt >= 200)
        if end:
            nI = cnt if sec == 1 else nI
            nIV = cnt if sec == 4 else nIV
            sec, cnt = sec + 1, 0
            if sec == 8:
                break
        M_next = SECTION_LEVELS[sec - 1] * sig.M_star if sec <= len(SECTION_LEVELS) else 0.0  # 7: the tail
        y = solve_ivp(rhs, (0.0, drive.T_s), y, method="RK45", args=(M_ref,), rtol=1e-6, atol=1e-9).y[:, -1]
        M_ref = M_next
    return time.perf_counter() - t0, k + 1


def run(args: argparse.Namespace) -> int:
    from sim import DriveConfig, iter_records, sample_population
    from sim._kernel import load_kernel

    dtype = torch.float64 if args.float64 else torch.float32
    try:
        sizes = [int(v) for v in args.sizes.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--sizes: expected comma-separated integers, received {args.sizes!r}") from None
    t0 = time.perf_counter()
    load_kernel()
    build_s = time.perf_counter() - t0
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"bench sim: {dtype}, torch threads {torch.get_num_threads()}, cpus {os.cpu_count()}, "
          f"load average {load:.2f}, kernel load/build {build_s:.2f} s")
    res: dict = {"dtype": str(dtype), "threads": torch.get_num_threads(), "load_average": load, "throughput": {}}
    print(f"{'batch':>7} {'substeps':>8} {'samples':>8} {'system-substeps/s':>18}")
    for B in sizes:
        rate, S, nk = _throughput(B, args.work, dtype)
        res["throughput"][B] = rate
        print(f"{B:>7} {S:>8} {nk:>8} {rate:>18.3e}")
    # baseline: solve_ivp per system
    pop = sample_population(max(1, args.baseline_systems), 7)
    per_sample = []
    for tr in pop.truth(DriveConfig(), 10.0):
        el, n = _solve_ivp_test(tr, args.baseline_samples)
        per_sample.append(el / n)
    ivp_per_sample = float(np.mean(per_sample))
    # records for a population
    t0 = time.perf_counter()
    n_rec, n_samp = 0, 0
    for rec in iter_records(sample_population(args.records, 0)):
        n_rec += 1
        n_samp += len(rec)
    rec_s = time.perf_counter() - t0
    mean_len = n_samp / max(1, n_rec)
    best_B = max((b for b in sizes if b >= 4096), default=max(sizes), key=lambda b: res["throughput"][b])
    fast_per_sample = 4 / res["throughput"][best_B]
    ivp_per_system = ivp_per_sample * mean_len
    ratio = ivp_per_sample / fast_per_sample
    print(f"solve_ivp (RK45, rtol 1e-6) baseline: {ivp_per_sample * 1e6:.0f} us per sample "
          f"({args.baseline_systems} systems x {args.baseline_samples} samples) -> {ivp_per_system:.1f} s per system "
          f"for a mean test of {mean_len:.0f} samples")
    print(f"fast path at batch {best_B}: {fast_per_sample * 1e9:.1f} ns per system-sample "
          f"-> {fast_per_sample * mean_len * 1e3:.2f} ms per system; ratio {ratio:.0f}x")
    print(f"records for {n_rec} population systems ({n_samp} samples): {rec_s:.2f} s (in memory, float64 arrays)")
    res.update(solve_ivp_s_per_sample=ivp_per_sample, solve_ivp_s_per_system=ivp_per_system,
               fast_s_per_system_sample=fast_per_sample, ratio=ratio, records=n_rec, records_s=rec_s,
               mean_record_samples=mean_len)
    if args.json_out:
        write_figures(args.json_out, res)
    sys.stdout.flush()
    return 0
