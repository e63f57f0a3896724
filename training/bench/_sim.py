"""``twomass bench sim``: the fused C kernel against a vectorized numpy RK4 of the same model and test.

All run the first ``--samples`` samples of the SPEC 2 switching test for the same ``--batch``
population systems, in the same dtype, with the same substeps and the same arithmetic (the
numpy baseline, :mod:`training.bench._numpy_rk4`, and the simulator's torch eager twin, its
fallback without a C compiler, are checked against the kernel in the tests). numpy runs on one
core, so the kernel runs once on one thread and once on all of its threads. The runs alternate
(numpy, torch, kernel, kernel, then again), so a load that comes and goes hits all of them; the
fastest of ``--repeat`` counts. The arithmetic rate (the kernel's count of add/sub/mul per
substep, the same work for every line) is compared with a square matmul measured in the same
run. The per-sample ``solve_ivp`` script is a labelled extra line on a tiny batch (float64, RK45).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from unittest import mock

import numpy as np
import torch

from training.bench._numpy_rk4 import FLOPS_PER_SUBSTEP as NUMPY_FLOPS_PER_SUBSTEP, TestOutput, switching_test
from training.bench._report import Table, machine_line, matmul_gflops, write_figures

HELP = ("simulator: fused C kernel (1 thread, all threads) and torch eager fallback vs vectorized numpy RK4, "
        "same test, dtype and batch")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--batch", type=int, default=4096, help="systems (default 4096)")
    parser.add_argument("--samples", type=int, default=2000,
                        help="samples of the test per system (default 2000: 0.5 s, sections I to III and the "
                             "zero-torque phases of most systems; 400 is section I alone)")
    parser.add_argument("--float64", action="store_true", help="float64 instead of the simulator's default float32")
    parser.add_argument("--repeat", type=int, default=3, help="runs per implementation, the fastest counts (default 3)")
    parser.add_argument("--naive-samples", type=int, default=200,
                        help="samples of the solve_ivp script, one system (default 200; 0 = skip)")
    parser.add_argument("--seed", type=int, default=1, help="population seed (default 1)")
    parser.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")


def _inputs(batch: int, seed: int, dtype: torch.dtype):
    from sim import DriveConfig, TestSignalConfig, sample_population
    from sim._integrate_fast import FastParams, default_substeps

    drive, signal = DriveConfig(), TestSignalConfig()
    params = sample_population(batch, seed)
    fp = FastParams.build(params, drive, default_substeps(params, drive), dtype)
    return drive, signal, params, fp


def kernel_test(fp, drive, signal, nk: int, threads: int | None = None) -> tuple[float, dict[str, torch.Tensor]]:
    """Wall time [s] and buffers ``n x nk`` of ``nk`` fused test samples (``threads``: the kernel's
    thread setting for this call; ``None``: as configured)."""
    from sim._integrate_fast import FastState, SignalState, new_test_buffers, run_test_chunk
    from sim._kernel import load_kernel

    lib = load_kernel()
    if lib is None:
        raise OSError("the fused C kernel is unavailable (no C compiler, or TWOMASS_NO_C_KERNEL set); nothing to bench")
    n = fp.iJM.numel()
    x, c, buf = FastState.zeros(n, fp.dtype), SignalState.start(n), new_test_buffers(n, nk, fp.dtype)
    env = {} if threads is None else {"TWOMASS_SIM_THREADS": str(threads)}
    with mock.patch.dict(os.environ, env):
        t0 = time.perf_counter()
        run_test_chunk(lib, x, fp, c, drive, signal.levels(drive), signal.n_timeout(drive), signal.n_tail(drive),
                       0, nk, buf)
        return time.perf_counter() - t0, buf


def torch_test(params, fp, drive, signal, nk: int):
    """Wall time [s] and response of the simulator's torch eager fallback (what runs without a C
    compiler or with ``TWOMASS_NO_C_KERNEL``): :func:`sim.simulate` with the switching controller,
    ``nk`` samples, the kernel's substeps and dtype; torch on one thread, as numpy."""
    from sim import SwitchingController, simulate

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t0 = time.perf_counter()
        resp = simulate(params, drive, SwitchingController(signal, drive, fp.dtype), nk, dtype=fp.dtype,
                        substeps=fp.S, use_kernel=False)
        return time.perf_counter() - t0, resp
    finally:
        torch.set_num_threads(before)


def numpy_test(fp, drive, signal, nk: int) -> tuple[float, TestOutput]:
    """Wall time [s] and output of the numpy baseline on the kernel's inputs ``fp``."""
    coef = {k: getattr(fp, a).numpy() for k, a in (("iJM", "iJM"), ("iJL", "iJL"), ("CF", "C_F"), ("DF", "D_F"),
                                                    ("s", "s"), ("MFC", "M_FC"), ("muF", "mu_F"), ("Mext", "M_ext"))}
    t0 = time.perf_counter()
    out = switching_test(coef, fp.S, fp.consts(), (drive.q_w, drive.counts_per_rad), signal.levels(drive),
                         drive.M_max, signal.n_timeout(drive), signal.n_tail(drive), nk)
    return time.perf_counter() - t0, out


