"""``twomass generate``: simulate a population, analyse each record, store features + truth."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "make training data: population responses and their features, sharded to disk (resumable)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="dataset folder (an interrupted run resumes here)")
    parser.add_argument("--n", type=int, default=20000, help="number of systems (default 20000)")
    parser.add_argument("--seed", type=int, default=1, help="population and noise seed (default 1)")
    parser.add_argument("--shard-size", type=int, default=500, help="systems per shard file (default 500)")
    parser.add_argument("--workers", type=int, default=None, help="analysis processes (default: CPU count)")
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from training.learning import GenerateConfig, generate, load_dataset

    if args.n < 1 or args.shard_size < 1:
        raise ValueError(f"--n and --shard-size: expected >= 1, received {args.n}, {args.shard_size}")
    config = GenerateConfig(n=args.n, seed=args.seed, shard_size=args.shard_size)
    with tqdm(total=args.n, unit="sys", disable=args.no_progress, desc="generate") as bar:
        generate(args.out, config, workers=args.workers, progress=bar.update)
    ds = load_dataset(args.out)
    print(f"{args.out}: {len(ds)} systems, {int(ds.ok.sum())} analysed, {len(ds) - int(ds.ok.sum())} rejected "
          f"by the analysis, sha256 {ds.sha256[:16]}")
    return 0
