"""``twomass bench train``: map making for N systems, ``twomass generate`` then ``twomass train``,
each a fresh process: wall time, CPU time and peak memory (largest process and whole process tree)."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from training.bench._report import ProcessCost, Table, machine_line, run_process, write_figures
from training.errors import UserError

HELP = "'twomass generate' + 'twomass train' of N systems, fresh processes: wall, CPU and peak memory"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=int, default=1000, help="systems (default 1000)")
    parser.add_argument("--seed", type=int, default=1, help="population and noise seed (default 1)")
    parser.add_argument("--size", type=int, nargs=2, default=(40, 40), metavar=("ROWS", "COLS"),
                        help="units of each map (default 40 40)")
    parser.add_argument("--ensemble", type=int, default=4, help="maps per ensemble (default 4)")
    parser.add_argument("--epochs", type=int, default=10, help="passes over the training data (default 10)")
    parser.add_argument("--workers", type=int, default=None, help="generate's analysis processes (default: its own)")
    parser.add_argument("--json", dest="json_out", default=None, help="also write the figures to this JSON file")


def run(args: argparse.Namespace) -> int:
    if args.n < 1:
        raise UserError(f"--n: expected >= 1, received {args.n}")
    from training.learning import TrainConfig

    # the map options, checked as train checks them, before a long generate
    TrainConfig(rows=args.size[0], cols=args.size[1], ensemble=args.ensemble, epochs=args.epochs)
    cli = [sys.executable, "-m", "training.cli"]
    print(machine_line(), flush=True)
    with tempfile.TemporaryDirectory(prefix="twomass-bench-") as tmp:
        data, maps = Path(tmp) / "data", Path(tmp) / "maps"
        workers = [] if args.workers is None else ["--workers", str(args.workers)]
        gen = run_process([*cli, "generate", "--out", str(data), "--n", str(args.n), "--seed", str(args.seed),
                           "--no-progress", *workers])
        train = run_process([*cli, "train", "--data", str(data), "--out", str(maps), "--logdir", str(Path(tmp) / "runs"),
                             "--size", *map(str, args.size), "--ensemble", str(args.ensemble),
                             "--epochs", str(args.epochs), "--no-progress"])
        data_mib = sum(f.stat().st_size for f in data.rglob("*") if f.is_file()) / 2**20
    table = Table(["step", "wall s", "CPU s", *ProcessCost.MEMORY])
    table.add(f"twomass generate --n {args.n}", f"{gen.wall:.1f}", f"{gen.cpu:.1f}", *gen.memory())
    table.add(f"twomass train ({args.size[0]} x {args.size[1]}, ensemble {args.ensemble}, {args.epochs} epochs)",
              f"{train.wall:.1f}", f"{train.cpu:.1f}", *train.memory())
    table.add("both", f"{gen.wall + train.wall:.1f}", f"{gen.cpu + train.cpu:.1f}",
              f"{max(gen.peak_rss_mib, train.peak_rss_mib):.0f}", f"{max(gen.peak_tree_mib, train.peak_tree_mib):.0f}")
    print(table.render())
    print(f"dataset on disk: {data_mib:.1f} MiB; CPU includes generate's worker processes")
    print(f"reproduce: {args.command_line}")
    if args.json_out:
        write_figures(args.json_out, {"n": args.n, "generate": vars(gen), "train": vars(train), "data_mib": data_mib})
    return 0