def _solve_ivp_test(p: dict, n_samples: int) -> tuple[float, int]:
    """The naive script: solve_ivp (RK45) per sample interval, one system, the switching controller in Python."""
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
    sec, cnt, nI, nIV, M_ref = 1, 0, 0, 0, 0.0
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
    from sim import DriveConfig, sample_population
    from sim._integrate_fast import kernel_threads
    from sim._config import cache_dir
    from sim._kernel import FLOPS_PER_SUBSTEP, KERNEL

    for name in ("batch", "samples", "repeat"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name}: expected a positive integer, received {getattr(args, name)}")
    if args.naive_samples < 0:
        raise ValueError(f"--naive-samples: expected an integer >= 0 (0: skip), received {args.naive_samples}")
    dtype = torch.float64 if args.float64 else torch.float32
    drive, signal, params, fp = _inputs(args.batch, args.seed, dtype)
    nk, S, B = args.samples, fp.S, args.batch
    all_threads = kernel_threads(B)  # the threads the kernel really uses: at most one per block of systems
    kernel_test(fp, drive, signal, 2)  # load (or build) the kernel outside the timings
    print(machine_line())
    print(f"test: the switching test (SPEC 2), first {nk} samples of {B} population systems (seed {args.seed}), "
          f"{S} RK4 substeps per sample, {str(dtype)[6:]}; runs alternate, the fastest of {args.repeat} counts")
    print(f"kernel library: {KERNEL.origin(cache_dir())}")
    flop = {t: matmul_gflops(dtype, t) for t in sorted({1, all_threads})}
    print("machine FLOP rate: " + ", ".join(f"{v:.1f} GFLOP/s on {t} thread(s)" for t, v in flop.items())
          + f" ({str(dtype)[6:]} matmul 1024 x 1024, the faster of numpy's BLAS and torch, 2 n^3 FLOP; "
          "it uses fused multiply-add, the kernel is compiled without: at most half of it is reachable)")

    work = B * nk * S  # system-substeps
    runs = {("numpy RK4, vectorized over systems", 1): lambda: numpy_test(fp, drive, signal, nk)[0],
            ("torch eager twin (the fallback without a C compiler)", 1):
                lambda: torch_test(params, fp, drive, signal, nk)[0],
            **{("fused C kernel", t): (lambda t=t: kernel_test(fp, drive, signal, nk, t)[0])
               for t in sorted({1, all_threads})}}
    walls: dict[tuple[str, int], list[float]] = {key: [] for key in runs}
    for _ in range(args.repeat):
        for key, fn in runs.items():
            walls[key].append(fn())
    rows = [(label, t, min(walls[label, t])) for label, t in runs]
    t_numpy = rows[0][2]
    table = Table(["implementation", "threads", "wall s", "system-substeps/s", "GFLOP/s", "% of matmul", "vs numpy"])
    figures: dict = {"batch": B, "samples": nk, "substeps": S, "dtype": str(dtype), "flops_per_substep":
                     FLOPS_PER_SUBSTEP, "matmul_gflops": flop, "runs": []}
    for label, t, wall in rows:
        gflops = work * FLOPS_PER_SUBSTEP / wall / 1e9
        table.add(label, t, f"{wall:.3f}", f"{work / wall:.3e}", f"{gflops:.2f}", f"{100 * gflops / flop[t]:.1f}",
                  f"{t_numpy / wall:.1f}x")
        figures["runs"].append({"implementation": label, "threads": t, "wall_s": wall, "substeps_per_s": work / wall})
    if args.naive_samples > 0:
        truth = sample_population(1, 7).truth(DriveConfig(), 10.0)[0]
        wall, done = _solve_ivp_test(truth, args.naive_samples)
        rate = done * S / wall  # the same samples at the kernel's substeps
        table.add("naive script: solve_ivp RK45 per sample, 1 system, float64", 1, f"{wall:.3f}", f"{rate:.3e}",
                  "-", "-", f"{rate / (work / t_numpy):.4f}x")
        figures["naive_s_per_sample"] = wall / done
    print(table.render())
    load = os.getloadavg()
    figures["load_average_after"] = load
    print(f"load average after the runs (1, 5, 15 min): {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on "
          f"{os.cpu_count()} CPUs (ratios are from one run; above ~0.5 other work shares the cores)")
    print(f"GFLOP/s counts {FLOPS_PER_SUBSTEP} add/sub/mul per system-substep for every line: the model's arithmetic "
          "as sim/_kernel.c writes and executes it (sim._kernel.FLOPS_PER_SUBSTEP; compares, min/max, selects, the "
          f"encoder and the controller not counted; numpy computes stage 1's shaft torque twice, "
          f"{NUMPY_FLOPS_PER_SUBSTEP}); the solve_ivp line counts its samples at the same substeps")
    print(f"reproduce: {args.command_line}")
    if args.json_out:
        write_figures(args.json_out, figures)
    return 0
