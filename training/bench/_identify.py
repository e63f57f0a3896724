"""``twomass bench identify``: wall time of ``twomass identify`` on simulated records, start-up included."""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from training.bench._run import write_figures
from training.errors import UserError

HELP = "wall time of 'twomass identify' on N population records (start-up included), with and without the refinement"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--records", type=int, default=100, help="population records to identify (default 100)")
    parser.add_argument("--seed", type=int, default=7, help="population and noise seed (default 7)")
    parser.add_argument("--repeat", type=int, default=5, help="runs per variant (default 5)")
    parser.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")


def _time_identify(paths: list[str], extra: list[str], out: Path) -> float:
    """Wall time [s] of one ``twomass identify`` process (a fresh interpreter: start-up included)."""
    cmd = [sys.executable, "-m", "training.cli", "identify", *paths, "--no-progress", "--out", str(out),
           "--overwrite", *extra]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode not in (0, 1):
        raise UserError(f"twomass identify failed (exit {res.returncode}): {res.stderr.strip().splitlines()[-1:]}")
    return wall


def run(args: argparse.Namespace) -> int:
    import sim

    if args.records < 1 or args.repeat < 1:
        raise UserError(f"--records and --repeat: expected >= 1, received {args.records}, {args.repeat}")
    drive, signal = sim.DriveConfig(), sim.TestSignalConfig()
    params = sim.sample_population(args.records, args.seed)
    with tempfile.TemporaryDirectory(prefix="twomass-bench-") as tmp:
        records = sim.responses_to_records(sim.simulate_test(params, drive, signal, seed=args.seed), params, drive,
                                           signal, names=[f"rec{i:04d}" for i in range(args.records)])
        paths = []
        for r in records:
            path = Path(tmp) / f"{r.name}.csv"
            sim.write_record(path, r)
            paths.append(str(path))
        samples = statistics.mean(len(r.speed) for r in records)
        print(f"{args.records} records, {samples:.0f} samples each on average; {os.cpu_count()} CPUs, "
              f"1-min load average {os.getloadavg()[0]:.2f}")
        figures: dict[str, dict[str, float]] = {}
        for label, extra in (("identify", []), ("identify --no-refine", ["--no-refine"])):
            walls = [_time_identify(paths, extra, Path(tmp) / "out.jsonl") for _ in range(args.repeat)]
            figures[label] = {"min_s": min(walls), "median_s": statistics.median(walls), "max_s": max(walls)}
            print(f"twomass {label}: wall {min(walls):.2f} / {statistics.median(walls):.2f} / {max(walls):.2f} s "
                  f"(min / median / max of {args.repeat})")
    if args.json_out:
        write_figures(args.json_out, {"records": args.records, "seed": args.seed, "mean_samples": samples,
                                      "figures": figures})
    return 0
